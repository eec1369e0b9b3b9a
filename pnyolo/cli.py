"""Command-line tools: ``pnyolo-train`` and ``pnyolo-eval`` (one-line errors, non-zero exit)."""
from __future__ import annotations

import json
from pathlib import Path

from dataset_spec.cli_support import OneLineArgumentParser, UserError, cli_main


def _train_parser() -> OneLineArgumentParser:
    p = OneLineArgumentParser(prog="pnyolo-train", description="Train a detector on a dataset_spec folder.")
    p.add_argument("dataset", help="dataset folder (dataset.json, scenarios/...)")
    p.add_argument("--config", help="YAML config (see configs/paper.yaml, configs/cpu.yaml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, e.g. train.epochs=3")
    p.add_argument("--model", help="model kind (shortcut for --set model.kind=...): pixelnerf-yolo | single-view")
    p.add_argument("--out", default="runs/pnyolo", help="output folder (checkpoints, logs, visualisations)")
    p.add_argument("--seed", type=int, help="random seed (shortcut for --set train.seed=...)")
    p.add_argument("--encoder-weights", help="local torchvision-style ResNet state dict")
    p.add_argument("--resume", action="store_true", help="continue from OUT/latest.pt exactly")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


@cli_main
def train_main(argv=None) -> int:
    args = _train_parser().parse_args(argv)
    from .config import load_config
    from .train import train

    sets = list(args.set)
    if args.model:
        sets.append(f"model.kind={args.model}")
    if args.seed is not None:
        sets.append(f"train.seed={args.seed}")
    if args.encoder_weights:
        sets.append(f"model.encoder.weights={args.encoder_weights}")
    cfg = load_config(args.config, sets)
    summary = train(args.dataset, cfg, args.out, resume=args.resume, quiet=args.quiet)
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
    p = OneLineArgumentParser(prog="pnyolo-eval", description="Evaluate a checkpoint on a dataset split.")
    p.add_argument("checkpoint")
    p.add_argument("dataset")
    p.add_argument("--split", default="test", choices=["train", "val", "test"])
    p.add_argument("--views", help="camera indices used as source views, e.g. 0,1,2 (default: eval.views or the first V)")
    p.add_argument("--out", help="output folder (default: CHECKPOINT's folder/eval_SPLIT)")
    p.add_argument("--metric", default="strict", choices=["strict", "paper"], help="headline counting mode")
    p.add_argument("--conf", type=float, help="confidence threshold (default: from the checkpoint's config)")
    p.add_argument("--nms-iou", type=float, help="NMS overlap threshold")
    p.add_argument("--examples", type=int, default=4, help="example detection images to write")
    p.add_argument("--device", default="auto")
    args = p.parse_args(argv)

    from .checkpoint import check_compatible, checkpoint_config, read_checkpoint
    from .data import MultiViewDataset
    from .evaluate import evaluate_dataset, headline, write_report
    from .model import build_model
    from .train import pick_device

    ckpt = read_checkpoint(args.checkpoint)
    cfg = checkpoint_config(ckpt)
    if args.conf is not None:
        cfg.eval.conf_threshold = args.conf
    if args.nms_iou is not None:
        cfg.eval.nms_iou = args.nms_iou
    views = _parse_views(args.views) or cfg.eval.views
    if views is not None and len(set(views)) != len(views):
        raise UserError(f"--views {args.views}: indices must be distinct")
    ds = MultiViewDataset(args.dataset, args.split, cfg, training=False, views=views)
    check_compatible(ckpt, cfg, ds.class_names, args.checkpoint)
    device = pick_device(args.device)
    model = build_model(cfg, len(ds.class_names))
    model.load_state_dict(ckpt["model"])
    model.to(device)
    out = Path(args.out) if args.out else Path(args.checkpoint).parent / f"eval_{args.split}"
    acc = evaluate_dataset(model, ds, cfg, device, example_dir=out / "examples", max_examples=args.examples)
    summary = acc.summary()
    write_report(summary, out, {"checkpoint": str(args.checkpoint), "split": args.split, "source_views": views,
                                "model_kind": cfg.model.kind, "headline_mode": args.metric})
    print(f"F1@{cfg.eval.select_iou} ({args.metric}) = {headline(summary, cfg.eval.select_iou, args.metric):.4f}; "
          f"AP50 = {summary['ap50']:.4f}; report in {out}")
    return 0
