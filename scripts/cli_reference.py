"""Regenerate docs/CLI.md from each console script's --help (run: .venv/bin/python scripts/cli_reference.py)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

COMMANDS = [
    ("blender-gen", ["list", "render"]),
    ("dataset-spec", ["validate", "info"]),
    ("project-labels", []),
    ("seg-viewer", []),
    ("pnyolo-train", []),
    ("pnyolo-eval", []),
    ("pnyolo-bench", []),
]


def help_text(argv: list[str]) -> str:
    bindir = Path(sys.executable).parent
    out = subprocess.run([str(bindir / argv[0]), *argv[1:], "--help"], capture_output=True, text=True)
    return (out.stdout or out.stderr).rstrip()


def main() -> None:
    parts = ["# Command-line reference\n", "Generated from `--help` by `scripts/cli_reference.py`.\n"]
    for cmd, subs in COMMANDS:
        parts.append(f"\n## `{cmd}`\n\n```text\n{help_text([cmd])}\n```\n")
        for sub in subs:
            parts.append(f"\n### `{cmd} {sub}`\n\n```text\n{help_text([cmd, sub])}\n```\n")
    Path(__file__).resolve().parent.parent.joinpath("docs", "CLI.md").write_text("".join(parts))


if __name__ == "__main__":
    main()
