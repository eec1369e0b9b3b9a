"""``pnyolo-checkpoint``: convert a checkpoint written before format 2 into one that holds data only."""
from __future__ import annotations

import sys

from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_file, cli_main

EXAMPLES = """examples:
  pnyolo-checkpoint upgrade runs/mv/best.pt                 asks whether you trust the file, converts it in place
  pnyolo-checkpoint upgrade old.pt --out new.pt --trust     no question (scripts): you vouch for old.pt

Checkpoints are read as data only (tensors, numbers, lists, dicts): no code in a file runs when pnyolo
loads it. Checkpoints written before format 2 hold pickled numpy objects, so reading them means running
the pickle: only do it for a file whose origin you trust (your own runs, a colleague you trust).
"""


def confirm(path: str, trust: bool) -> None:
    """Go on only when the user vouches for ``path``: ``--trust``, or 'y' at the prompt (a terminal)."""
    if trust:
        return
    if not sys.stdin.isatty():
        raise UserError(f"{path}: converting runs the Python code the file holds; confirm you trust it with --trust")
    answer = input(f"Converting {path} runs the Python code it holds. Do you trust where it came from? [y/N] ")
    if answer.strip().lower() not in ("y", "yes"):
        raise UserError(f"{path}: not converted (not confirmed)")


@cli_main
def main(argv=None) -> int:
    p = OneLineArgumentParser(prog="pnyolo-checkpoint", description=__doc__, epilog=EXAMPLES)
    sub = p.add_subparsers(dest="command", required=True)
    up = sub.add_parser("upgrade", help="convert a format-1 checkpoint (runs its pickle: trusted files only)")
    up.add_argument("checkpoint")
    up.add_argument("--out", help="where to write the converted checkpoint (default: in place)")
    up.add_argument("--trust", action="store_true", help="you vouch for the file: no question asked")
    args = p.parse_args(argv)
    out = check_output_file(args.out or args.checkpoint, "--out")

    from pnyolo.engine.checkpoint import upgrade_checkpoint

    confirm(args.checkpoint, args.trust)
    ckpt = upgrade_checkpoint(args.checkpoint, out)
    print(f"{out}: {ckpt['config']['model']['kind']} checkpoint, format {ckpt['format']} (data only)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
