"""``pnyolo-track``: a model's world detections over the frames of each test sequence, tracked on the ground
(``pnyolo.decoding.ground_tracker``) and scored with motmetrics at 1 m (MOTA, MOTP, IDF1, id switches).

Each frame's detections are those of every camera of the rig: the model on each item of the frame (every
camera scored once, the others its source views) with the items' 3D detections merged (one per road user
within ``eval.centre_nms_m``), or with ``--late-fusion`` every car's own-view detections pooled the same way.
"""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from dataset_spec.atomic import atomic_write_json, atomic_write_text
from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_dir, cli_main
from dataset_spec.names import below
from pnyolo.cli.options import add_run_options, check_threshold
from pnyolo.cooperation.late_fusion import send_threshold
from pnyolo.decoding.ground_tracker import TrackerPoint

EXAMPLES = """examples:
  pnyolo-track runs/bev/best.pt out/seq --split test                  the rig's detections, tracked
  pnyolo-track runs/bev/best.pt out/seq --late-fusion --out out/tracks   every car's own detections pooled
  pnyolo-track runs/bev/best.pt out/seq --variant noon --start 0.5 --keep 0.1 --min-hits 3
  pnyolo-track runs/bev/best.pt out/seq --choose-on val                 the tracker's point chosen by AMOTA on val

The tracker has an operating point of its own (start, keep, confirm, end: pnyolo.decoding.ground_tracker): detections
from --start start and continue tracks, those from --keep only continue confirmed ones. --choose-on val picks it
from a grid by the devkit's TrackingEval AMOTA on the validation sequences, as the benchmark does.

Writes tracks/<scenario>__<variant>.txt (MOTChallenge rows: frame from 1, track id, -1 x4, score, world x, y, 0)
and metrics.json (per sequence and overall: mota, motp in metres, idf1, num_switches, ...).
"""


def _parser() -> OneLineArgumentParser:
    p = OneLineArgumentParser(prog="pnyolo-track", description="Track a model's world detections over sequences.",
                              epilog=EXAMPLES)
    p.add_argument("checkpoint")
    p.add_argument("dataset")
    p.add_argument("--split", default="test", choices=["train", "val", "test"])
    p.add_argument("--variant", default=None, metavar="NAME|all", help="lighting variant (default: each scenario's first)")
    p.add_argument("--late-fusion", action="store_true", help="track the pooled own-view detections of every car")
    p.add_argument("--conf", type=float, help="with --late-fusion, what each car sends from (default: the checkpoint's "
                                              "eval.late_send, else eval.conf_threshold)")
    d = TrackerPoint()
    p.add_argument("--start", type=float, default=None, help="a detection this confident starts a track (default: "
                                                             "the detector's threshold, what its operating point keeps)")
    p.add_argument("--keep", type=float, default=None, help="from this, a detection continues a confirmed track "
                                                            "(default: half of --start)")
    p.add_argument("--gate", type=float, default=d.gate, metavar="SIGMAS",
                   help=f"association gate, standard deviations of the predicted position (default {d.gate:g})")
    p.add_argument("--min-hits", type=int, default=d.min_hits, help=f"detections that confirm a track (default "
                                                                      f"{d.min_hits})")
    p.add_argument("--max-missed", type=int, default=d.max_missed,
                   help=f"frames a confirmed track coasts undetected (default {d.max_missed})")
    p.add_argument("--choose-on", choices=["val"], default=None,
                   help="choose start, keep, confirm and end on the validation sequences by AMOTA (the others ignored)")
    p.add_argument("--out", help="output folder (default: CHECKPOINT's folder/tracks_SPLIT)")
    add_run_options(p)
    return p


@cli_main
def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    _check_point(args)
    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.engine.checkpoint import checkpoint_config, load_detector, read_checkpoint
    from pnyolo.engine.runtime import pick_device
    from pnyolo.cooperation.late_fusion import check_late_fusion
    from pnyolo.models import Decoding
    from pnyolo.tracking.nuscenes_tracking import per_view_tracking
    from pnyolo.tracking.run import sequence_classes, track_split
    from pnyolo.tracking.scoring import as_written, mot_lines, score_tracks

    out = check_output_dir(Path(args.out) if args.out else Path(args.checkpoint).parent / f"tracks_{args.split}")
    ckpt = read_checkpoint(args.checkpoint)
    cfg = checkpoint_config(ckpt)
    ds = MultiViewDataset(args.dataset, args.split, cfg, training=False, every_camera=True)
    variants = _variants(ds, args.variant)
    cfg.data.variants = sorted(set().union(*variants.values()))  # only the lightings tracked are predicted
    ds = MultiViewDataset(args.dataset, args.split, cfg, training=False, every_camera=True)
    device = pick_device(args.device)
    model, cfg = load_detector(ckpt, args.checkpoint, ds.class_names, device)
    check_late_fusion(Decoding.of(model), "pnyolo-track (tracks on the ground)")
    if args.conf is not None:
        cfg = replace(cfg, eval=replace(cfg.eval, conf_threshold=args.conf, late_send=None))  # a new point
    point = _point(args, send_threshold(cfg.eval) if args.late_fusion else cfg.eval.conf_threshold)
    if args.choose_on:
        point = _chosen_point(args, model, cfg, device)
    preds = _predicted(args, model, cfg, ds, device)
    sequences = track_split(preds, ds, cfg.eval, point, args.late_fusion, variants,
                            lambda keys: tqdm(keys, desc="tracking", unit="sequence", disable=args.quiet,
                                              file=sys.stderr))
    sequences = {name: (gt, as_written(rows)) for name, (gt, rows) in sequences.items()}  # scored as written
    for name, (_, rows) in sequences.items():
        atomic_write_text(below(out, "tracks", f"{name}.txt"), mot_lines(rows))
    summary = score_tracks(sequences)
    kit = per_view_tracking(sequences, sequence_classes(ds, sequences), ds.class_names)
    evaluation = _tracking_eval(args, ds, sequences, out)
    atomic_write_json(out / "metrics.json", {"checkpoint": str(args.checkpoint), "split": args.split,
                                             "late_fusion": args.late_fusion, "threshold_m": 1.0,
                                             "tracker_point": point.as_dict(), "chosen_on": args.choose_on,
                                             "metrics": summary,
                                             "per_view": kit, "devkit_tracking_eval": evaluation})
    o = summary["OVERALL"]
    amota = "" if kit is None or kit["amota"] is None else f"; AMOTA {kit['amota']:.3f}, AMOTP {kit['amotp']:.3f} m (2 m)"
    if evaluation and evaluation.get("amota") is not None:
        amota += f"; the devkit's TrackingEval on the split's export: AMOTA {evaluation['amota']:.3f}"
    print(f"{len(sequences)} sequences: MOTA {o['mota']:.3f}, MOTP {o['motp'] or 0:.3f} m, IDF1 {o['idf1']:.3f}, "
          f"{o['num_switches']} id switches (ground plane, 1 m){amota}; {out / 'metrics.json'}")
    return 0


def _check_point(args) -> None:
    """The tracker options, one line for a value out of its range (before any work)."""
    if args.conf is not None and not args.late_fusion:
        raise UserError("--conf goes with --late-fusion (what the cars send); the rig's tracks take --start and --keep")
    for value, option in ((args.conf, "--conf"), (args.start, "--start"), (args.keep, "--keep")):
        check_threshold(value, "eval.conf_threshold", option)
    if args.keep is not None and args.start is not None and not args.keep <= args.start:
        raise UserError(f"--keep {args.keep:g} must not exceed --start {args.start:g}")
    if not (args.gate > 0 and args.gate < float("inf")):
        raise UserError(f"--gate must be a number of standard deviations > 0, got {args.gate}")
    if args.min_hits < 1 or args.max_missed < 0:
        raise UserError("--min-hits must be >= 1 and --max-missed >= 0")


def _point(args, detection: float) -> TrackerPoint:
    """The tracker point the options give, the detector's threshold (``detection``) where --start is not given."""
    start = detection if args.start is None else args.start
    keep = start / 2 if args.keep is None else args.keep
    if not keep <= start:
        raise UserError(f"--keep {keep:g} must not exceed the start threshold {start:g} (give --start)")
    return TrackerPoint(start, keep, args.min_hits, args.max_missed, args.gate)


def _chosen_point(args, model, cfg, device) -> TrackerPoint:
    """``--choose-on val``: the grid's point of the highest AMOTA on the validation sequences
    (``pnyolo.tracking.choice``), as the benchmark chooses it."""
    import tempfile

    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.tracking.choice import amota_on, candidate_points, choose_point

    val = MultiViewDataset(args.dataset, "val", cfg, training=False, every_camera=True)
    if not any(val.ds.scenario(s).frames > 1 for s in val.scenarios):
        raise UserError(f"--choose-on val: the validation split of {args.dataset} holds no sequences to track")
    preds = _predicted(args, model, cfg, val, device)
    with tempfile.TemporaryDirectory(prefix="tracker-") as scratch:
        detection = send_threshold(cfg.eval) if args.late_fusion else cfg.eval.conf_threshold
        point, table = choose_point(amota_on(preds, val, cfg.eval, args.late_fusion, args.dataset, "val",
                                             Path(scratch)), candidate_points(detection=detection))
    print(f"tracker point chosen on val: start {point.start}, keep {point.keep}, confirm {point.min_hits}, end "
          f"{point.max_missed} (AMOTA {max((r['amota'] or 0) for r in table):.3f})")
    return point


def _predicted(args, model, cfg, ds, device):
    """The predictions the tracks are made of, by the one prediction plan (``pnyolo.bench.plan``): with
    --late-fusion every view alone (what each car sends), else the items themselves."""
    from pnyolo.bench.plan import predict_scoring
    from pnyolo.engine.predict import Trained

    scoring = predict_scoring(Trained(Path(args.checkpoint), model, cfg), ds, clean=not args.late_fusion,
                              own=args.late_fusion, device=device, progress=not args.quiet)
    return scoring.own if args.late_fusion else scoring.clean


def _tracking_eval(args, ds, sequences: dict, out: Path) -> dict | None:
    """The devkit's TrackingEval of the tracks on an export of the split (the figure a paper's nuScenes tracking
    table gives); None where the devkit is missing or the dataset has no depth and instance maps to export."""
    from pnyolo.evaluation.devkit_eval import available, devkit_tracking_eval, tracking_results

    if not (available() and ds.ds.info.has("depth") and ds.ds.info.has("instance")):
        return None
    keys = {f"{k.scenario}__{k.variant}": (k.scenario, k.variant) for k in ds.items}
    doc = tracking_results(sequences, keys, ds.class_names, ds.ds)
    return devkit_tracking_eval(args.dataset, args.split, doc, out, "all" if args.variant == "all" else args.variant)


def _variants(ds, variant: str | None) -> dict[str, set[str]]:
    out = {}
    for s in ds.scenarios:
        names = [v.name for v in ds.ds.scenario(s).lighting]
        if variant not in (None, "all") and variant not in names:
            raise UserError(f"--variant {variant!r}: scenario {s} has {names}")
        out[s] = set(names) if variant == "all" else {variant or names[0]}
    return out


if __name__ == "__main__":
    sys.exit(main())
