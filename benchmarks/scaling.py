"""What more distinct training scenes buy (issue 73): bev trained with the cpu preset's steps, configuration and
selection on 21, 42, 84 and 168 distinct training scenes, once as redraws of the cpu preset's 7 training layouts
and once as procedural layouts (``procedural-K``, one draw each), every scene under one lighting drawn by its name
and the seed, each scored on the cpu preset's unchanged validation and test splits. One ``pnyolo-bench`` run per
point into OUT/POINT, all sharing one dataset folder (OUT/dataset: renders reused across points), then the curve.

    python benchmarks/scaling.py --out out/scaling                              # every point, then the report
    python benchmarks/scaling.py --out out/scaling --points redraws-21,redraws-42
    python benchmarks/scaling.py --out out/scaling --report-only --publish docs/results/scaling

The report (OUT/report, or --publish DIR): ``scaling.md`` (a row per point: test F1@0.2, AP50 and hidden-but-seen
recall with their bootstrap standard errors over the test scenarios, validation F1, render and training seconds),
``scaling.png`` (those figures against distinct scenes, log scale) and ``points.json``.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

from dataset_spec.atomic import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
TRAIN_LAYOUTS = ["intersection_01", "intersection_02", "intersection_03", "intersection_04", "intersection_05",
                 "intersection_06", "intersection_08"]
SIZES = (21, 42, 84, 168)
POINTS = {**{f"redraws-{n}": ("redraws", n) for n in SIZES}, **{f"procedural-{n}": ("procedural", n) for n in SIZES}}


def training_scenes(kind: str, n: int) -> list[str]:
    """The ``n`` training scenes of a point: the 7 layouts drawn n / 7 times (the first draw, then -s1 ...), or
    procedural layouts 0 .. n - 1 (nested: a smaller set is part of every larger one)."""
    if kind == "redraws":
        return [layout if k == 0 else f"{layout}-s{k}" for k in range(n // len(TRAIN_LAYOUTS)) for layout in TRAIN_LAYOUTS]
    return [f"procedural-{k}" for k in range(n)]


def write_preset(out: Path, name: str) -> Path:
    """The point's preset file: the cpu preset with this training split and bev alone (no pose-noise sweep)."""
    sys.path.insert(0, str(ROOT))
    from pnyolo.bench.presets import load_preset

    cpu = load_preset("cpu")
    kind, n = POINTS[name]
    preset = {"base": "cpu", "description": f"scaling point {name}: bev on {n} distinct training scenes ({kind})",
              "splits": {"train": training_scenes(kind, n), "val": cpu.val, "test": cpu.test},
              "models": ["bev"], "primary": "", "baseline": "", "fusion": [], "pose_noise_sweep": []}
    path = out / "presets" / f"{name}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, yaml.safe_dump(preset, sort_keys=False))
    return path


def run_point(out: Path, name: str, seed: int) -> None:
    """One ``pnyolo-bench`` run of the point (renders and a finished training reused)."""
    cmd = [str(Path(sys.executable).parent / "pnyolo-bench"), str(write_preset(out, name)), "--out", str(out / name),
           "--data", str(out / "dataset"), "--seed", str(seed), "--quiet"]
    print("[scaling] " + " ".join(cmd), flush=True)
    t0 = time.time()
    subprocess.run(cmd, check=True)
    print(f"[scaling] {name}: {time.time() - t0:.0f} s", flush=True)


def render_seconds(out: Path) -> dict[str, float]:
    """Cycles seconds (data passes and RGB) of every scene that every blender-gen timings record under ``out``
    (the points' runs and renders made beforehand) knows, read once for all points."""
    seconds: dict[str, float] = {}
    for path in out.glob("timings/*.json"):
        for entry in json.loads(path.read_text()):
            seconds[entry["scenario"]] = seconds.get(entry["scenario"], 0.0) + sum(r["render_s"] for r in entry["renders"])
    for path in out.glob("*/render_seconds.json"):
        for scene, s in json.loads(path.read_text()).items():
            seconds.setdefault(scene, s["data_s"] + s["rgb_s"])
    return seconds


def _total(seconds: dict[str, float], scenes: list[str]) -> float | None:
    """The scenes' render seconds; None when a scene's are unknown."""
    return sum(seconds[s] for s in scenes) if all(s in seconds for s in scenes) else None


def point_figures(out: Path, name: str, seconds: dict[str, float]) -> dict | None:
    """The point's figures from its report.json (None before its run); ``seconds``: render_seconds(out)."""
    path = out / name / "report" / "report.json"
    if not path.is_file():
        return None
    report = json.loads(path.read_text())
    bev = report["models"]["bev"]
    se = bev.get("standard_errors") or {}
    hidden = bev["recall_by_visibility"]["0.2"].get("hidden here, seen in another view", {})
    timing = json.loads((out / name / "runs" / "bev" / "bench_timing.json").read_text())
    kind, n = POINTS[name]
    return {"point": name, "kind": kind, "scenes": n, "f1": bev["strict"]["0.2"]["f1"], "f1_se": _get(se, "f1", "0.2"),
            "ap50": bev["ap50"], "ap50_se": se.get("ap50"), "hidden_seen_recall": hidden.get("recall"),
            "hidden_seen_n": hidden.get("n"), "hidden_seen_recall_se": _get(se, "hidden_seen_recall", "0.2"),
            "val_f1": bev["selection"]["best_val_f1"], "val_f1_se": bev["selection"]["val_f1_se"],
            "train_s": timing["seconds"], "train_threads": timing.get("threads"),
            "train_from": timing.get("resumed_from", 0), "train_steps": timing.get("steps"),
            "render_s": _total(seconds, training_scenes(kind, n)),
            "command": report.get("command", "").replace(f"{ROOT}/", "")}   # paths as from the repository root


def _get(se: dict, key: str, iou: str):
    value = se.get(key)
    return value.get(iou) if isinstance(value, dict) else None


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def _resumed(row: dict) -> str:
    """Where a resumed training's seconds start: they count its last session only."""
    return f"; steps {row['train_from']}-{row['train_steps']} only, resumed" if row.get("train_from") else ""


def write_report(out: Path, rows: list[dict], folder: Path, missing: list[str]) -> None:
    """scaling.md, scaling.png and points.json into ``folder`` (``missing``: the points not run yet)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / "points.json", json.dumps(rows, indent=1) + "\n")
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.6))
    for ax, (key, title) in zip(axes, (("f1", "test F1@0.2"), ("ap50", "test AP50"),
                                       ("hidden_seen_recall", "test hidden-but-seen recall@0.2"),
                                       ("render_s", "render seconds of the training set"))):
        for kind, style in (("redraws", "o-"), ("procedural", "s--")):
            pts = [r for r in rows if r["kind"] == kind and r[key] is not None]
            if pts:
                err = [r.get(f"{key}_se") or 0 for r in pts] if key != "render_s" else None
                ax.errorbar([r["scenes"] for r in pts], [r[key] for r in pts], yerr=err, fmt=style, capsize=3,
                            label=f"{kind} of {'the 7 training layouts' if kind == 'redraws' else 'new layouts'}")
        ax.set_xscale("log", base=2)
        ax.set_xticks(SIZES, [str(s) for s in SIZES])
        ax.set_xlabel("distinct training scenes")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / "scaling.png", dpi=110)
    plt.close(fig)
    fmt = lambda v, se=None: "-" if v is None else (f"{v:.3f}" if se is None else f"{v:.3f} ± {se:.3f}")  # noqa: E731
    lines = ["# What more distinct training scenes buy (bev, cpu preset)", "",
             "bev trained with the cpu preset's 6000 steps, configuration and selection on each training set, scored "
             "on the cpu preset's validation and test splits (test: 6 scenes x 4 lightings). ± is one bootstrap "
             "standard error, test scenarios resampled. Made by `benchmarks/scaling.py`.", "",
             "| point | distinct scenes | validation F1@0.2 | test F1@0.2 | test AP50 | hidden-but-seen recall@0.2 (n) "
             "| render s (training set) | training s (threads) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['point']} | {r['scenes']} | {fmt(r['val_f1'], r['val_f1_se'])} | {fmt(r['f1'], r['f1_se'])} "
                     f"| {fmt(r['ap50'], r['ap50_se'])} | {fmt(r['hidden_seen_recall'], r['hidden_seen_recall_se'])} "
                     f"({r['hidden_seen_n']}) | {_seconds(r['render_s'])} | {r['train_s']:.0f} ({r['train_threads']}"
                     f"{_resumed(r)}) |")
    lines += ["", "Each point's run: " + "; ".join(f"{r['point']}: `{r['command']}`" for r in rows) + "."]
    bare = [r["point"] for r in rows if r["f1_se"] is None]
    if bare:
        lines += ["", f"No test standard error for {', '.join(bare)}: its run kept no per-scenario figures to resample "
                  "(made before issue 76)."]
    if missing:
        lines += ["", "Not run yet: " + ", ".join(missing) + "."]
    lines += ["", "![test figures against distinct training scenes](scaling.png)", ""]
    atomic_write_text(folder / "scaling.md", "\n".join(lines))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/scaling")
    p.add_argument("--points", default=",".join(POINTS), help=f"comma list of {', '.join(POINTS)}")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--report-only", action="store_true", help="only the report, from the points already run")
    p.add_argument("--publish", metavar="DIR", help="write the report there too (e.g. docs/results/scaling)")
    args = p.parse_args()
    out = Path(args.out).resolve()
    names = [n.strip() for n in args.points.split(",") if n.strip()]
    bad = [n for n in names if n not in POINTS]
    if bad:
        p.error(f"--points: unknown {bad}; known: {', '.join(POINTS)}")
    if not args.report_only:
        for name in names:
            run_point(out, name, args.seed)
    seconds = render_seconds(out)
    figures = {n: point_figures(out, n, seconds) for n in POINTS}
    rows = [r for r in figures.values() if r is not None]
    if not rows:
        print("scaling: no point has been run yet", file=sys.stderr)
        return 2
    write_report(out, rows, out / "report", [n for n, r in figures.items() if r is None])
    if args.publish:
        shutil.copytree(out / "report", Path(args.publish), dirs_exist_ok=True)
    print((out / "report" / "scaling.md").read_text())
    return 0 if all(math.isfinite(r["f1"]) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
