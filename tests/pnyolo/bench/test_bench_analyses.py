"""The bench report's analyses as registered classes (issue 86, item 4): one class, registered by its decorator, is
measured on the run's record, kept in report.json under its name and given its section; nothing else changes."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

import pnyolo.bench.analyses as registry
from pnyolo.bench.analyses import Analysis, analyses, register_analysis, run_analyses


def test_the_built_in_analyses_register_themselves_in_report_order():
    names = [a.name for a in analyses()]
    assert names[:2] == ["test_sets", "placement"]


def test_one_class_is_a_new_section_and_a_key_of_report_json(monkeypatch):
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))  # this test's classes leave no trace

    @register_analysis
    class RowCount(Analysis):  # as the benchmark guide writes one
        name, title, order = "row_count", "How many rows", 1

        def measure(self, run):
            return {"rows": len(run.results)} if run.results else None

        def lines(self, doc, run):
            return [f"{doc['rows']} rows."]

    for name in ("test_sets", "placement"):  # the built-in ones have nothing to say about this stand-in run
        monkeypatch.setitem(registry._REGISTRY, name, type(name, (Analysis,), {
            "name": name, "title": name, "measure": lambda self, run: None}))
    docs, lines = run_analyses(SimpleNamespace(results={"a": 1, "b": 2}))
    assert docs == {"row_count": {"rows": 2}, "test_sets": None, "placement": None}
    assert lines == ["## How many rows", "", "2 rows.", ""]
    docs, lines = run_analyses(SimpleNamespace(results={}))
    assert docs["row_count"] is None and lines == []  # nothing to say: no section
    with pytest.raises(ValueError, match="registered twice"):
        register_analysis(type("Other", (Analysis,), {"name": "row_count", "title": "x"}))
    with pytest.raises(TypeError, match="name and a title"):
        register_analysis(type("Nameless", (Analysis,), {}))
