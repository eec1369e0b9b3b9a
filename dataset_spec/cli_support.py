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


def cli_main(fn):
    """Decorate a ``main(argv=None) -> int`` so user errors become one line and an exit code."""

    @functools.wraps(fn)
    def wrapper(argv=None):
        prog = os.path.basename(sys.argv[0]) or fn.__module__
        try:
            return fn(argv)
        except (UserError, SpecError) as exc:
            print(f"{prog}: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"{prog}: interrupted (completed outputs are kept; re-run to resume)", file=sys.stderr)
            return 130

    return wrapper
