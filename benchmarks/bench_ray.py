"""Benchmark blender-gen on Ray against local workers at equal CPUs (issue 33).

    .venv/bin/python benchmarks/bench_ray.py                          # 4 toy layouts, 2 variants
    .venv/bin/python benchmarks/bench_ray.py --scenes intersection_01,intersection_02 --quality preview

Four renders of the same scenarios from scratch, each into its own folder:

* ``local, 1 CPU``: ``--workers 1`` pinned to one core (``taskset -c 0``);
* ``ray, 1 CPU``: a Ray head with ``--num-cpus 1`` pinned to the same core, ``--ray-cpus 1``;
* ``local, 2 CPUs``: ``--workers 2`` (two bpy processes over each scenario's cameras);
* ``ray, 2 CPUs``: a Ray head with ``--num-cpus 2``, ``--ray-cpus 1`` (two scenarios at a time).

The cluster is started before the clock runs (as a cluster already serving its users would be);
the clock covers the whole ``blender-gen render`` process. Reported: wall seconds, the ratio
Ray/local at equal CPUs (target <= 1.10), and the per-task overhead (Ray wall minus local wall,
per scenario, at one CPU, where there is no parallelism to hide it). Not a test: timings depend
on the machine and its load (``os.getloadavg`` is printed).
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dataset_spec.atomic import atomic_write_json

ROOT = Path(__file__).resolve().parent.parent
PORT = 6391


def ray_cli() -> str:
    return str(Path(sys.executable).parent / "ray")


def render(args: argparse.Namespace, out: Path, extra: list[str], pin: bool) -> float:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "blender_tools.cli", "render", "--scene", args.scenes, "--hdr", args.hdr,
           "--quality", args.quality, *(["--resolution", args.resolution] if args.resolution else []),
           "--out", str(out), "--no-progress", *extra]
    t0 = time.perf_counter()
    subprocess.run(["taskset", "-c", "0", *cmd] if pin else cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def with_cluster(cpus: int, pin: bool, fn):
    """``fn()`` while a Ray head with ``cpus`` CPUs runs on 127.0.0.1 (stopped afterwards)."""
    start = [ray_cli(), "start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(PORT),
             "--num-cpus", str(cpus), "--include-dashboard", "false", "--disable-usage-stats"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "RAY_AUTH_MODE": "disabled"}
    subprocess.run(["taskset", "-c", "0", *start] if pin else start, check=True, env=env,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(2)
        return fn()
    finally:
        subprocess.run([ray_cli(), "stop", "--force"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default="toy,toy-s1,toy-s2,toy-s3")
    p.add_argument("--hdr", default="noon,dusk")
    p.add_argument("--quality", default="preview")
    p.add_argument("--resolution", default="192x128")
    p.add_argument("--json", help="write the figures here too")
    args = p.parse_args()
    if shutil.which("taskset") is None:
        raise SystemExit("bench_ray: needs taskset (util-linux) to pin the 1-CPU runs")
    n = len(args.scenes.split(","))
    print(f"machine: {os.cpu_count()} cores, load average before: {os.getloadavg()[0]:.2f}; {n} scenarios")
    addr = ["--ray", f"127.0.0.1:{PORT}"]
    os.environ["RAY_AUTH_MODE"] = "disabled"  # the driver joins the benchmark's own cluster
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        render(args, t / "warm", [], pin=False)  # caches (HDR maps, bpy import) warm for every run
        wall = {
            "local_1": render(args, t / "local_1", ["--workers", "1"], pin=True),
            "ray_1": with_cluster(1, True, lambda: render(args, t / "ray_1", [*addr, "--ray-cpus", "1"], pin=True)),
            "local_2": render(args, t / "local_2", ["--workers", "2"], pin=False),
            "ray_2": with_cluster(2, False, lambda: render(args, t / "ray_2", [*addr, "--ray-cpus", "1"], pin=False)),
        }
    for cpus in (1, 2):
        lw, rw = wall[f"local_{cpus}"], wall[f"ray_{cpus}"]
        print(f"{cpus} CPU{'s' if cpus > 1 else ' '}: local {lw:7.1f} s   ray {rw:7.1f} s   ray/local {rw / lw:5.2f}")
    overhead = (wall["ray_1"] - wall["local_1"]) / n
    print(f"per-task overhead (1 CPU): {overhead:+.2f} s per scenario")
    print(f"scaling 1 -> 2 CPUs: local x{wall['local_1'] / wall['local_2']:.2f}, ray x{wall['ray_1'] / wall['ray_2']:.2f}")
    if args.json:
        atomic_write_json(args.json, {"wall_s": wall, "overhead_s_per_task": overhead, "scenarios": n})
    return 0


if __name__ == "__main__":
    sys.exit(main())
