"""Tracks scored by the nuScenes devkit's tracking algorithm (nuscenes-devkit 1.2.0, ``tracking_nips_2019``): AMOTA
and AMOTP (Weng et al. 2019: MOTAR and MOTP averaged over 40 recall thresholds, a threshold not reached counting
the worst value), by its own ``TrackingEvaluation`` on our sequences, beside motmetrics' MOTA / IDF1
(``scoring``)::

    classes = sequence_classes(ds, sequences)                  # sequence -> {actor id: class index}
    figures = per_view_tracking(sequences, classes, ["car", "pedestrian"])   # {"amota", "amotp", "classes": {...}}

A match is the devkit's: ground-plane centre distance within 2 m (not motmetrics' 1 m of ``scoring``). Each
sequence is one devkit scene, each frame one timestamp; the devkit's loaders (nuScenes' own scene splits, LiDAR
point filters) do not apply, so its ``TrackingBox`` lists are built here from our ground truth and track rows.
"""
from __future__ import annotations

import contextlib
import io

import numpy as np

from pnyolo.tracking.scoring import GroundTruth
from pnyolo.decoding.ground_tracker import TrackRow


def _kit():
    """The devkit's tracking pieces, or None where it is not installed (it needs numpy<2)."""
    try:
        from nuscenes.eval.common.config import config_factory
        from nuscenes.eval.tracking.algo import TrackingEvaluation
        from nuscenes.eval.tracking.constants import AVG_METRIC_MAP
        from nuscenes.eval.tracking.data_classes import TrackingBox
    except ImportError:
        return None
    cfg = config_factory("tracking_nips_2019")  # also tells TrackingBox the tracking names it accepts
    return cfg, TrackingEvaluation, TrackingBox, AVG_METRIC_MAP


def _box(kit_box, sample: str, xy, track: int, name: str, score: float = -1.0):
    return kit_box(sample_token=sample, translation=(float(xy[0]), float(xy[1]), 0.0), size=(1.0, 1.0, 1.0),
                   rotation=(1.0, 0.0, 0.0, 0.0), tracking_id=str(track), tracking_name=name,
                   tracking_score=float(score))


def _tracks(kit_box, sequences, classes, class_names: list[str], tracked: list[str]):
    """(ground-truth tracks, predicted tracks) of the classes ``tracked``: scene -> frame -> [TrackingBox], every
    frame in both."""
    gt_tracks, pred_tracks = {}, {}
    for seq, (gt, rows) in sequences.items():
        by_frame: dict[int, list[TrackRow]] = {}
        for r in rows:
            by_frame.setdefault(r.frame, []).append(r)
        g, p = {}, {}
        for frame, (ids, xy) in sorted(gt.items()):
            sample = f"{seq}/{frame}"
            g[frame] = [_box(kit_box, sample, xy[k], i, class_names[classes[seq][i]]) for k, i in enumerate(ids)
                        if class_names[classes[seq][i]] in tracked]
            p[frame] = [_box(kit_box, sample, (r.x, r.y), r.track, class_names[r.cls], r.score)
                        for r in by_frame.get(frame, []) if class_names[r.cls] in tracked]
        gt_tracks[seq], pred_tracks[seq] = g, p
    return gt_tracks, pred_tracks


def per_view_tracking(sequences: dict[str, tuple[GroundTruth, list[TrackRow]]], classes: dict[str, dict[int, int]],
                    class_names: list[str]) -> dict | None:
    """AMOTA and AMOTP per class with ground truth and their means (None: the devkit is not installed).
    ``classes``: per sequence, each ground-truth track id's class index into ``class_names``."""
    kit = _kit()
    if kit is None:
        return None
    cfg, evaluation, kit_box, avg = kit
    gt_tracks, pred_tracks = _tracks(kit_box, sequences, classes, class_names, cfg.tracking_names)
    per_class = {}
    for name in class_names:
        if name not in cfg.tracking_names:
            continue
        ev = evaluation(gt_tracks, pred_tracks, name, cfg.dist_fcn_callable, cfg.dist_th_tp, cfg.min_recall,
                        cfg.num_thresholds, cfg.metric_worst, verbose=False)
        with contextlib.redirect_stdout(io.StringIO()):  # the devkit prints as it goes
            md = ev.accumulate()
        figures = {}
        for metric, per_threshold in avg.items():
            values = np.array(md.get_metric(per_threshold), dtype=np.float64)
            if np.all(np.isnan(values)):
                break  # no ground truth of this class
            values[np.isnan(values)] = cfg.metric_worst[metric]  # a recall threshold not reached: the worst
            figures[metric] = float(np.mean(values))
        if figures:
            per_class[name] = figures
    mean = {m: float(np.mean([f[m] for f in per_class.values()])) if per_class else None for m in avg}
    return {**mean, "threshold_m": float(cfg.dist_th_tp), "classes": per_class}
