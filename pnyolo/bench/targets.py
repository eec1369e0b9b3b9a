"""The benchmark's targets, judged at each model's validation-chosen operating point: what the other
cameras must add and how the multi-view models must sample (each kind's own ``coverage_targets``), the
preset's primary model against its baseline, the best multi-view model, the ground-plane recall and the
time budget::

    checks = bench_targets(preset, run.results, run.timings)   # {target: (PASS / FAIL / None, its figures)}

No kind is named here: roles come from the preset (``primary``, ``baseline``), abilities from the kinds.

A target on a difference or a test figure with a standard error passes only when the figure is beyond its target by
one standard error (``RULE``: layouts resampled); with none measured (one layout) the figure itself decides, and
the line says so.
"""
from __future__ import annotations

from pnyolo.bench.presets import BenchPreset, multi_view_kinds
from pnyolo.bench.record import Result
from pnyolo.bench.state_targets import state_lines
from pnyolo.evaluation.bootstrap import difference_se, f1_of, hidden_recall_of, se_text
from pnyolo.evaluation.coverage import SEGMENT_MEASURES
from pnyolo.evaluation.evaluate import late_fusion_name, own_view_name
from pnyolo.evaluation.report import against_chance
from pnyolo.registry import model_class

OWN_VIEW_MARGIN = 0.2  # hidden-but-seen recall at least this much above the own-view-only ablation
CHANCE_MARGIN = 0.1  # hidden-but-seen recall at least this much above the single view's (chance: it cannot see them)
BEST_F1 = 0.55
RECALL_1M = 0.5  # hidden-but-seen recall within 1 m on the ground plane, models with 3D outputs
INFERENCE_FACTOR = 2.0  # a multi-view model's time per frame at most this times the baseline's
RULE = "PASS only where the figure minus one standard error (layouts resampled) reaches the target"


def beyond(value: float | None, se: float | None, target: float) -> bool | None:
    """The rule (``RULE``): ``value - se >= target``; the figure alone where no standard error was measured."""
    if value is None:
        return None
    return value - (se or 0.0) >= target


def fmt(v: float | None) -> str:
    """A share to three decimals, or n/a where there was nothing to measure."""
    return "n/a" if v is None else f"{v:.3f}"


def best_multi_view(results: dict[str, Result]) -> str | None:
    """The multi-view model with the best validation F1 (where models are compared, never test)."""
    cands = [k for k in multi_view_kinds(results) if results[k].choice is not None]
    return max(cands, key=lambda k: results[k].choice.best_val_f1) if cands else None


def bench_targets(preset: BenchPreset, results: dict[str, Result], timings: dict) -> dict[str, tuple[bool | None, str]]:
    """{target: (PASS / FAIL / None when nothing was measured, the figures it was judged on)}."""
    out: dict[str, tuple[bool | None, str]] = {}
    iou = preset.iou

    def at_least(name: str, value: float | None, target: float, text: str | None = None) -> None:
        out[name] = (None if value is None else value >= target, text or f"{fmt(value)} (target {target:g})")

    f1 = {k: r.figures.f1[iou] for k, r in results.items()}
    primary, baseline = preset.primary, preset.baseline
    chance = against_chance({k: r.metrics for k, r in results.items()}, iou, baseline or None)
    if primary in results:
        _above_chance(out, primary, chance, iou)
        if baseline in results:
            se = difference_se(results[primary].metrics, results[baseline].metrics, f1_of, iou)
            gain = f1[primary] - f1[baseline]
            out[f"{primary} F1@{iou} > {baseline} F1@{iou}"] = (
                beyond(gain, se, 1e-12), f"{f1[primary]:.3f} against {f1[baseline]:.3f} ({gain:+.3f} "
                                         f"{se_text(se, _layouts(results[primary]))})".replace(" )", ")"))
    for kind in multi_view_kinds(results):
        _multi_view_targets(out, at_least, kind, results, iou)
    _best_targets(out, results, f1, chance, iou)
    late = {late_fusion_name(k) for k in preset.late_fusion}
    for name, r in results.items():
        near = r.figures.within_1m
        if near and (name in multi_view_kinds(results) or name in late):
            at_least(f"{name}: hidden-but-seen recall within 1 m on the ground plane >= {RECALL_1M:g}", near.recall,
                     RECALL_1M, f"{fmt(near.recall)} (n = {near.n})")
    for kind in (k for k in preset.late_fusion if late_fusion_name(k) in results):  # the 3D state, the tracks (87, 88)
        out.update(state_lines(kind, results[kind].metrics, results[kind].tracking, preset.state_targets))
    floor = results[baseline].inference_ms if baseline in results else None
    if floor:
        for kind in multi_view_kinds(results):
            ms = results[kind].inference_ms if kind in results else None
            if ms:
                out[f"{kind} inference per frame <= {INFERENCE_FACTOR:g} x {baseline}"] = (
                    ms <= INFERENCE_FACTOR * floor, f"{ms:.0f} ms against {floor:.0f} ms")
    if preset.time_budget_s is not None:
        spent = cached_time(timings)
        out[f"the preset within {preset.time_budget_s / 60:g} minutes with the dataset cached"] = (
            None if spent is None else spent <= preset.time_budget_s,
            "n/a (a reused stage has no recorded time)" if spent is None else f"{spent / 60:.0f} min")
    return out


def _multi_view_targets(out: dict, at_least, kind: str, results: dict[str, Result], iou: str) -> None:
    """What the other source views must add to a multi-view kind, and its sampling coverage."""
    own = results.get(own_view_name(kind))
    if kind in results and own is not None:
        full_hs, own_hs = (r.figures.recall(iou).recall for r in (results[kind], own))
        gain = None if full_hs is None or own_hs is None else full_hs - own_hs
        se = difference_se(results[kind].metrics, own.metrics, hidden_recall_of, iou)
        out[f"{kind} hidden-but-seen recall >= own view only + {OWN_VIEW_MARGIN:g}"] = (
            beyond(gain, se, OWN_VIEW_MARGIN), f"{fmt(full_hs)} against {fmt(own_hs)} ({fmt(gain)} "
                                               f"{se_text(se, _layouts(results[kind]))}; target +{OWN_VIEW_MARGIN:g})"
            .replace("  ", " "))
    coverage = results[kind].coverage if kind in results else None
    for cls, groups in (coverage or {}).items():
        rec = groups["hidden-but-seen"]
        for m, target in model_class(kind).coverage_targets.items():
            if rec.get(m) is None and m in SEGMENT_MEASURES:  # a model that queries points: no segments to judge
                continue
            at_least(f"{kind} coverage of hidden-but-seen {cls}s: {m.replace('_', ' ')} >= {target:g}", rec[m],
                     target, f"{fmt(rec[m])} of {rec['n']} (target {target:g})")


def _above_chance(out: dict, name: str, chance: dict, iou: str, label: str | None = None) -> None:
    """``name``'s hidden-but-seen recall at least ``CHANCE_MARGIN`` above chance (``report.against_chance``), by
    one standard error (``RULE``)."""
    r = chance.get(name)
    se = "" if r is None else se_text(r["above_se"], r["scenarios"])
    out[f"{label or name}: hidden-but-seen recall@{iou} >= the single view's on the same objects + "
        f"{CHANCE_MARGIN:g}"] = (
        None if r is None else beyond(r["above"], r["above_se"], CHANCE_MARGIN),
        "n/a (no single view scored: no chance to compare with)" if r is None else
        f"{r['recall']:.3f} against {r['chance']:.3f} ({r['above']:+.3f}{' ' + se if se else ''}; target "
        f"+{CHANCE_MARGIN:g}; n = {r['n']})")


def _layouts(r: Result) -> int | None:
    """How many layouts a result's figures come from (1: no standard error to measure)."""
    return (r.metrics.get("standard_errors") or {}).get("layouts")


def _best_targets(out: dict, results: dict[str, Result], f1: dict, chance: dict, iou: str) -> None:
    """The best multi-view model's (by validation F1) hidden-but-seen recall against chance and its F1 (the recall
    over the best other view's pixels is a table of the report, not a target: four bins within their noise are no
    trend)."""
    best = best_multi_view(results)
    if best is None:
        return
    _above_chance(out, best, chance, iou, f"best multi-view model ({best}, by validation F1)")
    se = (results[best].metrics.get("standard_errors") or {}).get("f1", {}).get(iou)
    out[f"best multi-view model ({best}): F1@{iou} >= {BEST_F1:g}"] = (
        beyond(f1[best], se, BEST_F1), f"{fmt(f1[best])} {se_text(se, _layouts(results[best]))} (target {BEST_F1:g})"
        .replace("  ", " "))


def cached_time(timings: dict) -> float | None:
    """Seconds of everything but rendering, as a run with the dataset cached spends: a reused training
    counts the seconds it took when it ran (None: one with no record of them)."""
    rest = [v.get("trained_seconds") if isinstance(v, dict) else v for k, v in timings.items()
            if k not in ("total", "render (blender-gen)")]
    if any(not isinstance(v, (int, float)) for v in rest):
        return None
    return float(sum(rest))
