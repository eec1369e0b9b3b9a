"""The benchmark on sequences: what the fusions survive when the other cars' messages are late, and the
models' tracks on the ground.

    sweep = delay_sweep(preset, models, data_root)        # {name: {delay_ms: figures}}
    tracks = tracking(preset, models, data_root)          # {name: motmetrics' overall figures}
    lines = delay_lines(sweep, report_dir, preset) + tracking_lines(tracks)

The delay sweep scores every camera once at a frame with its source views (the other cars) of the frame
D ms earlier, for every delay on the same frames (those at least the largest delay into each test
sequence), at the operating points chosen on validation; late fusion moves each late detection to now by
the velocity its sender's own tracker gives it (message format 2). The preset's baseline and the own-view
ablations read no other car and hold at every delay. Tracking: each model with 3D detections, on every
camera of the rig and by late fusion, tracked on the ground (``pnyolo.tracking``) over each test sequence
under its first lighting, scored by motmetrics within 1 m.
"""
from __future__ import annotations

from pathlib import Path

from dataset_spec.atomic import atomic_savefig
from pnyolo.bench.presets import BenchPreset
from pnyolo.bench.robustness import FIGURES, figures
from pnyolo.bench.targets import fmt
from pnyolo.data.dataset import Delay, MultiViewDataset
from pnyolo.evaluation.evaluate import Comparison, evaluate_models, late_fusion_name, own_view_name
from pnyolo.evaluation.late_fusion import Channel
from pnyolo.tracking.senders import SenderTracks


def delay_sweep(preset: BenchPreset, models: dict, root) -> dict[str, dict]:
    """{name: {delay: figures}} at the preset's match IoU; ``models``: kind -> (model, cfg) at the chosen
    operating points (one grid)."""
    iou, last = preset.iou, max(preset.delay_sweep)
    multi = {k: mc for k, mc in models.items() if mc[0].reads_other_views}
    late = tuple(k for k, (m, _) in multi.items() if m.world_outputs)
    floors = {k: mc for k, mc in models.items() if k == preset.baseline}
    out: dict[str, dict] = {}
    senders = None  # one for every delay: each car's own detections of a frame are computed once
    for delay in (0.0, *preset.delay_sweep):
        data = MultiViewDataset(root, "test", next(iter(models.values()))[1], training=False, every_camera=True,
                                delay=Delay(delay, last))
        if delay and senders is None:
            senders = SenderTracks(data)
        plan = Comparison({**multi, **(floors if not delay else {})}, own_view=tuple(multi) if not delay else (),
                          late=late, channel=Channel(senders=senders if delay else None))
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
            cells = [rows.get(d, {}).get(key) for d in delays]
            lines.append(f"| {name} | " + " | ".join("-" if c is None else f"{c:.3f}" for c in cells) + " |")
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


def tracking(preset: BenchPreset, models: dict, root) -> dict[str, dict]:
    """{name: motmetrics' overall figures} of each model with 3D detections, on the rig and by late fusion."""
    import tempfile

    from pnyolo.evaluation.devkit_eval import available as devkit_available
    from pnyolo.evaluation.devkit_eval import devkit_tracking_eval, tracking_results
    from pnyolo.tracking.nuscenes_tracking import devkit_tracking
    from pnyolo.tracking.run import sequence_classes, track_split
    from pnyolo.tracking.scoring import score_tracks

    out = {}
    for kind, (model, cfg) in models.items():
        if not model.world_outputs:
            continue
        data = MultiViewDataset(root, "test", cfg, training=False, every_camera=True)
        keys = {f"{k.scenario}__{k.variant}": (k.scenario, k.variant) for k in data.items}
        for name, late in ((kind, False), (late_fusion_name(kind), True)):
            sequences = track_split(model, data, cfg.eval, None, late)
            kit = devkit_tracking(sequences, sequence_classes(data, sequences), data.class_names) or {}
            out[name] = {**score_tracks(sequences)["OVERALL"], "amota": kit.get("amota"), "amotp": kit.get("amotp")}
            if devkit_available():  # the devkit's TrackingEval on an export of the test split (first lighting)
                with tempfile.TemporaryDirectory() as tmp:
                    evaluation = devkit_tracking_eval(root, "test", tracking_results(sequences, keys, data.class_names),
                                                      Path(tmp), None)
                out[name]["devkit_tracking_eval"] = {k: evaluation.get(k) for k in ("amota", "amotp", "mota", "eval_set")}
    return out


def tracking_lines(tracks: dict) -> list[str]:
    lines = ["## Tracks on the ground", "",
             "Each test sequence under its first lighting, a model's 3D detections of every camera (or, for late "
             "fusion, every car's own) tracked on the ground (constant-velocity Kalman filter per track, "
             "minimum-cost assignment within 2 m, confirmed after 2 detections, ended after 3 missed frames) and "
             "scored by motmetrics within 1 m, Wildtrack's convention, by the nuScenes devkit's tracking "
             "algorithm within 2 m on every scored view's road users (AMOTA, AMOTP), and by the devkit's own "
             "TrackingEval on the test split's nuScenes export (one sample per frame, its ranges and point filter: the "
             "figure a paper's nuScenes tracking table gives).", "",
             "| model | MOTA | MOTP (m) | IDF1 | id switches | false positives | misses | road users | mostly tracked "
             "| AMOTA | AMOTP (m) | TrackingEval AMOTA | TrackingEval AMOTP (m) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, t in tracks.items():
        kit = t.get("devkit_tracking_eval") or {}
        lines.append(f"| {name} | {t['mota']:.3f} | {t['motp'] or 0:.3f} | {t['idf1']:.3f} | {t['num_switches']} | "
                     f"{t['num_false_positives']} | {t['num_misses']} | {t['num_unique_objects']} | "
                     f"{t['mostly_tracked']} | {fmt(t.get('amota'))} | {fmt(t.get('amotp'))} | {fmt(kit.get('amota'))} | "
                     f"{fmt(kit.get('amotp'))} |")
    return lines + [""]
