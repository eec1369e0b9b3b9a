"""Sampling coverage: does the multi-view model even query the points where a road user is?

For each ground-truth road user of a scored view, over the query points (every sample of every ray)
of the cell its YOLO target is assigned to (the cell that has to find it):

* ``in_box``: some point lies inside its 3D box;
* ``on_pixels``: some point projects onto its visible pixels (instance ids) in a source view that
  sees it; for a road user hidden in the target view that is another camera, the only place its
  appearance can come from;
* ``near_pixels``: some point projects within one feature cell (the encoder's finest stride) of them.

Split by class and by visibility: ``visible`` in the target view, ``hidden-but-seen`` (hidden there,
seen by another source view), ``fully hidden`` (no source view sees it: nothing to project onto).

Example::

    acc = CoverageAccumulator(class_names, stride=model.coverage_stride())
    out = predict_item(model, item, return_samples=True)
    acc.add_points(item, model.coverage_points(out, item), dataset.instance_maps(item))
    acc.summary()   # {"pedestrian": {"hidden-but-seen": {"n": 29, "in_box": 0.03, ...}, ...}, ...}
"""
from __future__ import annotations

import cv2
import numpy as np

from dataset_spec.boxes import points_in_box
from dataset_spec.camera import points_to_camera, project_camera_points
from pnyolo.data.item import Item

GROUPS = ("visible", "hidden-but-seen", "fully hidden")
MEASURES = ("in_box", "on_pixels", "near_pixels")


def object_coverage(points: np.ndarray, box: np.ndarray, views: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                    stride: float) -> dict[str, bool]:
    """Coverage of one road user by query points (P, 3) (world).

    Args:
        box: (7,) [cx, cy, cz, length, width, height, yaw] of its 3D box.
        views: (K, camera_to_world, mask) of each source view that sees it, ``mask`` (H, W) bool its
            visible pixels there.
        stride: pixels within which a projected point counts as near them.
    """
    in_box = bool(len(points)) and bool(points_in_box(points, box[:3], box[3:6], float(box[6])).any())
    on = near = False
    for K, c2w, mask in views:
        cam = points_to_camera(c2w, points)
        front = cam[:, 2] > 1e-3
        if not front.any():
            continue
        uv = np.rint(project_camera_points(K, cam[front])).astype(np.int64)
        h, w = mask.shape
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        if not inside.any():
            continue
        uv = uv[inside]
        on = on or bool(mask[uv[:, 1], uv[:, 0]].any())
        # distance (pixels) from each pixel to the nearest visible pixel of the road user
        dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
        near = near or bool((dist[uv[:, 1], uv[:, 0]] <= stride).any())
    return {"in_box": in_box, "on_pixels": on, "near_pixels": near}


class CoverageAccumulator:
    """Sums ``object_coverage`` over items, per class and visibility group."""

    def __init__(self, class_names: list[str], stride: float):
        self.class_names, self.stride = list(class_names), float(stride)
        self.counts = {c: {g: {"n": 0, **{m: 0 for m in MEASURES}} for g in GROUPS} for c in self.class_names}

    def add_points(self, item: Item, query_points, instance_maps: np.ndarray) -> None:
        """One item's scored views, ``query_points(v, j, row)`` the (P, 3) world points a model
        queries for road user ``j`` of view ``v`` (its row in ``boxes_3d``)."""
        K, c2w = item.K.numpy().astype(np.float64), item.camera_to_world.numpy().astype(np.float64)
        boxes = item.boxes_3d.numpy().astype(np.float64)
        for v in item.scored:
            gt = item.gt[v]
            for j, row in enumerate(gt.object_rows):
                pts = query_points(v, j, int(row))
                actor = item.actor_ids[int(row)]
                seen = [(K[u], c2w[u], instance_maps[u] == actor) for u in range(len(item.gt))]
                seen = [s for u, s in enumerate(seen) if s[2].any() and (u != v or gt.visible_fraction[j] > 0)]
                cov = object_coverage(pts, boxes[int(row)], seen, self.stride)
                group = ("visible" if gt.visible_fraction[j] > 0 else
                         "hidden-but-seen" if gt.seen_elsewhere[j] else "fully hidden")
                rec = self.counts[self.class_names[int(gt.classes[j])]][group]
                rec["n"] += 1
                for m in MEASURES:
                    rec[m] += int(cov[m])

    def summary(self) -> dict:
        """{class: {group: {"n", "in_box", "on_pixels", "near_pixels" (shares; None without objects)}}}."""
        out = {}
        for cls, groups in self.counts.items():
            out[cls] = {g: {"n": r["n"], **{m: (r[m] / r["n"] if r["n"] else None) for m in MEASURES}}
                        for g, r in groups.items()}
        return out


def coverage_markdown(summary: dict) -> str:
    """The coverage summary as a table: one row per class and group."""
    lines = ["| class | group | n | point in the 3D box | on its visible pixels in a view that sees it | "
             "within one feature cell of them |", "|---|---|---|---|---|---|"]
    fmt = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    for cls, groups in summary.items():
        for g, r in groups.items():
            if r["n"]:
                lines.append(f"| {cls} | {g} | {r['n']} | {fmt(r['in_box'])} | "
                             f"{fmt(r['on_pixels']) if g != 'fully hidden' else 'n/a'} | "
                             f"{fmt(r['near_pixels']) if g != 'fully hidden' else 'n/a'} |")
    return "\n".join(lines) + "\n"
