"""YOLO targets per view and their decoding.

Grid: ``S_h x S_w`` cells over the image (fractions, see ``geometry.grid_cell_centres``);
anchors ``(A, 2)`` are (w, h) fractions of the image. A ground-truth box goes to the cell that
holds its centre and to the anchor with the best width/height IoU; other anchors of that cell
whose w/h IoU exceeds the ignore threshold are ignored by the no-object loss.

Two boxes in one cell wanting the same anchor are common here: a road user hidden behind
another one projects to nearly the same place. The later box then takes the free anchor of that
cell with the next-best w/h IoU (``fallback``); only when every anchor of the cell holds an
object does it overwrite its best one. Without the fallback, 14% of the fully hidden objects of
the cpu benchmark's test views had no target slot at all (a recall ceiling of 0.78 on
hidden-but-seen objects even for a perfect detector; with it: see ``tests/pnyolo/components/test_pnyolo_components``).

Target layout (S_h, S_w, A, 9): ``[obj, x_in_cell, y_in_cell, w, h, class, weight, distance, object]`` with
obj 1 (object), 0 (no object) or -1 (ignored), x/y in [0, 1) inside the cell, w/h as image
fractions, ``weight`` the object's weight in the loss (1 unless ``build_targets`` is given ``extras``;
see ``model.loss.hidden_weight``) and ``distance`` the metres from the camera to the object's box centre
(0: not given; see ``model.loss.depth``), ``object`` the row + 1 of the object's 3D box in the item's
``boxes_3d`` (0: none given; the per-sample targets of ``pnyolo.components.occupancy`` need it).

Example::

    target = build_targets(yolo_boxes, classes, 6, 8, anchors, 0.5)
    target = view_targets(item.gt[v], item.grid, anchors, 0.5, cfg.model.loss)   # a view's, from its ground truth
    boxes = decode_boxes(raw_box, anchors)        # (..., S_h, S_w, A, 4) cx, cy, w, h fractions
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from dataset_spec.boxes import box_to_yolo

OBJ, IGNORE = 1.0, -1.0
TARGET_CHANNELS = 9  # obj, x, y, w, h, class, weight, distance, object (row + 1 in the item's boxes_3d)
DISTANCE, OBJECT = 7, 8  # channels
MAX_LOG_WH = 8.0  # clamp on tw/th before exp


def wh_iou(wh_a: Tensor, wh_b: Tensor) -> Tensor:
    """IoU of boxes sharing a centre: (N, 2) x (M, 2) -> (N, M)."""
    inter = torch.minimum(wh_a[:, None, 0], wh_b[None, :, 0]) * torch.minimum(wh_a[:, None, 1], wh_b[None, :, 1])
    return inter / (wh_a.prod(-1)[:, None] + wh_b.prod(-1)[None, :] - inter).clamp_min(1e-12)


def build_targets(boxes: Tensor, classes: Tensor, grid_h: int, grid_w: int, anchors: Tensor,
                  ignore_threshold: float = 0.5, fallback: bool = True, extras: Tensor | None = None) -> Tensor:
    """
    Args:
        boxes: (N, 4) YOLO [cx, cy, w, h] image fractions.
        classes: (N,) detector class indices.
        anchors: (A, 2) anchor (w, h) fractions.
        fallback: a box whose best anchor is taken in its cell goes to the cell's next-best free anchor.
        extras: (N, 3) each box's [loss weight, metres from the camera to its 3D centre, row + 1 of its 3D box
            in the item's ``boxes_3d``] (``box_extras``; None: 1, 0 unknown, 0 not given).
    Returns:
        (grid_h, grid_w, A, TARGET_CHANNELS) float targets.
    """
    A = anchors.shape[0]
    target = torch.zeros(grid_h, grid_w, A, TARGET_CHANNELS, dtype=torch.float32)
    if boxes.numel() == 0:
        return target
    boxes = boxes.to(torch.float32)
    ious = wh_iou(boxes[:, 2:], anchors.to(torch.float32))  # (N, A)
    # Larger boxes first: when a cell runs out of anchors, a small box sharing it wins (drawn last).
    order = torch.argsort(boxes[:, 2] * boxes[:, 3], descending=True)
    for n in order.tolist():
        cx, cy, w, h = boxes[n].tolist()
        weight, distance, obj_row = (1.0, 0.0, 0.0) if extras is None else extras[n].tolist()
        row, col = cell_of(cx, cy, grid_h, grid_w)
        ranked = torch.argsort(ious[n], descending=True).tolist()
        free = [a for a in ranked if target[row, col, a, 0] != OBJ]
        chosen = free[0] if fallback and free else ranked[0]
        for a in range(A):
            if a == chosen:
                target[row, col, a] = torch.tensor([OBJ, cx * grid_w - col, cy * grid_h - row, w, h,
                                                    float(classes[n]), weight, distance, obj_row])
            elif ious[n, a] > ignore_threshold and target[row, col, a, 0] != OBJ:
                target[row, col, a, 0] = IGNORE
    return target


def object_loss_weights(visible_fraction, seen_elsewhere, loss) -> torch.Tensor:
    """Loss weight per object of a view: ``model.loss.hidden_weight`` if it is fully hidden in the view
    (visible fraction 0) but another source view of the item sees it, ``model.loss.unseen_weight`` if no
    source view sees it, else 1 (``loss``: a YoloLossConfig)."""
    hidden = np.asarray(visible_fraction, dtype=np.float64).reshape(-1) <= 0
    seen = np.asarray(seen_elsewhere, dtype=bool).reshape(-1)
    w = np.ones(hidden.shape, dtype=np.float32)
    w[hidden & seen] = loss.hidden_weight
    w[hidden & ~seen] = loss.unseen_weight
    return torch.from_numpy(w)


def yolo_boxes(boxes, grid) -> Tensor:
    """(N, 4) pixel boxes of the encoded image -> (N, 4) float32 YOLO [cx, cy, w, h] fractions."""
    rows = [box_to_yolo(b, grid.width, grid.height) for b in np.asarray(boxes, dtype=np.float64).reshape(-1, 4)]
    return torch.tensor(np.array(rows), dtype=torch.float32).reshape(-1, 4)


def view_targets(gt, grid, anchors: Tensor, ignore_threshold: float, loss) -> Tensor:
    """One view's targets (S_h, S_w, A, TARGET_CHANNELS) from its ground truth (``ViewGroundTruth``):
    every road user in its cell and anchor, weighted by ``object_loss_weights`` (``loss``), the road
    users left out of the ground truth ignored (``ignore_regions``)."""
    extras = torch.stack([object_loss_weights(gt.visible_fraction, gt.seen_elsewhere, loss),
                          torch.tensor(np.asarray(gt.distances, dtype=np.float64), dtype=torch.float32),
                          torch.tensor(np.asarray(gt.object_rows, dtype=np.int64)).float() + 1], dim=1)
    target = build_targets(yolo_boxes(gt.boxes, grid), torch.tensor(np.asarray(gt.classes, dtype=np.int64)),
                           grid.grid_h, grid.grid_w, anchors, ignore_threshold, extras=extras)
    if gt.excluded_boxes is not None and len(gt.excluded_boxes):  # outside the ground truth, not background either
        target = ignore_regions(target, yolo_boxes(gt.excluded_boxes, grid))
    return target


def unseen_elsewhere_cells(gt, grid) -> Tensor:
    """(S_h, S_w) bool: the cells of one view's road users that no other source view sees."""
    return occupied_cells(yolo_boxes(gt.boxes, grid)[~torch.as_tensor(np.asarray(gt.seen_elsewhere, dtype=bool))],
                          grid.grid_h, grid.grid_w)


def ignore_regions(target: Tensor, boxes: Tensor) -> Tensor:
    """``target`` (S_h, S_w, A, C) with the cells of road users left out of the ground truth ignored.

    ``boxes`` (K, 4) YOLO [cx, cy, w, h] fractions of labels the thresholds rejected (too truncated,
    too far, too small): real road users, so not background. Every anchor of a cell whose centre
    lies inside such a box, and of the cell holding its centre (if in the image), becomes IGNORE
    unless it holds an object (KITTI's DontCare regions).
    """
    out = target.clone()
    grid_h, grid_w = target.shape[:2]
    cols, rows = cell_offsets(grid_h, grid_w)
    u, v = (cols[..., 0] + 0.5) / grid_w, (rows[..., 0] + 0.5) / grid_h  # cell centres (S_h, S_w)
    for cx, cy, w, h in boxes.reshape(-1, 4).tolist():
        cells = (u - cx).abs() <= w / 2
        cells &= (v - cy).abs() <= h / 2
        if 0 <= cx < 1 and 0 <= cy < 1:
            cells[cell_of(cx, cy, grid_h, grid_w)] = True
        free = cells[..., None] & (out[..., 0] != OBJ)
        out[..., 0][free] = IGNORE
    return out


def cell_of(cx: float, cy: float, grid_h: int, grid_w: int) -> tuple[int, int]:
    """(row, col) of the grid cell that holds a box centre (image fractions), clamped to the grid."""
    return min(max(int(cy * grid_h), 0), grid_h - 1), min(max(int(cx * grid_w), 0), grid_w - 1)


def target_cell(target: Tensor, row: int, box2d, g) -> int:
    """The flat cell of a view's ``target`` (S_h, S_w, A, TARGET_CHANNELS) whose slot holds the road
    user of ``boxes_3d`` row ``row``, or, if it lost its slot, the cell of its 2D box's centre
    (``box2d`` [x0, y0, x1, y1] pixels of grid ``g``)."""
    slot = ((target[..., 0] == OBJ) & (target[..., OBJECT] == row + 1)).nonzero()
    if len(slot):
        return int(slot[0, 0]) * g.grid_w + int(slot[0, 1])
    cx, cy = ((box2d[0] + box2d[2]) / 2 + 0.5) / g.width, ((box2d[1] + box2d[3]) / 2 + 0.5) / g.height
    r, c = cell_of(cx, cy, g.grid_h, g.grid_w)
    return r * g.grid_w + c


def occupied_cells(boxes: Tensor, grid_h: int, grid_w: int) -> Tensor:
    """(grid_h, grid_w) bool: the cells that hold the centre of one of ``boxes`` (N, 4) YOLO fractions,
    the cells ``build_targets`` gives them."""
    cells = torch.zeros(grid_h, grid_w, dtype=torch.bool)
    for cx, cy, _, _ in boxes.tolist():
        cells[cell_of(cx, cy, grid_h, grid_w)] = True
    return cells


def cell_offsets(grid_h: int, grid_w: int, device=None) -> tuple[Tensor, Tensor]:
    """(col, row) index grids of shape (S_h, S_w, 1)."""
    rows = torch.arange(grid_h, device=device, dtype=torch.float32)[:, None, None].expand(grid_h, grid_w, 1)
    cols = torch.arange(grid_w, device=device, dtype=torch.float32)[None, :, None].expand(grid_h, grid_w, 1)
    return cols, rows


def decode_boxes(raw_box: Tensor, anchors: Tensor) -> Tensor:
    """Raw (tx, ty, tw, th) (..., S_h, S_w, A, 4) -> (cx, cy, w, h) image fractions."""
    grid_h, grid_w = raw_box.shape[-4], raw_box.shape[-3]
    cols, rows = cell_offsets(grid_h, grid_w, raw_box.device)
    cx = (cols + torch.sigmoid(raw_box[..., 0])) / grid_w
    cy = (rows + torch.sigmoid(raw_box[..., 1])) / grid_h
    wh = anchors.to(raw_box) * torch.exp(raw_box[..., 2:4].clamp(max=MAX_LOG_WH))
    return torch.stack([cx, cy, wh[..., 0], wh[..., 1]], dim=-1)


def target_boxes(target: Tensor) -> Tensor:
    """Targets (..., S_h, S_w, A, 7) -> their boxes (cx, cy, w, h) fractions (..., S_h, S_w, A, 4)."""
    grid_h, grid_w = target.shape[-4], target.shape[-3]
    cols, rows = cell_offsets(grid_h, grid_w, target.device)
    return torch.stack([(cols + target[..., 1]) / grid_w, (rows + target[..., 2]) / grid_h,
                        target[..., 3], target[..., 4]], dim=-1)


def perfect_raw(target: Tensor, anchors: Tensor, num_classes: int, confident: float = 12.0) -> dict[str, Tensor]:
    """The raw renderer outputs that reproduce ``target`` exactly, distances included, keyed like
    ``RayOutputs``'s fields (for tests, debugging and ``evaluate.encoding_ceiling``)."""
    x = target[..., 1:3].clamp(1e-4, 1 - 1e-4)
    box = torch.cat([torch.log(x / (1 - x)), torch.log(target[..., 3:5].clamp_min(1e-8) / anchors)], dim=-1)
    obj = target[..., 0] == OBJ
    cls = torch.nn.functional.one_hot(target[..., 5].long(), num_classes).float() * 2 * confident - confident
    return {"ray_confidence": obj.float(), "box": box, "class_logits": cls, "depth": target[..., DISTANCE].clone()}
