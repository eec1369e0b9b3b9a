"""A scenario from above (``dataset-spec info DIR --plots OUT``): its buildings and other tall static
things, the camera cars with their view cones, and every road user's trajectory over the sequence,
coloured by class (a scenario of one frame shows where each stands).

    plot_trajectories(Dataset.open("out/ds"), "intersection_07", "out/stats/trajectories_intersection_07.png")
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .atomic import atomic_savefig
from .dataset import Dataset

CLASS_COLOURS = {"car": "tab:blue", "pedestrian": "tab:orange"}
CONE_M = 25.0  # length of a drawn view cone
MAX_STATIC_AREA = 600.0  # m^2: larger boxes are the ground, the road, the sidewalks (not drawn)


def footprint(center, size, yaw) -> np.ndarray:
    """(4, 2) the ground corners of a box of ``size`` at ``center`` turned by ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    half = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * np.asarray(size[:2]) / 2
    return half @ np.array([[c, s], [-s, c]]) + np.asarray(center[:2])


def view_cone(K: np.ndarray, width: int, c2w: np.ndarray) -> np.ndarray:
    """(3, 2) a camera's horizontal field of view on the ground: its centre and the two edge rays."""
    half = math.atan2(width / 2, K[0, 0])
    ends = [c2w[:3, :3] @ np.array([math.tan(a), 0.0, 1.0]) for a in (-half, half)]
    origin = c2w[:2, 3]
    return np.array([origin] + [origin + CONE_M * e[:2] / max(np.linalg.norm(e[:2]), 1e-9) for e in ends])


def plot_trajectories(ds: Dataset, name: str, path: str | Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    scn, seq = ds.scenario(name), ds.sequence(name)
    fig, ax = plt.subplots(figsize=(7, 7))
    for a in scn.actors:
        if a.id in seq.frames[0].actors or a.box.size[0] * a.box.size[1] > MAX_STATIC_AREA or a.box.size[2] < 1.0:
            continue
        ax.add_patch(Polygon(footprint(a.box.center, a.box.size, a.box.yaw), closed=True, color="0.75", lw=0))
    mounts = {c.mounted_on for c in scn.cameras}
    for a in scn.actors:
        if a.id not in seq.frames[0].actors:
            continue
        colour = CLASS_COLOURS.get(a.cls, "tab:green")
        track = np.array([fr.actors[a.id].center[:2] for fr in seq.frames])
        last = seq.frames[-1].actors[a.id]
        ax.add_patch(Polygon(footprint(last.center, a.box.size, last.yaw), closed=True, fill=a.id in mounts,
                             ec=colour, fc="0.2" if a.id in mounts else "none", lw=0.8))
        if np.ptp(track, axis=0).max() > 1e-3:
            ax.plot(track[:, 0], track[:, 1], "-", color=colour, lw=1.2)
            ax.plot(track[0, 0], track[0, 1], "o", color=colour, ms=2.5)
    for cam in scn.cameras:
        path_xy = np.array([fr.cameras[cam.name][:2, 3] for fr in seq.frames])
        cone = view_cone(cam.K, cam.width, seq.frames[-1].cameras[cam.name])
        ax.add_patch(Polygon(cone, closed=True, color="tab:red", alpha=0.12, lw=0))
        ax.plot(path_xy[:, 0], path_xy[:, 1], "-", color="tab:red", lw=1.5)
        ax.annotate(cam.name, cone[0], fontsize=7, color="tab:red")
    for cls, colour in CLASS_COLOURS.items():
        ax.plot([], [], "-", color=colour, label=f"{cls} trajectory")
    ax.plot([], [], "-", color="tab:red", label="camera and view cone")
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    timing = f", {len(seq.frames)} frames, {seq.seconds:.1f} s" if len(seq.frames) > 1 else ", one frame"
    ax.set_title(f"{name} from above{timing} (boxes at the last frame)", fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    ax.grid(alpha=0.2)
    fig.tight_layout()
    out = Path(path)
    atomic_savefig(fig, out, dpi=110)
    plt.close(fig)
    return out
