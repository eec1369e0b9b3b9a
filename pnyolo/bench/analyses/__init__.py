"""The bench report's analyses as registered classes (issue 86, item 4): each reads the run's record (its rows, the
predictions' files it kept, the dataset) and gives a JSON value for report.json (``analyses[NAME]``) and the lines
of its section in report.md. Adding one is one module in this folder holding one class; nothing else changes::

    @register_analysis
    class MyAnalysis(Analysis):
        name, title = "my_analysis", "What it shows"

        def measure(self, run):                # -> a JSON-able value, or None: nothing to say for this run
            return {"rows": len(run.results)}

        def lines(self, doc, run):             # -> the section's markdown lines
            return [f"{doc['rows']} rows."]

Every module of this package is imported on first use (``analyses()``), so its classes register themselves; the
report runs them in ``order`` (then name) after the test results.
"""
from __future__ import annotations

import importlib
import pkgutil
from typing import ClassVar

_REGISTRY: dict[str, type["Analysis"]] = {}


class Analysis:
    """One section of the bench report made from the record alone (the module docstring)."""

    name: ClassVar[str] = ""  # its key in report.json's ``analyses``
    title: ClassVar[str] = ""  # its section's heading
    order: ClassVar[int] = 100  # where its section goes among the analyses (lower first)

    def measure(self, run) -> dict | None:
        raise NotImplementedError

    def lines(self, doc: dict, run) -> list[str]:
        raise NotImplementedError


def register_analysis(cls: type[Analysis]) -> type[Analysis]:
    """Register ``cls`` under its ``name`` (a class decorator); one name, one class."""
    if not cls.name or not cls.title:
        raise TypeError(f"{cls.__name__}: an analysis needs a name and a title")
    if _REGISTRY.get(cls.name, cls) is not cls:
        raise ValueError(f"analysis {cls.name!r} is registered twice ({_REGISTRY[cls.name].__name__}, {cls.__name__})")
    _REGISTRY[cls.name] = cls
    return cls


def analyses() -> list[Analysis]:
    """One instance of every registered analysis, in report order (this package's modules imported first)."""
    for module in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{module.name}")
    return [cls() for cls in sorted(_REGISTRY.values(), key=lambda c: (c.order, c.name))]


def run_analyses(run) -> tuple[dict, list[str]]:
    """Every analysis on ``run``: ({name: its value}, the report's lines of those with something to say)."""
    docs, lines = {}, []
    for a in analyses():
        docs[a.name] = a.measure(run)
        if docs[a.name] is not None:
            lines += [f"## {a.title}", "", *a.lines(docs[a.name], run), ""]
    return docs, lines
