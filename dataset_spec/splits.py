"""Train/val/test splits by layout: a scenario and its redraws (``NAME-sK``) always share a split.

    splits = make_splits(names, seed=0)                     # a fresh seeded split of whole layouts
    splits, placed = extend_splits(ds.info.splits, names)   # existing assignment kept, new ones placed
    print(placement_line(placed))                           # one line saying where the new ones went

The rule for a scenario that is in no split yet (``extend_splits``): it joins the split its layout
already has; a new layout fills an empty split first (test, then val) and otherwise goes to the
split furthest below its share of layouts (70/15/15; ties in the order train, val, test). When no
split holds anything yet, the new layouts get the seeded split of ``make_splits`` instead.
"""
from __future__ import annotations

import random
import re

from .schema import SPLIT_NAMES

FRACTIONS = (0.7, 0.15, 0.15)
_REDRAW = re.compile(r"^(?P<base>.+)-s[1-9][0-9]*$")


def layout_of(scenario: str) -> str:
    """The layout a scenario draws: ``intersection_03`` for ``intersection_03-s2`` and for itself."""
    m = _REDRAW.match(scenario)
    return m["base"] if m else scenario


def make_splits(scenarios: list[str], fractions=FRACTIONS, seed: int = 0) -> dict[str, list[str]]:
    """Split scenarios into train/val/test by layout (redraws stay with their layout), deterministically.

    With at least three layouts every split gets at least one.
    """
    layouts = sorted({layout_of(s) for s in scenarios})
    random.Random(seed).shuffle(layouts)
    n = len(layouts)
    n_val = max(1, round(fractions[1] * n)) if n >= 3 else 0
    n_test = max(1, round(fractions[2] * n)) if n >= 2 else 0
    n_train = n - n_val - n_test
    where = {lay: "train" for lay in layouts[:n_train]}
    where.update({lay: "val" for lay in layouts[n_train:n_train + n_val]})
    where.update({lay: "test" for lay in layouts[n_train + n_val:]})
    return {split: sorted(s for s in set(scenarios) if where[layout_of(s)] == split) for split in SPLIT_NAMES}


def extend_splits(splits: dict[str, list[str]], scenarios: list[str], seed: int = 0, fractions=FRACTIONS
                  ) -> tuple[dict[str, list[str]], dict[str, tuple[str, str]]]:
    """``splits`` with every scenario of ``scenarios`` that is in none placed by the module's rule.

    Returns the new splits and, per placed scenario, ``(split, why)``; scenarios already in a split
    keep it."""
    out = {s: sorted(splits.get(s, [])) for s in SPLIT_NAMES}
    assigned = {name: s for s, names in out.items() for name in names}
    new = sorted(set(scenarios) - set(assigned))
    if not new:
        return out, {}
    if not assigned:
        fresh = make_splits(new, fractions, seed)
        return fresh, {name: (s, f"seeded split of new layouts, seed {seed}") for s, names in fresh.items()
                       for name in names}
    layout_split = {layout_of(name): s for name, s in assigned.items()}
    placed: dict[str, tuple[str, str]] = {}
    for name in new:
        lay = layout_of(name)
        if lay in layout_split:
            placed[name] = (layout_split[lay], f"its layout {lay}'s split")
        else:
            counts = {s: sum(1 for sp in layout_split.values() if sp == s) for s in SPLIT_NAMES}
            empty = [s for s in ("test", "val") if counts[s] == 0]
            if empty:
                choice, why = empty[0], f"new layout, the {empty[0]} split was empty"
            else:
                total = sum(counts.values()) + 1
                deficit = {s: f * total - counts[s] for s, f in zip(SPLIT_NAMES, fractions)}
                choice = max(SPLIT_NAMES, key=lambda s: (deficit[s], -SPLIT_NAMES.index(s)))
                why = "new layout, the split furthest below its share"
            layout_split[lay] = choice
            placed[name] = (choice, why)
    for name, (s, _) in placed.items():
        out[s] = sorted(out[s] + [name])
    return out, placed


def placement_line(placed: dict[str, tuple[str, str]], kept: int) -> str:
    """One line: how many scenarios kept their split and where the new ones went (and why)."""
    if not placed:
        return f"splits: all {kept} scenarios keep their split"
    groups: dict[tuple[str, str], list[str]] = {}
    for name, where in sorted(placed.items()):
        groups.setdefault(where, []).append(name)
    moves = "; ".join(f"{', '.join(names)} -> {s} ({why})" for (s, why), names in sorted(groups.items()))
    return f"splits: {kept} scenarios keep their split; {moves}"
