"""``pnyolo-eval``: a checkpoint (or another detector's results) scored on a dataset split, with the
fusion of two checkpoints, late fusion and the other cars' pose error as options."""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_dir, cli_main
from pnyolo.config.checks import EVAL_STATS
from pnyolo.cli.options import add_run_options, check_metres, check_threshold, parse_views, refuse_for_kind

EVAL_EXAMPLES = """examples:
  pnyolo-eval runs/mv/best.pt out/dataset --split test
  pnyolo-eval runs/mv/best.pt out/dataset --split test --views 2,0,1 --metric paper
  pnyolo-eval runs/mv/best.pt out/dataset --every-camera   score every camera of each scene once
  pnyolo-eval runs/mv/best.pt out/dataset --fuse runs/sv/best.pt --out out/compare
  pnyolo-eval runs/mv/best.pt out/dataset --norm-stats item     batch norm as in training (see pnyolo-bench)
  pnyolo-eval runs/bev/best.pt out/dataset --every-camera --late-fusion   each car alone, 3D detections pooled
  pnyolo-eval runs/mv/best.pt out/dataset --every-camera --own-view   and the model reading each camera alone
  pnyolo-eval out/bench_cpu/runs/bev/best.pt out/bench_cpu/dataset --every-camera --late-fusion \
      --late-rule from:out/bench_cpu    the bench's late-fusion row: its rule and bev's operating point
  pnyolo-eval runs/mv/best.pt out/dataset --every-camera --chance-from runs/sv/best.pt
                                                   hidden-but-seen recall above the single view's on the same objects
  pnyolo-eval runs/bev/best.pt out/dataset --every-camera --late-fusion --pose-noise 0.2,0.2   other cars' poses off
  pnyolo-eval runs/bev/best.pt out/seq --every-camera --late-fusion --delay-ms 200   the other cars' views 200 ms old
  pnyolo-eval runs/bev/best.pt out/ds --every-camera --late-fusion --into runs/single-view/best.pt
                                                   the other cars' bev reports added to each car's single view
  pnyolo-eval runs/bev/latest.pt out/wildtrack     an imported rig: also gt.txt, detections.txt, the field's MODA
  pnyolo-eval --results test.txt out/wildtrack     another tool's 'frame grid_x grid_y' rows, scored the same way
  pnyolo-eval --results results_nusc.json out/ds   nuScenes detection results (BEVFormer, mmdetection3d, ours)

Writes metrics.json, metrics.md, f1_vs_match_iou.png and examples/*.png (with --fuse or --late-fusion: one
folder per result plus comparison.json, comparison.md and a plot of them side by side). Detections with a 3D
position (kinds with world outputs; YOLO-grid detections at their distance) also get ground-plane metrics:
the devkit's DetectionEval on the split's export (--every-camera), a per-view AP and NDS, MODA / MODP,
recall within 1 m.
"""


def _parser() -> OneLineArgumentParser:
    p = OneLineArgumentParser(prog="pnyolo-eval", description="Evaluate a checkpoint on a dataset split.",
                              epilog=EVAL_EXAMPLES)
    p.add_argument("inputs", nargs="+", metavar="CHECKPOINT DATASET",
                   help="a checkpoint and a dataset folder (with --results: the dataset folder only)")
    p.add_argument("--results", metavar="PREDICTIONS.json|.txt",
                   help="score another detector's detections instead of a checkpoint: a COCO results file whose "
                        "image ids are those of this dataset's COCO export (project-labels --export coco), "
                        "nuScenes detection results whose sample tokens are those of its nuScenes export, or "
                        "'frame grid_x grid_y' rows (.txt, MVDet-family tools) on an imported dataset's grid")
    p.add_argument("--variant", default=None, metavar="NAME|all",
                   help="with --results: the lighting variants the export numbered (default: each scenario's "
                        "first; 'all': every one, as pnyolo-bench --external expects)")
    p.add_argument("--split", default="test", choices=["train", "val", "test"])
    p.add_argument("--views", help="camera indices used as source views, e.g. 0,1,2 (default: eval.views or the first V)")
    p.add_argument("--every-camera", action="store_true",
                   help="score every camera of each scenario once, in items of data.num_views cameras (the "
                        "others its source views), instead of the same views for every item (as pnyolo-bench)")
    p.add_argument("--out", help="output folder (default: CHECKPOINT's folder/eval_SPLIT)")
    p.add_argument("--metric", default="strict", choices=["strict", "paper"], help="headline counting mode")
    p.add_argument("--conf", type=float, help="confidence threshold (default: from the checkpoint's config)")
    p.add_argument("--nms-iou", type=float, help="NMS overlap threshold")
    p.add_argument("--depth-gap", type=float, metavar="METRES",
                   help="depth-gated NMS: boxes whose distance estimates differ by more do not suppress each other")
    p.add_argument("--norm-stats", choices=EVAL_STATS,
                   help="encoder batch-norm statistics: running averages, or those of the item's views as in "
                        "training (default: the checkpoint's model.encoder.eval_stats; applies to --fuse's too)")
    p.add_argument("--examples", type=int, default=4, help="example detection images to write")
    p.add_argument("--fuse", metavar="OTHER_CHECKPOINT",
                   help="also evaluate OTHER_CHECKPOINT (e.g. the single-view baseline) on the same views and the "
                        "union of both detectors' detections after NMS; reports all three side by side")
    p.add_argument("--late-fusion", action="store_true",
                   help="(a model with 3D detections) also evaluate late fusion: the model on each camera alone, every car's 3D detections "
                        "pooled in the world frame and projected into each view; reports the bytes a car sends")
    p.add_argument("--own-view", action="store_true",
                   help="(a model that reads other cameras) also the own-view ablation: each camera alone, its row "
                        "beside the model's (the bench's 'own view only')")
    p.add_argument("--late-rule", metavar="RULE",
                   help="with --late-fusion: how the cars' reports are pooled: best-car[:SEND], agreement:SEND,KEEP, "
                        "calibrated:SEND,KEEP,A,B,C, or from:BENCH (a pnyolo-bench run folder or its report.json: the "
                        "rule and the model's operating point it chose on validation); default: the checkpoint's eval")
    p.add_argument("--point-from", metavar="BENCH",
                   help="a pnyolo-bench run folder or its report.json: the operating points it chose on validation for "
                        "this checkpoint's kind, the --chance-from single view, the --into ego (and the late fusion into it) "
                        "and the --fuse partner, so the command line scores a bench row as the bench did; --conf and "
                        "the like win")
    p.add_argument("--chance-from", metavar="SINGLE_VIEW_CHECKPOINT",
                   help="also score this one-camera checkpoint on the same objects: its hidden-but-seen recall is the "
                        "chance the model's is compared with (without it no chance is stated)")
    p.add_argument("--into", metavar="EGO_CHECKPOINT",
                   help="with --late-fusion: also late fusion into this model (same grid): each target view keeps its "
                        "own detections and adds the other cars' reports where it has no box")
    p.add_argument("--ego-conf", type=float, metavar="T",
                   help="with --into: the ego model's confidence threshold (default: from its checkpoint)")
    p.add_argument("--pose-noise", metavar="SIGMA_M,SIGMA_DEG",
                   help="the other cars' poses wrong by this much (Gaussian on x, y, z in metres and on yaw in "
                        "degrees, per car, the target's own car exact), for the model and --late-fusion alike")
    p.add_argument("--seed", type=int, default=0, help="with --pose-noise: the seed of the pose errors (default 0)")
    p.add_argument("--delay-ms", type=float, default=0.0, metavar="D",
                   help="(sequences) the other cars' views D ms old: each camera scored once at its frame, its source "
                        "views' images and poses of the frame D earlier (a whole number of frames; frames without "
                        "one left out), for the model and --late-fusion alike (default 0: all of one frame)")
    p.add_argument("--from-ms", type=float, default=None, metavar="F",
                   help="(sequences) score only frames at least F ms into each sequence (default: --delay-ms), so "
                        "--delay-ms 0 --from-ms D scores exactly the frames, groups and grid --delay-ms D scores")
    p.add_argument("--class-base", type=int, choices=(0, 1), default=None,
                   help="with Ultralytics predictions: the first class's category_id (default: 1, as Ultralytics "
                        "8.1 and later write; 0 when any detection has category 0)")
    add_run_options(p)
    return p


@cli_main
def eval_main(argv=None) -> int:
    args = _parser().parse_intermixed_args(argv)  # options before, between or after the two positionals
    if args.results:
        if len(args.inputs) != 1:
            raise UserError("--results takes the dataset folder as its only positional argument")
        for flag, given in (("--late-fusion", args.late_fusion), ("--fuse", args.fuse), ("--pose-noise", args.pose_noise),
                            ("--into", args.into), ("--ego-conf", args.ego_conf is not None),
                            ("--delay-ms", args.delay_ms), ("--from-ms", args.from_ms is not None),
                            ("--every-camera", args.every_camera), ("--conf", args.conf is not None),
                            ("--nms-iou", args.nms_iou is not None), ("--norm-stats", args.norm_stats),
                            ("--late-rule", args.late_rule), ("--chance-from", args.chance_from is not None),
                            ("--point-from", args.point_from), ("--own-view", args.own_view)):
            if given:
                raise UserError(f"{flag} needs a checkpoint; with --results the detections are scored as given")
        return _eval_results(args)
    if args.class_base is not None:
        raise UserError("--class-base goes with --results")
    if len(args.inputs) != 2:
        raise UserError("give a checkpoint and a dataset folder (or --results PREDICTIONS.json and a dataset)")
    args.checkpoint, args.dataset = args.inputs
    for value, key, option in ((args.conf, "eval.conf_threshold", "--conf"), (args.nms_iou, "eval.nms_iou", "--nms-iou"),
                               (args.ego_conf, "eval.conf_threshold", "--ego-conf")):
        check_threshold(value, key, option)
    if args.examples < 0:
        raise UserError(f"--examples must be >= 0, got {args.examples}")
    if args.late_fusion and args.fuse:
        raise UserError("--late-fusion and --fuse exclude each other")
    if args.into and not args.late_fusion:
        raise UserError("--into needs --late-fusion: the checkpoint's cars send, the --into model receives")
    if args.ego_conf is not None and not args.into:
        raise UserError("--ego-conf goes with --into")
    if args.late_rule and not args.late_fusion:
        raise UserError("--late-rule goes with --late-fusion")
    if args.chance_from is not None and not args.chance_from.strip():
        raise UserError("--chance-from needs a single-view checkpoint's path, got an empty one")
    if args.chance_from and args.fuse:
        raise UserError("--chance-from and --fuse exclude each other (--fuse scores its own second model)")
    if args.own_view and args.delay_ms:
        raise UserError("--own-view reads each camera alone, which no delay changes: score it without --delay-ms "
                        "(--from-ms D scores the same frames)")
    if args.every_camera and args.views:
        raise UserError("--every-camera and --views exclude each other: --every-camera chooses the views")
    if not args.delay_ms >= 0 or args.delay_ms == float("inf"):
        raise UserError(f"--delay-ms must be a number of milliseconds >= 0, got {args.delay_ms:g}")
    if args.from_ms is not None and not (0 <= args.from_ms < float("inf")):
        raise UserError(f"--from-ms must be a number of milliseconds >= 0, got {args.from_ms:g}")
    check_metres(args.depth_gap, "--depth-gap")
    return _eval_checkpoint(args)


def _eval_checkpoint(args) -> int:
    from pnyolo.data.dataset import Delay, MultiViewDataset
    from pnyolo.bench.plan import predict_scoring
    from pnyolo.engine.checkpoint import checkpoint_config, load_detector, read_checkpoint
    from pnyolo.engine.predict import Trained
    from pnyolo.engine.runtime import pick_device
    from pnyolo.evaluation.devkit_eval import devkit_detection
    from pnyolo.evaluation.evaluate import Examples, score
    from pnyolo.evaluation.ground_moda import GroundRows
    from pnyolo.evaluation.nuscenes_results import WorldPool
    from pnyolo.cooperation.late_fusion import check_late_fusion
    from pnyolo.cooperation.pose_noise import parse_pose_noise
    from pnyolo.evaluation.report import HEADLINE_IOU, against_chance, headline, write_report
    from pnyolo.models import Decoding, eval_stats, use_eval_stats

    args.noise = parse_pose_noise(args.pose_noise, args.seed)
    ckpt = read_checkpoint(args.checkpoint)
    cfg = checkpoint_config(ckpt)
    out = Path(args.out) if args.out else Path(args.checkpoint).parent / f"eval_{args.split}"
    check_output_dir(out)
    views = None if args.every_camera else parse_views(args.views) or cfg.eval.views
    ds = MultiViewDataset(args.dataset, args.split, cfg, training=False, views=views, every_camera=args.every_camera,
                          delay=Delay(args.delay_ms, args.delay_ms if args.from_ms is None else args.from_ms))
    if ds.frames_left_out:
        start = args.delay_ms if args.from_ms is None else args.from_ms
        print(f"{ds.frames_left_out} frames less than {start:g} ms into their sequences left out (--delay-ms 0 "
              f"--from-ms {start:g} scores the same frames, groups and grid without a delay)")
    source_views = "every camera" if args.every_camera else views  # as the report names them
    device = pick_device(args.device)
    model, cfg = load_detector(ckpt, args.checkpoint, ds.class_names, device)
    if args.late_fusion:
        check_late_fusion(Decoding.of(model))
    refuse_for_kind(model, nms_iou=args.nms_iou, depth_gap=args.depth_gap, norm_stats=args.norm_stats)
    cfg = _apply_points(args, model, cfg)
    given = {key: option for option, key in ((args.conf, "conf_threshold"), (args.nms_iou, "nms_iou"),
                                             (args.depth_gap, "depth_gap")) if option is not None}
    cfg = replace(cfg, eval=replace(cfg.eval, **given))  # the command line's operating point: a new value
    if args.norm_stats:
        use_eval_stats(model, cfg, args.norm_stats)
    chance = _chance_model(args, ds, device) if args.chance_from else None
    if args.own_view and not model.reads_other_views:
        raise UserError(f"--own-view: a {cfg.model.kind} model reads its own camera only; the ablation is of a model "
                        "that reads the others")
    if args.fuse or args.late_fusion or args.noise or args.own_view:
        return _eval_fused(args, cfg, model, ds, source_views, device, out, chance)
    ground = GroundRows.for_dataset(ds, model)  # an imported Wildtrack / MultiviewX dataset: its grid's MODA
    pool = WorldPool(Decoding.of(model), cfg.eval, ds.ds) if _devkit_scores(args, ds) and model.world_outputs else None
    trained = Trained(Path(args.checkpoint), model, cfg)
    preds = predict_scoring(trained, ds, device=device, progress=not args.quiet).clean
    acc = score(preds, cfg.eval, ds, Examples(out / "examples", args.examples), ground=ground, pool=pool)
    summary = acc.summary()
    if pool is not None:  # the devkit's DetectionEval on an export of the split: the figure a paper's table has
        summary["devkit_detection_eval"] = devkit_detection(args.dataset, args.split, pool.document(ds.class_names), out)
    if chance is not None:
        summary["against_chance"] = against_chance({"model": summary, chance[0]: chance[1]}, HEADLINE_IOU,
                                                   chance[0]).get("model")
    if ground is not None:
        summary["ground_plane"] = g = ground.finish(out)
        print(g.get("skipped") or f"ground plane ({g['frames']} frames, {g['threshold_m']} m): MODA {g['moda']:.4f}, "
              f"MODP {g['modp'] or 0:.4f}, precision {g['precision'] or 0:.4f}, recall {g['recall']:.4f}")
    write_report(summary, out, {"checkpoint": str(args.checkpoint), "split": args.split, "source_views": source_views,
                                "model_kind": cfg.model.kind, "headline_mode": args.metric, "delay_ms": args.delay_ms,
                                "from_ms": args.from_ms,
                                "encoder_eval_stats": eval_stats(cfg)})
    print(f"F1@{HEADLINE_IOU} ({args.metric}) = {headline(summary, float(HEADLINE_IOU), args.metric):.4f}; "
          f"AP50 = {summary['ap50']:.4f}; report in {out}")
    return 0


def _devkit_scores(args, ds) -> bool:
    """Whether the devkit's DetectionEval can score this run as it scores a nuScenes split: the devkit installed,
    every camera of every frame scored (no --views, no delay), the dataset exportable (depth and instance maps)."""
    from pnyolo.evaluation.devkit_eval import available

    whole = (args.every_camera or args.results) and not args.views and not args.delay_ms and args.from_ms is None
    return bool(whole) and ds.ds.info.has("depth") and ds.ds.info.has("instance") and available()


def _apply_points(args, model, cfg):
    """``cfg`` at the bench's chosen point (``--point-from``), then ``--late-rule``'s (from a bench run: its operating
    point too), the command line's own options applied after: new config values, ``cfg`` itself untouched."""
    from pnyolo.cli.options import parse_late_rule
    from pnyolo.cli.points import apply_point, bench_point

    if args.point_from:
        cfg = apply_point(cfg, model, bench_point(args.point_from, cfg.model.kind, "--point-from "), args.checkpoint,
                          f"--point-from {args.point_from[:200]}")
    rule = parse_late_rule(args.late_rule, cfg.model.kind)
    if rule is None:
        return cfg
    if args.norm_stats:
        rule = {**rule, "eval_stats": None}  # the command line's statistics win
    return apply_point(cfg, model, rule, args.checkpoint, f"--late-rule {args.late_rule[:200]}")


def _chance_model(args, ds, device) -> tuple[str, dict]:
    """(its row name, its summary): the one-camera ``--chance-from`` checkpoint scored on the same objects."""
    from pnyolo.bench.plan import predict_scoring
    from pnyolo.cli.points import apply_point, bench_point
    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.engine.checkpoint import load_detector, read_checkpoint
    from pnyolo.engine.predict import Trained
    from pnyolo.evaluation.evaluate import score

    ckpt = read_checkpoint(args.chance_from)
    model, cfg = load_detector(ckpt, args.chance_from, ds.class_names, device)
    if model.reads_other_views:
        raise UserError(f"--chance-from {args.chance_from}: a {cfg.model.kind} model reads the other cameras; chance "
                        "is a model that reads the target camera alone (a single-view checkpoint)")
    if args.point_from:  # at the point the bench chose for it, as the bench's chance is
        cfg = apply_point(cfg, model, bench_point(args.point_from, cfg.model.kind, "--point-from "), args.chance_from,
                          f"--point-from {args.point_from[:200]}")
    same = MultiViewDataset(args.dataset, args.split, cfg, training=False, views=ds.views,
                            every_camera=args.every_camera)
    chance = predict_scoring(Trained(Path(args.chance_from), model, cfg), same, device=device, progress=not args.quiet)
    return f"{cfg.model.kind} (chance)", score(chance.clean, cfg.eval).summary()


def _eval_results(args) -> int:
    from pnyolo.data.dataset import open_dataset
    from pnyolo.evaluation.nuscenes_results import is_nuscenes_results, read_results, score_world_results
    from pnyolo.evaluation.predictions import image_index, read_coco_results, results_dataset, score_results
    from pnyolo.evaluation.report import HEADLINE_IOU, headline, write_report

    dataset_root = args.inputs[0]
    out = check_output_dir(args.out or Path(dataset_root) / "eval_results" / Path(args.results).stem)
    if args.results.endswith(".txt"):  # the field's 'frame grid_x grid_y' rows, on an imported dataset's grid
        from pnyolo.evaluation.ground_moda import score_ground_file
        return score_ground_file(dataset_root, args.results, args.split, out)
    views = parse_views(args.views)
    index = image_index(open_dataset(dataset_root), args.variant)
    ds, cfg = results_dataset(dataset_root, args.split, views, index)
    if is_nuscenes_results(args.results):  # 3D boxes per sample, put into every scored view
        results = read_results(args.results, ds.ds, args.split, ds.class_names)
        summary = score_world_results(results, ds, cfg.eval.match_ious, progress=not args.quiet).summary()
        if _devkit_scores(args, ds):  # and the devkit's own DetectionEval on an export of the split
            from dataset_spec.dataset import read_json
            from pnyolo.evaluation.devkit_eval import devkit_detection

            summary["devkit_detection_eval"] = devkit_detection(dataset_root, args.split, read_json(args.results), out,
                                                                args.variant)
    else:
        results = read_coco_results(args.results, ds.ds, index, args.split, args.class_base)
        summary = score_results(results, ds, cfg.eval.match_ious, progress=not args.quiet).summary()
    write_report(summary, out, {"results": str(args.results), "split": args.split, "variant": args.variant,
                                "source_views": "every camera" if views is None else views})
    print(f"F1@{HEADLINE_IOU} ({args.metric}) = {headline(summary, float(HEADLINE_IOU), args.metric):.4f}; "
          f"AP50 = {summary['ap50']:.4f}; report in {out}")
    return 0


def _eval_fused(args, cfg, model, ds, source_views, device, out, chance=None) -> int:
    from pnyolo.bench.plan import PredictionPlan, predict_plan
    from pnyolo.cli.points import apply_point, bench_point, into_choice
    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.engine.checkpoint import load_detector, read_checkpoint
    from pnyolo.engine.predict import Trained
    from pnyolo.evaluation.evaluate import OWN_VIEW, Examples, LateInto, evaluate_models
    from pnyolo.evaluation.report import HEADLINE_IOU, headline, write_comparison
    from pnyolo.models import use_eval_stats

    second = args.fuse or args.into  # the other checkpoint, on the same grid
    names, models = [cfg.model.kind], [(model, cfg)]
    if second:
        other, other_cfg = load_detector(read_checkpoint(second), second, ds.class_names, device, cfg.data)
        if args.point_from:  # the --into ego or the --fuse partner at the point the bench chose for it
            other_cfg = apply_point(other_cfg, other, bench_point(args.point_from, other_cfg.model.kind, "--point-from "),
                                    second, f"--point-from {args.point_from[:200]}")
        if args.norm_stats:
            use_eval_stats(other, other_cfg, args.norm_stats)
        if args.ego_conf is not None:
            other_cfg = replace(other_cfg, eval=replace(other_cfg.eval, conf_threshold=args.ego_conf))
        names.append(other_cfg.model.kind)
        models.append((other, other_cfg))
        if names[0] == names[1]:
            names = [f"{names[0]} (A)", f"{names[1]} (B)"]
    into = None
    if second and not args.fuse:  # late fusion into an ego
        send, ego_t = cfg.eval.conf_threshold, models[1][1].eval.conf_threshold
        if args.point_from and args.ego_conf is None:  # the bench's choice of the two thresholds
            send, ego_t = into_choice(args.point_from, cfg.model.kind, models[1][1].model.kind)
        into = LateInto(names[0], names[1], send, ego_t)
    trained = {n: Trained(Path(p), m, c) for n, p, (m, c) in zip(names, [args.checkpoint, second], models)}
    plan = PredictionPlan.of({n: t.decoding for n, t in trained.items()}, rows=(OWN_VIEW,) if args.own_view else (),
                             late=names[:1] if args.late_fusion else (), late_into=into, pose_noise=args.noise,
                             fuse=(names[0], names[1]) if args.fuse else None)
    senders = None  # under a delay the cars' messages come from the whole sequences, of every frame
    if args.late_fusion and args.delay_ms:
        senders = MultiViewDataset(args.dataset, args.split, cfg, training=False, views=ds.views,
                                   every_camera=args.every_camera)
    comparison = predict_plan(plan, trained, ds, device, not args.quiet, senders)
    pictures = Examples(out / "examples", args.examples) if args.fuse else None  # pictures of two models' rows
    accs = evaluate_models(comparison, ds, pictures, progress=not args.quiet)
    checkpoints = dict(zip(names, [str(args.checkpoint)] + ([str(second)] if second else [])))
    summaries = {e.name: a.summary() for e, a in accs.items()}
    noise = None if args.noise is None else {"sigma_m": args.noise.sigma_m, "sigma_deg": args.noise.sigma_deg,
                                             "seed": args.noise.seed}
    single = next((n for n, (m, _) in zip(names, models) if not m.reads_other_views), None)
    if chance is not None:
        summaries[chance[0]], single = chance[1], chance[0]
    write_comparison(summaries, out, {"checkpoints": checkpoints, "split": args.split, "source_views": source_views,
                                      "pose_noise": noise, "delay_ms": args.delay_ms, "from_ms": args.from_ms,
                                      "late_fusion": _late_text(cfg.eval) if args.late_fusion else None}, single=single)
    print("; ".join(f"{n}: F1@{HEADLINE_IOU} = {headline(s, float(HEADLINE_IOU), args.metric):.4f}"
                    for n, s in summaries.items()) + f"; report in {out}")
    return 0


def _late_text(ev) -> dict:
    """The late-fusion rule the run used, as metrics record it."""
    rule = "best car" if ev.late_keep is None else ("agreement" if ev.late_calibration is None else
                                                     "calibrated agreement")
    return {"rule": rule, "send": ev.late_send if ev.late_send is not None else ev.conf_threshold,
            "keep": ev.late_keep, "calibration": ev.late_calibration}


if __name__ == "__main__":
    sys.exit(eval_main())
