"""Pieces of the benchmark report that need neither Blender nor training."""
from __future__ import annotations

from pathlib import Path

from pnyolo.bench import PRESETS, TEST_LAYOUTS, TRAIN_LAYOUTS, VAL_LAYOUTS, _one_per_scenario_first


def test_examples_are_spread_over_scenarios_before_lightings():
    names = [f"{s}_{v}_a_vs_b.png" for s in ("intersection_07", "intersection_07-s1", "intersection_11")
             for v in ("dusk", "noon", "sunset")]
    order = [p.name for p in _one_per_scenario_first([Path(n) for n in sorted(names)],
                                                     ["intersection_07", "intersection_07-s1", "intersection_11"])]
    assert sorted(order) == sorted(names)
    assert order[:3] == ["intersection_07-s1_dusk_a_vs_b.png", "intersection_07_dusk_a_vs_b.png",
                         "intersection_11_dusk_a_vs_b.png"]  # one per street first (the longest prefix wins)
    assert order[3:6] == ["intersection_07-s1_noon_a_vs_b.png", "intersection_07_noon_a_vs_b.png",
                          "intersection_11_noon_a_vs_b.png"]


def test_held_out_layouts_never_reach_training_redrawn_or_not():
    base = lambda s: s.split("-s")[0]  # noqa: E731
    for preset in PRESETS.values():
        train, val, test = ({base(s) for s in split} for split in (preset.train, preset.val, preset.test))
        assert not (train & test) and not (train & val) and not (val & test), preset.name
    cpu = PRESETS["cpu"]
    assert {base(s) for s in cpu.train} == set(TRAIN_LAYOUTS) and cpu.test == TEST_LAYOUTS
    assert {base(s) for s in cpu.val} == set(VAL_LAYOUTS)
    assert len(cpu.train) > len(TRAIN_LAYOUTS)  # redrawn variants add scenes
