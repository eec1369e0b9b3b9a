"""Atomic file writes: write to a temporary file in the same folder, then rename.

A reader never sees a half-written file: it sees the old file, no file, or the new one.
Temporary files are named ``.<name>.tmp-<pid>-<n>`` and are removed on failure; a killed writer's
are removed by ``remove_stale_temporaries`` (what a resumed render does first).

Example::

    with atomic_path("out/depth.exr") as tmp:
        write_exr(tmp, depth)        # any writer that takes a path
    atomic_write_text("out/scenario.json", text)
"""
from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
from pathlib import Path
from typing import Any, Iterator

_counter = itertools.count()


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    ``suffix`` defaults to the target's suffix, so writers that pick a format from the
    file extension (OpenCV, OpenEXR) keep working.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}-{next(_counter)}{suffix}")
    try:
        yield tmp
        if not tmp.exists():
            raise OSError(f"writer produced no file for {path}")
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=1, allow_nan=False) + "\n")


def is_temporary(path: str | Path) -> bool:
    """True for leftovers of an interrupted atomic write (safe to delete)."""
    return ".tmp-" in Path(path).name and Path(path).name.startswith(".")


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` runs (another user's counts as running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def remove_stale_temporaries(root: str | Path) -> int:
    """Delete the temporary files below ``root`` whose writing process no longer runs (a kill
    leaves them behind); returns how many were removed."""
    removed = 0
    for path in Path(root).rglob(".*.tmp-*"):
        m = re.search(r"\.tmp-(\d+)-\d+", path.name)
        if m and path.is_file() and not process_alive(int(m.group(1))):
            path.unlink(missing_ok=True)
            removed += 1
    return removed
