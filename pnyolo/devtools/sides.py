"""This tree and, beside it, a git revision checked out in a temporary worktree: the sides a before/after benchmark
measures (benchmarks/forward_count.py, benchmarks/data_walk.py), and the run of such a script on one side.

Only the side that orchestrates imports this module: the script's ``--here`` run on an older revision imports that
revision's pnyolo, which may not have it, so the measuring code itself stays in the script."""
from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from pathlib import Path


@contextlib.contextmanager
def sides(root: Path, base: str | None, tmp: Path):
    """{name: checkout}: ``base`` (a worktree under ``tmp``, removed afterwards) first when given, then this tree."""
    if not base:
        yield {"this tree": root}
        return
    worktree = tmp / "base"
    subprocess.run(["git", "worktree", "add", "--detach", str(worktree), base], cwd=root, check=True,
                   capture_output=True)
    try:
        yield {base: worktree, "this tree": root}
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(worktree)], cwd=root, capture_output=True)


def run_here(script: str, root: Path, out: Path) -> dict:
    """``script --here root --out out`` in a fresh interpreter importing ``root``'s code (no plugins): its last
    stdout line, a JSON object."""
    env = {**os.environ, "PYTHONPATH": str(root), "PNYOLO_PLUGINS": "0"}
    res = subprocess.run([sys.executable, str(Path(script).resolve()), "--here", str(root), "--out", str(out)],
                         cwd=root, env=env, capture_output=True, text=True, timeout=3600)
    if res.returncode != 0:
        raise SystemExit(f"{root}: {Path(script).name} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])
