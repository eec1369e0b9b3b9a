"""What every command-line tool of the project shares: one-line errors, never a traceback
for a user mistake.

Example::

    @cli_main
    def main(argv=None) -> int:
        args = parser.parse_args(argv)
        if args.samples < 1:
            raise UserError("--samples must be >= 1")
        ...

Errors print as ``<prog>: error: <message>`` on stderr and exit with status 2
(``UserError``, ``SpecError``, argparse mistakes) or 130 (Ctrl-C). Bugs still raise.
"""
from __future__ import annotations

import argparse
import functools
import os
import sys
import tempfile
from pathlib import Path

from .atomic import output_root
from .errors import SpecError


class UserError(Exception):
    """A mistake in the user's input or options (not a bug): reported in one line."""


class OneLineArgumentParser(argparse.ArgumentParser):
    """ArgumentParser whose errors are one line (no usage dump) and exit 2."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message):  # noqa: D102 - argparse API
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _check_writable_below(path: Path, option: str, shown: Path) -> None:
    """One-line error unless the nearest existing folder at or above ``path`` can be written."""
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise UserError(f"{option} {shown}: {existing} is a file, so no folder can be made below it")
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as exc:
        raise UserError(f"{option} {shown}: cannot write in {existing} ({exc.strerror or exc})") from None


def check_output_dir(path: str | Path, option: str = "--out") -> Path:
    """``path`` as a folder the command may write into, checked before any work and created by
    nothing here (the first file written creates it). One-line ``UserError`` when it is a file,
    lies below a file, or its nearest existing folder cannot be written (read-only included)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserError(f"{option} {path}: is a file, not a folder")
    try:
        output_root(path)  # a link there (planted in a received folder) is refused; none may stand below it
    except SpecError as exc:
        raise UserError(f"{option} {exc}") from None
    _check_writable_below(path, option, path)
    return path


def check_output_file(path: str | Path, option: str) -> Path:
    """``path`` as a file the command writes later: not a folder, its folder writable."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{option} {path}: is a folder, not a file")
    try:
        output_root(path.parent)  # the folder it is written into, as given: never through a link
    except SpecError as exc:
        raise UserError(f"{option} {exc}") from None
    _check_writable_below(path.parent, option, path)
    return path


def program_name(fallback: str) -> str:
    """What the user ran, for error lines: the console script's name, or ``python -m MODULE`` for a module run with
    -m (whose ``sys.argv[0]`` is a file such as ``__main__.py``)."""
    prog = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    if spec is not None and (prog.endswith(".py") or not prog):
        return f"python -m {spec.name.removesuffix('.__main__')}"
    return prog or fallback


def cli_main(fn):
    """Decorate a ``main(argv=None) -> int`` so user errors become one line and an exit code."""

    @functools.wraps(fn)
    def wrapper(argv=None):
        prog = program_name(fn.__module__)
        try:
            return fn(argv)
        except (UserError, SpecError) as exc:
            print(f"{prog}: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"{prog}: interrupted (completed outputs are kept; re-run to resume)", file=sys.stderr)
            return 130

    return wrapper
