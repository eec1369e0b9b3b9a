"""This tree and, beside it, a git revision checked out in a temporary worktree: the sides a before/after benchmark
measures (benchmarks/forward_count.py, benchmarks/data_walk.py)."""
from __future__ import annotations

import contextlib
import subprocess
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
