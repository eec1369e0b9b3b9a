"""Benchmark blender-gen: seconds per view per preset, pipeline overhead, cost of an extra HDR variant.

    .venv/bin/python benchmarks/bench_render.py                       # intersection_07, preview + default
    .venv/bin/python benchmarks/bench_render.py --scene toy --quality preview
    .venv/bin/python benchmarks/bench_render.py --frames 1,10,50             sequences: the cost of a frame

For each preset it renders the scene twice from scratch (``--force``): with one HDR variant
(noon) and with two (noon, overcast). Reported:

* data pass (depth + ids) and RGB seconds per view (Cycles time of each render call),
* pipeline overhead = wall time of the whole ``blender-gen render`` / time inside Cycles
  (target <= 1.15: process start, scene build, export, PNG/EXR conversion, labelling),
* extra-variant cost = wall(2 variants) - wall(1 variant) versus the extra RGB renders' Cycles
  time (target: the extra variant costs only its RGB renders).

With ``--frames`` it renders sequences instead (preview, one HDR variant, from scratch): for each
frame count N the whole run's wall time, the seconds per frame, and the cost of a frame after the first,
(wall(N) - wall(1)) / (N - 1), beside the first frame's (today's single-frame render, wall(1)); goal:
at most 0.8 of it (the static scene is built, exported and labelled once; a frame moves the road users).

Not a test: timings depend on the machine and its load (``os.getloadavg`` is printed).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run(scene: str, quality: str, hdr: str, out: Path, frames: int = 1) -> dict:
    timings = out.with_suffix(".json")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "blender_tools.cli", "render", "--scene", scene, "--hdr", hdr,
                    "--quality", quality, "--out", str(out), "--force", "--no-progress", "--timings", str(timings),
                    "--frames", str(frames), "--fps", "10"], check=True, env=env, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    rec = json.loads(timings.read_text())[0]
    rec["process_wall_s"] = wall
    return rec


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="intersection_07")
    p.add_argument("--quality", default="preview,default")
    p.add_argument("--frames", default=None, metavar="N,N,...", help="time sequences of these frame counts instead")
    args = p.parse_args()
    print(f"machine: {os.cpu_count()} cores, load average before: {os.getloadavg()[0]:.2f}")
    if args.frames:
        return sequences(args.scene, [int(n) for n in args.frames.split(",")])
    with tempfile.TemporaryDirectory() as tmp:
        for quality in args.quality.split(","):
            one = run(args.scene, quality, "noon", Path(tmp) / f"{quality}_1")
            two = run(args.scene, quality, "noon,overcast", Path(tmp) / f"{quality}_2")
            data = [r["render_s"] for r in two["renders"] if r["kind"] == "data"]
            rgb = [r["render_s"] for r in two["renders"] if r["kind"] != "data"]
            extra_rgb = sum(r["render_s"] for r in two["renders"] if r["kind"] == "overcast")
            extra_wall = two["process_wall_s"] - one["process_wall_s"]
            print(f"[{quality}] {args.scene}: {len(data)} cameras")
            print(f"  data pass  {sum(data) / len(data):6.2f} s/view   RGB {sum(rgb) / len(rgb):6.2f} s/view/variant")
            for label, rec in (("1 variant ", one), ("2 variants", two)):
                print(f"  {label}: wall {rec['process_wall_s']:6.1f} s, Cycles {rec['render_s']:6.1f} s, "
                      f"overhead {rec['process_wall_s'] / rec['render_s']:.3f}")
            print(f"  extra variant: +{extra_wall:.1f} s wall for {extra_rgb:.1f} s of its RGB renders "
                  f"(ratio {extra_wall / extra_rgb:.2f})")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


def sequences(scene: str, counts: list[int]) -> int:
    """Seconds per frame of sequences of ``counts`` frames (preview, noon), as a markdown table."""
    walls = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in sorted(set([1] + counts)):
            rec = run(scene, "preview", "noon", Path(tmp) / f"seq_{n}", frames=n)
            walls[n] = (rec["process_wall_s"], rec["render_s"])
    first = walls[1][0]
    print(f"| frames | wall (s) | Cycles (s) | s per frame | a frame after the first (s) | of the first |")
    print("|---:|---:|---:|---:|---:|---:|")
    for n, (wall, cycles) in sorted(walls.items()):
        after = (wall - first) / (n - 1) if n > 1 else first
        print(f"| {n} | {wall:.1f} | {cycles:.1f} | {wall / n:.2f} | {after:.2f} | {after / first:.2f} |")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
