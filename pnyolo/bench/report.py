"""The benchmark report: ``report.md`` with pictures and ``report.json`` with every figure.

    result = write_report(run)     # run: the BenchRun every stage filled in (pnyolo.bench.record)

Its sentences read the record's typed results (``Result.figures``, ``.choice``, ``.late_choice``, ...);
the tables shared with ``pnyolo-eval`` (``pnyolo.evaluation.report``) read the rows as report.json holds them.
    result["targets"]      # {target text: True / False / None (nothing to measure)}
    result["target_figures"]   # {target text: what was measured}
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from dataset_spec import LabelThresholds
from dataset_spec.atomic import atomic_write_json, atomic_write_text
from pnyolo.bench.pictures import recall_plot
from pnyolo.bench.presets import BenchPreset, multi_view_kinds
from pnyolo.bench.record import (AGREEMENT, CALIBRATED, INTO_EGO, BenchRun, Choice, Figures, HiddenPoint,
                                 LateChoice, Result)
from pnyolo.bench.robustness import robustness_lines, trained_with_noise
from pnyolo.bench.targets import RULE, bench_targets, best_multi_view, fmt
from pnyolo.bench.analyses import run_analyses
from pnyolo.evaluation.bootstrap import difference_se, f1_of, hidden_recall_of, se_text, spread_text
from pnyolo.evaluation.coverage import coverage_markdown
from pnyolo.evaluation.evaluate import FUSION, late_fusion_name, own_view_name
from pnyolo.cooperation.message import DETECTION_BYTES, HEADER_BYTES
from pnyolo.evaluation.report import comparison_markdown, false_positive_markdown, write_comparison
from pnyolo.registry import kinds, model_class


def _hidden_target_lines(point: HiddenPoint, baseline: str, baseline_f1: float, iou: str) -> list[str]:
    head = (f"**Operating point for the hidden-recall target** (for information; the targets below are judged at "
            f"the F1 point): the highest confidence whose validation recall@{iou} on hidden-but-seen objects "
            f"reaches {point.target:g}, same checkpoint and NMS. ")
    if point.threshold is None:
        return [head + f"No candidate threshold reaches it on validation (at most {fmt(point.best_val_recall)}).", ""]
    return [head + f"Confidence {point.threshold:.2f} (validation F1@{iou} {point.val_f1:.3f}, hidden-but-seen "
            f"recall {point.val_hidden_recall:.3f}); on test F1@{iou} {point.test_f1:.3f} ({baseline} at its own "
            f"point {baseline_f1:.3f}) and hidden-but-seen recall {fmt(point.test_hidden_recall)}.", ""]


def _seconds(v) -> str:
    if isinstance(v, dict):  # a reused stage: what it took when it ran
        return "reused" + (f" (took {v['trained_seconds']:.0f} when run)" if v.get("trained_seconds") else "")
    return "reused" if v is None else f"{v:.0f}"


def _one_per_scenario_first(pictures: list[Path], scenarios: list[str]) -> list[Path]:
    """``pictures`` (named ``SCENARIO_...``) reordered round-robin over ``scenarios``, so the first few
    shown come from different streets rather than one street under every lighting."""
    def scenario_of(p: Path) -> str:
        return max((s for s in scenarios if p.name.startswith(s + "_")), key=len, default="")

    rank: dict[str, int] = {}
    keyed = []
    for p in pictures:
        s = scenario_of(p)
        keyed.append((rank.setdefault(s, 0), p.name, p))
        rank[s] += 1
    return [p for _, _, p in sorted(keyed)]


def _selection_text(kind: str, sel: Choice, iou: str) -> str:
    stats = f", {sel.eval_stats} batch-norm statistics"
    stats += f", NMS IoU {sel.nms_iou}" if sel.nms_iou is not None else ""
    stats += f", depth gap {sel.depth_gap:g} m" if sel.depth_gap is not None else ""
    stats += f", {sel.depth_peaks} depth peaks" if sel.depth_peaks > 1 else ""
    se = spread_text(sel.val_f1_se, sel.val_layouts)
    return (f"{kind} `{sel.checkpoint}` (step {sel.step}{stats}) at {sel.threshold:.2f} (validation F1@{iou} "
            f"{sel.val_f1:.3f}; best {sel.best_val_f1:.3f} at {sel.best_threshold:.2f}, standard error {se})")


def _sweep_table(grid: tuple[float, ...], sweeps: dict[str, list[dict]]) -> str:
    """Markdown: one row per confidence threshold, one column per sweep, cells ``F1 / hidden recall``."""
    lines = ["| confidence | " + " | ".join(sweeps) + " |", "|---|" + "---|" * len(sweeps)]
    for i, t in enumerate(grid):  # every sweep ran over the same grid, in its order
        cells = []
        for rows in sweeps.values():
            hs = rows[i]["hidden_seen_recall"]
            cells.append(f"{rows[i]['f1']:.3f} / {fmt(hs)}")
        lines.append(f"| {t:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _f1_and_hidden(figures: Figures, iou: str) -> str:
    """"F1@IOU ..., hidden-but-seen recall ..." of one row."""
    return f"F1@{iou} {figures.f1[iou]:.3f}, hidden-but-seen recall {fmt(figures.recall(iou).recall)}"


def _own_view_lines(results: dict[str, Result], iou: str) -> list[str]:
    """The report's paragraph on each multi-view model with each view's own image alone (if evaluated)."""
    lines = []
    for kind in multi_view_kinds(results):
        if own_view_name(kind) not in results or kind not in results:
            continue
        full, own = results[kind].figures, results[own_view_name(kind)].figures
        full_hs, own_hs = full.recall(iou).recall, own.recall(iou).recall
        lines += [f"**What the other source views add to {kind}**: `{own_view_name(kind)}` is the same model at the "
                  f"same operating point, {model_class(kind).own_view_text}: F1@{iou} {own.f1[iou]:.3f} "
                  f"against {full.f1[iou]:.3f} with every source view ({_difference(results, kind, own_view_name(kind), iou)}); "
                  f"recall on hidden-but-seen objects {fmt(own_hs)} against {fmt(full_hs)} "
                  f"({_difference(results, kind, own_view_name(kind), iou, hidden=True)}). Whatever it finds of objects "
                  "hidden in its own view without the other views comes from what one image suggests, not from "
                  "seeing them.", ""]
    return lines


def _late_fusion_lines(preset: BenchPreset, results: dict[str, Result], iou: str) -> list[str]:
    lines = []
    for kind in preset.late_fusion:
        late = results.get(late_fusion_name(kind))
        if late is None:
            continue
        sent, feats = late.figures.bytes_per_car_frame, late.feature_bytes
        size = "" if sent is None else (f" A car sends {sent:.0f} bytes per frame (its detections: a {HEADER_BYTES}-byte "
                                        f"header and {DETECTION_BYTES} bytes each, pnyolo.cooperation.message)")
        size += "" if feats is None else (f", against {feats / 2**20:.1f} MiB of encoder feature maps a multi-view model "
                                          "reads from its camera.")
        lines += [f"**Late fusion** (`{late_fusion_name(kind)}`): the {kind} model run on every camera alone, each "
                  "car's 3D detections pooled in the world frame (same-class centres within eval.centre_nms_m merged) "
                  f"and projected into each target view: {_f1_and_hidden(late.figures, iou)}"
                  + _against_one_car(results, kind, iou) + "." + _rule_text(late.late_choice, iou) + size, ""]
    return lines


def _late_into_lines(results: dict[str, Result], iou: str) -> list[str]:
    """Late fusion into the ego model (``late_choice.choose_late_into``), against the ego alone."""
    lines = []
    for name, r in results.items():
        sel = r.late_choice
        if sel is None or sel.rule != INTO_EGO or sel.ego not in results:
            continue
        sender = name.split(",")[0]
        lines += [f"**Late fusion into {sel.ego}** (`{name}`): each target view's car keeps its own {sel.ego} "
                  f"detections from confidence {sel.ego_threshold:.2f} and adds the road users the other cars' "
                  f"{sender} models report (sent from {sel.send:.2f}, the best car's report of each, projected "
                  f"into the view where its own detections have no box): {_f1_and_hidden(r.figures, iou)}, against "
                  f"{sel.ego} alone: {_f1_and_hidden(results[sel.ego].figures, iou)}. "
                  f"Both thresholds chosen on validation (F1@{iou} {sel.val_f1:.3f}; {sel.ego} alone "
                  f"{sel.ego_val_f1:.3f}).", ""]
    return lines


def _against_one_car(results: dict[str, Result], kind: str, iou: str) -> str:
    """", against one car alone (the own-view row): F1 ..., hidden-but-seen recall ..." where there is one, with the
    differences' paired standard errors."""
    one = results.get(own_view_name(kind))
    if one is None:
        return ""
    late = late_fusion_name(kind)
    return (f", against one car alone (`{own_view_name(kind)}`): {_f1_and_hidden(one.figures, iou)} (differences: "
            f"F1 {_difference(results, late, own_view_name(kind), iou)}, hidden-but-seen recall "
            f"{_difference(results, late, own_view_name(kind), iou, hidden=True)})")


def _difference(results: dict[str, Result], a: str, b: str, iou: str, hidden: bool = False) -> str:
    """Row ``a``'s F1@``iou`` (or hidden-but-seen recall) minus row ``b``'s, with its paired bootstrap standard
    error over the test layouts ("+0.073 ± 0.021"; "n/a (one layout)")."""
    fa, fb = results[a].figures, results[b].figures
    va, vb = (fa.recall(iou).recall, fb.recall(iou).recall) if hidden else (fa.f1[iou], fb.f1[iou])
    if va is None or vb is None:
        return "n/a"
    se = difference_se(results[a].metrics, results[b].metrics, hidden_recall_of if hidden else f1_of, iou)
    return f"{va - vb:+.3f} {se_text(se, results[a].metrics.get('standard_errors', {}).get('layouts'))}".rstrip()


def _rule_text(sel: LateChoice | None, iou: str) -> str:
    """The late-fusion rule chosen on validation (a ``record.LateChoice``; None: none), in a sentence."""
    if sel is None:
        return ""
    if sel.rule == AGREEMENT:
        rule = (f"agreement: cars send from confidence {sel.send:.2f}, each road user's reports are scored by "
                f"noisy-OR over the cars and kept from {sel.keep:.2f}")
    elif sel.rule == CALIBRATED:
        a, b, c = sel.calibration
        rule = (f"calibrated agreement: cars send from confidence {sel.send:.2f}, each report's score s at d metres "
                f"from its sender becomes sigmoid({a:.2f} logit(s) {b:+.2f} d/10 m {c:+.2f}) (fitted on validation), "
                f"and each road user's reports are scored by noisy-OR over the cars and kept from {sel.keep:.2f}")
    else:
        rule = f"the best car's detection of each road user, kept from confidence {sel.send:.2f}"
    se = spread_text(sel.val_f1_se, sel.val_layouts)
    return (f" Rule chosen on validation: {rule} (validation F1@{iou} {sel.val_f1:.3f}, standard error {se}; the "
            f"best-car rule {sel.best_car_val_f1:.3f}).")


def _model_table(results: dict[str, Result], timings: dict, kinds: list[str]) -> list[str]:
    lines = ["| model | training (s) | threads | inference per frame (ms) | threads | distance error (m) |",
             "|---|---|---|---|---|---|"]
    for k in kinds:
        r = results[k]
        de, ms = r.figures.distance_error_m, r.inference_ms
        lines.append(f"| {k} | {_seconds(timings.get(f'train {k}'))} | {r.train_threads or '-'} | "
                     f"{'-' if ms is None else f'{ms:.0f}'} | {r.inference_threads or '-'} | "
                     f"{'-' if de is None else f'{de:.2f}'} |")
    return lines + [""]


def _time_lines(run: BenchRun) -> list[str]:
    """The delay sweep and the tracks, where the run measured them (``pnyolo.bench.time_axis``)."""
    from pnyolo.bench.time_axis import delay_lines, tracking_lines

    delays = {n: r.delay_sweep for n, r in run.results.items() if r.delay_sweep is not None}
    tracks = {n: r.tracking for n, r in run.results.items() if r.tracking is not None}
    return (delay_lines(delays, run.report, run.preset) if delays else []) + (tracking_lines(tracks) if tracks else [])


def _sweep_rows(run: BenchRun) -> dict:
    """The pose-noise sweep's rows: this run's (a model trained with pose noise named so), then those
    of the runs set beside it (read into the record when the run started)."""
    own = {n: r.pose_noise_sweep for n, r in run.results.items() if r.pose_noise_sweep is not None}
    return trained_with_noise(own, {k: m.config.train.pose_noise for k, m in run.models.items()}) | run.beside_rows


def _selection_lines(preset: BenchPreset, results: dict[str, Result], iou: str) -> str:
    """How each operating point was chosen on validation, and what was chosen."""
    return ("Chosen on the validation split, the same procedure for every model: the checkpoint (the run's end "
            "`latest.pt` or its best-validation `best.pt`) and the encoder's batch-norm statistics outside "
            "training (`running` averages, or `item`: those of the views encoded together, as in every training "
            f"step) and, for a model decoded by 2D NMS, the NMS IoU (of {', '.join(str(n) for n in preset.nms_grid)})"
            + (f" and, for a model with distance estimates, the depth gap of depth-gated NMS (of "
               f"{', '.join('none' if g is None else f'{g:g} m' for g in preset.depth_gaps)})"
               if preset.depth_gaps != (None,) else "")
            + (f" and, for a model that renders rays, the depth peaks kept per ray (of "
               f"{', '.join(str(k) for k in preset.depth_peaks)})" if preset.depth_peaks != (1,) else "")
            + f" with the best F1@{iou} at its best confidence threshold, "
            f"then the threshold by the one-standard-error rule (the lowest threshold whose validation F1@{iou} is "
            "within one bootstrap standard error, validation layouts resampled, of the best): "
            + ", ".join(_selection_text(k, r.choice, iou) for k, r in results.items() if r.choice is not None) + ".")


def _head_lines(run: BenchRun, names: list[str]) -> list[str]:
    """The report's title, command, models, ground truth, selection and the data table."""
    preset, iou = run.preset, run.preset.iou
    anchors = "" if run.anchors is None else str(run.anchors)
    lines = [f"# Occlusion benchmark: `{preset.name}` preset", "", f"{preset.description}.", "",
             f"Command: `{run.command}`  ", f"Seed: {run.seed}; models: {', '.join(names)}; training budget: "
             f"{preset.steps} steps per model; config `{preset.config}` {preset.config_text()}", "",
             *[f"- `{k}`: {model_class(k).description}" for k in names if k in kinds()], "",
             f"Ground truth (every model): every car and pedestrian with in-frame fraction >= "
             f"{LabelThresholds().min_in_frame} and distance <= {preset.max_distance} m, *including fully "
             f"hidden ones*; {'anchors fitted to the training labels: ' + anchors if anchors else 'anchors from the config'}.",
             _selection_lines(preset, run.results, iou), "",
             f"Scored on validation and test: {preset.scored_text(run.num_views)}.", "",
             "## Data", "", "Render: Cycles seconds of the split's data passes (depth, ids) and RGB renders when "
             "they were rendered (- where the bench did not render them); size: its scenario folders on disk.", "",
             "| split | scenarios | images (views x lighting) | labels per lighting | fully hidden labels | "
             "render: data passes / RGB (s) | size (MB) |", "|---|---|---|---|---|---|---|"]
    for split in ("train", "val", "test"):
        st = run.statistics[split]
        cost = "-" if st.get("render_data_s") is None else f"{st['render_data_s']:.0f} / {st['render_rgb_s']:.0f}"
        size = f"{st['bytes'] / 1e6:.1f}" if "bytes" in st else "-"
        lines.append(f"| {split} | {', '.join(st['scenarios'])} | {st['images']} | {st['labels_per_lighting']} | "
                     f"{st['fully_hidden_labels']} | {cost} | {size} |")
    return lines


def _results_lines(run: BenchRun, rows: dict[str, dict], best: str | None) -> list[str]:
    """The test results: the comparison, the fusion, the ablations, late fusion, the ceilings, the
    robustness sweep, the coverage, the false positives and every candidate threshold (``rows``: the results
    as report.json holds them, for the tables shared with pnyolo-eval; ``best``: the best multi-view model)."""
    preset, iou = run.preset, run.preset.iou
    results = run.results
    ceiling = next(r.figures.view_ceiling for r in results.values() if r.figures.view_ceiling is not None)
    fused = preset.fusion
    lines = ["", "## Results on the held-out scenarios", "",
             "![F1 versus match IoU](f1_vs_match_iou.png) ![recall by visibility](recall_by_visibility.png)", "",
             comparison_markdown(rows, single=preset.baseline or None), "",
             *([f"`fusion`: the union of {fused[0]}'s and {fused[1]}'s detections after NMS (the paper's Table 6.11).",
                ""] if FUSION in results else []),
             *_own_view_lines(results, iou), *_late_fusion_lines(preset, results, iou),
             *_late_into_lines(results, iou),
             f"**Single-view ceiling** (share of test ground truth with any visible pixel in its own view): "
             f"{ceiling.recall_ceiling:.3f} of {ceiling.n} ({ceiling.fully_hidden} fully hidden). "
             "No detector reading one view can exceed this recall.", "",
             *robustness_lines(_sweep_rows(run), run.report, iou, preset.baseline), *_time_lines(run)]
    for kind in multi_view_kinds(results):
        cov = results[kind].coverage
        if cov:
            lines += [f"**Sampling coverage** of {kind} on the test split: over {model_class(kind).coverage_text}, the "
                      "share with a point inside its 3D box, one projecting onto its visible pixels in a source view "
                      "that sees it, and one within one feature cell (the encoder's finest stride) of them.", "",
                      coverage_markdown(cov)]
    for kind, r in results.items():
        enc = r.encoding_ceiling
        if enc:
            gap = f", depth gap {enc.depth_gap:g} m with exact distances" if enc.depth_gap is not None else ""
            lines += [f"**Encoding ceiling** of {kind} (a perfect detector: the test targets decoded and NMS-ed at "
                      f"{enc.nms_iou}{gap} like its outputs): recall@{iou} {enc.recall:.3f}, on hidden-but-seen "
                      f"objects {fmt(enc.hidden_seen_recall())}. Objects sharing a grid cell beyond its anchors, or "
                      "suppressed by NMS with their occluder, are lost to any model decoded that way.", ""]
    fp_table = false_positive_markdown(rows, iou)
    return lines + ([fp_table] if fp_table else []) + _threshold_lines(run, best)


def _threshold_lines(run: BenchRun, best: str | None) -> list[str]:
    """Every candidate threshold on validation and test, and the hidden-recall operating point (that of
    ``best``, the best multi-view model: what a user needing the hidden-recall target would take)."""
    preset, iou = run.preset, run.preset.iou
    val = {k: r.choice.val_sweep for k, r in run.results.items() if r.choice is not None}
    test = {k: r.test_sweep for k, r in run.results.items() if r.test_sweep is not None}
    lines = []
    if val or test:
        lines += [f"Every candidate confidence threshold (each model at its chosen NMS IoU), F1@{iou} / recall@{iou} "
                  "on hidden-but-seen objects, on the validation split (where the thresholds were chosen) and, for "
                  "information only, on the test split.",
                  "", _sweep_table(preset.conf_grid, {f"{k} (val)": v for k, v in val.items()}
                                   | {f"{k} (test)": v for k, v in test.items()}), ""]
    hidden_point = None if best is None else run.results[best].hidden_point
    if hidden_point is not None:
        base = run.results.get(preset.baseline)
        f1 = float("nan") if base is None else base.figures.f1.get(iou, float("nan"))
        lines += [f"({best})"] + _hidden_target_lines(hidden_point, preset.baseline, f1, iou)
    return lines


def _tail_lines(run: BenchRun, checks: dict, names: list[str]) -> list[str]:
    """Training and inference per model, the targets, the timings and the example pictures."""
    lines = ["## Models: training and inference", "",
             "Inference: forward pass and decoding of one frame (data.num_views views), evaluation mode, the "
             "median over 12 test items on this machine.", "", *_model_table(run.results, run.timings, names)]
    lines += ["## Targets", "", f"A target on a difference or a test figure: {RULE}; with one layout, the figure "
              "itself.", ""]
    for name, (ok, figures) in checks.items():
        lines.append(f"- {'PASS' if ok else ('n/a' if ok is None else 'FAIL')}: {name}: {figures}")
    lines += ["", "## Timings (seconds, this machine)", "", "| stage | seconds |", "|---|---|"]
    for k, v in run.timings.items():
        lines.append(f"| {k} | {_seconds(v)} |")
    panels = [p for p in (run.report / "examples").glob("*_vs_*.png") if not p.stem.endswith("_top_down")]
    examples = _one_per_scenario_first(sorted(panels), run.preset.test)
    if examples:
        lines += ["", "## Where the multi-view model finds what the single view cannot", "",
                  "Each picture: the first model's detections (top rows) and the second's (bottom), on the same "
                  "source views, then the frame from above: view cones (the target's red), road users by what "
                  "the target camera sees of them, each hidden-but-seen one found or missed by the first model, "
                  "every model's detections placed on the ground; see `examples/`.", ""]
        for p in examples[:4]:
            lines.append(f"![{p.stem}](examples/{p.name})")
            above = p.with_name(f"{p.stem}_top_down.png")
            if above.is_file():
                lines.append(f"![{above.stem}](examples/{above.name})")
    for movie in sorted((run.report / "examples").glob("*_top_down.gif"))[:1]:
        lines += ["", "A test sequence from above, frame by frame (every model's detections, the first model's "
                  "hidden-but-seen finds):", "", f"![{movie.stem}](examples/{movie.name})"]
    return lines


def write_report(run: BenchRun) -> dict:
    """The run's comparison (every model's figures), report.md and report.json in ``run.report``,
    rendered from the record alone; returns report.json's content."""
    preset, report, iou = run.preset, run.report, run.preset.iou
    results, rows = run.results, run.summaries()
    write_comparison(rows, report, {"checkpoints": {k: str(m.checkpoint) for k, m in run.models.items()}},
                     single=preset.baseline or None)
    names = [k for k in preset.models if k in results]
    checks = bench_targets(preset, results, run.timings)
    recall_plot(results, report / "recall_by_visibility.png", iou)
    best = best_multi_view(results)
    hidden_point = None if best is None else results[best].hidden_point
    analysed, analysis_lines = run_analyses(run)  # the registered analyses (pnyolo.bench.analyses)
    lines = [*_head_lines(run, names), *_results_lines(run, rows, best), *analysis_lines,
             *_tail_lines(run, checks, names)]
    atomic_write_text(report / "report.md", "\n".join(lines) + "\n")
    f1 = {k: r.figures.f1[iou] for k, r in results.items()}
    hidden = {k: r.figures.recall(iou).recall for k, r in results.items()}
    result = {"preset": asdict(preset), "seed": run.seed, "command": run.command, "timings": run.timings,
              "dataset": run.statistics, "targets": {k: ok for k, (ok, _) in checks.items()},
              "target_figures": {k: fig for k, (_, fig) in checks.items()}, f"f1_at_{iou}": f1,
              "hidden_seen_elsewhere_recall": {**hidden, "n": results[names[0]].figures.recall(iou).n},
              "single_view_ceiling": rows[names[0]]["single_view_ceiling"],
              "hidden_target_point": None if hidden_point is None else hidden_point.as_json(), "models": rows,
              "analyses": analysed,
              **({"pose_noise_beside": {k: str(v) for k, v in run.beside.items()}} if run.beside else {})}
    atomic_write_json(report / "report.json", result)
    return result
