"""The one exception type readers, writers and the validator raise for bad data."""
from __future__ import annotations

from pathlib import Path


class SpecError(Exception):
    """A file or folder does not follow the dataset spec.

    The message always names the offending path, so command-line tools can print
    ``str(err)`` as a one-line error.
    """

    def __init__(self, path: str | Path | None, message: str):
        self.path = None if path is None else Path(path)
        self.message = message
        super().__init__(f"{path}: {message}" if path is not None else message)
