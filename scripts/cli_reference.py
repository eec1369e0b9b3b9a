"""Regenerate docs/CLI.md from each console script's --help.

    .venv/bin/python scripts/cli_reference.py            # rewrite docs/CLI.md
    .venv/bin/python scripts/cli_reference.py --check    # exit 1 when it is out of date (a test runs this)
"""
from __future__ import annotations

import difflib
import os
import subprocess
import sys
from pathlib import Path

COMMANDS = [
    ("blender-gen", ["list", "render"]),
    ("dataset-spec", ["validate", "info", "split", "import"]),
    ("project-labels", []),
    ("seg-viewer", []),
    ("pnyolo-train", []),
    ("pnyolo-eval", []),
    ("pnyolo-predict", []),
    ("pnyolo-export", []),
    ("pnyolo-checkpoint", ["upgrade"]),
    ("pnyolo-track", []),
    ("pnyolo-bench", []),
]


def help_text(argv: list[str]) -> str:
    bindir = Path(sys.executable).parent
    # argparse wraps to the terminal: fixed, so the file is reproducible; pnyolo's own kinds, not installed plugins
    env = {**os.environ, "COLUMNS": "110", "PNYOLO_PLUGINS": "0"}
    out = subprocess.run([str(bindir / argv[0]), *argv[1:], "--help"], capture_output=True, text=True, env=env)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} --help failed ({out.returncode}): {out.stderr.strip()[-300:]}")
    return out.stdout.rstrip()


INTRO = """# Command-line reference
Generated from `--help` by `scripts/cli_reference.py`.

On several machines: `blender-gen render --ray auto|local|ADDRESS` renders one Ray task per
scenario; `torchrun --nproc_per_node N -m pnyolo.cli train ...` (or `pnyolo-train --nproc N`) trains
data-parallel with the options of `pnyolo-train`. How to start the cluster and what each option
does: [docs/guide/scale-out.md](guide/scale-out.md).
"""


def reference() -> str:
    parts = [INTRO]
    for cmd, subs in COMMANDS:
        parts.append(f"\n## `{cmd}`\n\n```text\n{help_text([cmd])}\n```\n")
        for sub in subs:
            parts.append(f"\n### `{cmd} {sub}`\n\n```text\n{help_text([cmd, sub])}\n```\n")
    return "".join(parts)


def main() -> int:
    path = Path(__file__).resolve().parent.parent / "docs" / "CLI.md"
    text = reference()
    if "--check" in sys.argv[1:]:
        if path.read_text() != text:
            diff = difflib.unified_diff(path.read_text().splitlines(), text.splitlines(), "docs/CLI.md", "--help", n=0)
            print(f"{path} is out of date: run {Path(__file__).name}\n" + "\n".join(list(diff)[:20]), file=sys.stderr)
            return 1
        return 0
    path.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
