"""Two test sets in every bench report (issue 85): each row's F1, precision, recall and hidden-but-seen recall on the
built-in test layouts and on the new layouts (``pnyolo.bench.new_layouts``). A set's figures are sums over its
scenarios (the summaries keep each scenario's strict TP, FP, FN and hidden-but-seen found / n), and their standard
errors resample that set's layouts (``pnyolo.evaluation.bootstrap``)::

    doc = sets_json(rows, scenarios, "0.2")     # per report row and set: its figures
    lines = sets_lines(doc, "0.2")
"""
from __future__ import annotations

import numpy as np

from dataset_spec.splits import layout_of
from pnyolo.bench.analyses import Analysis, register_analysis
from pnyolo.bench.new_layouts import NEW, by_test_set
from pnyolo.evaluation.bootstrap import ONE_LAYOUT, UNIT, f1_of, figure_se, hidden_recall_of


@register_analysis
class TwoTestSets(Analysis):
    name, title, order = "test_sets", "Two test sets: built-in layouts and new layouts", 10

    def measure(self, run) -> dict:
        return sets_json(run.summaries(), run.preset.test, run.preset.iou)

    def lines(self, doc: dict, run) -> list[str]:
        return sets_lines(doc, run.preset.iou)


def restricted(summary: dict, scenarios: list[str]) -> dict:
    """``summary`` with its per-scenario sums kept for ``scenarios`` only (one test set's share of a row)."""
    per = summary.get("per_scenario") or {}
    return {**summary, "per_scenario": {s: per[s] for s in scenarios if s in per}}


def _sums(per: dict, key: str, iou: str) -> np.ndarray:
    rows = [v.get(key, {}).get(iou) for v in per.values()]
    rows = [r for r in rows if r is not None]
    return np.asarray(rows, dtype=np.float64).sum(axis=0) if rows else np.zeros(3)


def set_figures(summary: dict, scenarios: list[str], iou: str) -> dict | None:
    """One row's figures on one test set: F1@``iou``, precision, recall and hidden-but-seen recall from the set's sums,
    F1's and the hidden recall's standard errors over the set's layouts; None without per-scenario sums."""
    sub = restricted(summary, scenarios)
    per = sub["per_scenario"]
    if not per:
        return None
    sums = lambda key, at: _sums(per, key, at)  # noqa: E731 - the statistics' own formulas read these
    tp, fp, fn = sums("counts", iou)[:3]
    n = sums("hidden_seen", iou)[1]
    layouts = len({layout_of(s) for s in per})
    return {"scenarios": len(per), "layouts": layouts,
            "f1": float(f1_of(iou)(sums)), "f1_se": figure_se([sub], f1_of(iou)),
            "precision": tp / (tp + fp) if tp + fp else 0.0, "recall": tp / (tp + fn) if tp + fn else 0.0,
            "hidden_seen_recall": float(hidden_recall_of(iou)(sums)) if n else None, "hidden_seen_n": int(n),
            "hidden_seen_recall_se": figure_se([sub], hidden_recall_of(iou)) if n else None}


def sets_json(rows: dict[str, dict], scenarios: list[str], iou: str) -> dict:
    """Per test set its scenarios and, per report row (``rows``: name -> summary), its figures (``set_figures``)."""
    sets = by_test_set(scenarios)
    return {"unit": UNIT, "iou": iou, "sets": {name: {"scenarios": names, "rows": {
        k: f for k, s in rows.items() if (f := set_figures(s, names, iou)) is not None}} for name, names in sets.items()}}


def _cell(f: dict | None, key: str) -> str:
    if f is None or f.get(key) is None:
        return "-"
    se = f.get(f"{key}_se")
    spread = f" ± {se:.3f}" if se is not None else (f" ({ONE_LAYOUT})" if f["layouts"] == 1 else "")
    return f"{f[key]:.3f}{spread}"


def sets_lines(doc: dict, iou: str) -> list[str]:
    """The report's section: each row's F1@``iou`` and hidden-but-seen recall on each test set, with standard errors."""
    sets = doc["sets"]
    lines = ["The test split's scenarios by set: the preset's built-in test layouts, and procedural layouts no model "
             "trained on (one draw each). Every other figure of this report is over the whole test split. Standard "
             f"errors: {UNIT}.", ""]
    for name, s in sets.items():
        layouts = sorted({layout_of(x) for x in s["scenarios"]})
        lines.append(f"- {name}: {len(s['scenarios'])} scenarios of {len(layouts)} layouts")
    if NEW not in sets:
        lines.append(f"- {NEW}: none in this preset's test split (`splits.test.new_layouts`)")
    names = list(sets)
    lines += ["", "| row | " + " | ".join(f"{n}: F1@{iou} | {n}: hidden-but-seen recall" for n in names) + " |",
              "|---|" + "---|---|" * len(names)]
    for row in dict.fromkeys(r for s in sets.values() for r in s["rows"]):
        cells = [c for n in names for c in (_cell(sets[n]["rows"].get(row), "f1"),
                                            _cell(sets[n]["rows"].get(row), "hidden_seen_recall"))]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return lines + [""]
