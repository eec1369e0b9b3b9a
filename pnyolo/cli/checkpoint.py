"""``pnyolo-checkpoint``: convert a checkpoint written before format 2 into one that holds data only."""
from __future__ import annotations

import argparse
import sys

from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_file, cli_main

EXAMPLES = """examples:
  pnyolo-checkpoint upgrade runs/mv/best.pt --out runs/mv/best_v2.pt
  pnyolo-checkpoint upgrade runs/mv/best.pt --force          converts it in place

Checkpoints are read as data only (tensors, numbers, lists, dicts): no code in a file runs when pnyolo
loads it. Checkpoints written before format 2 hold numpy's random state as pickled arrays; converting one
reads exactly those numpy arrays and nothing else (any other object in the file is refused), then checks
the result whole before it writes anything. The config is written in today's form (older loss weights moved
into model.loss); a format-2 checkpoint is converted that way too.
"""


@cli_main
def main(argv=None) -> int:
    p = OneLineArgumentParser(prog="pnyolo-checkpoint", description=__doc__, epilog=EXAMPLES)
    sub = p.add_subparsers(dest="command", required=True)
    up = sub.add_parser("upgrade", help="convert an older checkpoint to format 2 and today's config (read as data: "
                                        "no code runs)")
    up.add_argument("checkpoint")
    up.add_argument("--out", help="where to write the converted checkpoint (default: in place, with --force)")
    up.add_argument("--force", action="store_true", help="replace --out (or the checkpoint itself) if it exists")
    up.add_argument("--trust", action="store_true", help=argparse.SUPPRESS)  # accepted: no longer needed
    args = p.parse_args(argv)
    out = check_output_file(args.out or args.checkpoint, "--out")
    if out.exists() and not args.force:
        raise UserError(f"--out {out} exists; --force replaces it" + ("" if args.out else " (the checkpoint itself)"))

    from dataset_spec.atomic import remove_stale_temporaries_of
    from pnyolo.engine.checkpoint import upgrade_checkpoint

    remove_stale_temporaries_of(out)  # what a killed conversion left beside it
    ckpt = upgrade_checkpoint(args.checkpoint, out)
    print(f"{out}: {ckpt['config']['model']['kind']} checkpoint, format {ckpt['format']} (data only)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
