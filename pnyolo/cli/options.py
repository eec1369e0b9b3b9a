"""Options the evaluation, tracking and prediction commands share: ``--device`` and ``--quiet``, ``--views``,
thresholds checked against the config's ranges, and options a model kind cannot use refused for that kind."""
from __future__ import annotations

import math

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt
from pnyolo.config.checks import RANGES


def add_run_options(p, quiet: str = "no progress bar") -> None:
    """``--device`` (where the model runs) and ``--quiet`` (``quiet``: what it leaves out), as every command
    that runs a model has them."""
    p.add_argument("--device", default="auto",
                   help="where the model runs: auto (a GPU when there is one) | cpu | cuda[:N] (default auto)")
    p.add_argument("--quiet", action="store_true", help=quiet)


def check_threshold(value: float | None, key: str, option: str) -> None:
    """``--conf`` and the like: the range of config key ``key`` (NaN refused), one line naming ``option``."""
    if value is not None and value not in RANGES[key]:
        raise UserError(f"{option} must be {RANGES[key]}, got {value}")


def check_metres(value: float | None, option: str) -> None:
    """A distance option: a finite number > 0 (NaN and infinity refused)."""
    if value is not None and not (value > 0 and math.isfinite(value)):
        raise UserError(f"{option} must be a number of metres > 0, got {value}")


def refuse_for_kind(model, nms_iou=None, depth_gap=None, norm_stats=None) -> None:
    """Options given (not None) that ``model``'s kind cannot use, refused in one line naming why."""
    kind, tuned = model.kind, type(model).tuned
    if depth_gap is not None and "depth_gap" not in tuned:
        raise UserError(f"--depth-gap: {kind} estimates no distances along its boxes to gate NMS by")
    if nms_iou is not None and "nms_iou" not in tuned:
        raise UserError(f"--nms-iou: {kind} is not decoded by 2D NMS (its detections are merged in the world, "
                        "eval.centre_nms_m)")
    if norm_stats is not None and getattr(model, "encoder", None) is None:
        raise UserError(f"--norm-stats: {kind} has no image encoder whose batch-norm statistics to choose")


def parse_views(text: str | None) -> list[int] | None:
    """``--views 0,1,2`` -> [0, 1, 2]; one-line errors for anything but distinct indices >= 0."""
    if text is None:
        return None
    try:
        views = [int(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise UserError(f"--views {text!r}: expected camera indices like 0,1,2") from None
    if not views or min(views) < 0:
        raise UserError(f"--views {text!r}: expected camera indices >= 0 like 0,1,2")
    if len(set(views)) != len(views):
        raise UserError(f"--views {text}: indices must be distinct")
    return views


def _mapping(value) -> dict:
    """``value`` where it is a mapping, else an empty one (a report from someone else may hold anything)."""
    return value if isinstance(value, dict) else {}


LATE_RULES = ("best-car", "agreement", "calibrated")  # late fusion's rules, as the bench chooses among them


def parse_late_rule(text: str | None, kind: str) -> dict | None:
    """``--late-rule``: the late-fusion rule as the config's eval keys (late_send, late_keep, late_calibration) and,
    from a bench run, that kind's chosen operating point too: ``best-car[:SEND]``, ``agreement:SEND,KEEP``,
    ``calibrated:SEND,KEEP,A,B,C`` or ``from:REPORT.json`` (a pnyolo-bench report, or its run folder: the rule and
    operating point it chose on validation for ``kind``). None: the checkpoint's own."""
    if text is None:
        return None
    rule, _, rest = text.partition(":")
    if rule == "from":
        return _bench_late_rule(rest, kind)
    if rule not in LATE_RULES:
        raise UserError(f"--late-rule {excerpt(text)}: one of {', '.join(LATE_RULES)} (with :numbers) or from:REPORT.json")
    try:
        numbers = [float(v) for v in rest.split(",")] if rest else []
    except ValueError:
        raise UserError(f"--late-rule {excerpt(text)}: numbers after the colon, comma-separated") from None
    wanted = {"best-car": (0, 1), "agreement": (2,), "calibrated": (5,)}[rule]
    if len(numbers) not in wanted or not all(math.isfinite(v) for v in numbers) or \
            not all(0 <= v <= 1 for v in numbers[:2]):
        raise UserError(f"--late-rule {excerpt(text)}: {rule} takes " + {
            "best-car": "an optional send score (best-car:0.45)", "agreement": "send and keep scores (agreement:0.3,0.6)",
            "calibrated": "send and keep scores and the calibration a, b, c (calibrated:0.3,0.6,1.1,-0.2,0.4)"}[rule])
    return {"late_send": numbers[0] if numbers else None, "late_keep": numbers[1] if rule != "best-car" else None,
            "late_calibration": numbers[2:] if rule == "calibrated" else None}


def _bench_late_rule(path_text: str, kind: str) -> dict:
    """The rule and the operating point a pnyolo-bench run chose on validation for ``kind``'s late fusion."""
    from pnyolo.cli.points import bench_point, bench_rows

    path, rows = read = bench_rows(path_text, "--late-rule from:")
    late = _mapping(rows.get(f"{kind}, late fusion")).get("late_fusion_selection")
    if not isinstance(late, dict):
        raise UserError(f"--late-rule from:{path}: that run chose no late-fusion rule for {kind}")
    best_car = late.get("rule") == "best car"
    return {"late_send": late.get("send"), "late_keep": None if best_car else late.get("keep"),
            "late_calibration": late.get("calibration"), **bench_point(path_text, kind, "--late-rule from:", read)}
