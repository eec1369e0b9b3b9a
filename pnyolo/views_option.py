"""The ``--views`` option of the evaluation and prediction commands."""
from __future__ import annotations

from dataset_spec.cli_support import UserError


def parse_views(text: str | None) -> list[int] | None:
    """``--views 0,1,2`` -> [0, 1, 2]; one-line errors for anything but distinct indices >= 0."""
    if text is None:
        return None
    try:
        views = [int(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise UserError(f"--views {text!r}: expected camera indices like 0,1,2") from None
    if not views or min(views) < 0:
        raise UserError(f"--views {text!r}: expected camera indices >= 0 like 0,1,2")
    if len(set(views)) != len(views):
        raise UserError(f"--views {text}: indices must be distinct")
    return views
