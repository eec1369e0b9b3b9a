"""Two test sets in every bench report (issue 85): the preset's built-in test layouts, and procedural layouts no model
ever trained on ("new layouts": what a user of procedural layouts wants to know). A split may add new layouts
(``splits.test: {layouts: [...], redraws: 1, new_layouts: 24}``); their names are fixed by the split alone, so every
run and preset holds the same ones, and they are disjoint from training by construction (no training split may name
them: ``presets._check``) and from each other (validation and test draw from separate blocks)::

    new_layout_names("test", 3)             # ["procedural-20000", "procedural-20001", "procedural-20002"]
    by_test_set(["intersection_07", "procedural-20000"])   # {"built-in": [...], "new layouts": [...]}

The report's section on them: ``pnyolo.bench.analyses.two_test_sets``.
"""
from __future__ import annotations

from dataset_spec.splits import layout_of

BUILT_IN, NEW = "built-in", "new layouts"
FIRST = {"val": 10000, "test": 20000}  # procedural-K of the new layouts: a block a split (training draws from 0 up)
PREFIX = "procedural-"


def new_layout_names(split: str, count: int) -> list[str]:
    """The ``count`` new layouts a split adds: ``procedural-K`` from its block (one draw each)."""
    return [f"{PREFIX}{FIRST[split] + k}" for k in range(count)]


def is_new_layout(scenario: str) -> bool:
    """Whether a scenario (or a redraw of it) is one of the held-out blocks' procedural layouts."""
    layout = layout_of(scenario)
    if not layout.startswith(PREFIX) or not layout[len(PREFIX):].isdigit():
        return False
    return int(layout[len(PREFIX):]) >= min(FIRST.values())


def by_test_set(scenarios: list[str]) -> dict[str, list[str]]:
    """``scenarios`` by test set: the built-in layouts, then the new ones (a set without a scenario left out)."""
    sets = {BUILT_IN: [s for s in scenarios if not is_new_layout(s)], NEW: [s for s in scenarios if is_new_layout(s)]}
    return {k: v for k, v in sets.items() if v}
