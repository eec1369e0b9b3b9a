"""The tracker's operating point, chosen on validation separately from the detection F1 point: the point of a grid
(``GRID``: start, keep, confirm, end) whose tracks score the highest AMOTA on the validation sequences, by the
nuScenes devkit's own TrackingEval on an export of the validation split (by its tracking algorithm on our
sequences where the devkit is missing). MOTA and IDF1 are then reported at the chosen point on test::

    score = amota_on(preds, val_dataset, cfg.eval, False, data_root, "val", scratch)   # validation only
    point, table = choose_point(score)                  # TrackerPoint, [{start, keep, ..., "amota"}, ...]

Ties keep the earlier point of the grid (the grid lists the stricter starts first: fewer tracks for the same AMOTA).
"""
from __future__ import annotations

import itertools
from pathlib import Path
from typing import Callable

from pnyolo.decoding.ground_tracker import TrackerPoint

GRID = {"start": (0.6, 0.4), "keep": (0.2, 0.1), "min_hits": (2, 3), "max_missed": (3, 1)}


def candidate_points(grid: dict = GRID, detection: float | None = None) -> list[TrackerPoint]:
    """Every point of ``grid`` whose keep does not exceed its start, in the grid's order; ``detection`` (the
    detector's own threshold) adds it as a start and half of it as a keep (a weak model's scores may all lie below
    the grid's)."""
    keys = ("start", "keep", "min_hits", "max_missed")
    if detection is not None:
        grid = {**grid, "start": tuple(dict.fromkeys([*grid["start"], detection])),
                "keep": tuple(dict.fromkeys([*grid["keep"], detection / 2]))}
    return [TrackerPoint(**dict(zip(keys, values))) for values in itertools.product(*(grid[k] for k in keys))
            if values[1] <= values[0]]


def choose_point(score: Callable[[TrackerPoint], float | None], points: list[TrackerPoint] | None = None
                 ) -> tuple[TrackerPoint, list[dict]]:
    """The point of ``points`` (default ``candidate_points()``) with the highest ``score`` (None: nothing to score,
    last), ties to the earlier; and the table of every point's score."""
    points = candidate_points() if points is None else points
    table = [{**p.as_dict(), "amota": score(p)} for p in points]
    best = max(range(len(points)), key=lambda i: (table[i]["amota"] is not None, table[i]["amota"] or 0.0, -i))
    return points[best], table


def amota_on(preds, dataset, ev, late_fusion: bool, root, split: str, scratch: Path) -> Callable[[TrackerPoint], float | None]:
    """A score of tracker points: the AMOTA of ``preds`` (a model's predictions of ``dataset``, the sequences of
    ``split``, own-view ones for ``late_fusion``) tracked at the point, by the devkit's TrackingEval on an export of
    ``split`` made once into ``scratch`` (each scenario's first lighting, the sequences tracked; an export already
    there is the same split's, made by an earlier call: reused), or by its tracking algorithm on our sequences where
    the devkit is missing."""
    from dataset_spec.atomic import atomic_write_json
    from pnyolo.evaluation.devkit_eval import available, complete_results, export_split, tracking_eval, tracking_results
    from pnyolo.tracking.nuscenes_tracking import per_view_tracking
    from pnyolo.tracking.run import sequence_classes, track_split

    made = Path(scratch) / "nuscenes"
    exported = (made if made.is_dir() else export_split(root, split, made, None, scenarios=list(dataset.scenarios))
                ) if available() else None
    keys = {f"{k.scenario}__{k.variant}": (k.scenario, k.variant) for k in dataset.items}

    def score(point: TrackerPoint) -> float | None:
        sequences = track_split(preds, dataset, ev, point, late_fusion)
        if exported is None:
            return (per_view_tracking(sequences, sequence_classes(dataset, sequences), dataset.class_names) or
                    {}).get("amota")
        doc = tracking_results(sequences, keys, dataset.class_names, dataset.ds)
        if not any(doc["results"].values()):
            return None
        doc, _ = complete_results(doc, exported, split)
        path = Path(scratch) / "results_tracking.json"
        atomic_write_json(path, doc)
        return tracking_eval(exported, path, split, Path(scratch) / "kit")["amota"]
    return score
