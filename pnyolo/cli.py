"""Command-line tools: ``pnyolo-train`` and ``pnyolo-eval`` (one-line errors, non-zero exit)."""
from __future__ import annotations

import json
from pathlib import Path

from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_dir, cli_main
from pnyolo.config import EVAL_STATS, RANGES


TRAIN_EXAMPLES = """examples:
  pnyolo-train out/dataset --config configs/cpu.yaml --out runs/mv            multi-view, CPU-sized
  pnyolo-train out/dataset --config configs/cpu.yaml --model single-view --out runs/sv
  pnyolo-train out/dataset --config configs/paper.yaml --encoder-weights resnet34.pth --out runs/paper
  pnyolo-train out/dataset --config configs/cpu.yaml --set train.epochs=50 --set model.sampler.num_samples=32
  pnyolo-train out/dataset --config configs/cpu.yaml --out runs/mv --resume   continue exactly after a stop
  pnyolo-train out/dataset --config configs/cpu.yaml --out runs/mv --force    start that run over

Writes OUT/latest.pt (atomic), OUT/epoch_NNNN.pt, OUT/best.pt (validation F1), log.jsonl, epochs.csv,
vis/*.png and config.yaml; an OUT that holds a run needs --resume or --force. On --resume the logs are cut
back to the checkpoint's step (a "resume" event marks the place). Configuration keys: configs/*.yaml,
pnyolo/config.py.
"""

EVAL_EXAMPLES = """examples:
  pnyolo-eval runs/mv/best.pt out/dataset --split test
  pnyolo-eval runs/mv/best.pt out/dataset --split test --views 2,0,1 --metric paper
  pnyolo-eval runs/mv/best.pt out/dataset --every-camera   score every camera of each scene once
  pnyolo-eval runs/mv/best.pt out/dataset --fuse runs/sv/best.pt --out out/compare
  pnyolo-eval runs/mv/best.pt out/dataset --norm-stats item     batch norm as in training (see pnyolo-bench)

Writes metrics.json, metrics.md, f1_vs_match_iou.png and examples/*.png (with --fuse: one folder per
model plus comparison.json, comparison.md and a plot of all three).
"""


def _train_parser() -> OneLineArgumentParser:
    p = OneLineArgumentParser(prog="pnyolo-train", description="Train a detector on a dataset_spec folder.",
                              epilog=TRAIN_EXAMPLES)
    p.add_argument("dataset", help="dataset folder (dataset.json, scenarios/...)")
    p.add_argument("--config", help="YAML config (see configs/paper.yaml, configs/cpu.yaml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, e.g. train.epochs=3")
    p.add_argument("--model", help="model kind (shortcut for --set model.kind=...): pixelnerf-yolo | single-view")
    p.add_argument("--out", default="runs/pnyolo", help="output folder (checkpoints, logs, visualisations)")
    p.add_argument("--seed", type=int, help="random seed (shortcut for --set train.seed=...)")
    p.add_argument("--encoder-weights", help="local torchvision-style ResNet state dict")
    p.add_argument("--resume", action="store_true", help="continue from OUT/latest.pt exactly")
    p.add_argument("--force", action="store_true",
                   help="start over in an OUT that holds a run (its checkpoints, logs and pictures are deleted)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


@cli_main
def train_main(argv=None) -> int:
    args = _train_parser().parse_args(argv)
    from pnyolo.config import load_config
    from pnyolo.engine.train import train

    sets = list(args.set)
    if args.model:
        sets.append(f"model.kind={args.model}")
    if args.seed is not None:
        sets.append(f"train.seed={args.seed}")
    if args.encoder_weights:
        sets.append(f"model.encoder.weights={args.encoder_weights}")
    cfg = load_config(args.config, sets)
    summary = train(args.dataset, cfg, args.out, resume=args.resume, quiet=args.quiet, force=args.force)
    print(json.dumps(summary))
    return 0


def _parse_views(text: str | None) -> list[int] | None:
    if text is None:
        return None
    try:
        return [int(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise UserError(f"--views {text!r}: expected camera indices like 0,1,2") from None


@cli_main
def eval_main(argv=None) -> int:
    p = OneLineArgumentParser(prog="pnyolo-eval", description="Evaluate a checkpoint on a dataset split.",
                              epilog=EVAL_EXAMPLES)
    p.add_argument("checkpoint")
    p.add_argument("dataset")
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
    p.add_argument("--device", default="auto")
    args = p.parse_args(argv)

    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.engine.checkpoint import checkpoint_config, load_detector, read_checkpoint
    from pnyolo.engine.train import pick_device
    from pnyolo.evaluation.evaluate import evaluate_dataset
    from pnyolo.evaluation.report import headline, write_report
    from pnyolo.models import use_eval_stats

    for value, key, option in ((args.conf, "eval.conf_threshold", "--conf"), (args.nms_iou, "eval.nms_iou", "--nms-iou")):
        if value is not None and value not in RANGES[key]:
            raise UserError(f"{option} must be {RANGES[key]}, got {value}")
    if args.examples < 0:
        raise UserError(f"--examples must be >= 0, got {args.examples}")
    ckpt = read_checkpoint(args.checkpoint)
    cfg = checkpoint_config(ckpt)
    out = Path(args.out) if args.out else Path(args.checkpoint).parent / f"eval_{args.split}"
    check_output_dir(out)
    if args.every_camera and args.views:
        raise UserError("--every-camera and --views exclude each other: --every-camera chooses the views")
    views = None if args.every_camera else _parse_views(args.views) or cfg.eval.views
    if views is not None and len(set(views)) != len(views):
        raise UserError(f"--views {args.views}: indices must be distinct")
    ds = MultiViewDataset(args.dataset, args.split, cfg, training=False, views=views, every_camera=args.every_camera)
    source_views = "every camera" if args.every_camera else views  # as the report names them
    device = pick_device(args.device)
    model, cfg = load_detector(ckpt, args.checkpoint, ds.class_names, device)
    if args.conf is not None:
        cfg.eval.conf_threshold = args.conf
    if args.nms_iou is not None:
        cfg.eval.nms_iou = args.nms_iou
    if args.depth_gap is not None:
        if not args.depth_gap > 0:
            raise UserError(f"--depth-gap must be > 0 metres, got {args.depth_gap}")
        cfg.eval.depth_gap = args.depth_gap
    if args.norm_stats:
        use_eval_stats(model, cfg, args.norm_stats)
    if args.fuse:
        return _eval_fused(args, cfg, model, ds, source_views, device, out)
    acc = evaluate_dataset(model, ds, cfg, device, example_dir=out / "examples", max_examples=args.examples)
    summary = acc.summary()
    write_report(summary, out, {"checkpoint": str(args.checkpoint), "split": args.split, "source_views": source_views,
                                "model_kind": cfg.model.kind, "headline_mode": args.metric,
                                "encoder_eval_stats": cfg.model.encoder.eval_stats})
    print(f"F1@{cfg.eval.select_iou} ({args.metric}) = {headline(summary, cfg.eval.select_iou, args.metric):.4f}; "
          f"AP50 = {summary['ap50']:.4f}; report in {out}")
    return 0


def _eval_fused(args, cfg, model, ds, source_views, device, out) -> int:
    from pnyolo.engine.checkpoint import load_detector, read_checkpoint
    from pnyolo.evaluation.evaluate import evaluate_models
    from pnyolo.evaluation.report import headline, write_comparison
    from pnyolo.models import use_eval_stats

    other, other_cfg = load_detector(read_checkpoint(args.fuse), args.fuse, ds.class_names, device, cfg.data)
    if args.norm_stats:
        use_eval_stats(other, other_cfg, args.norm_stats)
    names = [cfg.model.kind, other_cfg.model.kind]
    if names[0] == names[1]:
        names = [f"{names[0]} (A)", f"{names[1]} (B)"]
    accs = evaluate_models({names[0]: (model, cfg), names[1]: (other, other_cfg)}, ds, device, fuse=True,
                           example_dir=out / "examples", max_examples=args.examples)
    summaries = {n: a.summary() for n, a in accs.items()}
    write_comparison(summaries, out, {"checkpoints": {names[0]: str(args.checkpoint), names[1]: str(args.fuse)},
                                      "split": args.split, "source_views": source_views})
    t = cfg.eval.select_iou
    print("; ".join(f"{n}: F1@{t} = {headline(s, t, args.metric):.4f}" for n, s in summaries.items())
          + f"; report in {out}")
    return 0
