"""The scaling curve's points and report (``benchmarks/scaling.py`` runs the points): which training scenes each point
names, its figures from its bench report (test F1@0.2 on each test set, the built-in layouts and the new layouts no
point trained on, and the new layouts' hidden-but-seen recall, with standard errors over layouts), the differences
between points (procedural against redraws at equal scenes, each doubling) with theirs (paired where both points keep
their per-scenario sums), and the report. --keep carries an earlier report's points into the curve, so that points
run in different sessions join one curve.

    python benchmarks/scaling_curve.py --out out/scaling                            # OUT/report from the points run
    python benchmarks/scaling_curve.py --out out/scaling --publish docs/results/scaling
    python benchmarks/scaling_curve.py --out out/scaling --keep docs/results/scaling/points.json   # earlier points too

The report (OUT/report, or --publish DIR too): ``scaling.md``, ``scaling.png`` (the figures against distinct
training scenes) and ``points.json``.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dataset_spec.atomic import atomic_write_text  # noqa: E402 - after the repository is on the path
from pnyolo.bench.new_layouts import BUILT_IN, NEW, by_test_set  # noqa: E402
from pnyolo.evaluation.bootstrap import UNIT, difference_se, f1_of, hidden_recall_of, se_text  # noqa: E402

TRAIN_LAYOUTS = ["intersection_01", "intersection_02", "intersection_03", "intersection_04", "intersection_05",
                 "intersection_06", "intersection_08"]
SIZES = (21, 42, 84, 168)
POINTS = {**{f"redraws-{n}": ("redraws", n) for n in SIZES}, **{f"procedural-{n}": ("procedural", n) for n in SIZES}}
IOU = "0.2"
FIGURES = ("layouts", "f1", "f1_se", "hidden_seen_recall", "hidden_seen_recall_se", "hidden_seen_n")
STATISTICS = {"f1": f1_of, "hidden_seen_recall": hidden_recall_of}  # the figures a difference between points is of


def training_scenes(kind: str, n: int) -> list[str]:
    """The ``n`` training scenes of a point: the 7 layouts drawn n / 7 times (the first draw, then -s1 ...), or
    procedural layouts 0 .. n - 1 (nested: a smaller set is part of every larger one)."""
    if kind == "redraws":
        return [layout if k == 0 else f"{layout}-s{k}" for k in range(n // len(TRAIN_LAYOUTS)) for layout in TRAIN_LAYOUTS]
    return [f"procedural-{k}" for k in range(n)]


def render_seconds(out: Path) -> dict[str, float]:
    """Cycles seconds (data passes and RGB) of every scene that every blender-gen timings record under ``out``
    (the points' runs, adopted ones and renders made beforehand) knows, read once for all points."""
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


def load_report(out: Path, name: str) -> dict | None:
    """The point's report.json (None before its run)."""
    path = out / name / "report" / "report.json"
    return json.loads(path.read_text()) if path.is_file() else None


def point_figures(out: Path, name: str, report: dict, seconds: dict[str, float]) -> dict:
    """The point's figures from its ``report`` (``load_report``); ``seconds``: render_seconds(out)."""
    bev = report["models"]["bev"]
    se = bev.get("standard_errors") or {}
    hidden = bev["recall_by_visibility"][IOU].get("hidden here, seen in another view", {})
    timing = json.loads((out / name / "runs" / "bev" / "bench_timing.json").read_text())
    sets = _test_sets(report)
    kind, n = POINTS[name]
    return {"point": name, "kind": kind, "scenes": n, "f1": bev["strict"][IOU]["f1"], "f1_se": _get(se, "f1", IOU),
            "ap50": bev["ap50"], "ap50_se": se.get("ap50"), "hidden_seen_recall": hidden.get("recall"),
            "hidden_seen_n": hidden.get("n"), "hidden_seen_recall_se": _get(se, "hidden_seen_recall", IOU),
            "sets": {k: {f: v["rows"]["bev"].get(f) for f in FIGURES} for k, v in sets.items() if "bev" in v["rows"]},
            "per_scenario": _test_sums(bev, sets),
            "val_f1": bev["selection"]["best_val_f1"], "val_f1_se": bev["selection"]["val_f1_se"],
            "train_s": timing["seconds"], "train_threads": timing.get("threads"),
            "train_from": timing.get("resumed_from", 0), "train_steps": timing.get("steps"),
            "render_s": _total(seconds, training_scenes(kind, n)),
            "command": _from_root(report.get("command", ""))}


def _from_root(text: str) -> str:
    """``text`` (a command, a path) with paths inside the repository as from its root."""
    return text.replace(f"{ROOT}/", "")


def _test_sets(report: dict) -> dict:
    """The report's test sets (``two_test_sets``): name -> {"scenarios": [...], "rows": {row: its figures}}."""
    return (report.get("analyses") or {}).get("test_sets", {}).get("sets", {})


def _get(se: dict, key: str, iou: str):
    value = se.get(key)
    return value.get(iou) if isinstance(value, dict) else None


def _test_sums(bev: dict, sets: dict) -> dict:
    """bev's per-scenario sums at IOU over the test sets' scenarios: what a paired difference with a point of a later
    session resamples, kept in points.json."""
    per = bev.get("per_scenario") or {}
    return {s: {key: {IOU: per[s][key][IOU]} for key in ("counts", "hidden_seen") if IOU in per[s].get(key, {})}
            for v in sets.values() for s in v["scenarios"] if s in per}


def compared_pairs(names) -> list[tuple[str, str]]:
    """The (a, b) pairs of run points whose difference a - b the report states: procedural against redraws at equal
    scenes, then each kind's doublings."""
    pairs = [(f"procedural-{n}", f"redraws-{n}") for n in SIZES]
    pairs += [(f"{kind}-{big}", f"{kind}-{small}") for kind in ("redraws", "procedural")
              for small, big in zip(SIZES, SIZES[1:])]
    return [(a, b) for a, b in pairs if a in names and b in names]


def _set_sums(row: dict, test_set: str) -> dict | None:
    """The row's per-scenario sums on one test set, as a summary ``difference_se`` reads (None when not kept)."""
    per = row.get("per_scenario") or {}
    names = by_test_set(list(per)).get(test_set)
    return {"per_scenario": {s: per[s] for s in names}} if names else None


def difference(ra: dict, rb: dict, test_set: str) -> dict | None:
    """``ra`` - ``rb`` (point rows) on one test set in F1@0.2 and hidden-but-seen recall, each with its standard
    error: paired (layouts resampled) when both rows keep the same scenarios' sums, else unpaired (the root of the
    two squared standard errors, which ignores the correlation the shared test layouts bring); None when not both
    scored."""
    fa, fb = (r.get("sets", {}).get(test_set) for r in (ra, rb))
    if not fa or not fb or fa["layouts"] != fb["layouts"]:
        return None
    sa, sb = _set_sums(ra, test_set), _set_sums(rb, test_set)
    paired = bool(sa and sb and set(sa["per_scenario"]) == set(sb["per_scenario"]))
    row = {"a": ra["point"], "b": rb["point"], "set": test_set, "layouts": fa["layouts"], "paired": paired}
    for key, statistic in STATISTICS.items():
        both = fa.get(key) is not None and fb.get(key) is not None
        row[key] = fa[key] - fb[key] if both else None
        if not both:
            row[f"{key}_se"] = None
        elif paired:
            row[f"{key}_se"] = difference_se(sa, sb, statistic, IOU)
        else:
            ses = (fa.get(f"{key}_se"), fb.get(f"{key}_se"))
            row[f"{key}_se"] = math.hypot(*ses) if None not in ses else None
    return row


def differences(rows: list[dict]) -> list[dict]:
    """Per compared pair and test set: ``difference`` of the two points' rows (``point_figures``, or kept ones)."""
    by_name = {r["point"]: r for r in rows}
    found = (difference(by_name[a], by_name[b], test_set) for a, b in compared_pairs(by_name)
             for test_set in (BUILT_IN, NEW))
    return [d for d in found if d is not None]


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def _resumed(row: dict) -> str:
    """Where a resumed training's seconds start: they count its last session only."""
    return f"; steps {row['train_from']}-{row['train_steps']} only, resumed" if row.get("train_from") else ""


def _value(v: float | None, se: float | None = None, layouts: int | None = None, sign: bool = False) -> str:
    """A figure as the report prints it: "0.557 ± 0.017", "+0.012 ± 0.020", "n/a (one layout)" for one layout."""
    if v is None:
        return "-"
    text = f"{v:+.3f}" if sign else f"{v:.3f}"
    return f"{text} {se_text(se, layouts)}".rstrip()


def _set(row: dict, test_set: str, key: str) -> str:
    f = row.get("sets", {}).get(test_set)
    if not f:
        return "-"
    text = _value(f.get(key), f.get(f"{key}_se"), f.get("layouts"))
    return f"{text} ({f['hidden_seen_n']})" if key == "hidden_seen_recall" and f.get(key) is not None else text


PANELS = ((BUILT_IN, "f1", f"test F1@{IOU}: {BUILT_IN} layouts"), (NEW, "f1", f"test F1@{IOU}: {NEW}"),
          (NEW, "hidden_seen_recall", f"hidden-but-seen recall@{IOU}: {NEW}"),
          (None, "render_s", "render seconds of the training set"))


def write_plot(rows: list[dict], path: Path) -> None:
    """Each point's figures on each test set against distinct training scenes (log scale), one line per kind."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PANELS), figsize=(15, 3.6))
    for ax, (test_set, key, title) in zip(axes, PANELS):
        for kind, style, shift in (("redraws", "o-", 0.97), ("procedural", "s--", 1.03)):  # apart at equal scenes
            figs = [(r["scenes"] * shift, r if test_set is None else r.get("sets", {}).get(test_set)) for r in rows
                    if r["kind"] == kind]
            pts = [(n, f) for n, f in figs if f and f.get(key) is not None]
            if pts:
                ax.errorbar([n for n, _ in pts], [f[key] for _, f in pts],
                            yerr=[f.get(f"{key}_se") or 0 for _, f in pts], fmt=style, capsize=3,
                            label=f"{kind} of the 7 training layouts" if kind == "redraws" else "procedural layouts")
        ax.set_xscale("log", base=2)
        ax.set_xticks(SIZES, [str(s) for s in SIZES])
        ax.set_xlabel("distinct training scenes")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table_lines(rows: list[dict]) -> list[str]:
    """The report's table: a row per point."""
    lines = [f"| point | distinct scenes | validation F1@{IOU} (best threshold) | test F1@{IOU}: {BUILT_IN} "
             f"| test F1@{IOU}: {NEW} | hidden-but-seen recall@{IOU}: {NEW} (n) | test AP50 (both sets) "
             "| render s (training set) "
             "| training s (threads) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['point']} | {r['scenes']} | {_value(r['val_f1'], r['val_f1_se'])} "
                     f"| {_set(r, BUILT_IN, 'f1')} | {_set(r, NEW, 'f1')} | {_set(r, NEW, 'hidden_seen_recall')} "
                     f"| {_value(r['ap50'], r['ap50_se'])} | {_seconds(r['render_s'])} | {r['train_s']:.0f} "
                     f"({r['train_threads']}{_resumed(r)}) |")
    return lines


UNPAIRED = "unpaired: a kept point without per-scenario sums (ignores that both share the test layouts)"


def difference_lines(diffs: list[dict]) -> list[str]:
    """The report's differences, each with its standard error and how it was resampled."""
    if not diffs:
        return ["No two points to compare yet (procedural against redraws at equal scenes, or a doubling)."]
    lines = [f"Differences on the same test scenarios (standard errors: {UNIT}; paired, or as the last column says):",
             "", f"| difference | test set | F1@{IOU} | hidden-but-seen recall@{IOU} | standard error |",
             "|---|---|---|---|---|"]
    for d in diffs:
        lines.append(f"| {d['a']} - {d['b']} | {d['set']} | {_value(d['f1'], d['f1_se'], d['layouts'], True)} "
                     f"| {_value(d['hidden_seen_recall'], d['hidden_seen_recall_se'], d['layouts'], True)} "
                     f"| {'paired' if d.get('paired', True) else UNPAIRED} |")
    return lines


def _kept(row: dict) -> str:
    return f" (kept from `{row['kept_from']}`)" if row.get("kept_from") else ""


def write_report(rows: list[dict], diffs: list[dict], folder: Path, missing: list[str]) -> None:
    """scaling.md, scaling.png and points.json into ``folder`` (``missing``: the points not run yet)."""
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / "points.json", json.dumps({"points": rows, "differences": diffs}, indent=1) + "\n")
    write_plot(rows, folder / "scaling.png")
    lines = ["# What more distinct training scenes buy (bev, cpu preset)", "",
             "bev trained with the cpu preset's steps, configuration and selection on each training set, scored on the "
             f"cpu preset's validation and test splits. The test split's two sets: its {BUILT_IN} layouts, and {NEW} "
             "(procedural layouts no point trained on, one draw each). ± is one bootstrap standard error, "
             f"{UNIT}. Made by `benchmarks/scaling.py`.", "", *table_lines(rows), "", *difference_lines(diffs), "",
             "Each point's run: " + "; ".join(f"{r['point']}: `{r['command']}`{_kept(r)}" for r in rows) + "."]
    bare = [r["point"] for r in rows if not r.get("sets")]
    if bare:
        lines += ["", f"No figures by test set for {', '.join(bare)}: its report predates the two test sets "
                  "(issue 85)."]
    if missing:
        lines += ["", "Not run yet: " + ", ".join(missing) + "."]
    lines += ["", "![test figures against distinct training scenes](scaling.png)", ""]
    atomic_write_text(folder / "scaling.md", "\n".join(lines))


def kept_points(path: Path | None) -> tuple[list[dict], list[dict]]:
    """An earlier report's points.json (checked by ``keep_problem``), read once: its point rows, each marked as kept,
    and its differences; nothing without ``path``."""
    if path is None:
        return [], []
    doc = json.loads(path.read_text())
    where = _from_root(str(path.resolve()))
    return [{**r, "kept_from": r.get("kept_from") or where} for r in doc["points"]], doc.get("differences", [])


def report(out: Path, publish: Path | None = None, keep: Path | None = None) -> int:
    """The curve from the points under ``out`` into OUT/report (and ``publish``), with the rows of ``keep`` (an
    earlier points.json) for points ``out`` has not run: 0, 1 when a figure is not finite, 2 when no point is known."""
    seconds, reports = render_seconds(out), {n: r for n in POINTS if (r := load_report(out, n)) is not None}
    known = {n: point_figures(out, n, r, seconds) for n, r in reports.items()}
    kept_rows, kept_diffs = kept_points(keep)
    kept = {r["point"]: r for r in kept_rows if r["point"] not in known}
    known.update(kept)
    if not known:
        print("scaling: no point has been run yet", file=sys.stderr)
        return 2
    rows = [known[n] for n in POINTS if n in known]
    published = {(d["a"], d["b"], d["set"]): d for d in kept_diffs
                 if d["a"] in kept and d["b"] in kept}   # two kept points: their difference as it was published
    diffs = [published.get((d["a"], d["b"], d["set"]), d) for d in differences(rows)]
    write_report(rows, diffs, out / "report", [n for n in POINTS if n not in known])
    if publish:
        shutil.copytree(out / "report", publish, dirs_exist_ok=True)
    print((out / "report" / "scaling.md").read_text())
    return 0 if all(math.isfinite(r["f1"]) for r in rows) else 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/scaling", help="the folder benchmarks/scaling.py ran the points into")
    p.add_argument("--publish", metavar="DIR", help="write the report there too (e.g. docs/results/scaling)")
    p.add_argument("--keep", metavar="POINTS_JSON",
                   help="an earlier report's points.json: its points that OUT has not run stay in the curve")
    args = p.parse_args(argv)
    out = Path(args.out).resolve()
    problem = f"--out {args.out} is not a folder" if not out.is_dir() else keep_problem(args.keep)
    if problem:
        print(f"scaling: {problem}", file=sys.stderr)
        return 2
    return report(out, Path(args.publish) if args.publish else None, Path(args.keep) if args.keep else None)


def keep_problem(keep: str | None) -> str | None:
    """What is wrong with --keep (None when absent or a points.json of this curve's points)."""
    if keep is None:
        return None
    try:
        rows = json.loads(Path(keep).read_text())["points"]
        bad = [r.get("point") for r in rows
               if r.get("point") not in POINTS or not all(k in r for k in ("f1", "kind", "scenes", "sets"))]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        return f"--keep {keep}: not a scaling points.json ({type(e).__name__})"
    return f"--keep {keep}: rows that are not this curve's points: {bad}" if bad else None


if __name__ == "__main__":
    sys.exit(main())
