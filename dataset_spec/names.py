"""Names read from data become folder and file names: one rule for all of them, and one function that
builds every path below a root (a dataset, an ``--out`` folder) and refuses to leave it::

    check_name("intersection_07")          # None when legal, else what is wrong ("contains '/'")
    below(out, "views", camera, "x.png")   # out / views / camera / x.png, or UnsafePath if it would leave out
    safe_name("Car 01/ä")                  # "Car_01_" : a legal name made from any text (imports, .blend files)

The rule (scenario, camera, actor and lighting-variant names, split entries): 1-128 characters among
letters, digits, ``_``, ``-`` and ``.``, starting with a letter, a digit or ``_`` (never ``.``: no
``..``, no hidden or temporary-looking file; never ``-``: no name that reads as an option).
"""
from __future__ import annotations

import os
import re
from pathlib import Path

from .errors import SpecError

MAX_NAME = 128
_LEGAL = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
_ILLEGAL_CHAR = re.compile(r"[^A-Za-z0-9_.-]")


class UnsafePath(SpecError):
    """A path built from data would leave the folder it belongs to (a one-line error like every SpecError)."""


def excerpt(value, limit: int = 60) -> str:
    """``repr(value)`` cut to about ``limit`` characters (error messages quote bad values bounded)."""
    import reprlib

    short = reprlib.Repr()
    short.maxstring = short.maxother = limit
    short.maxlist = short.maxtuple = short.maxdict = short.maxset = 6
    short.maxlevel = 3
    text = short.repr(value)
    return text if len(text) <= limit + 10 else text[:limit] + "..."


def check_name(name) -> str | None:
    """None when ``name`` is a legal name, else a short phrase saying why not."""
    if not isinstance(name, str):
        return f"expected a string, got {type(name).__name__}"
    if not name:
        return "is empty"
    if len(name) > MAX_NAME:
        return f"is {len(name)} characters long (at most {MAX_NAME})"
    if _LEGAL.fullmatch(name):
        return None
    bad = _ILLEGAL_CHAR.search(name)
    if bad is not None:
        return f"contains {bad.group()!r} (names use letters, digits, '_', '-' and '.')"
    return f"starts with {name[0]!r} (names start with a letter, a digit or '_')"


def check_relative_path(text) -> str | None:
    """None when ``text`` is a relative path of legal names joined by ``/`` (a mesh file below its
    scenario folder), else why not."""
    if not isinstance(text, str) or not text:
        return "expected a relative path"
    for part in text.split("/"):
        why = check_name(part)
        if why is not None:
            return f"part {excerpt(part)} {why}"
    return None


def safe_name(text: str, fallback: str = "unnamed") -> str:
    """A legal name made from any text: other characters become ``_``, a leading ``.``/``-`` gets a ``_``
    before it, cut to the length limit (for names an import or a user's .blend file supplies)."""
    name = _ILLEGAL_CHAR.sub("_", str(text))[:MAX_NAME] or fallback
    if not _LEGAL.fullmatch(name):
        name = ("_" + name)[:MAX_NAME]
    return name


def below(root: str | Path, *parts: str) -> Path:
    """``root / parts...``, refused (``UnsafePath``) when the result, links resolved as far as they exist,
    is not inside ``root``: an absolute part, ``..`` or a link planted below ``root`` that points out."""
    root = Path(root)
    path = root.joinpath(*parts)
    base = Path(os.path.realpath(root))
    real = Path(os.path.realpath(path))
    if real != base and base not in real.parents:
        raise UnsafePath(path, f"leaves {root} (a name or link in the data points outside it)")
    return path


MAX_FILE_NAME = 255  # bytes of one path component on the common file systems


class JoinedNames:
    """Names an export builds by joining names (``scenario__variant``, ``scenario__camera__variant``): each checked
    once, before anything is written, for length as a file name (with the longest suffix it gets) and for colliding
    with another join (``toy_01`` + ``a__b`` and ``toy_01__a`` + ``b`` are both ``toy_01__a__b``)::

        scenes = JoinedNames("nuScenes scene", suffix="__f0000.png")
        scenes("intersection_07", "noon")      # "intersection_07__noon"; SpecError on a clash or a long name
    """

    def __init__(self, what: str, suffix: str = "", sep: str = "__"):
        self.what, self.suffix, self.sep = what, suffix, sep
        self.made: dict[str, tuple[str, ...]] = {}

    def __call__(self, *parts: str) -> str:
        name = self.sep.join(parts)
        prior = self.made.setdefault(name, tuple(parts))
        if prior != tuple(parts):
            raise SpecError(None, f"{self.what} {excerpt(name)} would be made by both {excerpt(list(prior))} and "
                                  f"{excerpt(list(parts))}; rename one (names joined by {self.sep!r} must not collide)")
        length = len((name + self.suffix).encode())
        if length > MAX_FILE_NAME:
            raise SpecError(None, f"{self.what} {excerpt(name)} is a file name of {length} bytes with its suffix, "
                                  f"above {MAX_FILE_NAME}; shorten the names it joins ({excerpt(list(parts))})")
        return name
