"""The placement probe (issue 87, item 1): what limits a detector's translation error (the devkit's ATE)? Each
detection of a nuScenes results file is matched as the devkit matches for its true-positive errors (2 m, by
score) on the split's export with buses and trucks as cars (the classes the models name), and its ground-plane error
is split along the line of sight from the nearest camera of its sample (depth) and across it (lateral), by distance.
Depth error that dominates and grows with distance says the lift is the limit (depth supervision, a depth
distribution); errors alike in every direction say the grid or the heatmap is. Duplicates within 1 m of a
higher-scoring detection of the same class say what a suppression by centre distance would remove.

    .venv/bin/python benchmarks/placement_errors.py out/bench_cpu_seq/dataset \\
        --results bev=out/bench_cpu_seq/bev/results_nusc_test.json --split test --out out/placement

Writes OUT/placement.json, OUT/placement.md and OUT/placement.png (error along the ray against distance).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="placement_errors.py", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog="example:\n" + __doc__.split("\n\n")[1])
    p.add_argument("dataset", help="the dataset folder the results were made on")
    p.add_argument("--results", action="append", required=True, metavar="NAME=RESULTS.json",
                   help="a model's nuScenes results on the split (repeatable)")
    p.add_argument("--split", default="test", help="the split the results cover (default test)")
    p.add_argument("--radius", type=float, default=2.0, help="matching distance, metres (the devkit's TP errors: 2)")
    p.add_argument("--duplicate-radius", type=float, default=1.0, help="what counts as a duplicate, metres")
    p.add_argument("--out", default="out/placement", help="output folder (default out/placement)")
    return p.parse_args()


def _evaluate(dataset: str, split: str, results: Path, radius: float, dup_radius: float) -> dict:
    from pnyolo.evaluation.placement import placement_of

    return placement_of(dataset, split, json.loads(results.read_text()), radius, dup_radius)


def _fmt(v, digits=2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _markdown(figures: dict) -> str:
    lines = ["# Placement errors: along the line of sight (depth) and across it", "",
             "Matches as the devkit's true-positive errors (2 m, by score); radial > 0: placed farther than it is. "
             "Share: the squared error's part along the ray, standard error over layouts.", ""]
    for model, classes in figures.items():
        for c, f in classes.items():
            lines += [f"## {model}, {c}: {f['matches']} matches, {f['predictions']} predictions "
                      f"({f['duplicates']} within 1 m of a higher-scoring one), {f['ground_truth']} ground truth", "",
                      "| distance | n | median error m | RMS radial m | RMS lateral m | mean radial m | radial share |",
                      "|---|---|---|---|---|---|---|"]
            for r in f["rows"]:
                share = "-" if r["radial_share"] is None else \
                    f"{r['radial_share']:.2f} ± {_fmt(r['radial_share_se'])}"
                lines.append(f"| {r['bin']} | {r['n']} | {_fmt(r['median_error_m'])} | {_fmt(r['rms_radial_m'])} | "
                             f"{_fmt(r['rms_lateral_m'])} | {_fmt(r['mean_radial_m'])} | {share} |")
            lines.append("")
    return "\n".join(lines)


def _picture(figures: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dataset_spec.atomic import atomic_savefig

    panels = [(m, c, f) for m, cl in figures.items() for c, f in cl.items()]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.6), squeeze=False)
    for ax, (m, c, f) in zip(axes[0], panels):
        pts = f["points"]
        ax.scatter(pts["distance"], pts["radial"], s=3, alpha=0.4, label="along the ray")
        ax.scatter(pts["distance"], pts["lateral"], s=3, alpha=0.4, label="across")
        ax.axhline(0, color="k", lw=0.5)
        ax.set(title=f"{m}, {c}", xlabel="distance from the nearest camera, m", ylabel="error, m")
        ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)


def main() -> int:
    args = _parse()
    sys.path.insert(0, str(ROOT))
    from dataset_spec.atomic import atomic_write_json, atomic_write_text

    named = dict(r.split("=", 1) for r in args.results if "=" in r)
    missing = [p for p in named.values() if not Path(p).is_file()]
    if len(named) != len(args.results) or missing:
        sys.exit(f"placement_errors.py: --results NAME=RESULTS.json, an existing file ({missing or args.results})")
    if not (Path(args.dataset) / "dataset.json").is_file():
        sys.exit(f"placement_errors.py: {args.dataset} holds no dataset.json")
    out = Path(args.out)
    figures = {name: _evaluate(args.dataset, args.split, Path(p), args.radius, args.duplicate_radius)
               for name, p in named.items()}
    atomic_write_json(out / "placement.json", figures)
    atomic_write_text(out / "placement.md", _markdown(figures))
    _picture(figures, out / "placement.png")
    print(_markdown(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
