"""Late fusion by agreement: a road user that several cars report is more certain than one that a single
car reports, so the cars' detections of one road user are gathered and scored together.

    groups = gather(dets, 1.0)                      # [(best, members)] by score, one per road user
    fused = fuse_agreeing(dets, owners, 1.0)        # the best box of each, scored 1 - prod(1 - s_car)

A group is formed greedily by score, as centre NMS forms them: the best not yet taken detection gathers
the not yet taken ones of its class whose ground-plane centres lie within ``radius`` metres. Its fused
score is the noisy-OR of the cars in it, each car counted once by its best member:
``1 - prod_cars (1 - s_car)``. Two cars at 0.5 give 0.75, one car at 0.5 stays 0.5; a false positive of
one car's own view is rarely repeated by another car at the same place, so a keep threshold above the
send threshold keeps what cars agree on and what one car is sure of (chosen on validation by the
benchmark, ``pnyolo.bench.selection.choose_late_fusion``).
"""
from __future__ import annotations

import numpy as np

from pnyolo.decoding.detections import WorldDetections


def gather(dets: WorldDetections, radius: float) -> list[tuple[int, np.ndarray]]:
    """(the group's best detection, every member's index) for each road user, greedily by score."""
    taken = np.zeros(len(dets), dtype=bool)
    groups = []
    for i in np.argsort(-dets.scores, kind="stable"):
        if taken[i]:
            continue
        near = np.hypot(*(dets.boxes[:, :2] - dets.boxes[i, :2]).T) < radius
        members = np.flatnonzero(~taken & near & (dets.classes == dets.classes[i]))
        taken[members] = True
        groups.append((int(i), members))
    return groups


def noisy_or(scores: np.ndarray, owners: np.ndarray) -> float:
    """``1 - prod(1 - s)`` over the distinct ``owners``, each by its highest score."""
    best = {}
    for s, o in zip(scores.tolist(), owners.tolist()):
        best[o] = max(best.get(o, 0.0), s)
    return float(1.0 - np.prod([1.0 - s for s in best.values()]))


def fuse_agreeing(dets: WorldDetections, owners: np.ndarray, radius: float) -> WorldDetections:
    """One detection per road user: the best box of each group (``gather``), scored by the noisy-OR of
    the cars (``owners``, one per detection) that reported it."""
    groups = gather(dets, radius)
    keep = np.asarray([i for i, _ in groups], dtype=np.int64)
    scores = np.asarray([noisy_or(dets.scores[m], owners[m]) for _, m in groups], dtype=np.float64)
    return WorldDetections(dets.boxes[keep].reshape(-1, 7), scores, dets.classes[keep])
