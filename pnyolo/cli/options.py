"""Options the evaluation, tracking and prediction commands share: ``--device`` and ``--quiet``, ``--views``,
thresholds checked against the config's ranges, and options a model kind cannot use refused for that kind."""
from __future__ import annotations

import math

from dataset_spec.cli_support import UserError
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
