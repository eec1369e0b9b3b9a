"""The picture for the detector guide (issue 72): one cell of a target view whose road user (a pedestrian hidden
there, seen by another camera) is the cell's target, its frustum segments (``model.sampler.footprint`` frustum:
each coarse sample a bin of the cell's frustum) and where each segment is read in two other views: its footprint
(the box holding the projection of every point of the segment), coloured by depth, the pedestrian's visible
pixels outlined. The cpu preset's pixelNeRF-YOLO sampler; the geometry needs no trained weights.

With ``--evidence PNG`` (issue 89) also where along that road user's ray the views agree
(``model.sampler.footprint: evidence``, ``pnyolo.components.segment_evidence``): the agreement at every sub-point of
every coarse segment, read from the ImageNet-pretrained EfficientNet-Lite0's maps (no detector training), with the
road user's distance marked, and the sub-points drawn in a view that sees it.

    .venv/bin/python benchmarks/footprint_picture.py out/bench_cpu/dataset --out docs/images/frustum_footprints.jpg
    .venv/bin/python benchmarks/footprint_picture.py out/bench_cpu_seq/dataset --split val --scenario intersection_09 \
        --out /tmp/f.jpg --evidence docs/images/segment_evidence.png
"""
from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dataset_spec.atomic import atomic_write_bytes  # noqa: E402
from pnyolo.bench.presets import load_preset  # noqa: E402
from pnyolo.components.footprints import segment_footprints, segment_radius  # noqa: E402
from pnyolo.config import load_config  # noqa: E402
from pnyolo.data.dataset import MultiViewDataset  # noqa: E402
from pnyolo.engine.predict import Condition, predict  # noqa: E402
from pnyolo.models import build_model  # noqa: E402


def pick(item, maps, max_m: float = np.inf) -> tuple[int, int, int] | None:
    """(view, ground-truth index, 3D row) of a pedestrian hidden in its view, seen by two other views, at most
    ``max_m`` metres from its camera."""
    for v in item.scored:
        gt = item.gt[v]
        for j, row in enumerate(gt.object_rows):
            actor = item.actor_ids[int(row)]
            seen = [u for u in range(len(item.gt)) if u != v and (maps[u] == actor).any()]
            if item.class_names[int(gt.classes[j])] == "pedestrian" and gt.visible_fraction[j] == 0 and len(seen) >= 2 \
                    and gt.distances[j] <= max_m:
                return v, j, int(row)
    return None


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset")
    p.add_argument("--scenario", default="intersection_07")
    p.add_argument("--split", default="test")
    p.add_argument("--out", default=str(ROOT / "docs" / "images" / "frustum_footprints.jpg"))
    p.add_argument("--evidence", metavar="PNG", help="also draw where along the road user's ray the views agree")
    args = p.parse_args()
    preset = load_preset("cpu")
    sets = [*preset.overrides, *preset.model_overrides.get("pixelnerf-yolo", []), "model.sampler.footprint=frustum",
            "model.sampler.fine_samples=0"]
    cfg = load_config(ROOT / "configs" / "cpu.yaml", sets)
    ds = MultiViewDataset(args.dataset, args.split, cfg, scenarios=[args.scenario], every_camera=True)
    torch.manual_seed(0)
    model = build_model(cfg, len(ds.class_names))
    for k in range(len(ds)):
        item = ds[k]
        maps = ds.instance_maps(item)
        chosen = pick(item, maps, cfg.model.sampler.far - 2 if args.evidence else np.inf)  # on the ray's samples
        if chosen is not None:
            break
    else:
        raise SystemExit(f"{args.scenario}: no hidden pedestrian seen by two other cameras")
    v, j, row = chosen
    out = predict(model, [item], cfg.eval, Condition(samples=True)).items[0].out
    seg = model.coverage_points(out, item)(v, j, row)
    centres = seg.origins + seg.t[:, None] * seg.dirs
    K, c2w = item.K.double(), item.camera_to_world.double()
    actor = item.actor_ids[row]
    others = [u for u in range(len(item.gt)) if u != v and (maps[u] == actor).any()][:2]
    panels = [_target_panel(item, v, seg)]
    for u in others:
        cam = (torch.linalg.inv(c2w[u]) @ torch.cat([torch.as_tensor(centres), torch.ones(len(centres), 1,
                                                                                         dtype=torch.float64)], 1).T).T
        half, front = segment_footprints(cam[None, :, :3], segment_radius(torch.as_tensor(seg.half),
                                                                          torch.as_tensor(seg.lateral)), K[u:u + 1, 0, 0],
                                         K[u:u + 1, 1, 1])
        uv = (K[u] @ (cam[:, :3] / cam[:, 2:3]).T).T[:, :2]
        panels.append(_footprint_panel(item, u, uv.numpy(), half[0].numpy(), front[0].numpy(), seg.t, maps[u] == actor))
    sheet = np.concatenate(panels, axis=1)
    sheet = cv2.resize(sheet, (sheet.shape[1] * 2, sheet.shape[0] * 2), interpolation=cv2.INTER_NEAREST)
    _, data = cv2.imencode(Path(args.out).suffix, sheet[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 85])
    atomic_write_bytes(Path(args.out), data.tobytes())
    print(f"{args.scenario}: view {item.camera_names[v]}, pedestrian {actor} hidden there, its cell's "
          f"{len(seg.t)} segments ({seg.t.min():.1f}-{seg.t.max():.1f} m) read in {[item.camera_names[u] for u in others]}"
          f" -> {args.out}")
    if args.evidence:
        evidence_picture(sets, item, v, row, others[0], maps[others[0]] == actor, Path(args.evidence))
    return 0


def evidence_picture(sets: list[str], item, v: int, row: int, u: int, mask: np.ndarray, out: Path) -> None:
    """The agreement along the ray from view ``v``'s camera through road user ``row``'s centre, and its sub-points
    in view ``u`` (which sees it, ``mask``), coloured by agreement."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pnyolo.components.frustums import Frustums
    from pnyolo.components.geometry import Cameras
    from pnyolo.components.segment_evidence import read_segments, sub_points

    pre = load_config(ROOT / "configs" / "cpu.yaml", [
        *sets, "model.sampler.footprint=evidence", "model.encoder.backbone=efficientnet_lite0",
        "model.encoder.pretrained=true", "model.encoder.num_layers=2", "model.encoder.context_channels=0"])
    model = build_model(pre, len(item.class_names)).eval()
    K, c2w = item.K.float(), item.camera_to_world.float()
    origin, centre = c2w[v, :3, 3], item.boxes_3d[row, :3].float()
    distance = float((centre - origin).norm())
    direction = (centre - origin) / distance
    m = pre.model.sampler.evidence_points
    with torch.no_grad():
        coarse = model.sample(origin[None], direction[None])
        half = (coarse.t_far - coarse.t_near)[:, None] / (2 * coarse.t.shape[1])
        feats = model.encoder(item.images.float())
        cams = Cameras(K, c2w, item.grid.width, item.grid.height)
        own = torch.arange(len(K))[:, None] == v  # the target view sees one pixel all along: left out
        ev, _ = read_segments(Frustums(origin[None], direction[None], coarse.t, half.expand_as(coarse.t)), cams, feats,
                              model.encoder.strides, m, own)
        ts = sub_points(coarse.t, half.expand_as(coarse.t), m).reshape(-1).numpy()
        uv, _, _, valid = cams.project(origin + torch.as_tensor(ts, dtype=torch.float32)[:, None] * direction)
    score = ev.scores.reshape(-1).numpy()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.6), gridspec_kw={"width_ratios": [1.2, 1]})
    a.plot(ts, score, color="0.3", lw=1)
    a.scatter(ts, score, c=score, cmap="viridis", s=9, zorder=3)
    a.axvline(distance, color="magenta", ls="--",
              label=f"the pedestrian ({distance:.1f} m), hidden in {item.camera_names[v]}")
    for edge in (coarse.t - half).reshape(-1).numpy():
        a.axvline(edge, color="0.85", lw=0.6, zorder=0)
    a.set_xlabel(f"metres along {item.camera_names[v]}'s ray through it (grey: the coarse segments)")
    a.set_ylabel("agreement of the other views (-log spread)")
    a.legend(loc="upper left", fontsize=8)
    img = _image(item, u)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(img, contours, -1, (255, 0, 255), 1)
    b.imshow(img)
    seen = valid[u].numpy()
    b.scatter(uv[u, seen, 0].numpy(), uv[u, seen, 1].numpy(), c=score[seen], cmap="viridis", s=6)
    b.set_title(f"{item.camera_names[u]}: the ray's sub-points by agreement", fontsize=9)
    b.axis("off")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(out, buf.getvalue())
    others = valid.numpy().sum(0) - valid[v].numpy()
    best = ts[int(np.argmax(np.where(others >= 2, score, -np.inf)))]
    print(f"evidence: the views agree most at {best:.1f} m along the ray, the pedestrian at {distance:.1f} m -> {out}")


def _image(item, view: int) -> np.ndarray:
    return np.ascontiguousarray((item.images[view].permute(1, 2, 0).numpy() * 255).astype(np.uint8))


def _target_panel(item, v: int, seg) -> np.ndarray:
    """The target view with the cell (its rays' pixel) marked."""
    img = _image(item, v)
    K, c2w = item.K[v].double().numpy(), item.camera_to_world[v].double().numpy()
    far = seg.origins[0] + seg.t.max() * seg.dirs[0]
    cam = np.linalg.inv(c2w) @ np.append(far, 1.0)
    u, w = (K @ (cam[:3] / cam[2]))[:2]
    cell = item.grid.cell_px if hasattr(item.grid, "cell_px") else 8
    cv2.rectangle(img, (int(u - cell / 2), int(w - cell / 2)), (int(u + cell / 2), int(w + cell / 2)), (255, 40, 40), 2)
    cv2.putText(img, f"target {item.camera_names[v]}: the cell", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
    return img


def _footprint_panel(item, u: int, uv: np.ndarray, half: np.ndarray, front: np.ndarray, t: np.ndarray,
                     mask: np.ndarray) -> np.ndarray:
    """A source view with every segment's footprint box, near (yellow) to far (blue), the road user outlined."""
    img = _image(item, u)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(img, contours, -1, (255, 0, 255), 2)
    span = max(float(t.max() - t.min()), 1e-6)
    for k in np.argsort(-t):
        if not front[k]:
            continue
        a = (t[k] - t.min()) / span
        colour = (int(255 * (1 - a)), int(220 * (1 - a) + 60 * a), int(255 * a))
        (x, y), (hx, hy) = uv[k], half[k]
        cv2.rectangle(img, (int(x - hx), int(y - hy)), (int(x + hx), int(y + hy)), colour, 1)
    cv2.putText(img, f"{item.camera_names[u]}: footprints", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
    return img


if __name__ == "__main__":
    sys.exit(main())
