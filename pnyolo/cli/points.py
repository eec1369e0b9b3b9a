"""Operating points handed to the command line (issue 86): the bench chooses each model's point on validation and
records it in its report.json; ``--point-from BENCH`` (a pnyolo-bench run folder or its report.json) gives
pnyolo-eval those values for the checkpoint, the ``--chance-from`` single view and the ``--into`` ego, so every row
of a bench report is one command line away. A point is a value: a new config, never a write into one::

    point = bench_point("out/bench_cpu", "bev", "--point-from")     # eval keys, eval_stats, checkpoint
    cfg = apply_point(cfg, model, point, "runs/bev/best.pt", "--point-from out/bench_cpu")
    send, ego_threshold = into_choice("out/bench_cpu", "bev", "single-view")
"""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt
from pnyolo.config.checks import EVAL_STATS

POINT_KEYS = ("conf_threshold", "nms_iou", "depth_gap", "depth_peaks")  # the eval keys a bench chooses


def bench_rows(path_text: str, option: str) -> tuple[Path, dict]:
    """(report.json's path, its rows by name) of a pnyolo-bench run folder or report.json."""
    from dataset_spec.dataset import read_json

    path = Path(path_text)
    path = path / "report" / "report.json" if path.is_dir() else path
    doc = read_json(path, f"{option} a pnyolo-bench report.json")
    rows = doc.get("models") if isinstance(doc, dict) else None
    return path, rows if isinstance(rows, dict) else {}


def bench_point(path_text: str, kind: str, option: str, read: tuple[Path, dict] | None = None) -> dict:
    """The operating point the bench chose on validation for ``kind``: threshold, NMS IoU, depth gap and peaks as
    eval keys, and its batch-norm statistics and checkpoint file; one line where it chose none or names odd values.
    ``read``: ``bench_rows``' answer, where the caller has read the record already."""
    path, rows = read or bench_rows(path_text, option)
    chosen = (rows.get(kind) or {}).get("selection") if isinstance(rows.get(kind), dict) else None
    if not isinstance(chosen, dict):
        raise UserError(f"{option}{path}: that run chose no operating point for {kind}")
    if chosen.get("eval_stats") not in (None, *EVAL_STATS) or not isinstance(chosen.get("checkpoint"), (str, type(None))):
        raise UserError(f"{option}{path}: its choice for {kind} names eval_stats {excerpt(chosen.get('eval_stats'))} "
                        f"and checkpoint {excerpt(chosen.get('checkpoint'))} (expected one of {EVAL_STATS} and a file name)")
    return {"conf_threshold": chosen.get("threshold"), "nms_iou": chosen.get("nms_iou"),
            "depth_gap": chosen.get("depth_gap"), "depth_peaks": chosen.get("depth_peaks"),
            "eval_stats": chosen.get("eval_stats"), "checkpoint": chosen.get("checkpoint")}


def into_choice(path_text: str, sender: str, ego: str) -> tuple[float, float]:
    """(send threshold, the ego's threshold) the bench chose on validation for ``sender``'s late fusion into ``ego``."""
    path, rows = bench_rows(path_text, "--point-from ")
    row = rows.get(f"{sender}, late fusion into {ego}")
    choice = row.get("late_fusion_selection") if isinstance(row, dict) else None
    if not isinstance(choice, dict) or not all(isinstance(choice.get(k), (int, float)) for k in ("send", "ego_threshold")):
        raise UserError(f"--point-from {path}: that run chose no late fusion of {sender} into {ego}")
    return float(choice["send"]), float(choice["ego_threshold"])


def apply_point(cfg, model, point: dict, checkpoint, where: str):
    """``cfg`` at ``point`` (``bench_point``'s, or a late rule's: eval keys, where given) as a new config value, checked
    as a config's values are; the point's batch-norm statistics applied to ``model``; a note where the bench chose
    another checkpoint file than ``checkpoint``."""
    from pnyolo.config.checks import validate
    from pnyolo.models import use_eval_stats

    given = {k: point[k] for k in POINT_KEYS if k in point and (point[k] is not None or k == "depth_gap")}
    given.update({k: point[k] for k in ("late_send", "late_keep", "late_calibration") if k in point})
    cfg = replace(cfg, eval=replace(cfg.eval, **given))
    try:  # every value a bench report hands on passes the checks the command line's and a config's pass
        validate(cfg)
    except UserError as exc:
        raise UserError(f"{where}: {exc}") from None
    if point.get("eval_stats"):
        use_eval_stats(model, cfg, point["eval_stats"])
    if point.get("checkpoint") and Path(checkpoint).name != point["checkpoint"]:
        print(f"pnyolo-eval: note: the bench chose {point['checkpoint']} for {cfg.model.kind}; this is "
              f"{Path(checkpoint).name}", file=sys.stderr)
    return cfg
