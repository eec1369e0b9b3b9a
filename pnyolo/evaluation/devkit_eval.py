"""The nuScenes devkit's own evaluations, run on an export of the split made for the purpose: ``DetectionEval``
(mAP, NDS) and ``TrackingEval`` (AMOTA, AMOTP) exactly as a paper's nuScenes table is made: one sample per frame,
class ranges measured from each sample's LIDAR_TOP ego, ground truth no sensor sees (no pseudo-LiDAR point) left
out, the detection config ``detection_cvpr_2019`` / ``tracking_nips_2019``. This is the figure to set beside a
BEVFormer or mmdetection3d table; the per-view AP of ``nuscenes_metrics`` (each scored view its own sample, our
ignore rule) is another figure and is named so::

    export = export_split("out/dataset", "test", tmp / "nuscenes")       # every lighting variant of the split
    kit = detection_eval(export, "results_nusc_test.json", "test", tmp / "kit")   # {"map", "nds", "errors", ...}

The only change to the stock configs: the classes scored are those the export holds (car, truck, bus, pedestrian:
``dataset_spec.nuscenes_format``), so a class that cannot occur does not count as an AP of 0 in the mean (over the
stock ten classes every figure would be 4/10 of these). Beside it, ``DetectionEval over car and pedestrian``: the
classes our models name, on an export whose buses and trucks are cars (as the models are trained to name them), the
config's ``class_names`` narrowed after ``config_factory`` (its ``class_range`` keeps every class: the devkit
asserts on a smaller one). Facts: ../shared/reference/FACTS.md (the devkit).
"""
from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

from dataset_spec.nuscenes_format import DETECTION_NAMES, SPLIT_NAMES, VERSION

CLASSES = sorted(set(DETECTION_NAMES.values()))  # what the export's categories are as detection names
NAMED = ["car", "pedestrian"]  # what our models name (buses and trucks are cars to them)


def available() -> bool:
    """Whether the devkit is installed (it needs numpy<2)."""
    try:
        import nuscenes.eval.detection.evaluate  # noqa: F401
    except ImportError:
        return False
    return True


def export_split(dataset_root, split: str, out: Path, variant: str | None = "all", refined: bool = True,
                 scenarios: list[str] | None = None) -> Path:
    """The nuScenes export of ``split``'s scenarios (or of ``scenarios`` of it) into ``out`` (the devkit's dataroot):
    every lighting variant, or ``variant`` (None: each scenario's first), as ``project-labels --export nuscenes
    --variant`` makes it (``refined`` False: buses and trucks as cars)."""
    from dataset_spec import Dataset
    from tools.exporters.nuscenes import export_nuscenes

    ds = Dataset.open(dataset_root)
    return export_nuscenes(ds, out, scenarios or ds.split(split), variant=variant, refined=refined)


def complete_results(doc: dict, export: Path, split: str) -> tuple[dict, int]:
    """``doc`` (nuScenes results) with every sample of ``split`` present (the devkit wants one entry a sample; a
    sample without boxes is an empty list) and only those; returns it and how many samples were added empty."""
    tokens = split_samples(export, split)
    results = {t: doc["results"].get(t, []) for t in tokens}
    return {**doc, "results": results}, sum(t not in doc["results"] for t in tokens)


def split_samples(export: Path, split: str) -> list[str]:
    """The sample tokens of ``split``'s scenes in an export (its VERSION/splits.json and tables)."""
    names = set(json.loads((export / VERSION / "splits.json").read_text())[SPLIT_NAMES[split]])
    scenes = {s["token"] for s in json.loads((export / VERSION / "scene.json").read_text()) if s["name"] in names}
    return [s["token"] for s in json.loads((export / VERSION / "sample.json").read_text()) if s["scene_token"] in scenes]


def detection_eval(export: Path, results: Path, split: str, out: Path, classes: list[str] = CLASSES) -> dict:
    """``DetectionEval`` on the export over ``classes``: mAP, NDS, the true-positive errors, AP per class and
    distance threshold, and per threshold the mean over the classes."""
    from nuscenes.eval.detection.config import config_factory
    from nuscenes.eval.detection.evaluate import DetectionEval
    from nuscenes.nuscenes import NuScenes

    cfg = config_factory("detection_cvpr_2019")
    cfg.class_names = list(classes)  # narrowed after the factory: class_range keeps every class (the docstring)
    with contextlib.redirect_stdout(io.StringIO()):  # the devkit prints as it goes
        nusc = NuScenes(version=VERSION, dataroot=str(export), verbose=False)
        metrics, _ = DetectionEval(nusc, cfg, str(results), SPLIT_NAMES[split], str(out), verbose=False).evaluate()
    s = _finite(metrics.serialize())
    aps = s["label_aps"]
    by_distance = {d: _mean([aps[c][d] for c in classes if aps.get(c, {}).get(d) is not None])
                   for d in sorted({d for c in classes for d in aps.get(c, {})}, key=float)}
    return {"map": s["mean_ap"], "nds": s["nd_score"], "errors": s["tp_errors"], "ap": aps, "ap_by_distance": by_distance,
            "classes": list(classes), "config": "detection_cvpr_2019", "eval_set": SPLIT_NAMES[split]}


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


def tracking_eval(export: Path, results: Path, split: str, out: Path, classes: list[str] = CLASSES) -> dict:
    """``TrackingEval`` on the export over ``classes``: AMOTA, AMOTP and the rest of its summary, per class too."""
    from nuscenes.eval.common.config import config_factory
    from nuscenes.eval.tracking.evaluate import TrackingEval

    cfg = config_factory("tracking_nips_2019")
    cfg.class_names = [c for c in cfg.tracking_names if c in classes]
    cfg.tracking_names = cfg.class_names
    with contextlib.redirect_stdout(io.StringIO()):
        metrics, _ = TrackingEval(cfg, str(results), SPLIT_NAMES[split], str(out), VERSION, str(export),
                                  verbose=False).evaluate()
    s = _finite(metrics.serialize())
    return {"amota": s["amota"], "amotp": s["amotp"], "mota": s.get("mota"), "motp": s.get("motp"),
            "label_metrics": s.get("label_metrics"), "classes": cfg.class_names, "config": "tracking_nips_2019",
            "eval_set": SPLIT_NAMES[split]}


def _finite(value):
    """The devkit's serialised figures with NaN (nothing to measure) as None, as JSON holds them."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return None if isinstance(value, float) and value != value else value


def devkit_detection(dataset_root, split: str, doc: dict, out: Path, variant: str | None = "all") -> dict:
    """``detection_eval`` of nuScenes results ``doc`` on ``split`` (its ``variant`` lighting, as ``export_split``):
    the split exported to a temporary folder, the results completed with every sample (``complete_results``) and
    kept as ``out/results_nusc_SPLIT.json``."""
    import tempfile

    from dataset_spec.atomic import atomic_write_json

    if not any(doc["results"].values()):  # the devkit's filters need one box to know the box type
        return {"map": None, "nds": None, "skipped": "no boxes: DetectionEval cannot score an empty results file"}
    with tempfile.TemporaryDirectory(prefix="devkit-") as tmp:
        export = export_split(dataset_root, split, Path(tmp) / "nuscenes", variant)
        doc, empty = complete_results(doc, export, split)
        path = Path(out) / f"results_nusc_{split}.json"
        atomic_write_json(path, doc)
        figures = detection_eval(export, path, split, Path(tmp) / "kit")
        named = export_split(dataset_root, split, Path(tmp) / "named", variant, refined=False)  # the same samples
        figures["car_pedestrian"] = {**detection_eval(named, path, split, Path(tmp) / "kit_named", NAMED),
                                     "buses_and_trucks": "as cars"}
    return {**figures, "results": path.name, "samples_without_results": empty}


def tracking_results(sequences: dict, keys: dict[str, tuple[str, str]], class_names: list[str], ds) -> dict:
    """nuScenes tracking results of track rows: ``sequences`` name -> (ground truth, [TrackRow]), ``keys`` name ->
    (scenario, lighting variant); a box a row, on the ground (size 1 m: the devkit matches by centre distance), in
    the global frame of ``ds``'s export."""
    from dataset_spec.nuscenes_format import GlobalFrames, sample_token

    rows: dict[str, list] = {}
    frames = GlobalFrames(ds)
    for name, (_, tracks) in sequences.items():
        scenario, variant = keys[name]
        ox, oy, _ = (float(v) for v in frames(scenario))
        for r in tracks:
            token = sample_token(scenario, variant, r.frame)
            rows.setdefault(token, []).append({
                "sample_token": token, "translation": [float(r.x) + ox, float(r.y) + oy, 0.0], "size": [1.0, 1.0, 1.0],
                "rotation": [1.0, 0.0, 0.0, 0.0], "velocity": [float(r.vx), float(r.vy)],
                "tracking_id": f"{name}/{r.track}", "tracking_name": class_names[r.cls],
                "tracking_score": float(r.score)})
    return {"meta": {"use_camera": True, "use_lidar": False, "use_radar": False, "use_map": False,
                     "use_external": False}, "results": rows}


def devkit_tracking_eval(dataset_root, split: str, doc: dict, out: Path, variant: str | None,
                         scenarios: list[str] | None = None) -> dict:
    """``tracking_eval`` of tracking results ``doc`` on ``split`` (its ``variant`` lighting, as ``export_split``; only
    ``scenarios`` of it where given: the sequences tracked), the results completed with every sample and kept as
    ``out/results_nusc_tracking_SPLIT.json``."""
    import tempfile

    from dataset_spec.atomic import atomic_write_json

    if not any(doc["results"].values()):
        return {"amota": None, "amotp": None, "skipped": "no boxes: TrackingEval cannot score an empty results file"}
    with tempfile.TemporaryDirectory(prefix="devkit-") as tmp:
        export = export_split(dataset_root, split, Path(tmp) / "nuscenes", variant, scenarios=scenarios)
        doc, empty = complete_results(doc, export, split)
        path = Path(out) / f"results_nusc_tracking_{split}.json"
        atomic_write_json(path, doc)
        figures = tracking_eval(export, path, split, Path(tmp) / "kit")
        named = export_split(dataset_root, split, Path(tmp) / "named", variant, refined=False, scenarios=scenarios)
        figures["car_pedestrian"] = {**tracking_eval(named, path, split, Path(tmp) / "kit_named", NAMED),
                                     "buses_and_trucks": "as cars"}
    return {**figures, "results": path.name, "samples_without_results": empty}
