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
    preds = predict(model, dataset, cfg.eval, Condition(samples=True))    # pnyolo.engine.predict
    p = preds.items[0]
    acc.add_points(p.item, model.coverage_points(p.out, p.item), dataset.instance_maps(p.item))
    acc.summary()   # {"pedestrian": {"hidden-but-seen": {"n": 29, "in_box": 0.03, ...}, ...}, ...}
"""
from __future__ import annotations

import cv2
import numpy as np

from dataset_spec.boxes import points_in_box
from dataset_spec.camera import points_to_camera, project_camera_points
from pnyolo.components.footprints import Segments
from pnyolo.data.item import Item

GROUPS = ("visible", "hidden-but-seen", "fully hidden")
MEASURES = ("in_box", "on_pixels", "near_pixels", "fine_in_box", "segment_in_box", "footprint_on_pixels")
SEGMENT_MEASURES = MEASURES[4:]  # what a model reading frustum segments (model.sampler.footprint frustum) adds


def _segment_coverage(seg: Segments, box: np.ndarray, views) -> dict[str, bool]:
    """Whether a segment meets the box, and whether a segment's footprint in a view that sees the road user holds
    some of its visible pixels (``pnyolo.components.footprints``: the region its features are read over)."""
    import torch

    from pnyolo.components.footprints import segment_footprints, segment_radius
    from pnyolo.components.occupancy import segments_meet_boxes

    tensor = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64))  # noqa: E731
    meets = segments_meet_boxes(tensor(seg.origins), tensor(seg.dirs), tensor(seg.t)[:, None], tensor(seg.half)[:, None],
                                tensor(seg.lateral)[:, None], tensor(box)[None])
    radius = segment_radius(tensor(seg.half), tensor(seg.lateral))
    on = False
    for K, c2w, mask in views:
        cam = points_to_camera(c2w, seg.centres())
        half, front = segment_footprints(tensor(cam)[None], radius, tensor([K[0, 0]]), tensor([K[1, 1]]))
        half, front = half[0].numpy(), front[0].numpy()
        uv = project_camera_points(K, np.where(front[:, None], cam, 1.0))
        table = np.pad(mask.astype(np.int64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))  # summed-area table
        h, w = mask.shape
        x0 = np.clip(np.floor(uv[:, 0] - half[:, 0] + 0.5), 0, w).astype(np.int64)
        x1 = np.clip(np.floor(uv[:, 0] + half[:, 0] + 0.5) + 1, 0, w).astype(np.int64)
        y0 = np.clip(np.floor(uv[:, 1] - half[:, 1] + 0.5), 0, h).astype(np.int64)
        y1 = np.clip(np.floor(uv[:, 1] + half[:, 1] + 0.5) + 1, 0, h).astype(np.int64)
        count = table[y1, x1] - table[y0, x1] - table[y1, x0] + table[y0, x0]
        on = on or bool((front & (count > 0)).any())
    return {"segment_in_box": bool(meets.any()), "footprint_on_pixels": on}


def object_coverage(query, box: np.ndarray, views: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                    stride: float) -> dict[str, bool | None]:
    """Coverage of one road user by query points (P, 3) (world), or by a ray-casting model's ``Segments``
    (measured at their centres; ``fine_in_box``: a fine sample inside its box; as frustum segments where they are:
    ``SEGMENT_MEASURES``; None where not measured).

    Args:
        box: (7,) [cx, cy, cz, length, width, height, yaw] of its 3D box.
        views: (K, camera_to_world, mask) of each source view that sees it, ``mask`` (H, W) bool its
            visible pixels there.
        stride: pixels within which a projected point counts as near them.
    """
    segments = query if isinstance(query, Segments) else None
    points = query.centres() if segments is not None else query
    fine = None if segments is None else points[segments.half == 0]
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
    segment = dict.fromkeys(SEGMENT_MEASURES) if segments is None or segments.lateral is None or not len(points) \
        else _segment_coverage(segments, box, views)
    fine_in_box = None if fine is None else bool(len(fine)) and bool(
        points_in_box(fine, box[:3], box[3:6], float(box[6])).any())
    return {"in_box": in_box, "on_pixels": on, "near_pixels": near, "fine_in_box": fine_in_box, **segment}


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
                    if cov[m] is None:
                        rec[m] = None  # not measured (points, not segments)
                    elif rec[m] is not None:
                        rec[m] += int(cov[m])

    def summary(self) -> dict:
        """{class: {group: {"n", and each of ``MEASURES`` (shares; None without objects or not measured)}}}."""
        out = {}
        for cls, groups in self.counts.items():
            out[cls] = {g: {"n": r["n"], **{m: (r[m] / r["n"] if r["n"] and r[m] is not None else None)
                                             for m in MEASURES}} for g, r in groups.items()}
        return out


def coverage_markdown(summary: dict) -> str:
    """The coverage summary as a table: one row per class and group (the segment columns where measured)."""
    segments = any(r.get("segment_in_box") is not None for groups in summary.values() for r in groups.values())
    fine = any(r.get("fine_in_box") is not None for groups in summary.values() for r in groups.values())
    lines = ["| class | group | n | point in the 3D box | on its visible pixels in a view that sees it | "
             "within one feature cell of them |" + (" fine sample in the 3D box |" if fine else "")
             + (" segment meets the 3D box | a segment's footprint holds its visible pixels in a view that sees it |"
                if segments else ""),
             "|---|---|---|---|---|---|" + ("---|" if fine else "") + ("---|---|" if segments else "")]
    fmt = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    for cls, groups in summary.items():
        for g, r in groups.items():
            if r["n"]:
                hidden = g == "fully hidden"
                lines.append(f"| {cls} | {g} | {r['n']} | {fmt(r['in_box'])} | "
                             f"{fmt(r['on_pixels']) if not hidden else 'n/a'} | "
                             f"{fmt(r['near_pixels']) if not hidden else 'n/a'} |"
                             + (f" {fmt(r.get('fine_in_box'))} |" if fine else "")
                             + (f" {fmt(r.get('segment_in_box'))} | "
                                f"{fmt(r.get('footprint_on_pixels')) if not hidden else 'n/a'} |" if segments else ""))
    return "\n".join(lines) + "\n"
