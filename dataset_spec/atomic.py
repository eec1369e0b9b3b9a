"""Atomic file writes: write to a temporary file in the same folder, then rename.

A reader never sees a half-written file: it sees the old file, no file, or the new one.
Temporary files are named ``.<name>.tmp-<pid>-<random>``, created exclusively (never an existing file
or a link planted there) and removed on failure; a killed writer's are removed by
``remove_stale_temporaries`` (what a resumed render does first). The rename replaces a link at the
target instead of writing through it, so nothing lands outside the folder; ``append_text`` adds to a
log without following a link either.

Output roots: a command declares the folders it writes below (``output_root``: ``check_output_dir`` does,
and a dataset being written); no component between a declared root and a file written below it may be
a link, so a link planted inside a received folder (a dataset's ``exports/``, a run's ``eval_test/``)
or inside a chosen ``--out`` never sends files elsewhere. A root given as a default inside received
data is refused when it is itself a link.

Example::

    output_root("out/eval")             # files below it are written only through real folders
    with atomic_path("out/depth.exr") as tmp:
        write_exr(tmp, depth)        # any writer that takes a path
    atomic_write_text("out/scenario.json", text)
    atomic_savefig(fig, "out/plot.png", dpi=110)   # a matplotlib figure
"""
from __future__ import annotations

import contextlib
import glob
import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

from .errors import SpecError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_umask()  # what a plain open() would give the file (mkstemp makes it 0600)


_ROOTS: set[str] = set()  # folders this process writes below (absolute, links not resolved)


def output_root(path: str | Path, allow_link: bool = False) -> Path:
    """Declare ``path`` a folder this process writes below: from now on no link may stand between it and a
    file written there. Refused (``SpecError``) when ``path`` is itself a link, unless ``allow_link`` (a
    dataset folder the user named, which may be a link of theirs)."""
    path = Path(path)
    if os.path.islink(path) and not allow_link:
        raise SpecError(path, f"is a link (to {os.readlink(path)}); outputs are never written through links: "
                              "give the folder itself")
    _ROOTS.add(os.path.abspath(path))
    return path


def check_no_links(folder: str | Path) -> None:
    """``SpecError`` when a component of ``folder`` below a declared output root is a link (see ``output_root``)."""
    here = os.path.abspath(folder)
    for root in _ROOTS:
        if here != root and not here.startswith(root + os.sep):
            continue
        part = root
        for name in Path(os.path.relpath(here, root)).parts if here != root else ():
            part = os.path.join(part, name)
            if os.path.islink(part):
                raise SpecError(part, "is a link inside an output folder; outputs are never written through links")


def make_folder(folder: str | Path) -> Path:
    """``folder`` created where missing, each component a real folder below any declared output root."""
    folder = Path(folder)
    check_no_links(folder)
    folder.mkdir(parents=True, exist_ok=True)
    check_no_links(folder)  # a link raced in while it was made
    return folder


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    ``suffix`` defaults to the target's suffix, so writers that pick a format from the
    file extension (OpenCV, OpenEXR) keep working.
    """
    path = Path(path)
    make_folder(path.parent)
    suffix = path.suffix if suffix is None else suffix
    fd, name = tempfile.mkstemp(suffix=suffix, prefix=f".{path.stem}.tmp-{os.getpid()}-", dir=path.parent)
    os.fchmod(fd, _FILE_MODE)
    os.close(fd)  # created with O_EXCL by mkstemp: a new file nobody else placed there, which the writer fills
    tmp = Path(name)
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


@contextlib.contextmanager
def staged_folder(out: str | Path) -> Iterator[Path]:
    """A new temporary folder beside ``out`` to write a whole result into; on success it becomes ``out`` in one
    rename (the files ``out`` held beside the result kept: linked in first, the old folder renamed aside and then
    removed), on failure it is removed: ``out`` is then as it was. What a killed run left (its staging folder, or
    ``out`` renamed aside between the two renames) is cleaned up or put back first, so ``out`` never holds a mix of
    two runs' files."""
    out = Path(out)
    make_folder(out.parent)
    _recover_staged(out)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-{os.getpid()}-", dir=out.parent))
    try:
        yield tmp
        if not exists(out):
            os.rename(tmp, out)
            return
        for folder, dirs, _ in os.walk(tmp):  # a link in out where the result has a folder: refused, not replaced
            for name in dirs:
                mine = out / Path(folder).relative_to(tmp) / name
                if os.path.islink(mine):
                    raise SpecError(mine, "is a link inside an output folder; outputs are never written through links")
        for folder, dirs, files in os.walk(out):  # links are not followed: a linked folder is kept as a link
            rel = Path(folder).relative_to(out)
            for name in files + [d for d in dirs if os.path.islink(os.path.join(folder, d))]:
                if not exists(tmp / rel / name):
                    make_folder(tmp / rel)
                    os.link(os.path.join(folder, name), tmp / rel / name, follow_symlinks=False)
        aside = out.parent / f".{out.name}.old-{os.getpid()}"
        os.rename(out, aside)
        os.rename(tmp, out)
        shutil.rmtree(aside, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _recover_staged(out: Path) -> None:
    """Undo what a killed ``staged_folder`` left beside ``out``: its staging folders are removed, and ``out``
    renamed aside is put back when nothing took its place (else removed)."""
    for path in sorted(out.parent.glob(f".{glob.escape(out.name)}.*-*")):
        m = re.fullmatch(rf"\.{re.escape(out.name)}\.(tmp|old)-(\d+)(-.*)?", path.name)
        if not m or not path.is_dir() or path.is_symlink() or process_alive(int(m.group(2))):
            continue
        if m.group(1) == "old" and not exists(out):
            os.rename(path, out)
        else:
            shutil.rmtree(path, ignore_errors=True)


def atomic_savefig(fig, path: str | Path, **kwargs) -> None:
    """``fig.savefig`` (a matplotlib figure) written atomically; the format from ``path``'s suffix."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or None, **kwargs)


def append_text(path: str | Path, text: str, expect: tuple[int, int] | None = None) -> tuple[int, int]:
    """Append ``text`` to ``path`` (created if absent), refusing to write into any file but its own: through a
    symbolic link planted there (``O_NOFOLLOW``), into a file with another name too (a hard link: more than one link),
    or, given ``expect`` (the identity an earlier append returned), into another file put in its place. Returns the
    file's identity (device, inode) for the next append: a file a run keeps appending to is checked every time."""
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
    check_no_links(Path(path).parent)
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as exc:
        if Path(path).is_symlink():
            raise OSError(f"{path} is a link; refusing to write through it") from None
        raise exc
    with os.fdopen(fd, "a", encoding="utf-8", newline="") as fh:
        st = os.fstat(fd)
        if st.st_nlink > 1:
            raise SpecError(path, f"has {st.st_nlink} names (a hard link to another file); refusing to write into it")
        if expect is not None and (st.st_dev, st.st_ino) != tuple(expect):
            raise SpecError(path, "is another file than the one this run wrote (replaced while it ran); refusing to "
                                  "write into it")
        fh.write(text)
    return st.st_dev, st.st_ino


def exists(path: str | Path) -> bool:
    """Whether anything is at ``path``, a dangling link included (``Path.exists`` follows links)."""
    return os.path.lexists(path)


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
    return _remove_stale(Path(root).rglob(".*.tmp-*"))


def remove_stale_temporaries_of(path: str | Path) -> int:
    """``remove_stale_temporaries`` for the one file ``path`` (its atomic writes' leftovers beside it)."""
    path = Path(path)
    return _remove_stale(path.parent.glob(f".{glob.escape(path.stem)}.tmp-*"))


def _remove_stale(paths) -> int:
    removed = 0
    for path in paths:
        m = re.search(r"\.tmp-(\d+)-", path.name)
        if m and path.is_file() and not process_alive(int(m.group(1))):
            path.unlink(missing_ok=True)
            removed += 1
    return removed
