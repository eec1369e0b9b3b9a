"""Two test sets (issue 85): new layouts, procedural and never trained on, named by their split alone and disjoint from
training and from each other; rendered with their own options; each report row's figures on each set from its
scenarios' sums, with standard errors over that set's layouts."""
from __future__ import annotations

from pathlib import Path

import pytest

from dataset_spec.cli_support import UserError
from pnyolo.bench.presets import preset_from_dict
from pnyolo.bench.analyses.two_test_sets import set_figures, sets_json, sets_lines
from pnyolo.bench.new_layouts import BUILT_IN, NEW, by_test_set, is_new_layout, new_layout_names

SPLITS = {"train": {"layouts": ["intersection_01"], "redraws": 1},
          "val": {"layouts": ["intersection_02"], "new_layouts": 2},
          "test": {"layouts": ["intersection_03"], "new_layouts": 3}}


def _preset(splits=SPLITS, **extra):
    raw = {"description": "x", "splits": splits, "render": ["--quality", "preview"], "models": ["bev"],
           "split_render": {"test": ["--frames", "2", "--fps", "10"]}, **extra}
    return preset_from_dict(raw, Path("configs/bench/x.yaml"))


def test_new_layouts_are_named_by_their_split_and_never_shared():
    val, test = new_layout_names("val", 12), new_layout_names("test", 24)
    assert val == new_layout_names("val", 12) and test[:3] == new_layout_names("test", 3)  # the same on every run
    assert not set(val) & set(test) and len(set(val)) == 12 and len(set(test)) == 24
    assert all(is_new_layout(s) for s in [*val, *test, f"{test[0]}-s2"])
    assert not any(is_new_layout(s) for s in ["procedural-5", "procedural-167", "intersection_07", "procedural-x"])


def test_a_preset_adds_them_renders_them_apart_and_keeps_them_from_training():
    p = _preset()
    assert p.val == ["intersection_02", *new_layout_names("val", 2)]
    assert p.test == ["intersection_03", *new_layout_names("test", 3)]
    groups = p.render_groups()
    assert [(s, names) for s, names, _ in groups] == [("train", p.train), ("val", ["intersection_02"]),
                                                       ("val", p.val[1:]), ("test", ["intersection_03"]),
                                                       ("test", p.test[1:])]
    assert groups[3][2] == ["--frames", "2", "--fps", "10", "--split", "test"]  # the built-ins: their split's options
    assert groups[4][2] == ["--hdr", "random", "--split", "test"]  # the new ones: one lighting, one frame
    with pytest.raises(UserError, match="held out"):
        _preset({**SPLITS, "train": {"layouts": ["intersection_01"], "new_layouts": 2}})
    with pytest.raises(UserError, match="training may not see them"):
        _preset({**SPLITS, "train": ["intersection_01", "procedural-20007"]})
    with pytest.raises(UserError, match="new_layouts_render"):
        _preset(new_layouts_render=["--out", "/tmp/x"])
    with pytest.raises(UserError, match="new_layouts: a whole number"):
        _preset({**SPLITS, "test": {"layouts": ["intersection_03"], "new_layouts": -1}})


def _summary(per: dict) -> dict:
    return {"per_scenario": {s: {"counts": {"0.2": c}, "hidden_seen": {"0.2": h}} for s, (c, h) in per.items()}}


def test_a_set_s_figures_are_its_scenarios_sums():
    new = new_layout_names("test", 2)
    summary = _summary({"intersection_07": ([8, 2, 2], [1, 2]), "intersection_07-s1": ([2, 2, 2], [1, 2]),
                        "intersection_11": ([5, 5, 0], [0, 0]), new[0]: ([3, 1, 1], [2, 4]), new[1]: ([1, 3, 1], [0, 0])})
    scenarios = list(summary["per_scenario"])
    sets = by_test_set(scenarios)
    assert sets == {BUILT_IN: scenarios[:3], NEW: new}
    built = set_figures(summary, sets[BUILT_IN], "0.2")
    tp, fp, fn = 15, 9, 4  # intersection_07 and its redraw are one layout: two layouts in all
    assert built["f1"] == pytest.approx(2 * tp / (2 * tp + fp + fn)) and built["layouts"] == 2
    assert built["precision"] == pytest.approx(tp / (tp + fp)) and built["recall"] == pytest.approx(tp / (tp + fn))
    assert built["hidden_seen_recall"] == pytest.approx(2 / 4) and built["f1_se"] > 0
    one = set_figures(summary, sets[NEW][:1], "0.2")
    assert one["f1"] == pytest.approx(6 / 8) and one["f1_se"] is None and one["hidden_seen_recall"] == 0.5
    doc = sets_json({"bev": summary, "no sums": {"per_scenario": None}}, scenarios, "0.2")
    assert list(doc["sets"][NEW]["rows"]) == ["bev"]  # a row without per-scenario sums has no set figures
    text = "\n".join(sets_lines(doc, "0.2"))
    assert f"| bev | {built['f1']:.3f} ± {built['f1_se']:.3f} |" in text and "new layouts: F1@0.2" in text
