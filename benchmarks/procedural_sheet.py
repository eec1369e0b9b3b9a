"""A contact sheet of procedural draws from above (no Blender): roads, sidewalks, buildings, parked and moving
cars, pedestrians and the camera cars' view directions of ``procedural-K`` for K in a range.

    .venv/bin/python benchmarks/procedural_sheet.py --first 0 --count 12 --out docs/images/procedural_draws.png
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blender_tools.scenarios import build_model  # noqa: E402
from blender_tools.scene_model import pose_matrix  # noqa: E402

COLOURS = {"road": "#3a3a3a", "sidewalks": "#b9b5ad", "island": "#5f8f4a", "building": "#c98a6b", "wall": "#8f8f8f",
           "tree": "#3f7f3f", "pedestrian": "#d9342b", "car": "#3d6fd6", "camera": "#f2b705"}


def _footprints(actor) -> list[np.ndarray]:
    """Each part's ground rectangle (4, 2) in the world: its box's corners from above."""
    T = pose_matrix(actor.location, (0.0, 0.0, actor.yaw))
    out = []
    for part in actor.parts:
        sx, sy = part.size[0] / 2, part.size[1] / 2
        local = np.array([[-sx, -sy, 0], [sx, -sy, 0], [sx, sy, 0], [-sx, sy, 0]])
        P = pose_matrix(part.location, part.rotation)
        pts = (T @ P @ np.c_[local, np.ones(4)].T).T[:, :2]
        out.append(pts)
    return out


def _kind(actor) -> str:
    if actor.cls == "pedestrian":
        return "pedestrian"
    if actor.cls == "car":
        return "camera" if actor.extras.get("drive") == "camera" else "car"
    for key in ("road", "sidewalks", "island", "wall", "tree"):
        if actor.name.startswith(key) or actor.extras.get("kind") == key:
            return key
    return "building" if actor.extras.get("kind") == "building" else ""


def draw(ax, name: str) -> None:
    model = build_model(name, 0)
    for order in ("road", "sidewalks", "island", "building", "wall", "tree", "car", "pedestrian", "camera"):
        for a in model.actors:
            if _kind(a) != order:
                continue
            for quad in _footprints(a):
                ax.fill(quad[:, 0], quad[:, 1], color=COLOURS[order], lw=0)
    for rig in model.cameras:  # each camera car's view direction
        car = model.actor(rig.mounted_on)
        d = np.array([np.cos(car.yaw), np.sin(car.yaw)]) * 12
        ax.arrow(car.location[0], car.location[1], d[0], d[1], width=0.6, color=COLOURS["camera"], lw=0)
    drawn = model.extras["procedural"]
    ax.set_title(f"{name}: {len(drawn['arms'])} arms" + (", roundabout" if drawn["roundabout"] else "")
                 + f", {len(model.cameras)} cameras", fontsize=8)
    ax.set_xlim(-60, 60)
    ax.set_ylim(-60, 60)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_facecolor("#dcd9d2")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--first", type=int, default=0)
    p.add_argument("--count", type=int, default=12)
    p.add_argument("--out", default="docs/images/procedural_draws.png")
    args = p.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = 4
    rows = -(-args.count // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.3 * rows))
    for ax, k in zip(axes.ravel(), range(args.first, args.first + args.count)):
        draw(ax, f"procedural-{k}")
    for ax in axes.ravel()[args.count:]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    print(f"written: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
