"""What more distinct training scenes buy (issues 73, 85): bev trained with the cpu preset's steps, configuration and
selection on 21, 42, 84 and 168 distinct training scenes, once as redraws of the cpu preset's 7 training layouts
and once as procedural layouts (``procedural-K``, one draw each), every scene under one lighting drawn by its name
and the seed, each scored on the cpu preset's validation and test splits: the test split's two sets, its built-in
layouts and the new layouts no point trained on (``pnyolo.bench.new_layouts``). One ``pnyolo-bench`` run per point
into OUT/POINT, all sharing one dataset folder (OUT/dataset: renders reused across points), then the curve. A
finished bench run that trained bev on a point's scenes with the cpu preset's settings and splits (the cpu preset's
own run is redraws-84) stands for that point with --adopt, checked before any work.

    python benchmarks/scaling.py --out out/scaling                              # every point, then the report
    python benchmarks/scaling.py --out out/scaling --points procedural-84,procedural-168
    python benchmarks/scaling.py --out out/scaling --adopt redraws-84=runs/bench_cpu --report-only
    python benchmarks/scaling.py --out out/scaling --report-only --publish docs/results/scaling

The report (OUT/report, or --publish DIR too) is ``benchmarks/scaling_curve.py``'s: the table of points, each
paired difference with its standard error, the plot.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scaling_curve import POINTS, report, training_scenes  # noqa: E402 - the curve's module beside this one

from dataset_spec.atomic import atomic_write_text  # noqa: E402

# the preset keys that shape bev's training, selection and test: an adopted run must share them with the cpu preset
SHARED = ("val", "test", "render", "hdr", "split_render", "new_layouts_render", "config", "overrides", "steps",
          "max_distance", "anchors", "select_iou", "conf_grid", "nms_grid")


class ScalingError(Exception):
    """A user mistake named in one line (the script exits 2)."""


def _cpu():
    from pnyolo.bench.presets import load_preset

    return load_preset("cpu")


def write_preset(out: Path, name: str) -> Path:
    """The point's preset file: the cpu preset with this training split and bev alone (no pose-noise sweep)."""
    cpu = _cpu()
    kind, n = POINTS[name]
    preset = {"base": "cpu", "description": f"scaling point {name}: bev on {n} distinct training scenes ({kind})",
              "splits": {"train": training_scenes(kind, n), "val": cpu.val, "test": cpu.test},
              "models": ["bev"], "primary": "", "baseline": "", "fusion": [], "pose_noise_sweep": []}
    path = out / "presets" / f"{name}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, yaml.safe_dump(preset, sort_keys=False))
    return path


def _plain(value):
    """``value`` as report.json holds it (tuples as lists)."""
    return json.loads(json.dumps(value))


def check_adoption(name: str, run: Path, seed: int) -> None:
    """Whether the finished bench run ``run`` may stand for the point ``name``: bev trained on exactly the point's
    scenes with the cpu preset's settings, splits and ``seed``; ScalingError naming the first difference."""
    where = f"--adopt {name}={run}"
    if name not in POINTS:
        raise ScalingError(f"{where}: unknown point; known: {', '.join(POINTS)}")
    report = run / "report" / "report.json"
    if not report.is_file() or not (run / "runs" / "bev" / "bench_timing.json").is_file():
        raise ScalingError(f"{where}: not a finished bench run with bev (no report/report.json or runs/bev)")
    doc = json.loads(report.read_text())
    preset, cpu = doc.get("preset") or {}, _cpu()
    kind, n = POINTS[name]
    if sorted(preset.get("train") or []) != sorted(training_scenes(kind, n)):
        raise ScalingError(f"{where}: its training split is not the point's {n} scenes ({kind})")
    for key in SHARED:
        if preset.get(key) != _plain(getattr(cpu, key)):
            raise ScalingError(f"{where}: its {key} differs from the cpu preset's")
    if (preset.get("model_overrides") or {}).get("bev", []) != _plain(cpu.model_overrides.get("bev", [])):
        raise ScalingError(f"{where}: its bev model_overrides differ from the cpu preset's")
    if doc.get("seed") != seed:
        raise ScalingError(f"{where}: run with seed {doc.get('seed')}, not {seed}")


def adopt(out: Path, name: str, run: Path) -> None:
    """OUT/POINT as a link to the checked run (a link of an earlier adoption replaced, a point's own run kept)."""
    link = out / name
    if link.is_symlink():
        link.unlink()
    elif link.exists():
        raise ScalingError(f"--adopt {name}: {link} holds the point's own run; remove it to adopt another")
    link.parent.mkdir(parents=True, exist_ok=True)
    link.symlink_to(run.resolve(), target_is_directory=True)


def run_point(out: Path, name: str, seed: int) -> None:
    """One ``pnyolo-bench`` run of the point (renders and a finished training reused)."""
    cmd = [str(Path(sys.executable).parent / "pnyolo-bench"), str(write_preset(out, name)), "--out", str(out / name),
           "--data", str(out / "dataset"), "--seed", str(seed), "--quiet"]
    print("[scaling] " + " ".join(cmd), flush=True)
    t0 = time.time()
    subprocess.run(cmd, check=True)
    print(f"[scaling] {name}: {time.time() - t0:.0f} s", flush=True)


def _adoptions(values: list[str], seed: int) -> dict[str, Path]:
    """--adopt POINT=DIR values, each checked (``check_adoption``) before any work."""
    adopted = {}
    for value in values:
        name, sep, run = value.partition("=")
        if not sep or not run:
            raise ScalingError(f"--adopt {value}: expected POINT=DIR (e.g. redraws-84=runs/bench_cpu)")
        check_adoption(name, Path(run), seed)
        adopted[name] = Path(run)
    return adopted


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/scaling")
    p.add_argument("--points", default=",".join(POINTS), help=f"comma list of {', '.join(POINTS)} to run")
    p.add_argument("--adopt", action="append", default=[], metavar="POINT=DIR",
                   help="a finished bench run standing for a point (checked: bev, the point's scenes, the cpu preset)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--report-only", action="store_true",
                   help="only the report, from the points already run (benchmarks/scaling_curve.py)")
    p.add_argument("--publish", metavar="DIR", help="write the report there too (e.g. docs/results/scaling)")
    args = p.parse_args(argv)
    out = Path(args.out).resolve()
    names = [n.strip() for n in args.points.split(",") if n.strip()]
    bad = [n for n in names if n not in POINTS]
    if bad:
        p.error(f"--points: unknown {bad}; known: {', '.join(POINTS)}")
    try:
        adopted = _adoptions(args.adopt, args.seed)
        for name, run in adopted.items():
            adopt(out, name, run)
    except ScalingError as e:
        print(f"scaling: {e}", file=sys.stderr)
        return 2
    if not args.report_only:
        for name in [n for n in names if n not in adopted]:
            run_point(out, name, args.seed)
    return report(out, Path(args.publish) if args.publish else None)


if __name__ == "__main__":
    sys.exit(main())
