"""A caller of an exported graph that knows only its metadata (``pnyolo.convention``): no project import.
Run as ``python onnx_client.py MODEL.onnx FRAME.npz OUT.json``; FRAME.npz holds ``images`` (V, h, w, 3)
uint8 RGB at their own size, ``K`` (V, 3, 3) for that size and ``camera_to_world`` (V, 4, 4); a ground-plane
graph's grid comes from the convention's rule. Writes the detections decoded by the documented formulas."""
import json
import sys

import cv2
import numpy as np
import onnxruntime as ort


def ground_grid(conv: dict, K: np.ndarray, c2w: np.ndarray, width: int) -> list:
    """[x0, y0, nx, ny] by the convention's grid rule over every view (K at the encoded width)."""
    rule, c = conv["grid"], conv["cell_m"]
    if rule["bounds"] is not None:
        x_min, y_min, x_max, y_max = rule["bounds"]
    else:
        u = -0.5 + np.arange(rule["fan"]) * width / (rule["fan"] - 1)
        pts = []
        for k, pose in zip(K, c2w):
            d = np.stack([(u - k[0, 2]) / k[0, 0], np.zeros_like(u), np.ones_like(u)], -1) @ pose[:3, :3].T
            d = d[:, :2] / np.linalg.norm(d[:, :2], axis=1, keepdims=True)
            pts += [pose[:2, 3], *(pose[:2, 3] + rule["range_m"] * d)]
        (x_min, y_min), (x_max, y_max) = np.min(pts, axis=0), np.max(pts, axis=0)
    x0, y0 = np.floor(x_min / c) * c, np.floor(y_min / c) * c
    m = rule["multiple"]
    side = lambda n: max(m, int(np.ceil(n / m)) * m)  # noqa: E731
    return [x0, y0, side(int(np.ceil((x_max - x0) / c))), side(int(np.ceil((y_max - y0) / c)))]


def encoded_K(frame, width: int, height: int) -> np.ndarray:
    """The intrinsics at the encoded W x H (the convention's rule for K)."""
    K = frame["K"].astype(np.float64).copy()
    h, w = frame["images"].shape[1:3]
    sx, sy = width / w, height / h
    K[:, 0, :2] *= sx
    K[:, 1, 1] *= sy
    K[:, 0, 2] = (K[:, 0, 2] + 0.5) * sx - 0.5
    K[:, 1, 2] = (K[:, 1, 2] + 0.5) * sy - 0.5
    return K


def inputs(conv: dict, frame, width: int, height: int) -> dict:
    images, K = frame["images"], encoded_K(frame, width, height)
    resized = [cv2.resize(im, (width, height), interpolation=cv2.INTER_AREA) for im in images]
    feeds = {"images": (np.stack(resized).transpose(0, 3, 1, 2) / np.float32(255)).astype(np.float32),
             "K": K.astype(np.float32), "camera_to_world": frame["camera_to_world"].astype(np.float32)}
    if "points" in conv["inputs"]:
        x0, y0, nx, ny = ground_grid(conv, K, frame["camera_to_world"], width)
        c = conv["cell_m"]
        pts = np.meshgrid(y0 + (np.arange(int(ny)) + .5) * c, x0 + (np.arange(int(nx)) + .5) * c,
                          conv["ground_z"] + np.array(conv["heights"]), indexing="ij")
        feeds["points"] = np.stack(pts, -1)[..., [1, 0, 2]].astype(np.float32)
    return {k: v for k, v in feeds.items() if k in conv["inputs"]}


def sigmoid(x):
    return 1 / (1 + np.exp(-x))


def iou(a, b):
    lo, hi = np.maximum(a[:2], b[:, :2]), np.minimum(a[2:], b[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    area = lambda r: (r[..., 2] - r[..., 0]) * (r[..., 3] - r[..., 1])  # noqa: E731
    return inter / (area(a) + area(b) - inter)


def world_boxes(K, c2w, u, v, dist, state) -> list:
    """The convention's world boxes: the centre on the ray through pixel (u, v) at ``dist``, the size and heading from
    ``state`` (P, 6), the heading turned by the azimuth of the line from the camera centre to the box centre."""
    rays = np.linalg.solve(K, np.stack([u, v, np.ones_like(u)]))  # (3, P) camera directions
    dirs = (c2w[:3, :3] @ (rays / np.linalg.norm(rays, axis=0))).T
    centres = c2w[:3, 3] + dirs * dist[:, None]
    size = np.exp(np.minimum(state[:, :3], 4))
    yaw = np.arctan2(state[:, 3], state[:, 4]) / 2 + np.where(state[:, 5] < 0, np.pi, 0.0)
    yaw = yaw + np.arctan2(centres[:, 1] - c2w[1, 3], centres[:, 0] - c2w[0, 3])
    return np.concatenate([centres, size, np.arctan2(np.sin(yaw), np.cos(yaw))[:, None]], axis=1).tolist()


def yolo_grid(conv: dict, out: dict, width: int, height: int, K: np.ndarray, c2w: np.ndarray) -> list:
    views = []
    anchors = np.array(conv["anchors"])
    for v in range(out["confidence"].shape[0]):
        conf, box, logits = (out[n][v] for n in ("confidence", "box", "class_logits"))
        depth = out["depth"][v] if "depth" in out else np.full(conf.shape, np.nan)  # a kind without distances
        S_h, S_w = conf.shape[:2]
        rows, cols = np.meshgrid(np.arange(S_h), np.arange(S_w), indexing="ij")
        x = (cols[..., None] + sigmoid(box[..., 0])) / S_w
        y = (rows[..., None] + sigmoid(box[..., 1])) / S_h
        bw = anchors[:, 0] * np.exp(np.minimum(box[..., 2], 8))
        bh = anchors[:, 1] * np.exp(np.minimum(box[..., 3], 8))
        xyxy = np.stack([x * width - .5 - bw * width / 2, y * height - .5 - bh * height / 2,
                         x * width - .5 + bw * width / 2, y * height - .5 + bh * height / 2], -1)
        keep = conf >= conv["conf_threshold"]
        boxes, scores, classes, dist = xyxy[keep], conf[keep], logits[keep].argmax(-1), depth[keep]
        order = np.argsort(-scores, kind="stable")
        kept = []
        for i in order:
            near = iou(boxes[i], boxes[kept]) > conv["nms_iou"] if kept else np.zeros(0, bool)
            if conv["depth_gap"] is not None:
                near &= ~(np.abs(dist[kept] - dist[i]) > conv["depth_gap"])
            if not near.any():
                kept.append(i)
        views.append({"boxes": boxes[kept].tolist(), "scores": scores[kept].tolist(),
                      "classes": classes[kept].tolist()})
        if "state" in out:  # the centre pixel of a box, as the box's corners above give it
            u, w_px = (x * width - .5)[keep][kept], (y * height - .5)[keep][kept]
            views[-1]["world_boxes"] = world_boxes(K[v], c2w[v].astype(np.float64), u, w_px, dist[kept],
                                                   out["state"][v][keep][kept].astype(np.float64))
    return views


def ground(conv: dict, out: dict, grid: list) -> list:
    heat, reg = sigmoid(out["heatmap"][0].astype(np.float64)), out["regression"][0].astype(np.float64)
    C, ny, nx = heat.shape
    padded = np.pad(heat, ((0, 0), (1, 1), (1, 1)), constant_values=-np.inf)
    local = np.max([padded[:, i:i + ny, j:j + nx] for i in range(3) for j in range(3)], axis=0)
    peaks = np.where(heat == local, heat, 0).reshape(-1)
    flat = np.argsort(-peaks, kind="stable")[: conv["top_k"]]
    flat = flat[peaks[flat] >= conv["conf_threshold"]]
    x0, y0 = grid[:2]
    c = conv["cell_m"]
    dets = []
    for f in flat:
        k, iy, ix = np.unravel_index(f, heat.shape)
        r = reg[:, iy, ix]
        size = np.exp(np.minimum(r[3:6], 4))
        yaw = np.arctan2(r[6], r[7]) / 2 + (np.pi if r[8] < 0 else 0.0)
        box = [x0 + (ix + r[0]) * c, y0 + (iy + r[1]) * c, r[2], *size, yaw]
        if all(d["class"] != k or np.hypot(d["box"][0] - box[0], d["box"][1] - box[1]) >= conv["centre_nms_m"]
               for d in dets):
            dets.append({"box": [float(b) for b in box], "score": float(peaks[f]), "class": int(k)})
    return dets


def main(model_path: str, frame_path: str, out_path: str) -> None:
    session = ort.InferenceSession(model_path, providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    conv = json.loads(meta["pnyolo.convention"])
    width, height = (int(s) for s in meta["pnyolo.size"].split("x"))
    if not (8 <= width and 8 <= height and width * height <= 1 << 26):  # the documented range: never allocate more
        raise SystemExit(f"pnyolo.size {meta['pnyolo.size']!r} is out of range")
    frame = np.load(frame_path)
    names = [o.name for o in session.get_outputs()]
    out = dict(zip(names, session.run(names, inputs(conv, frame, width, height))))
    grid = ground_grid(conv, encoded_K(frame, width, height), frame["camera_to_world"], width) if "heatmap" in out else None
    result = ground(conv, out, grid) if "heatmap" in out else yolo_grid(
        conv, out, width, height, encoded_K(frame, width, height), frame["camera_to_world"])
    imported = sorted(m for m in sys.modules if m.split(".")[0] in ("pnyolo", "dataset_spec", "torch"))
    with open(out_path, "w") as f:
        json.dump({"detections": result, "outputs": names, "imported": imported}, f)


if __name__ == "__main__":
    main(*sys.argv[1:])
