"""Tracks scored the field's way with ``motmetrics`` (CLEAR MOT and IDF1) on the ground plane: a track
matches a road user whose centre lies within ``threshold_m`` (1 m, Wildtrack's convention).

    gt = ground_truth_tracks(ds, "intersection_07", class_names)    # frame -> (ids, (N, 2) centres)
    rows = as_written(rows)                                          # positions as mot_lines writes them
    summary = score_tracks({"intersection_07": (gt, rows)})          # mota, motp (m), idf1, switches, ...
    text = mot_lines(rows)                                           # what anyone re-scores gets the same figures
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from dataset_spec import Dataset
from pnyolo.decoding.ground_tracker import TrackRow

THRESHOLD_M = 1.0
METRICS = ["mota", "motp", "idf1", "num_switches", "num_false_positives", "num_misses", "num_objects",
           "mostly_tracked", "mostly_lost", "num_unique_objects", "idtp", "idfp", "idfn"]
SUMS = ("num_objects", "num_misses", "num_false_positives", "num_switches", "idtp", "idfp", "idfn")

GroundTruth = dict[int, tuple[list[int], np.ndarray]]  # frame -> (track ids, (N, 2) centres)


def mot_lines(rows: list[TrackRow]) -> str:
    """MOTChallenge rows of tracks on the ground: frame from 1, track id, -1 x4 (no box), score, world x, y (m, to
    1 micrometre), 0."""
    return "".join(f"{r.frame + 1},{r.track},-1,-1,-1,-1,{r.score:.4f},{r.x:.6f},{r.y:.6f},0\n" for r in rows)


def as_written(rows: list[TrackRow]) -> list[TrackRow]:
    """``rows`` with their positions as ``mot_lines`` writes them, so figures scored on them are those anyone
    recomputes from the file."""
    return [replace(r, x=float(f"{r.x:.6f}"), y=float(f"{r.y:.6f}")) for r in rows]


def ground_truth_tracks(ds: Dataset, scenario: str, class_names: list[str]) -> GroundTruth:
    """Each frame's road users of ``class_names`` that are ground truth in at least one camera then (a label
    the thresholds keep), with their ground centres; the actor id is the track id."""
    out = {}
    for frame in ds.frames(scenario):
        scn = ds.scenario_at(scenario, frame)
        kept = {o.instance_id for cam in scn.cameras for o in ds.read_labels(scenario, cam.name, frame).kept()}
        actors = sorted((a for a in scn.actors if a.cls in class_names and a.id in kept), key=lambda a: a.id)
        out[frame] = ([a.id for a in actors], np.array([a.box.center[:2] for a in actors]).reshape(-1, 2))
    return out


def accumulate(gt: GroundTruth, rows: list[TrackRow], threshold_m: float = THRESHOLD_M):
    """A ``motmetrics.MOTAccumulator`` of one sequence: per frame, ground-plane distances (NaN beyond
    ``threshold_m``: no match)."""
    import motmetrics as mm

    acc = mm.MOTAccumulator(auto_id=False)
    by_frame: dict[int, list[TrackRow]] = {}
    for r in rows:
        by_frame.setdefault(r.frame, []).append(r)
    for frame, (ids, xy) in sorted(gt.items()):
        hyp = by_frame.get(frame, [])
        h_xy = np.array([[r.x, r.y] for r in hyp]).reshape(-1, 2)
        dist = np.linalg.norm(xy[:, None, :] - h_xy[None, :, :], axis=2) if len(xy) and len(h_xy) else \
            np.zeros((len(xy), len(h_xy)))
        dist = np.where(dist <= threshold_m, dist, np.nan)
        acc.update(list(ids), [r.track for r in hyp], dist, frameid=frame)
    return acc


def score_tracks(sequences: dict[str, tuple[GroundTruth, list[TrackRow]]], threshold_m: float = THRESHOLD_M) -> dict:
    """Per sequence and overall (every sequence's frames together): MOTA, MOTP (mean matched distance, m),
    IDF1, id switches, false positives, misses, objects, mostly tracked / lost."""
    import motmetrics as mm

    names = sorted(sequences)
    accs = [accumulate(*sequences[n], threshold_m) for n in names]
    host = mm.metrics.create()
    table = host.compute_many(accs, metrics=METRICS, names=names, generate_overall=True)
    return {name: {m: _plain(m, table.loc[name, m]) for m in METRICS} for name in table.index}


def _plain(metric: str, value):
    """A figure as JSON: counts as integers, rates as floats, NaN (nothing to measure) as None."""
    value = float(value)
    if np.isnan(value):
        return None
    return int(value) if metric.startswith(("num_", "mostly_")) else value


def _rates(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MOTA and IDF1 of (..., SUMS) summed counts."""
    objects, misses, fps, switches, idtp, idfp, idfn = (sums[..., k] for k in range(len(SUMS)))
    mota = 1 - (misses + fps + switches) / np.maximum(objects, 1)
    idf1 = 2 * idtp / np.maximum(2 * idtp + idfp + idfn, 1)
    return mota, idf1


def track_errors(rows: dict[str, dict], minus: dict[str, dict] | None = None) -> dict:
    """Bootstrap standard errors of MOTA and IDF1 over the sequences of ``score_tracks``' per-sequence ``rows``
    (names ``SCENARIO__VARIANT``), layouts resampled (``pnyolo.evaluation.bootstrap``); with ``minus`` (another
    tracker's rows of the same sequences) the difference's, paired, and the difference itself. None where the
    sequences come from one layout."""
    from pnyolo.evaluation.bootstrap import draws_of, layout_groups, layout_sums

    names = sorted(n for n in rows if n != "OVERALL")
    groups = layout_groups([n.split("__")[0] for n in names])

    def counts(table: dict) -> np.ndarray:
        return layout_sums(np.array([[float(table[n][k] or 0) for k in SUMS] for n in names]).reshape(-1, len(SUMS)),
                           groups)

    a = counts(rows)
    b = counts(minus) if minus is not None else None
    whole = [_rates(x.sum(axis=0)) for x in ([a] if b is None else [a, b])]
    out = {"layouts": len(groups), "mota": None, "idf1": None}
    if b is not None:
        out.update(mota_difference=float(whole[0][0] - whole[1][0]), idf1_difference=float(whole[0][1] - whole[1][1]))
    if len(groups) < 2:
        return out
    idx = draws_of(len(groups))
    drawn = [_rates(x[idx].sum(axis=1)) for x in ([a] if b is None else [a, b])]
    mota, idf1 = drawn[0] if b is None else (drawn[0][0] - drawn[1][0], drawn[0][1] - drawn[1][1])
    out.update(mota=float(np.std(mota, ddof=1)), idf1=float(np.std(idf1, ddof=1)))
    return out
