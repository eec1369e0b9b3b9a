"""The benchmark's pose-noise sweep: what each fusion survives when the other cars' poses are wrong.

    sweep = pose_noise_sweep(preset, scorings, noisy, test, summaries)           # {name: {sigma: figures}}
    sweep = trained_with_noise(sweep, {kind: [0.2, 0.2]})                         # names say how it trained
    sweep |= read_sweep(Path("out/cpu/report/report.json"), preset, "no noise")   # another run's rows beside
    lines = robustness_lines(sweep, report_dir, "0.2", preset.baseline)           # table, verdicts, plot

Every multi-view model and the ground-plane model's late fusion are evaluated on test with the other
cars' poses wrong by sigma (metres and degrees together, ``pnyolo.cooperation.pose_noise``), each at
the operating point chosen on validation without noise. The preset's baseline (a single view) and the
own-view ablations read no other car: their figures hold at every sigma, the floor the fusions fall towards.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

from dataset_spec.atomic import atomic_savefig
from dataset_spec.cli_support import UserError
from dataset_spec.dataset import read_json
from dataset_spec.errors import SpecError
from dataset_spec.names import excerpt
from pnyolo.bench.presets import BenchPreset
from pnyolo.cooperation.late_fusion import Channel
from pnyolo.cooperation.pose_noise import PoseNoise
from pnyolo.evaluation.bootstrap import UNIT, difference_se, f1_of, se_text
from pnyolo.evaluation.evaluate import Comparison, Scoring, evaluate_models, late_fusion_name, own_view_name
from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE
from pnyolo.evaluation.metrics_3d import ground_ap

ROW_NAME = re.compile(r"[A-Za-z0-9_.,+() -]{1,160}")  # the characters the report's own row names use
FIGURES = {"f1": "F1@{iou}", "hidden_seen_recall": "hidden-but-seen recall@{iou}", "ap_1m": "AP within 1 m",
           "moda": "MODA"}


def figures(summary: dict, iou: str, floor: dict | None = None) -> dict:
    """The sweep's four figures of one summary at match IoU ``iou`` (None where a model has no such figure), F1's and
    the hidden-but-seen recall's standard errors (layouts resampled), and with ``floor`` (the baseline's summary, on
    the same scenarios) F1's difference from it with its paired standard error."""
    hidden = summary["recall_by_visibility"].get(iou, {}).get(HIDDEN_SEEN_ELSEWHERE)
    m3 = summary.get("3d") or {}
    se = summary.get("standard_errors") or {}
    out = {"f1": summary["strict"][iou]["f1"], "hidden_seen_recall": hidden["recall"] if hidden else None,
           "ap_1m": ground_ap(m3),
           "moda": m3.get("moda"), "f1_se": (se.get("f1") or {}).get(iou),
           "hidden_seen_recall_se": (se.get("hidden_seen_recall") or {}).get(iou), "layouts": se.get("layouts")}
    if floor is not None:
        out["f1_over_baseline"] = out["f1"] - floor["strict"][iou]["f1"]
        out["f1_over_baseline_se"] = difference_se(summary, floor, f1_of, iou)
    return out


def pose_noise_sweep(preset: BenchPreset, scorings: dict[str, Scoring], noisy: dict, test, summaries: dict,
                     seed: int = 0) -> dict[str, dict]:
    """{name: {sigma: figures}} at the preset's match IoU: sigma 0 from ``summaries`` (the run without
    noise), the others measured at the preset's sigmas; ``scorings``: the multi-view kinds' test predictions at
    their chosen operating points (the cars' own-view messages: no other car's pose reaches them), ``noisy``:
    sigma -> kind -> their test predictions with the other cars' poses wrong by sigma."""
    iou = preset.iou
    late = tuple(k for k, s in scorings.items() if s.decoding.world_outputs)
    names = [late_fusion_name(k) for k in late] + list(scorings)
    floors = [n for n in (preset.baseline, *(own_view_name(k) for k in scorings)) if n in summaries]
    floor = summaries.get(preset.baseline)
    out = {n: {"0": figures(summaries[n], iou, floor if n in names else None)} for n in [*names, *floors]
           if n in summaries}
    for sigma in preset.pose_noise_sweep:
        plan = Comparison({k: Scoring(s.config, noisy[sigma][k], None, s.cars) for k, s in scorings.items()}, late=late,
                          channel=Channel(PoseNoise(sigma, sigma, seed)))
        named = {e.name: a for e, a in evaluate_models(plan, test).items()}
        for n in names:
            out[n][f"{sigma:g}"] = figures(named[n].summary(), iou, floor)
        for n in floors:
            out[n][f"{sigma:g}"] = out[n]["0"]  # no other car's pose reaches it
    return out


def trained_with_noise(sweep: dict, noise: dict[str, list | None]) -> dict:
    """``sweep`` with the rows of each model kind trained with pose noise (``noise``: kind ->
    train.pose_noise) renamed to say so, e.g. "KIND, late fusion (trained with pose noise 0.2 m, 0.2 deg)"."""
    suffix = {k: f" (trained with pose noise {pn[0]:g} m, {pn[1]:g} deg)" for k, pn in noise.items() if pn and any(pn)}
    names = {n: n + s for k, s in suffix.items() for n in (k, late_fusion_name(k), own_view_name(k))}
    return {names.get(n, n): rows for n, rows in sweep.items()}


def read_sweep(path: Path, preset: BenchPreset, label: str) -> dict:
    """Another bench run's sweep rows (its report.json), each named "NAME (LABEL)", to set beside this
    run's: it must have scored the same test scenarios at the same sigmas (UserError otherwise)."""
    where = f"--sweep-beside {label}={path}"
    if not ROW_NAME.fullmatch(label):
        raise UserError(f"{where}: the label {excerpt(label)} is not a row name (letters, digits, spaces and "
                        "_ - . , + ( ) only: it goes into the report as it is)")
    try:
        other = read_json(path, "report.json")
        rows = {n: s["pose_noise_sweep"] for n, s in other["models"].items() if "pose_noise_sweep" in s}
        test = other["preset"]["test"]
    except (KeyError, TypeError, AttributeError, SpecError) as e:
        raise UserError(f"{where}: not a bench report.json ({excerpt(str(e))})") from None
    if not rows:
        raise UserError(f"{where}: that run has no pose-noise sweep")
    for name, sweep in rows.items():
        if not isinstance(sweep, dict) or not sweep:
            raise UserError(f"{where}: the sweep of {excerpt(name)} is {excerpt(sweep)}, not a mapping of sigmas to "
                            "figures")
        if not isinstance(name, str) or not ROW_NAME.fullmatch(name):
            raise UserError(f"{where}: row name {excerpt(name)} is not a model row's name (letters, digits, spaces and "
                            "_ - . , + ( ) only: it goes into the report as it is)")
        for sigma, figs in sweep.items():
            if not _is_number(sigma) or not isinstance(figs, dict) or not set(FIGURES) <= set(figs) or \
                    not all(figs[k] is None or _is_number(figs[k]) and not isinstance(figs[k], str) for k in FIGURES):
                raise UserError(f"{where}: row {excerpt(sigma)} of the sweep of {excerpt(name)} is not a sigma with "
                                f"{', '.join(FIGURES)} as numbers")
    if not isinstance(test, list) or sorted(map(str, test)) != sorted(preset.test):
        raise UserError(f"{where}: that run tested {sorted(test)}, this preset tests {sorted(preset.test)}")
    sigmas = sorted(next(iter(rows.values())), key=float)
    own = sorted(["0", *(f"{s:g}" for s in preset.pose_noise_sweep)], key=float)
    if sigmas != own:
        raise UserError(f"{where}: that run's sigmas {sigmas} are not this preset's {own}")
    # the four figures only: another run's standard errors are not checked, so not carried
    return {f"{n} ({label})": {sigma: {k: figs[k] for k in FIGURES} for sigma, figs in r.items()} for n, r in rows.items()}


def cell(row: dict, key: str) -> str:
    """A sweep's figure as its tables print it: the value and, for F1 and hidden-but-seen recall, its standard error."""
    v = row.get(key)
    if v is None:
        return "-"
    se = row.get(f"{key}_se") if key in ("f1", "hidden_seen_recall") else None
    return f"{v:.3f} {se_text(se, row.get('layouts'))}".rstrip()


def _diff(row: dict, floor: float) -> float:
    return row.get("f1_over_baseline", row["f1"] - floor)


def _over(row: dict, floor: float) -> str:
    """A row's F1 over the single view's with its paired standard error; another run's row (``read_sweep``: the four
    figures only) says it has none."""
    diff = _diff(row, floor)
    if "layouts" not in row:
        return f"{diff:+.3f} n/a (another run's row: no paired standard error)"
    return f"{diff:+.3f} {se_text(row.get('f1_over_baseline_se'), row.get('layouts'))}".rstrip()


def _beyond(row: dict, floor: float) -> bool:
    """More than one standard error above the floor; with no standard error (one layout), above it."""
    return _diff(row, floor) - (row.get("f1_over_baseline_se") or 0.0) > 0


def _is_number(text) -> bool:
    try:
        return math.isfinite(float(text))
    except (TypeError, ValueError):
        return False


def robustness_lines(sweep: dict, report: Path, iou: str, baseline: str = "") -> list[str]:
    """The report's section: one table a figure, whether each fusion still beats the ``baseline`` (a
    single view) at each sigma, and a plot (``robustness.png``). The baseline's row may come from
    another run (a name starting with it)."""
    if not sweep:
        return []
    sigmas = list(next(iter(sweep.values())))
    lines = ["## When the other cars' poses are wrong", "",
             "Every other car's pose off by Gaussian noise of sigma metres (x, y, z) and sigma degrees (yaw), the "
             "target car exact; each model at the operating point chosen on validation without noise. The single "
             "view and the own-view ablations read no other car: noise cannot touch them.", ""]
    for key, title in FIGURES.items():
        lines += [f"**{title.format(iou=iou)}**", "", "| model | " + " | ".join(f"sigma {s}" for s in sigmas) + " |",
                  "|---|" + "---|" * len(sigmas)]
        lines += [f"| {n} | " + " | ".join(cell(rows[s], key) for s in sigmas) + " |" for n, rows in sweep.items()]
        lines.append("")
    single = next((n for n in sweep if baseline and (n == baseline or n.startswith(baseline + " ("))), None)
    if single is not None:
        floor = sweep[single]["0"]["f1"]
        lines.append(f"F1@{iou} over the single view's ({floor:.3f}), with its paired standard error ({UNIT}); "
                     "beyond: more than one standard error above it.")
        for n, rows in sweep.items():
            if n.startswith(baseline) or own_view_name("") in n:
                continue
            diffs = [f"sigma {s}: {_over(rows[s], floor)}" for s in sigmas]
            beyond = [s for s in sigmas if _beyond(rows[s], floor)]
            lines.append(f"- {n}: {'; '.join(diffs)}; beyond at sigma {', '.join(beyond) if beyond else 'none'}.")
        lines.append("")
    _plot(sweep, sigmas, report / "robustness.png", iou)
    return lines + ["![F1 and hidden-but-seen recall against pose noise](robustness.png)", ""]


def _plot(sweep: dict, sigmas: list[str], path: Path, iou: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [float(s) for s in sigmas]
    rows_of_legend = (len(sweep) + 2) // 3
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6 + 0.2 * rows_of_legend))
    for ax, key in zip(axes, ("f1", "hidden_seen_recall")):
        for k, (n, rows) in enumerate(sweep.items()):
            y = [rows[s][key] for s in sigmas]
            if all(v is not None for v in y):
                ax.plot(x, y, marker="o", label=n, color=f"C{k % 10}", linestyle="-" if k < 10 else "--")
        ax.set_xlabel("pose noise sigma (m and deg)")
        ax.set_ylabel(FIGURES[key].format(iou=iou))
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()  # below both panels, clear of the lines
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0.055 * rows_of_legend, 1, 1))
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
