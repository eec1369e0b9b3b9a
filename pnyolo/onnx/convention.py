"""The calling convention of an exported graph, written into the file's metadata (``pnyolo.convention``,
JSON) so that a caller outside Python needs nothing else: each input's name, shape, dtype and meaning,
the resize rule and camera conventions, each output's encoding with its decoding formula and the
constants it needs (``Model.graph_convention``: a kind's outputs are its own). docs/guide/detector.md
prints the same text for each kind."""
from __future__ import annotations

INPUTS = {
    "images": "float32 (V, 3, H, W): each view's RGB image (channels R, G, B), values 0..1 (uint8 / 255), resized "
              "to W x H (the size in pnyolo.size) with area interpolation (OpenCV INTER_AREA)",
    "K": "float32 (V, 3, 3): each view's intrinsics at the encoded W x H, pixel centres at integer coordinates "
         "(a K for an image of w x h: fx, skew scale by W/w, fy by H/h; cx' = (cx + 0.5) W/w - 0.5, cy' likewise)",
    "camera_to_world": "float32 (V, 4, 4): each camera's pose, camera axes x right, y down, z forward "
                       "(OpenCV), world metres with z up (SPEC.md)",
}


def calling_convention(model, input_shapes: dict[str, list], output_shapes: dict[str, list],
                       class_names: list[str], ev) -> dict:
    """The convention of ``model``'s graph (inputs and outputs as exported, their shapes with symbolic
    axes as strings) for evaluation settings ``ev``."""
    own = model.graph_convention(ev)
    inputs = {**INPUTS, **own.pop("inputs", {})}
    return {
        "kind": model.kind, "classes": list(class_names),
        "inputs": {n: {"shape": s, "meaning": inputs[n]} for n, s in input_shapes.items()},
        "outputs": {n: {"shape": s, "meaning": own["outputs"].get(n.split(".")[-1], "")} for n, s in output_shapes.items()},
        **{k: v for k, v in own.items() if k != "outputs"},
    }


YOLO_GRID_OUTPUTS = {
    "confidence": "(V, S_h, S_w, A): the score of anchor a at grid cell (row, col) of view v, 0..1",
    "box": "(V, S_h, S_w, A, 4) raw (tx, ty, tw, th): centre x = (col + sigmoid(tx)) / S_w, y = (row + sigmoid(ty)) / "
           "S_h (image fractions), width = anchors[a][0] exp(min(tw, 8)), height = anchors[a][1] exp(min(th, 8)) "
           "(fractions); in pixels of the encoded image x0 = x W - 0.5 - width W / 2, x1 = x W - 0.5 + width W / 2, "
           "y likewise with H",
    "class_logits": "(V, S_h, S_w, A, C): the class is the argmax (names in classes)",
    "depth": "(V, S_h, S_w, A): the distance along the ray through the box centre, metres",
    "surface_depth": "(V, h, w): each view's planar depth map, metres (an auxiliary output)",
    "state": "(V, S_h, S_w, A, 6) where given: length, width, height = exp(min(s0..s2, 4)) metres; heading about world "
             "z = atan2(s3, s4) / 2, plus pi where s5 < 0, plus the azimuth of the line from the view's camera centre "
             "to the box centre (the centre: the ray through the box centre pixel at depth)",
}
YOLO_GRID_DECODING = ("keep candidates with confidence >= conf_threshold; greedy NMS by score over all classes at "
                      "IoU > nms_iou (with depth_gap set: two boxes whose depths differ by more than depth_gap metres "
                      "never suppress each other); with peaks.* outputs (a trailing axis K of depth peaks per anchor) "
                      "the candidates are those instead of the plain outputs")
BEV_OUTPUTS = {
    "heatmap": "(1, C, ny, nx) logits: score = sigmoid; a detection is a cell whose score is the maximum of its "
               "3x3 neighbourhood and >= conf_threshold (at most top_k, highest first)",
    "regression": "(1, 9, ny, nx) at a detection's cell (iy, ix): centre x = x0 + (ix + r0) cell_m, y = y0 + (iy + r1) "
                  "cell_m, z = r2; length, width, height = exp(min(r3..r5, 4)); yaw = atan2(r6, r7) / 2, plus pi "
                  "where r8 < 0 (radians, about world z: r6, r7 the axis, r8 which way along it)",
}
BEV_DECODING = ("peaks are taken by score, equal scores (INT8 heatmaps make neighbouring values equal) in the order of "
                "their flat index (class, row, column), both of two equal neighbours being peaks; same-class centres "
                "closer than centre_nms_m metres: the later one dropped (greedy in that order); a world box projects "
                "into a view by camera_to_world and K (its 8 corners, clipped at the camera's near plane, give the "
                "box; pnyolo-predict then keeps it in a view when the camera is not inside it, it is at most the "
                "view's label max_distance away, at least min_box_pixels wide and high at the image's own size, and "
                "its in-frame fraction is at least min_in_frame: the dataset's label thresholds, labels.json)")
BEV_GRID = ("the grid pnyolo-predict and the benchmark use (any other grid works, with other scores near its edges): "
            "for each view whose sight it covers (pnyolo-predict: every view), its camera's ground position (x, y) "
            "and the points range_m metres from it along the horizontal directions of fan pixels u = -0.5 + k (W) / "
            "(fan - 1), k = 0..fan-1, across its principal row (the direction R (u - cx) / fx, 0, 1) with R the "
            "camera_to_world rotation, its x and y normalised); over all of them x_min, y_min, x_max, y_max; the "
            "corner x0 = floor(x_min / cell_m) cell_m, y0 likewise; nx = ceil((x_max - x0) / cell_m) rounded up to "
            "a multiple of multiple (at least multiple), ny likewise; with bounds [x_min, y_min, x_max, y_max] set, "
            "those instead of the views' points")
PIXELS = ("boxes are in pixels of the encoded W x H image (pixel centres at integer coordinates); in the camera "
          "image's own w x h pixels x' = (x + 0.5) w / W - 0.5, y' = (y + 0.5) h / H - 0.5")
BEV_POINTS = ("float32 (ny, nx, len(heights), 3): the ground grid's pillar points (the grid as pnyolo chooses it: "
              "the convention's grid rule), ny x nx cells of cell_m with lower corner (x0, y0): points[iy, ix, k] = (x0 + (ix + 0.5) cell_m, y0 + (iy + 0.5) cell_m, "
              "ground_z + heights[k]); numpy: np.stack(np.meshgrid(y0 + (np.arange(ny) + .5) * "
              "cell_m, x0 + (np.arange(nx) + .5) * cell_m, ground_z + np.array(heights), indexing='ij'), -1)"
              "[..., [1, 0, 2]]")
