"""Command-line tools: ``pnyolo-train`` (here) and ``pnyolo-eval`` (``pnyolo.cli.eval``), one-line errors and
a non-zero exit; ``python -m pnyolo.cli train|eval|predict`` is what torchrun starts on every rank."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

from dataset_spec.cli_support import OneLineArgumentParser, UserError, cli_main
from pnyolo.cli.eval import eval_main  # noqa: F401 - the pnyolo-eval entry point, also started by torchrun
from pnyolo.registry import kinds


TRAIN_EXAMPLES = """examples:
  pnyolo-train out/dataset --config configs/cpu.yaml --out runs/mv            multi-view, CPU-sized
  pnyolo-train out/dataset --config configs/cpu.yaml --model single-view --out runs/sv
  pnyolo-train out/dataset --config configs/cpu.yaml --model bev --out runs/bev       ground-plane multi-view
  pnyolo-train out/dataset --config configs/paper.yaml --encoder-weights resnet34.pth --out runs/paper
  pnyolo-train out/dataset --config configs/cpu.yaml --set train.epochs=50 --set model.sampler.num_samples=32
  pnyolo-train out/dataset --config configs/cpu.yaml --out runs/mv --resume   continue exactly after a stop
  pnyolo-train out/dataset --config configs/cpu.yaml --out runs/mv --force    start that run over
  pnyolo-train out/dataset --config configs/cpu.yaml --out runs/ddp --nproc 2  data-parallel (torchrun)
  torchrun --nnodes 2 --nproc_per_node 4 --rdzv_endpoint HOST:29500 -m pnyolo.cli train out/dataset --out runs/big

Writes OUT/latest.pt (atomic), OUT/epoch_NNNN.pt, OUT/best.pt (validation F1), log.jsonl, epochs.csv,
vis/*.png and config.yaml; an OUT that holds a run needs --resume or --force. On --resume the logs are cut
back to the checkpoint's step (a "resume" event marks the place). Configuration keys: configs/*.yaml,
pnyolo/config/__init__.py.
"""

def _train_parser() -> OneLineArgumentParser:
    p = OneLineArgumentParser(prog="pnyolo-train", description="Train a detector on a dataset_spec folder.",
                              epilog=TRAIN_EXAMPLES)
    p.add_argument("dataset", help="dataset folder (dataset.json, scenarios/...)")
    p.add_argument("--config", help="YAML config (see configs/paper.yaml, configs/cpu.yaml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, e.g. train.epochs=3")
    p.add_argument("--model", help=f"model kind (shortcut for --set model.kind=...): {' | '.join(kinds())}")
    p.add_argument("--out", default="runs/pnyolo", help="output folder (checkpoints, logs, visualisations)")
    p.add_argument("--seed", type=int, help="random seed (shortcut for --set train.seed=...)")
    p.add_argument("--encoder-weights", help="local torchvision-style ResNet state dict")
    p.add_argument("--resume", action="store_true", help="continue from OUT/latest.pt exactly")
    p.add_argument("--force", action="store_true",
                   help="start over in an OUT that holds a run (its checkpoints, logs and pictures are deleted)")
    p.add_argument("--nproc", type=int, default=1, metavar="N",
                   help="data-parallel training in N processes on this machine (torchrun; gloo on CPU, nccl on "
                        "GPU): each step takes N x train.items_per_step items")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bar, no start line (a run without validation still says so)")
    return p


@cli_main
def train_main(argv=None) -> int:
    args = _train_parser().parse_args(argv)
    from pnyolo.config import load_config
    from pnyolo.engine.preflight import preflight
    from pnyolo.training.train import train

    sets = list(args.set)
    if args.model:
        sets.append(f"model.kind={args.model}")
    if args.seed is not None:
        sets.append(f"train.seed={args.seed}")
    if args.encoder_weights:
        sets.append(f"model.encoder.weights={args.encoder_weights}")
    cfg = load_config(args.config, sets)
    if args.nproc < 1:
        raise UserError(f"--nproc must be >= 1, got {args.nproc}")
    if args.nproc > 1:
        check_processes(args.nproc, cfg.train.device)
    if args.nproc > 1 and "WORLD_SIZE" not in os.environ:  # launch the same command under torchrun
        preflight(args.dataset, cfg, args.out, args.resume, args.force, processes=args.nproc)  # one line, not one a worker
        rest = _without_option(list(sys.argv[1:] if argv is None else argv), "--nproc")
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={args.nproc}",
               "-m", "pnyolo.cli", "train", *rest]
        with tempfile.TemporaryDirectory(prefix="pnyolo_nproc_") as scratch:  # torchrun's torchelastic_* go here
            return subprocess.run(cmd, env={**os.environ, "TMPDIR": scratch}).returncode
    summary = train(args.dataset, cfg, args.out, resume=args.resume, quiet=args.quiet, force=args.force)
    if os.environ.get("RANK", "0") == "0":
        print(json.dumps(summary, allow_nan=False))  # JSON as other tools read it (no NaN)
    return 0


def check_processes(nproc: int, device: str) -> None:
    """``--nproc`` on CUDA: one process per GPU (NCCL refuses two on one), refused in one line beyond the GPUs
    CUDA sees, before any work."""
    import torch

    from pnyolo.engine.runtime import pick_device

    if pick_device(device).type == "cuda" and nproc > torch.cuda.device_count():
        raise UserError(f"--nproc {nproc}: CUDA sees {torch.cuda.device_count()} GPU(s) and data-parallel training "
                        f"runs one process per GPU; give --nproc {torch.cuda.device_count()} or fewer, or "
                        "--set train.device=cpu (processes on the CPU)")


def _without_option(argv: list[str], option: str) -> list[str]:
    """``argv`` without ``option VALUE`` / ``option=VALUE``."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == option:
            skip = True
        elif not a.startswith(option + "="):
            out.append(a)
    return out


def main(argv=None) -> int:
    """``python -m pnyolo.cli train|eval|predict ARGS`` (what torchrun starts on every rank)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    from pnyolo.cli.predict import main as predict_main

    commands = {"train": train_main, "eval": eval_main, "predict": predict_main}
    if not argv or argv[0] not in commands:
        print(f"usage: python -m pnyolo.cli {{{','.join(commands)}}} ARGS", file=sys.stderr)
        return 2
    return commands[argv[0]](argv[1:])


if __name__ == "__main__":
    sys.exit(main())
