"""Evaluation reports: metrics as markdown and JSON, F1-versus-match-IoU plots, side-by-side comparisons.

    write_report(acc.summary(), "out/eval")                       # metrics.json, metrics.md, f1_vs_match_iou.png
    write_comparison({"mv": s_mv, "sv": s_sv}, "out/compare")     # one folder per model + comparison.*
"""
from __future__ import annotations

from pathlib import Path

from dataset_spec.atomic import atomic_savefig, atomic_write_json, atomic_write_text
from pnyolo.evaluation.bootstrap import difference_se, f1_of, hidden_recall_of, se_text
from pnyolo.evaluation.evaluate import FUSION, LATE_FUSION, OWN_VIEW
from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE


HEADLINE_IOU = "0.2"  # the match IoU of the headline figures: what the CLI prints, every table's groups and chance


def against_chance(summaries: dict[str, dict], iou: str, single: str | None) -> dict[str, dict]:
    """Each model's hidden-but-seen recall beside the single view's on the same objects (``single``: its row; it
    cannot see them, so what it finds is chance: lenient matching and learned priors), with the paired bootstrap
    standard error of the margin: {name: {recall, n, chance, chance_source, above, above_se, scenarios}}. No single
    view scored on these objects: no chance at all (a floor from other data is not this data's chance)."""
    def hidden(name):
        return summaries[name]["recall_by_visibility"].get(iou, {}).get(HIDDEN_SEEN_ELSEWHERE)

    base = hidden(single) if single in summaries else None
    if base is None:
        return {}
    out = {}
    for name in summaries:
        g = hidden(name)
        if g is not None and g["n"] and name != single:
            out[name] = {"recall": g["recall"], "n": g["n"], "chance": base["recall"],
                         "chance_source": f"{single} on the same objects", "above": g["recall"] - base["recall"],
                         "above_se": difference_se(summaries[name], summaries[single], hidden_recall_of, iou),
                         "scenarios": scenarios(summaries[name])}
    return out


def scenarios(summary: dict) -> int | None:
    """How many layouts (the bootstrap's units) a summary's figures come from (None: not recorded)."""
    se = summary.get("standard_errors") or {}
    return se.get("layouts", se.get("scenarios"))  # a summary of before layouts counted scenarios


def figure_text(value: float | None, summary: dict, key: str, iou: str | None = None) -> str:
    """A figure with its bootstrap standard error, "0.459 ± 0.021" ("n/a (one layout)" for one layout)."""
    if value is None:
        return "-"
    se = (summary.get("standard_errors") or {}).get(key)
    se = se.get(iou) if isinstance(se, dict) else se
    text = se_text(se, scenarios(summary))
    return f"{value:.3f} {text}".rstrip()


def chance_markdown(summaries: dict[str, dict], iou: str, single: str | None) -> str:
    """``against_chance`` as a table (empty where no single view was scored or nothing is hidden here and seen
    elsewhere)."""
    rows = against_chance(summaries, iou, single)
    if not rows:
        return ""
    first = next(iter(rows.values()))
    lines = [f"Hidden-but-seen recall@{iou} against chance: a road user fully hidden in its camera is found by a "
             f"model that reads that camera alone only by chance (lenient matching, learned priors); chance here is "
             f"{first['chance_source']} ({first['chance']:.3f}). ± is one bootstrap standard error, layouts "
             "resampled (the margin's paired: the same draws for both).", "",
             "| model | hidden-but-seen recall (n) | chance | above chance |", "|---|---|---|---|"]
    lines += [f"| {n} | {r['recall']:.3f} ({r['n']}) | {r['chance']:.3f} | "
              + f"{r['above']:+.3f} {se_text(r['above_se'], r['scenarios'])}".rstrip() + " |" for n, r in rows.items()]
    return "\n".join(lines) + "\n"


def difference_rows(summaries: dict[str, dict], single: str | None) -> list[tuple[str, str, str]]:
    """The differences a report states, as (label, row, the row it is set against): every multi-view row minus the
    single view, each model minus its own view alone (what the other views add), each late fusion minus one car."""
    out = []
    for name in summaries:
        own = f"{name}, {OWN_VIEW}"
        if single in summaries and name not in (single, FUSION) and not name.endswith(OWN_VIEW):
            out.append((f"{name} minus {single}", name, single))
        if own in summaries:
            out.append((f"{name} minus its own view alone", name, own))
        if name.endswith(f", {LATE_FUSION}") and f"{name.split(',')[0]}, {OWN_VIEW}" in summaries:
            out.append((f"{name} minus one car alone", name, f"{name.split(',')[0]}, {OWN_VIEW}"))
    return out


def differences_markdown(summaries: dict[str, dict], iou: str, single: str | None) -> str:
    """F1@``iou`` and hidden-but-seen recall differences (``difference_rows``), each with its paired bootstrap
    standard error over the scenarios."""
    rows = difference_rows(summaries, single)
    if not rows:
        return ""
    lines = [f"Differences at match IoU {iou}, each with one paired bootstrap standard error (layouts resampled: "
             "a scene and its redraws one unit; the same draws for both rows):", "", "| difference | F1 | hidden-but-seen recall |", "|---|---|---|"]
    for label, a, b in rows:
        sa, sb = summaries[a], summaries[b]
        ha, hb = (s["recall_by_visibility"].get(iou, {}).get(HIDDEN_SEEN_ELSEWHERE) for s in (sa, sb))
        f1 = sa["strict"][iou]["f1"] - sb["strict"][iou]["f1"]
        cells = [f"{f1:+.3f} {se_text(difference_se(sa, sb, f1_of, iou), scenarios(sa))}".rstrip()]
        if ha and hb and ha["n"]:
            cells.append(f"{ha['recall'] - hb['recall']:+.3f} "
                         f"{se_text(difference_se(sa, sb, hidden_recall_of, iou), scenarios(sa))}".rstrip())
        else:
            cells.append("-")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def comparison_markdown(summaries: dict[str, dict], iou_for_bins: str = HEADLINE_IOU, single: str | None = None) -> str:
    """One row per model (F1 at every match IoU, precision and recall at ``iou_for_bins``, AP, the
    paper's counting), recall per ground-truth group side by side, each model's hidden-but-seen recall
    against chance (``single``: the single view's row, if scored) and the differences the report states, the
    headline figures with bootstrap standard errors, and the ground-plane metrics of the models with 3D outputs."""
    names = list(summaries)
    ious = list(next(iter(summaries.values()))["strict"])
    t = iou_for_bins
    lines = [f"F1 at every match IoU (the headline, F1@{t}, and AP50 with one bootstrap standard error, layouts "
             "resampled):", "", "| model | " + " | ".join(f"F1@{i}" for i in ious) + f" | P@{t} | R@{t} | AP50 | "
             f"AP50:95 | F1@{t} (paper's counting) |", "|---|" + "---|" * (len(ious) + 5)]
    for n in names:
        s = summaries[n]
        paper = s.get("paper", {}).get(t)
        paper_f1 = "-" if paper is None else f"{paper['f1']:.3f}"
        lines.append(f"| {n} | " + " | ".join(figure_text(s['strict'][i]['f1'], s, "f1", i) if i == t else
                                              f"{s['strict'][i]['f1']:.3f}" for i in ious)
                     + f" | {s['strict'][t]['precision']:.3f} | {s['strict'][t]['recall']:.3f} | "
                     f"{figure_text(s['ap50'], s, 'ap50')} | {s['ap50_95']:.3f} | {paper_f1} |")
    groups = []
    for n in names:
        for g in summaries[n]["recall_by_visibility"].get(iou_for_bins, {}):
            if g not in groups:
                groups.append(g)
    lines += ["", f"Recall at match IoU {iou_for_bins} by ground-truth group (target-view visibility; whether another "
              "source view sees the object):", "", "| group | n | " + " | ".join(names) + " |",
              "|" + "---|" * (2 + len(names))]
    for g in groups:
        rec = [summaries[n]["recall_by_visibility"].get(iou_for_bins, {}).get(g) for n in names]
        n_gt = next((r["n"] for r in rec if r), 0)
        cells = [("-" if not r else figure_text(r["recall"], summaries[n], "hidden_seen_recall", iou_for_bins)
                  if g == HIDDEN_SEEN_ELSEWHERE else f"{r['recall']:.3f}") for n, r in zip(names, rec)]
        lines.append(f"| {g} | {n_gt} | " + " | ".join(cells) + " |")
    for table in (chance_markdown(summaries, iou_for_bins, single), differences_markdown(summaries, iou_for_bins,
                                                                                          single)):
        if table:
            lines += ["", table]
    table_3d = metrics_3d_markdown(summaries)
    return "\n".join(lines) + "\n" + ("\n" + table_3d if table_3d else "") + "\n" + bins_markdown(summaries)


def bins_markdown(summaries: dict[str, dict]) -> str:
    """F1@0.2 / AP50 / recall / hidden-but-seen recall by ground-truth distance and box height
    (``pnyolo.evaluation.metrics_bins``), one row per model and bin."""
    rows = {n: s["by_bin"] for n, s in summaries.items() if s.get("by_bin")}
    if not rows:
        return ""
    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    lines = ["By distance (0-13 m: the paper's range) and by box height: F1 and recall at match IoU 0.2, AP50, "
             "recall of the road users hidden in the target view but seen by another (n). A false positive counts in "
             "the bin of its own distance estimate or height: '-' where a model has no distance estimates.", "",
             "| model | bin | n | F1 | recall | AP50 | hidden-but-seen recall (n) |", "|---|---|---|---|---|---|---|"]
    for n, by in rows.items():
        for kind in ("distance", "height"):
            for name, b in by[kind].items():
                lines.append(f"| {n} | {name} | {b['n']} | {fmt(b['f1'])} | {fmt(b['recall'])} | {fmt(b['ap50'])} | "
                             f"{fmt(b['hidden_seen_recall'])} ({b['n_hidden_seen']}) |")
    return "\n".join(lines) + "\n"


def devkit_eval_lines(summaries: dict[str, dict]) -> list[str]:
    """The devkit's DetectionEval on an export of the split (``devkit_eval``), where it was run: the figure a paper's
    nuScenes table gives."""
    rows = {n: s["devkit_detection_eval"] for n, s in summaries.items()
            if (s.get("devkit_detection_eval") or {}).get("map") is not None}
    if not rows:
        return []
    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    classes = next(iter(rows.values()))["classes"]
    errors = list(next(iter(rows.values()))["errors"])
    lines = ["**The nuScenes devkit's DetectionEval** on the split's nuScenes export (one sample per frame, class "
             "ranges from each sample's LIDAR_TOP ego, ground truth no camera sees left out, `detection_cvpr_2019` "
             f"over the export's classes {', '.join(classes)}; the models whose outputs are 3D boxes, the results "
             "each was given: `results_nusc_test.json` in its folder): the figure to set beside a paper's nuScenes "
             "table.", "",
             "| model | mAP | NDS | " + " | ".join(f"AP {c}" for c in classes) + " | " + " | ".join(errors) + " |",
             "|---|---|---|" + "---|" * (len(classes) + len(errors))]
    for n, k in rows.items():
        aps = [sum(k["ap"][c].values()) / len(k["ap"][c]) if k["ap"].get(c) else None for c in classes]
        lines.append(f"| {n} | {fmt(k['map'])} | {fmt(k['nds'])} | " + " | ".join(fmt(a) for a in aps) + " | "
                     + " | ".join(fmt(k["errors"][e]) for e in errors) + " |")
    named = {n: k["car_pedestrian"] for n, k in rows.items() if (k.get("car_pedestrian") or {}).get("map") is not None}
    if named:
        first = next(iter(named.values()))
        dists, errors = list(first["ap_by_distance"]), list(first["errors"])
        lines += ["", "**DetectionEval over car and pedestrian** (the classes the models name; buses and trucks counted "
                  "as cars, as the models are trained to name them, on an export whose categories say so; the same "
                  "results files): mAP and NDS, AP per class and at each centre distance (mean over the two classes), "
                  "and the five true-positive errors.", "",
                  "| model | mAP | NDS | AP car | AP pedestrian | " + " | ".join(f"AP@{d} m" for d in dists) + " | "
                  + " | ".join(errors) + " |", "|---|---|---|---|---|" + "---|" * (len(dists) + len(errors))]
        for n, k in named.items():
            per = [sum(k["ap"][c].values()) / len(k["ap"][c]) if k["ap"].get(c) else None for c in ("car", "pedestrian")]
            lines.append(f"| {n} | {fmt(k['map'])} | {fmt(k['nds'])} | " + " | ".join(fmt(a) for a in per) + " | "
                         + " | ".join(fmt(k["ap_by_distance"].get(d)) for d in dists) + " | "
                         + " | ".join(fmt(k["errors"][e]) for e in errors) + " |")
    return lines + [""]


def metrics_3d_markdown(summaries: dict[str, dict]) -> str:
    """The ground-plane metrics (``pnyolo.evaluation.metrics_3d``) of the models that have them: the nuScenes
    devkit's mAP, NDS and errors, then MODA / MODP and recall within 1 m."""
    rows = {n: s["3d"] for n, s in summaries.items() if s.get("3d")}
    if not rows:
        return ""
    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    lines = [*devkit_eval_lines(summaries),
             "On the ground plane (world boxes, every scored view's road users; a model detecting in its views "
             "places each detection at its distance along the ray through the box centre, without a box: no scale "
             "or orientation error). **Per-view AP** by the devkit's accumulate, calc_ap and calc_tp (each scored view "
             "one sample with its own labels, fully hidden road users included, our ignore rule; centre distance; "
             "NDS = (5 mAP + sum of max(0, 1 - error)) / 10, an error it cannot measure counting 0). Not the devkit's "
             "DetectionEval, and not comparable with a paper's nuScenes table:", ""]
    kit = {n: m["per_view"] for n, m in rows.items() if m.get("per_view")}
    if kit:
        dists = list(next(iter(kit.values()))["ap"])
        names = list(next(iter(kit.values()))["errors"])
        lines += ["| model | " + " | ".join(f"AP@{d} m" for d in dists) + " | mAP | NDS | " + " | ".join(names) + " |",
                  "|---|" + "---|" * (len(dists) + 2 + len(names))]
        lines += [f"| {n} | " + " | ".join(fmt(m["ap"][d]["mean"]) for d in dists) + f" | {fmt(m['map'])} | "
                  f"{fmt(m['nds'])} | " + " | ".join(fmt(m["errors"][e]) for e in names) + " |" for n, m in kit.items()]
    else:
        lines.append("(nuscenes-devkit is not installed: pip install nuscenes-devkit==1.2.0, which needs numpy<2)")
    lines += ["", "MODA / MODP (Hungarian matching within 0.5 m for pedestrians, 1 m otherwise) and recall within 1 m:",
              "", "| model | MODA | MODP | recall 1 m | fully hidden | hidden, seen elsewhere |", "|---|---|---|---|---|---|"]
    for n, m in rows.items():
        r = m["recall_within_1m"]
        lines.append(f"| {n} | {fmt(m['moda'])} | {fmt(m['modp'])} | {fmt(r['all']['recall'])} | "
                     f"{fmt(r['fully hidden in the target view']['recall'])} | "
                     f"{fmt(r['hidden here, seen in another view']['recall'])} |")
    return "\n".join(lines) + "\n"


FALSE_POSITIVE_NOTE = ("*On a ground-truth object*: a duplicate, a wrong class or a box given to another detection; "
                       "*near an object*: overlapping a labelled road user, but too little; "
                       "*on no labelled object*: nothing there (for the multi-view model typically a ray crossing "
                       "another view's object away from its true depth). *Ignored*: detections of road users "
                       "outside the ground truth (too far or too truncated), neither true nor false positives.")


def false_positive_markdown(summaries: dict[str, dict], iou: str = "0.2") -> str:
    """Where each model's unmatched detections lie (``MetricAccumulator.false_positive_breakdown``)."""
    fps = {k: s["false_positives"][iou] for k, s in summaries.items() if iou in s.get("false_positives", {})}
    if not fps:
        return ""
    cats = [c for c, v in next(iter(fps.values())).items() if isinstance(v, dict)]
    lines = [f"Where the unmatched detections (false positives at match IoU {iou}) lie:", "",
             "| false positives | " + " | ".join(fps) + " |", "|---|" + "---|" * len(fps),
             "| all | " + " | ".join(str(f["n"]) for f in fps.values()) + " |"]
    lines += [f"| {c} | " + " | ".join(f"{f[c]['count']} ({f[c]['share']:.0%})" for f in fps.values()) + " |"
              for c in cats]
    lines.append("| ignored (on an excluded object; not in *all*) | "
                 + " | ".join(str(f["ignored"]) for f in fps.values()) + " |")
    return "\n".join(lines + ["", FALSE_POSITIVE_NOTE, ""])


def comparison_plot(summaries: dict[str, dict], path: str | Path, mode: str = "strict") -> None:
    """F1 versus match IoU for several models (the paper's Figure 6.6)."""
    plot_f1_curves({name: s[mode] for name, s in summaries.items()}, path, f"F1 ({mode})")


def plot_f1_curves(curves: dict[str, dict], path: str | Path, ylabel: str = "F1") -> None:
    """One line per entry of ``curves`` ({label: {match IoU: {"f1": ...}}}), F1 against match IoU."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for label, by_iou in curves.items():
        ax.plot([float(t) for t in by_iou], [m["f1"] for m in by_iou.values()], marker="o", label=label)
    ax.set_xlabel("match IoU threshold")
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)


def write_comparison(summaries: dict[str, dict], out_dir: str | Path, extra: dict | None = None,
                     single: str | None = None) -> None:
    """One report per model, and comparison.json / .md / .png side by side (``single``: the single view's
    row, the chance level of the others' hidden-but-seen recall)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name, summary in summaries.items():
        write_report(summary, out / name, extra)
    chance = against_chance(summaries, HEADLINE_IOU, single)
    atomic_write_json(out / "comparison.json", {**(extra or {}), "models": summaries,
                                                **({"hidden_seen_against_chance": chance} if chance else {})})
    atomic_write_text(out / "comparison.md", settings_text(extra) + comparison_markdown(summaries, single=single))
    comparison_plot(summaries, out / "f1_vs_match_iou.png")


def markdown_table(summary: dict) -> str:
    """One model's metrics.md: every match IoU in both countings (strict F1 with its bootstrap standard error),
    AP, the ground-truth groups and false positives at the headline IoU, against chance where a single view was
    scored on the same objects (``pnyolo-eval --chance-from``), the ground plane and the bins."""
    lines = ["| match IoU | mode | precision | recall | F1 | TP | FP | FN |", "|---|---|---|---|---|---|---|---|"]
    for mode in ("strict", "paper"):
        for t, m in summary[mode].items():
            f1 = figure_text(m["f1"], summary, "f1", t) if mode == "strict" else f"{m['f1']:.3f}"
            lines.append(f"| {t} | {mode} | {m['precision']:.4f} | {m['recall']:.4f} | {f1} | "
                         f"{m['tp']} | {m['fp']} | {m['fn']} |")
    lines += ["", f"AP50 {figure_text(summary['ap50'], summary, 'ap50')} · AP50:95 {summary['ap50_95']:.4f} · views "
              f"{summary['views']} · ground truth {summary['ground_truth']} · predictions {summary['predictions']} "
              f"(± one bootstrap standard error, {scenarios(summary) or '?'} layouts resampled)", ""]
    rv = summary["recall_by_visibility"]
    key = HEADLINE_IOU if HEADLINE_IOU in rv else next(iter(rv), None)
    if key:
        lines += [f"Recall at match IoU {key} (strict) by ground truth group:", "", "| group | recall | n |", "|---|---|---|"]
        lines += [f"| {g} | " + (figure_text(v['recall'], summary, 'hidden_seen_recall', key)
                                 if g == HIDDEN_SEEN_ELSEWHERE else f"{v['recall']:.4f}") + f" | {v['n']} |"
                  for g, v in rv[key].items()]
        lines += ["", false_positive_markdown({"detections": summary}, key)]
    chance = summary.get("against_chance")
    if chance:
        lines += [f"Hidden-but-seen recall@{HEADLINE_IOU} against chance ({chance['chance_source']}): "
                  f"{chance['recall']:.3f} against {chance['chance']:.3f}, above chance {chance['above']:+.3f} "
                  f"{se_text(chance['above_se'], chance['scenarios'])}".rstrip() + ".", ""]
    de = summary.get("distance_error", {})
    if de.get("mean_abs_m") is not None:
        lines += ["", f"Distance estimate: mean absolute error {de['mean_abs_m']:.2f} m over {de['n']} matched detections"]
    table_3d = metrics_3d_markdown({"this model": summary})
    if table_3d:
        lines += ["", table_3d]
    table_bins = bins_markdown({"this model": summary})
    if table_bins:
        lines += ["", table_bins]
    if summary["ground_truth"] and (summary.get("single_view_ceiling") or {}).get("recall_ceiling", 0) is None:
        lines += ["", "Visibility was not measured (camera data without instance maps): the groups by visible "
                      "fraction and the hidden-but-seen figures are left out."]
    g = summary.get("ground_plane") or {}
    if g.get("moda") is not None:
        lines += ["", f"The field's ground-plane evaluation ({g['frames']} frames, {g['threshold_m']:g} m, grid rows in "
                      f"gt.txt / detections.txt): MODA {g['moda']:.4f}, MODP {_dash(g['modp'])}, precision "
                      f"{_dash(g['precision'])}, recall {_dash(g['recall'])} ('-': nothing to measure, as metrics.json's "
                      "null)"]
    return "\n".join(lines) + "\n"


def _dash(value: float | None) -> str:
    """A figure to four decimals, or '-' where there was nothing to measure (metrics.json's null)."""
    return "-" if value is None else f"{value:.4f}"


def f1_plot(summary: dict, path: str | Path) -> None:
    """F1 versus match IoU of one model, in both counting modes."""
    plot_f1_curves({f"F1 ({mode})": summary[mode] for mode in ("strict", "paper")}, path)


def settings_text(extra: dict | None) -> str:
    """The run's settings (``extra``: split, delay, from_ms, pose noise, late-fusion rule, ...) as the first line of
    metrics.md and comparison.md, so two reports of different settings are told apart."""
    shown = {k: v for k, v in (extra or {}).items() if isinstance(v, (str, int, float, list, dict)) and v != ""}
    return ("Run: " + "; ".join(f"{k} {v}" for k, v in shown.items()) + "\n\n") if shown else ""


def write_report(summary: dict, out_dir: str | Path, extra: dict | None = None) -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "metrics.json", {**(extra or {}), **summary})
    atomic_write_text(out / "metrics.md", settings_text(extra) + markdown_table(summary))
    f1_plot(summary, out / "f1_vs_match_iou.png")


def headline(summary: dict, iou: float, mode: str = "strict") -> float:
    return float(summary[mode][f"{iou:.1f}"]["f1"]) if f"{iou:.1f}" in summary[mode] else float("nan")


