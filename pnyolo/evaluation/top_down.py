"""One frame from above, for a person to read at a glance: every camera's view cone (the target view's
in red), each road user's footprint coloured by what the target camera makes of it (seen; hidden but
seen by another camera; hidden from all; outside its labels), each hidden-but-seen road user marked
found or missed by the first model, and every model's detections with a ground position::

    rgb = top_down(item, {"bev": bev_dets, "single-view": sv_dets}, target=0, iou=0.2)   # (H, W, 3) uint8
"""
from __future__ import annotations

import numpy as np

from dataset_spec.trajectories import footprint, view_cone
from pnyolo.data.item import Item
from pnyolo.decoding.detections import ViewDetections
from pnyolo.evaluation.matching import match_strict

SEEN, HIDDEN_SEEN, HIDDEN, UNLABELLED = "tab:green", "tab:orange", "0.45", "0.8"
MARKERS = ["o", "s", "^", "D", "v", "P"]  # one per model


def ground_status(item: Item, target: int) -> dict[int, str]:
    """Each row of the item's 3D boxes -> its colour in the target view: SEEN, HIDDEN_SEEN, HIDDEN, or
    UNLABELLED (left out of that view's ground truth)."""
    gt = item.gt[target]
    status = {r: UNLABELLED for r in range(0 if item.boxes_3d is None else len(item.boxes_3d))}
    for k, row in enumerate(gt.object_rows if gt.object_rows is not None else []):
        hidden = gt.visible_fraction[k] <= 1e-6
        status[int(row)] = (HIDDEN_SEEN if gt.seen_elsewhere[k] else HIDDEN) if hidden else SEEN
    return status


def hidden_seen_found(item: Item, dets: ViewDetections, target: int, iou: float) -> list[tuple[int, bool]]:
    """(row of the item's 3D boxes, found) of each road user hidden in the target view but seen by
    another, found meaning matched by ``dets`` (strict, at ``iou``)."""
    gt = item.gt[target]
    if gt.object_rows is None:
        return []
    found = match_strict(dets, gt, iou)[1]
    return [(int(row), bool(found[k])) for k, row in enumerate(gt.object_rows)
            if gt.visible_fraction[k] <= 1e-6 and gt.seen_elsewhere[k]]


def top_down(item: Item, detections: dict[str, list[ViewDetections]], target: int, iou: float,
             title: str = "", tracks: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """The picture as RGB (H, W, 3) uint8; ``detections``: each model's by view (a list, or a dict holding
    the target view), the first one's matches (strict, at ``iou``) decide found or missed; ``tracks``:
    id -> (k, 2) ground positions."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch, Polygon

    fig, ax = plt.subplots(figsize=(6.4, 6.4))
    K, c2w = item.K.double().numpy(), item.camera_to_world.double().numpy()
    for v in range(len(K)):
        cone = view_cone(K[v], item.grid.width, c2w[v])
        colour = "tab:red" if v == target else "tab:blue"
        ax.add_patch(Polygon(cone, closed=True, color=colour, alpha=0.15 if v == target else 0.07, lw=0))
        ax.plot(*cone[0], "^", color=colour, ms=6)
    boxes = np.zeros((0, 7)) if item.boxes_3d is None else item.boxes_3d.double().numpy().reshape(-1, 7)
    for row, colour in ground_status(item, target).items():
        b = boxes[row]
        ax.add_patch(Polygon(footprint(b[:3], b[3:6], b[6]), closed=True, fc=colour, ec="k", lw=0.4,
                             alpha=0.5 if colour == UNLABELLED else 0.9))
    names = list(detections)
    for row, ok in hidden_seen_found(item, detections[names[0]][target], target, iou) if names else []:
        ax.annotate("found" if ok else "missed", boxes[row, :2], xytext=(4, 4), textcoords="offset points",
                    fontsize=7, color="tab:green" if ok else "tab:red", weight="bold")
    for n, name in enumerate(names):
        d = detections[name][target]
        centres = d.centres if d.centres is not None else np.zeros((0, 3))
        centres = centres[np.isfinite(centres).all(axis=1)] if len(centres) else centres
        ax.plot(centres[:, 0], centres[:, 1], MARKERS[n % len(MARKERS)], mfc="none", mew=1.2, ms=7,
                label=f"{name} ({len(centres)} placed on the ground)")
    for n, (tid, xy) in enumerate(sorted((tracks or {}).items())):
        ax.plot(xy[:, 0], xy[:, 1], "-", color="tab:purple", lw=1.2, label="tracks" if n == 0 else None)
        ax.annotate(str(tid), xy[-1], xytext=(-8, -9), textcoords="offset points", fontsize=6, color="tab:purple")
    handles = ax.get_legend_handles_labels()[0] + [
        Patch(fc=colour, ec="k", lw=0.4, label=what)
        for colour, what in ((SEEN, "seen by the target camera"), (HIDDEN_SEEN, "hidden there, seen by another"),
                             (HIDDEN, "hidden from every camera"), (UNLABELLED, "not in the target's labels"))]
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"{item.scenario} frame {item.frame} {item.variant}: target view {target} (red)", fontsize=9)
    ax.legend(handles=handles, fontsize=6.5, loc="upper right")
    ax.grid(alpha=0.2)
    fig.tight_layout()
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return rgb


class SequenceMovie:
    """The frames from above of one test sequence (the first scenario of several frames met, its first
    lighting and target view), with the tracks (``GroundTracker``) of the first model that places its
    detections on the ground, written as an animated GIF at the sequence's rate::

        movie = SequenceMovie(iou=0.2)
        for item, dets in ...: movie.add(item, dets, fps)      # dets: each model's per view
        movie.write("report/examples")                         # SCENARIO_top_down.gif, or nothing
    """

    def __init__(self, iou: float):
        self.iou, self.key, self.frames, self.fps = iou, None, {}, None

    def add(self, item: Item, detections: dict[str, list[ViewDetections]], fps: float | None) -> None:
        if not fps or not item.scored:  # a scenario of one frame has no sequence
            return
        key = (item.scenario, item.variant, item.scored[0])
        if self.key is None:
            self.key, self.fps = key, fps
        if key == self.key:
            self.frames[item.frame] = (item, {n: d[item.scored[0]] for n, d in detections.items()})

    def tracks(self) -> dict[int, dict[int, np.ndarray]]:
        """frame -> {track id: (k, 2) its ground positions up to that frame} of the first model with world
        boxes in the target view (none without such a model)."""
        from pnyolo.decoding.detections import WorldDetections
        from pnyolo.decoding.ground_tracker import EVERY_DETECTION, GroundTracker

        order = sorted(self.frames)
        name = next((n for n, d in self.frames[order[0]][1].items() if d.world_boxes is not None), None)
        if name is None:
            return {f: {} for f in order}
        tracker = GroundTracker(self.fps, EVERY_DETECTION)  # the detections drawn, at the run's operating point
        for f in order:
            d = self.frames[f][1][name]
            tracker.step(f, WorldDetections(np.asarray(d.world_boxes).reshape(-1, 7), d.scores, d.classes))
        rows = tracker.rows()
        return {f: {r.track: np.array([(q.x, q.y) for q in rows if q.track == r.track and q.frame <= f])
                    for r in rows if r.frame == f} for f in order}

    def write(self, folder) -> None:
        from dataset_spec.names import below
        from tools.viewer import write_gif

        if len(self.frames) < 2:
            return
        trails, pictures = self.tracks(), []
        for f in sorted(self.frames):
            item, dets = self.frames[f]
            v = item.scored[0]
            pictures.append(top_down(item, {n: {v: d} for n, d in dets.items()}, v, self.iou, f"{item.scenario} {item.variant}: frame {f}, t = "
                                     f"{f / self.fps:.1f} s, target view {v} (red)", trails[f]))
        write_gif(below(folder, f"{self.key[0]}_top_down.gif"), pictures, self.fps)
