"""A preset's targets on the 3D state and the tracks (issues 87 and 88), judged for every model with 3D detections:
the devkit's DetectionEval over car and pedestrian (NDS, mAP, AP at a distance, the mean true-positive errors), the
ground plane (MODA, AP within 1 m) and the tracks (TrackingEval AMOTA over car and pedestrian, MOTA, IDF1)::

    state_targets: {nds: 0.40, car_ap_0.5: 0.35, pedestrian_ap_1: 0.25, mate: 0.45, amota: 0.30, mota: 0.3}

A name is one of ``NAMES`` or ``CLASS_ap_D`` (CLASS car or pedestrian, D a devkit distance: 0.5, 1, 2, 4). The true-
positive errors are "at most", every other figure "at least". Where a figure has a standard error (MOTA, IDF1) the
target passes only beyond it by one (``targets.RULE``); the devkit's figures carry none, and the line says so.
"""
from __future__ import annotations

import re

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt
from pnyolo.evaluation.metrics_3d import ground_ap

# name -> (what the line says, "at least" or "at most")
NAMES = {"nds": ("DetectionEval NDS (car, pedestrian)", "at least"),
         "map": ("DetectionEval mAP (car, pedestrian)", "at least"),
         "mate": ("DetectionEval mATE, m (car, pedestrian)", "at most"),
         "mase": ("DetectionEval mASE (car, pedestrian)", "at most"),
         "maoe": ("DetectionEval mAOE, rad (car, pedestrian)", "at most"),
         "mave": ("DetectionEval mAVE, m/s (car, pedestrian)", "at most"),
         "maae": ("DetectionEval mAAE (car, pedestrian)", "at most"),
         "moda": ("MODA on the ground plane", "at least"),
         "ground_ap_1": ("ground-plane AP within 1 m (per view)", "at least"),
         "amota": ("TrackingEval AMOTA (car, pedestrian)", "at least"),
         "mota": ("MOTA of its tracks", "at least"),
         "idf1": ("IDF1 of its tracks", "at least")}
AP_NAME = re.compile(r"(car|pedestrian)_ap_(0\.5|1|2|4)")
ERRORS = {"mate": "trans_err", "mase": "scale_err", "maoe": "orient_err", "mave": "vel_err", "maae": "attr_err"}


def check_state_targets(value, where: str) -> dict[str, float]:
    """A preset's ``state_targets``: names of ``NAMES`` or ``CLASS_ap_D`` to finite numbers (one-line errors)."""
    if not isinstance(value, dict):
        raise UserError(f"{where}: state_targets: a mapping of figure names to targets, got {excerpt(value)}")
    for name, target in value.items():
        if not isinstance(name, str) or not (name in NAMES or AP_NAME.fullmatch(name)):
            raise UserError(f"{where}: state_targets: unknown figure {excerpt(name)} (known: {', '.join(NAMES)}, "
                            "car_ap_D, pedestrian_ap_D with D 0.5, 1, 2 or 4)")
        if isinstance(target, bool) or not isinstance(target, (int, float)) or target != target or abs(target) > 1e6:
            raise UserError(f"{where}: state_targets.{name}: a number, got {excerpt(target)}")
    return {k: float(v) for k, v in value.items()}


def _distance_ap(aps: dict, cls: str, d: str) -> float | None:
    """The devkit's AP of ``cls`` at distance ``d`` (its keys floats in memory, strings once through JSON)."""
    for key, value in (aps.get(cls) or {}).items():
        if float(key) == float(d):
            return value
    return None


def figure(name: str, metrics: dict, tracking: dict | None) -> tuple[float | None, float | None, int | None]:
    """(value, standard error, layouts) of a state target's figure for one row (its test ``metrics`` and tracks)."""
    kit = (metrics.get("devkit_detection_eval") or {}).get("car_pedestrian") or {}
    m3 = metrics.get("3d") or {}
    tracks = tracking or {}
    se = tracks.get("standard_errors") or {}
    if name in ("nds", "map"):
        return kit.get(name), None, None
    if name in ERRORS:
        return (kit.get("errors") or {}).get(ERRORS[name]), None, None
    if name == "moda":
        return m3.get("moda"), None, None
    if name == "ground_ap_1":
        return ground_ap(m3), None, None
    if name == "amota":
        return ((tracks.get("devkit_tracking_eval") or {}).get("car_pedestrian") or {}).get("amota"), None, None
    if name in ("mota", "idf1"):
        return tracks.get(name), se.get(name), se.get("layouts")
    cls, d = AP_NAME.fullmatch(name).groups()
    return _distance_ap(kit.get("ap") or {}, cls, d), None, None


def state_lines(kind: str, metrics: dict, tracking: dict | None, targets: dict[str, float]
                ) -> dict[str, tuple[bool | None, str]]:
    """{target line: (PASS / FAIL / None when not measured, its figure)} of one row with 3D detections."""
    out = {}
    for name, target in targets.items():
        label, way = NAMES.get(name, (f"DetectionEval {name.replace('_ap_', ' AP within ')} m", "at least"))
        value, se, layouts = figure(name, metrics, tracking)
        if value is None:
            ok = None
        elif way == "at least":
            ok = value - (se or 0.0) >= target
        else:
            ok = value + (se or 0.0) <= target
        spread = f" ± {se:.3f}" if se is not None else (" (n/a: one layout)" if layouts == 1 else
                                                        "" if value is None else
                                                        " (the devkit's figure: no standard error)" if "Eval" in label
                                                        else " (no standard error measured)")
        sign = ">=" if way == "at least" else "<="
        out[f"{kind}: {label} {sign} {target:g}"] = (
            ok, "n/a (not measured)" if value is None else f"{value:.3f}{spread} (target {sign} {target:g})")
    return out
