"""Bootstrap standard errors of test figures and of differences between them, layouts resampled.

The resampled unit is the layout (``dataset_spec.splits.layout_of``: a scene, its redraws ``NAME-sK``, their lighting
variants and frames). A redraw shares its layout's streets, buildings and cameras, so resampling scenarios (let alone
items) as if independent would understate the noise. A summary (``MetricAccumulator.summary``) keeps, per scenario,
what its figures are sums of (``per_scenario``: strict TP, FP, FN and hidden-but-seen found / n at every match IoU);
the scenarios of a layout are summed into one unit, and a figure's standard error, or a difference's between two rows
scored on the same scenarios (paired: the same draws for both), is the spread of the figure over ``DRAWS``
resamplings of the layouts::

    se = figure_se([summary], f1_of("0.2"))                         # one row's F1@0.2
    se = figure_se([mv, sv], lambda a, b: hidden_recall_of("0.2")(a) - hidden_recall_of("0.2")(b))

One layout has no spread to measure: None, which reports print as "n/a (one layout)".
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from dataset_spec.splits import layout_of

DRAWS = 1000  # resamplings (seeded: the same standard error on every run)
SEED = 0
ONE_LAYOUT = "n/a (one layout)"  # what a report prints for the standard error of a single layout
UNIT = "layouts resampled (a scene and its redraws one unit)"  # what reports say the resampled unit is


def layout_groups(scenarios: list[str]) -> list[list[int]]:
    """The positions of ``scenarios`` grouped by their layout, layouts in sorted order: the bootstrap's units."""
    groups: dict[str, list[int]] = {}
    for k, name in enumerate(scenarios):
        groups.setdefault(layout_of(name), []).append(k)
    return [groups[g] for g in sorted(groups)]


def layout_sums(per_unit: np.ndarray, groups: list[list[int]]) -> np.ndarray:
    """(units, ...) sums per scenario -> (layouts, ...) sums per layout of ``layout_groups``."""
    return np.stack([per_unit[g].sum(axis=0) for g in groups]) if groups else per_unit[:0]


def draws_of(n: int, draws: int = DRAWS, seed: int = SEED) -> np.ndarray:
    """(draws, n) indices of ``n`` units drawn with replacement (seeded)."""
    return np.random.default_rng(seed).integers(0, n, size=(draws, n))


def _stacked(summary: dict, units: list[str], key: str, iou: str) -> np.ndarray:
    """(units, k) per-scenario sums of ``key`` at ``iou`` (zeros where a scenario has none)."""
    rows = [summary["per_scenario"][u].get(key, {}).get(iou) for u in units]
    width = len(next((r for r in rows if r is not None), [0, 0, 0]))
    return np.asarray([r if r is not None else [0] * width for r in rows], dtype=np.float64).reshape(len(units), width)


def f1_of(iou: str) -> Callable[[Callable], np.ndarray]:
    """The statistic F1@``iou`` (strict): 2 TP / (2 TP + FP + FN) of the drawn scenarios' sums."""
    def stat(sums) -> np.ndarray:
        tp, fp, fn = (c[..., i] for c in [sums("counts", iou)] for i in range(3))
        den = 2 * tp + fp + fn
        return np.where(den > 0, 2 * tp / np.maximum(den, 1e-12), 0.0)
    return stat


def hidden_recall_of(iou: str) -> Callable[[Callable], np.ndarray]:
    """The statistic hidden-but-seen recall@``iou``: found / n of the drawn scenarios' sums (NaN where none)."""
    def stat(sums) -> np.ndarray:
        c = sums("hidden_seen", iou)
        return np.where(c[..., 1] > 0, c[..., 0] / np.maximum(c[..., 1], 1), np.nan)
    return stat


def figure_se(summaries: list[dict], statistic: Callable, draws: int = DRAWS, seed: int = SEED) -> float | None:
    """The bootstrap standard error of ``statistic(*rows)`` where each row is a function ``sums(key, iou)`` giving
    (draws, k) sums of one summary's per-scenario figures over the same drawn layouts (paired across rows).
    None with fewer than two layouts, or when a summary keeps no per-scenario figures."""
    if not summaries or any(not s.get("per_scenario") for s in summaries):
        return None
    units = sorted(summaries[0]["per_scenario"])
    groups = layout_groups(units)
    if len(groups) < 2 or any(sorted(s["per_scenario"]) != units for s in summaries):
        return None
    idx = draws_of(len(groups), draws, seed)

    def sums_of(summary):
        return lambda key, iou: layout_sums(_stacked(summary, units, key, iou), groups)[idx].sum(axis=1)

    values = np.asarray(statistic(*[sums_of(s) for s in summaries]), dtype=np.float64)
    values = values[np.isfinite(values)]
    return float(values.std(ddof=1)) if len(values) > 1 else None


def difference_se(a: dict, b: dict, statistic_of: Callable[[str], Callable], iou: str) -> float | None:
    """The paired standard error of ``statistic(a) - statistic(b)`` (``statistic_of(iou)``: ``f1_of``,
    ``hidden_recall_of``), both rows scored on the same scenarios (layouts resampled)."""
    stat = statistic_of(iou)
    return figure_se([a, b], lambda x, y: stat(x) - stat(y))


def se_text(se: float | None, layouts: int | None = None) -> str:
    """A standard error as reports print it: "± 0.021", "n/a (one layout)", or "" where none was measured."""
    if se is not None:
        return f"± {se:.3f}"
    return ONE_LAYOUT if layouts == 1 else ""


def spread_text(se: float, layouts: int | None) -> str:
    """A validation choice's standard error as logs and reports print it: "0.021", or "n/a (one layout)"."""
    return ONE_LAYOUT if layouts == 1 else f"{se:.3f}"
