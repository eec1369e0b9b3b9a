"""A model's tracks over the sequences of a split (shared by ``pnyolo-track`` and the benchmark).

    preds = predict(model, dataset, cfg.eval)                                 # pnyolo.engine.predict
    sequences = track_split(preds, dataset, cfg.eval, TrackerPoint())         # name -> (ground truth, rows)
    summary = score_tracks(sequences)                                         # pnyolo.tracking.scoring

Each frame's detections are those of every camera of the rig: the model's predictions of each item of the
frame (a dataset with ``every_camera``: each camera scored once, the others its source views) scoring at least the
tracker's ``keep`` (the tracker has an operating point of its own, ``TrackerPoint``), with the items'
3D detections merged (one per road user within ``eval.centre_nms_m``), or with ``late_fusion`` (own-view
predictions) every car's own-view detections pooled as late fusion pools them (``late_fusion.pool_cars``: by
agreement when ``eval.late_keep`` is set).
"""
from __future__ import annotations

from dataset_spec.names import JoinedNames
from pnyolo.cooperation.calibration import calibrated
from pnyolo.cooperation.late_fusion import car_id, pool_cars, send_threshold
from pnyolo.tracking.scoring import GroundTruth, ground_truth_tracks
from pnyolo.decoding.ground_tracker import GroundTracker, TrackerPoint, TrackRow


def track_sequence(preds, dataset, sequence: tuple[str, str], ev, point: TrackerPoint,
                   late_fusion: bool = False) -> list[TrackRow]:
    """One sequence's tracks, ``sequence`` = (scenario, lighting variant): each frame's world detections (every
    item of the frame, from ``preds``, the predictions of ``dataset``, from ``point.keep`` up) into a
    ``GroundTracker`` at ``point``."""
    scenario, variant = sequence
    tracker = GroundTracker(dataset.ds.scenario(scenario).fps or 1.0, point)
    by_frame: dict[int, list[int]] = {}  # the sequence's items, by frame (one pass over the dataset)
    for k, key in enumerate(dataset.items):
        if (key.scenario, key.variant) == (scenario, variant):
            by_frame.setdefault(key.frame, []).append(k)
    for frame in dataset.ds.frames(scenario):
        found, owners = [], []
        for k in by_frame.get(frame, []):
            item = preds.items[k].item
            dets = preds.world_at(k, ev, send_threshold(ev) if late_fusion else point.keep)
            found += calibrated(dets, item, ev.late_calibration) if late_fusion else dets
            owners += [car_id(item, b) for b in range(len(found) - len(owners))]
        tracker.step(frame, pool_cars(found, owners, ev.centre_nms_m, ev.late_keep if late_fusion else None))
    return tracker.rows()


def track_split(preds, dataset, ev, point: TrackerPoint, late_fusion: bool = False,
                variants: dict[str, set[str]] | None = None, progress=None) -> dict[str, tuple[GroundTruth, list[TrackRow]]]:
    """Every (scenario, lighting variant) of ``dataset`` (``preds``: a model's predictions of its items, own-view
    ones for ``late_fusion``; those of ``variants``: scenario -> names; None: each
    scenario's first) tracked at ``point``: ``"SCENARIO__VARIANT"`` -> (ground truth, track rows); ``progress``
    wraps the sequences (e.g. tqdm)."""
    if variants is None:
        variants = {s: {dataset.ds.scenario(s).lighting[0].name} for s in dataset.scenarios}
    keys = sorted({(k.scenario, k.variant) for k in dataset.items if k.variant in variants.get(k.scenario, ())})
    out, joined = {}, JoinedNames("tracked sequence")
    for scenario, variant in (progress(keys) if progress else keys):
        rows = track_sequence(preds, dataset, (scenario, variant), ev, point, late_fusion)
        out[joined(scenario, variant)] = (ground_truth_tracks(dataset.ds, scenario, dataset.class_names), rows)
    return out


def sequence_classes(dataset, sequences: dict) -> dict[str, dict[int, int]]:
    """Per sequence of ``track_split``, each road user's actor id (its track id) -> its class index."""
    out, scenario_of = {}, {f"{k.scenario}__{k.variant}": k.scenario for k in dataset.items}
    for name in sequences:
        scn = dataset.ds.scenario(scenario_of[name])
        out[name] = {a.id: dataset.class_names.index(a.cls) for a in scn.actors if a.cls in dataset.class_names}
    return out
