"""Time to label one view with 50 actors (synthetic boxes; no Blender).

Measures ``tools.projection.measure_view`` (silhouettes, fractions, boxes; meshes and the instance
map already in memory) and ``label_view`` (plus reading the instance PNG), at a few resolutions and
mesh sizes. Meshes are boxes (12 triangles) or subdivided boxes to mimic real car meshes.

    .venv/bin/python benchmarks/bench_projection.py [--repeats 5]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dataset_spec import Actor, Box3D, CameraInfo, Dataset, DatasetInfo, LightingVariant, Scenario  # noqa: E402
from dataset_spec.synthetic import BOX_FACES, look_at, raycast, simple_intrinsics  # noqa: E402
from tools.projection import label_view, measure_view  # noqa: E402


def subdivided_box(actor: Actor, levels: int):
    """The actor's box as a triangle mesh with each triangle split 4-fold ``levels`` times."""
    verts, faces = actor.box.corners, BOX_FACES
    for _ in range(levels):
        tri = verts[faces]  # (F, 3, 3)
        mids = (tri + np.roll(tri, -1, axis=1)) / 2  # midpoints of edges 01, 12, 20
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        ab, bc, ca = mids[:, 0], mids[:, 1], mids[:, 2]
        new = np.stack([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))], 1)
        verts, faces = new.reshape(-1, 3), np.arange(new.shape[0] * 12).reshape(-1, 3)
    return verts, faces


def scene(n_actors: int, width: int, height: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    actors = []
    for i in range(n_actors):
        ped = i % 3 == 0
        size = (0.5, 0.6, 1.75) if ped else (4.3, 1.8, 1.5)
        centre = (rng.uniform(-18, 18), rng.uniform(4, 45), size[2] / 2)
        actors.append(Actor(i + 2, f"a{i}", "pedestrian" if ped else "car",
                            Box3D(np.array(centre), np.array(size), float(rng.uniform(-3, 3)))))
    cam = CameraInfo("cam", width, height, simple_intrinsics(width, height), look_at((0, -4, 1.6), (0, 20, 1.0)))
    return actors, cam


def timed(fn, repeats: int) -> tuple[float, object]:
    result = fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print(f"{'resolution':>11} {'tris/actor':>10} {'labels':>6} {'measure_view':>13}")
    for width, height in ((480, 270), (960, 540), (1920, 1080)):
        for levels in (0, 3):
            actors, cam = scene(50, width, height)
            meshes = {a.id: subdivided_box(a, levels) for a in actors}
            scn = Scenario("bench", actors, [cam], [])
            _, inst, _ = raycast(scn, cam)
            seconds, labels = timed(lambda: measure_view(cam, actors, meshes, inst, {"car", "pedestrian"}),
                                    args.repeats)
            print(f"{width:>5}x{height:<5} {len(meshes[actors[0].id][1]):>10} {len(labels):>6} "
                  f"{seconds * 1000:>10.1f} ms")
    with tempfile.TemporaryDirectory() as tmp:
        actors, cam = scene(50, 960, 540)
        ds = Dataset.create(Path(tmp) / "ds", DatasetInfo("bench"))
        for a in actors:
            a.mesh = ds.write_mesh("bench", a.id, a.box.corners, BOX_FACES)
        scn = Scenario("bench", actors, [cam], [LightingVariant("noon", "noon.exr")])
        ds.write_scenario(scn)
        ds.write_instance("bench", "cam", raycast(scn, cam)[1])
        seconds, labels = timed(lambda: label_view(ds, "bench", "cam"), args.repeats)
        print(f"label_view incl. reading 50 PLY meshes and instance.png, 960x540: {seconds * 1000:.1f} ms "
              f"({len(labels.objects)} labels)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
