"""The benchmark on sequences: what the fusions survive when the other cars' messages are late, and the
models' tracks on the ground.

    sweep = delay_sweep(preset, seen, whole, late)          # {name: {delay_ms: figures}}
    tracks = tracking(seen, whole, data_root, report_dir)   # {name: motmetrics' overall figures}
    lines = delay_lines(sweep, report_dir, preset) + tracking_lines(tracks)

``seen``: each model's ``Scoring`` of the whole test sequences (``whole``: every camera, every frame), predicted by
the test stage (``pnyolo.bench.testing``); ``late``: each delay's dataset and the multi-view models' predictions
of it. Nothing here runs a model.

The delay sweep scores every camera once at a frame with its source views (the other cars) of the frame
D ms earlier, for every delay on the same frames (those at least the largest delay into each test
sequence), at the operating points chosen on validation; late fusion moves each late detection to now by
the velocity its sender's own tracker gives it (message format 2): the messages and the tracks are the
cars' own detections of the whole sequences (``cooperation.senders.OwnViews``). The preset's baseline and the own-view
ablations read no other car and hold at every delay. Tracking: each model with 3D detections, on every
camera of the rig and by late fusion, tracked on the ground (``pnyolo.tracking``) over each test sequence
under its first lighting, scored by motmetrics within 1 m.
"""
from __future__ import annotations

from pathlib import Path

from dataset_spec.atomic import atomic_savefig
from pnyolo.bench.presets import BenchPreset
from pnyolo.bench.robustness import FIGURES, cell, figures
from pnyolo.bench.targets import fmt
from pnyolo.data.dataset import Delay, MultiViewDataset
from pnyolo.evaluation.bootstrap import se_text
from pnyolo.evaluation.evaluate import Comparison, Scoring, evaluate_models, late_fusion_name, own_view_name


def delay_sweep(preset: BenchPreset, seen: dict[str, Scoring], whole: MultiViewDataset, late: dict) -> dict[str, dict]:
    """{name: {delay: figures}} at the preset's match IoU; ``seen``: kind -> its Scoring of the ``whole`` test
    sequences at its chosen operating point (one grid); ``late``: delay -> (its dataset, kind -> the multi-view
    models' predictions of it)."""
    iou, last = preset.iou, max(preset.delay_sweep)
    multi = [k for k, s in seen.items() if s.decoding.reads_other_views]
    lates = tuple(k for k in multi if seen[k].decoding.world_outputs)
    floors = [k for k in seen if k == preset.baseline]
    out: dict[str, dict] = {}
    zero = MultiViewDataset(whole.ds.root, "test", whole.cfg, training=False, every_camera=True, delay=Delay(0.0, last),
                            scenarios=whole.scenarios)
    for delay, (data, preds) in {0.0: (zero, None), **late}.items():
        if not delay:  # the same frames without a delay: the whole sequences' predictions of them
            plan = Comparison({k: Scoring(seen[k].config, seen[k].clean.on(data), seen[k].own.on(data) if k in multi
                                          else None, seen[k].cars) for k in [*multi, *floors]},
                              own_view=tuple(multi), late=lates)
        else:
            plan = Comparison({k: Scoring(seen[k].config, preds[k], None, seen[k].cars) for k in multi}, late=lates)
        for entry, acc in evaluate_models(plan, data).items():
            out.setdefault(entry.name, {})[f"{delay:g}"] = figures(acc.summary(), iou)
    for name in [preset.baseline, *(own_view_name(k) for k in multi)]:
        if name in out:  # no other car's message reaches it
            out[name].update({f"{d:g}": out[name]["0"] for d in preset.delay_sweep})
    return out


def delay_lines(sweep: dict, report_dir: Path, preset: BenchPreset) -> list[str]:
    """The report's section: a table per figure over the delays and a plot of F1 and hidden-but-seen recall."""
    delays = ["0", *(f"{d:g}" for d in preset.delay_sweep)]
    lines = ["## When the other cars' messages are late", "",
             f"Each camera scored once at a frame of a test sequence, its source views (the other cars' images, "
             f"poses or detections) of the frame D ms earlier; every delay on the same frames (at least "
             f"{delays[-1]} ms into each sequence), at the operating points chosen on validation. Late fusion moves each "
             "late detection to now by the velocity its sender's own tracker gives it (message format 2). The single "
             "view and the own-view ablations read no other car: they hold at every delay.", ""]
    for key in ("f1", "hidden_seen_recall"):
        lines += [f"| {FIGURES[key].format(iou=preset.iou)} | " + " | ".join(f"{d} ms" for d in delays) + " |",
                  "|---|" + "---:|" * len(delays)]
        for name, rows in sweep.items():
            lines.append(f"| {name} | " + " | ".join(cell(rows.get(d, {}), key) for d in delays) + " |")
        lines.append("")
    _plot(sweep, delays, report_dir / "delay.png", preset.iou)
    return lines + ["![F1 and hidden-but-seen recall against the delay](delay.png)", ""]


def _plot(sweep: dict, delays: list[str], path: Path, iou: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    x = [float(d) for d in delays]
    for ax, key in zip(axes, ("f1", "hidden_seen_recall")):
        for name, rows in sweep.items():
            y = [rows.get(d, {}).get(key) for d in delays]
            if all(v is not None for v in y):
                ax.plot(x, y, "o-", label=name, lw=1.2, ms=3)
        ax.set_xlabel("delay of the other cars' messages (ms)")
        ax.set_title(FIGURES[key].format(iou=iou), fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)


def tracking(seen: dict[str, Scoring], whole: MultiViewDataset, root, report: Path,
             val: tuple[MultiViewDataset, dict[str, Scoring]] | None = None) -> dict[str, dict]:
    """{name: motmetrics' overall figures} of each model with 3D detections (``seen``: its Scoring of the ``whole``
    test sequences), on the rig and by late fusion, each at the tracker point chosen on ``val`` (the validation
    sequences and each model's Scoring of them; None: the validation split holds no sequences, the default point);
    the tracks TrackingEval scored kept as ``report/NAME/results_nusc_tracking_test.json``."""
    import tempfile

    from pnyolo.decoding.ground_tracker import TrackerPoint
    from pnyolo.evaluation.devkit_eval import available as devkit_available
    from pnyolo.evaluation.devkit_eval import devkit_tracking_eval, tracking_results
    from pnyolo.cooperation.late_fusion import send_threshold
    from pnyolo.tracking.choice import amota_on, candidate_points, choose_point
    from pnyolo.tracking.nuscenes_tracking import per_view_tracking
    from pnyolo.tracking.run import sequence_classes, track_split
    from pnyolo.tracking.scoring import score_tracks, track_errors

    out, per_sequence = {}, {}
    keys = {f"{k.scenario}__{k.variant}": (k.scenario, k.variant) for k in whole.items}
    scratch = tempfile.TemporaryDirectory(prefix="tracker-")  # the validation export, made once for every choice
    for kind, s in seen.items():
        for name, late in ((kind, False), (late_fusion_name(kind), True)):
            detection = send_threshold(s.config.eval) if late else s.config.eval.conf_threshold
            point, chosen = TrackerPoint.at_detection(detection), {
                "chosen_on": "default (the detector's threshold): the validation split holds no sequences"}
            if val is not None:
                v = val[1][kind]
                point, table = choose_point(amota_on(v.own if late else v.clean, val[0], v.config.eval, late, root,
                                                     "val", Path(scratch.name)), candidate_points(detection=detection))
                chosen = {"chosen_on": "val", "val_amota": max((r["amota"] for r in table if r["amota"] is not None),
                                                                default=None), "val_table": table}
            sequences = track_split(s.own if late else s.clean, whole, s.config.eval, point, late)
            kit = per_view_tracking(sequences, sequence_classes(whole, sequences), whole.class_names) or {}
            per_sequence[name] = score_tracks(sequences)
            out[name] = {**per_sequence[name]["OVERALL"], "amota": kit.get("amota"), "amotp": kit.get("amotp"),
                         "tracker_point": point.as_dict(), **chosen,
                         "standard_errors": track_errors(per_sequence[name])}
            if late:  # the cars' fused tracks against the rig's, paired over the same sequences
                out[name]["against_rig"] = track_errors(per_sequence[name], per_sequence[kind])
            if devkit_available():  # the devkit's TrackingEval on an export of the test split (first lighting)
                evaluation = devkit_tracking_eval(root, "test", tracking_results(sequences, keys, whole.class_names, whole.ds),
                                                  report / name, None, scenarios=list(whole.scenarios))
                keep = ("amota", "amotp", "mota", "eval_set", "results")
                out[name]["devkit_tracking_eval"] = {
                    **{k: evaluation.get(k) for k in keep},
                    "car_pedestrian": {k: (evaluation.get("car_pedestrian") or {}).get(k) for k in ("amota", "amotp", "mota")}}
    scratch.cleanup()
    return out


def tracking_lines(tracks: dict) -> list[str]:
    lines = ["## Tracks on the ground", "",
             "Each test sequence under its first lighting, a model's 3D detections of every camera (or, for late "
             "fusion, every car's own) tracked on the ground (constant-velocity Kalman filter per track, two-stage "
             "minimum-cost assignment within the gate of the predicted position's uncertainty: detections from the "
             "start score start and continue tracks, those from the keep score only continue confirmed ones; its "
             "operating point chosen on the validation sequences by the devkit's TrackingEval AMOTA, columns "
             "start / keep / confirm / end, or the default where validation holds no sequences) and "
             "scored by motmetrics within 1 m, Wildtrack's convention, by the nuScenes devkit's tracking "
             "algorithm within 2 m on every scored view's road users (AMOTA, AMOTP), and by the devkit's own "
             "TrackingEval on the test split's nuScenes export (one sample per frame, its ranges and point filter: the "
             "figure a paper's nuScenes tracking table gives; the tracks it scored: `results_nusc_tracking_test.json` in "
             "the model's folder), over the four classes the export holds and over car and pedestrian, the classes the "
             "models name (buses and trucks as cars; the four-class mean averages in their zeros).", "",
             "| model | tracker point (chosen on) | MOTA | MOTP (m) | IDF1 | id switches | false positives | misses | "
             "road users | mostly tracked | AMOTA | AMOTP (m) | TrackingEval AMOTA | TrackingEval AMOTP (m) | "
             "TrackingEval AMOTA, car and pedestrian |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, t in tracks.items():
        kit, p = t.get("devkit_tracking_eval") or {}, t.get("tracker_point") or {}
        at = (f"{p.get('start')} / {p.get('keep')} / {p.get('min_hits')} / {p.get('max_missed')} "
              f"({'val' if t.get('chosen_on') == 'val' else 'default'})") if p else "-"
        se = t.get("standard_errors") or {}
        lines.append(f"| {name} | {at} | {t['mota']:.3f} {se_text(se.get('mota'), se.get('layouts'))} | "
                     f"{t['motp'] or 0:.3f} | {t['idf1']:.3f} {se_text(se.get('idf1'), se.get('layouts'))} | "
                     f"{t['num_switches']} | {t['num_false_positives']} | {t['num_misses']} | {t['num_unique_objects']} "
                     f"| {t['mostly_tracked']} | {fmt(t.get('amota'))} | {fmt(t.get('amotp'))} | "
                     f"{fmt(kit.get('amota'))} | {fmt(kit.get('amotp'))} | "
                     f"{fmt((kit.get('car_pedestrian') or {}).get('amota'))} |")
    versus = [(n, t["against_rig"]) for n, t in tracks.items() if t.get("against_rig")]
    if versus:
        lines += ["", "MOTA and IDF1 carry one bootstrap standard error (layouts resampled). The cars' fused tracks "
                  "against the rig's (every camera's detections together), paired over the same sequences:", ""]
        lines += [f"- {n}: MOTA {d['mota_difference']:+.3f} {se_text(d['mota'], d['layouts'])}, IDF1 "
                  f"{d['idf1_difference']:+.3f} {se_text(d['idf1'], d['layouts'])}".rstrip() for n, d in versus]
    return lines + [""]
