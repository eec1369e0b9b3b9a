"""Training logs: ``log.jsonl`` (one JSON record per step and event) and ``epochs.csv`` (one row per epoch).

A resumed run continues from its checkpoint, so ``truncate_logs`` first drops what the interrupted
run logged after it (those steps are redone) and the log marks the resume with an event.
"""
from __future__ import annotations

import csv
import io
import json
import shutil
from pathlib import Path

from dataset_spec.atomic import append_text, atomic_write_text, exists
from dataset_spec.cli_support import UserError

# What a training run writes into its folder (pnyolo.training.train).
RUN_FILES = ("latest.pt", "best.pt", "log.jsonl", "epochs.csv", "config.yaml")
RUN_GLOBS = ("epoch_*.pt",)
RUN_DIRS = ("vis", "tensorboard")


class JsonlLog:
    """A run's ``log.jsonl``, appended record by record; every append checks it is still the file the first one
    wrote (``append_text``: no link planted, nothing put in its place while the run goes on)."""

    def __init__(self, path: Path):
        self.path, self.identity = path, None

    def write(self, record: dict) -> None:
        self.identity = append_text(self.path, json.dumps(record, default=float) + "\n", self.identity)


def append_csv(path: Path, row: dict) -> None:
    text = io.StringIO()
    w = csv.DictWriter(text, fieldnames=list(row))
    if not exists(path):
        w.writeheader()
    w.writerow(row)
    append_text(path, text.getvalue())


def run_outputs(out: Path) -> list[Path]:
    """The files and folders of a training run in ``out`` (empty: none)."""
    found = [out / n for n in (*RUN_FILES, *RUN_DIRS) if exists(out / n)]  # a dangling link counts
    return found + sorted(p for g in RUN_GLOBS for p in out.glob(g))


def clear_run(out: Path) -> None:
    """Delete a training run's outputs from ``out`` (``pnyolo-train --force``); other files stay."""
    for path in run_outputs(out):
        shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()


def truncate_logs(out: Path, step: int, epoch: int) -> None:
    """Keep the log records up to ``step`` and the epoch rows up to ``epoch`` (rewritten atomically)."""
    log = out / "log.jsonl"
    for path in (log, out / "epochs.csv"):
        if path.is_symlink():  # a planted link: never read its target into the run's log
            raise UserError(f"--resume: {path} is a link; a run's logs are its own files")
    if log.is_file():
        try:
            kept = [line for line in log.read_text(encoding="utf-8").splitlines()
                    if line.strip() and json.loads(line).get("step", 0) <= step]
        except (ValueError, AttributeError, TypeError):
            raise UserError(f"--resume: {log} is not a log this run wrote (a line is not a JSON record)") from None
        atomic_write_text(log, "".join(line + "\n" for line in kept))
    table = out / "epochs.csv"
    if table.is_file():
        rows = list(csv.DictReader(io.StringIO(table.read_text(encoding="utf-8"))))
        rows = [r for r in rows if int(r["epoch"]) <= epoch]
        if not rows:
            table.unlink()  # append_csv writes the header again with the first row
            return
        text = io.StringIO()
        w = csv.DictWriter(text, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
        atomic_write_text(table, text.getvalue())


class TensorBoardLog:
    """TensorBoard event files of a training run (``train.tensorboard``), as nerfstudio's and
    Ultralytics' users read them: ``tensorboard --logdir runs/``.

    Scalars ``loss/*`` (every term and the total), ``train/lr``, ``train/step_seconds``,
    ``val/f1@IOU`` for every match IoU, ``val/ap50``, ``val/recall/GROUP``; pictures ``val/ITEM`` of
    a few validation items with their detections. A resumed run passes ``purge_step``: the events the
    interrupted run wrote after its checkpoint are dropped, so the curves continue without repeats.
    """

    def __init__(self, folder: Path, purge_step: int | None = None):
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            from dataset_spec.cli_support import UserError

            raise UserError("train.tensorboard needs the tensorboard package (pip install tensorboard), or set "
                            "train.tensorboard: false") from None
        self.writer = SummaryWriter(log_dir=str(folder), purge_step=purge_step)

    def step(self, step: int, loss: float, terms: dict[str, float], lr: float, seconds: float) -> None:
        self.writer.add_scalar("loss/total", loss, step)
        for name, value in terms.items():
            self.writer.add_scalar(f"loss/{name}", value, step)
        self.writer.add_scalar("train/lr", lr, step)
        self.writer.add_scalar("train/step_seconds", seconds, step)

    def validation(self, step: int, summary: dict, recall_iou: float) -> None:
        for iou, m in summary["strict"].items():
            self.writer.add_scalar(f"val/f1@{iou}", m["f1"], step)
        self.writer.add_scalar("val/ap50", summary["ap50"], step)
        for group, r in summary["recall_by_visibility"].get(f"{recall_iou:.1f}", {}).items():
            self.writer.add_scalar(f"val/recall/{group}", r["recall"], step)

    def picture(self, step: int, tag: str, image) -> None:
        """``image`` (H, W, 3) uint8 RGB."""
        self.writer.add_image(tag, image, step, dataformats="HWC")

    def close(self) -> None:
        self.writer.flush()
        self.writer.close()
