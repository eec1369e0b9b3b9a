"""Bootstrap standard errors of test figures and of differences, scenarios resampled (issue 76)."""
from __future__ import annotations

import numpy as np
import pytest

from pnyolo.evaluation.bootstrap import difference_se, f1_of, figure_se, hidden_recall_of, se_text
from pnyolo.evaluation.metrics import MetricAccumulator, ViewDetections, ViewGroundTruth


def _view(rng, hits: int, misses: int, ghosts: int):
    """A view with ``hits`` found road users, ``misses`` missed ones (hidden but seen elsewhere) and ``ghosts``
    false positives, all of class 0."""
    n = hits + misses
    gt_boxes = np.array([[20 * k, 0, 20 * k + 10, 10] for k in range(n)], dtype=float).reshape(-1, 4)
    ghost_boxes = np.array([[500 + 20 * k, 0, 510 + 20 * k, 10] for k in range(ghosts)], dtype=float).reshape(-1, 4)
    det_boxes = np.vstack([gt_boxes[:hits], ghost_boxes])
    visible = np.r_[np.ones(hits), np.zeros(misses)]
    gt = ViewGroundTruth(gt_boxes, np.zeros(n, np.int64), visible_fraction=visible, seen_elsewhere=np.ones(n, bool))
    return ViewDetections(det_boxes, rng.uniform(0.5, 1, len(det_boxes)), np.zeros(len(det_boxes), np.int64)), gt


def _summary(spec: list[tuple[str, int, int, int]]) -> dict:
    rng = np.random.default_rng(0)
    acc = MetricAccumulator((0.2, 0.5), 1, ["car"])
    for unit, hits, misses, ghosts in spec:
        acc.add(*_view(rng, hits, misses, ghosts), unit)
    return acc.summary()


def test_a_figures_standard_error_resamples_layouts_and_one_layout_has_none():
    varied = _summary([("a", 9, 1, 0), ("b", 2, 8, 5), ("c", 6, 4, 2), ("a", 5, 5, 1)])
    se = varied["standard_errors"]
    assert se["scenarios"] == se["layouts"] == 3 and varied["per_scenario"]["a"]["counts"]["0.2"] == [14, 1, 6]
    assert se["f1"]["0.2"] > 0.05 and se["ap50"] > 0
    assert se["hidden_seen_recall"]["0.2"] == pytest.approx(0.0, abs=1e-12)  # the hidden misses: none ever found
    same = _summary([("a", 5, 5, 2), ("b", 5, 5, 2), ("c", 5, 5, 2)])  # every scenario alike: no spread
    assert same["standard_errors"]["f1"]["0.2"] == pytest.approx(0.0, abs=1e-12)
    one = _summary([("a", 9, 1, 0), ("a", 2, 8, 5)])
    assert one["standard_errors"]["f1"]["0.2"] is None and one["standard_errors"]["ap50"] is None
    assert se_text(None, 1) == "n/a (one layout)" and se_text(0.0213, 3) == "± 0.021"
    redraws = _summary([("a", 9, 1, 0), ("a-s1", 2, 8, 5)])  # a layout and its redraw: one unit, no spread
    assert redraws["standard_errors"]["layouts"] == 1 and redraws["standard_errors"]["f1"]["0.2"] is None


def test_the_layout_bootstrap_matches_an_exhaustive_resample_of_a_small_case():
    """Issue 85: the unit is the layout (a scene and its redraws): with 3 layouts (one drawn twice) the bootstrap's
    F1 standard error equals, within Monte Carlo error, the exact one over all 3^3 equally likely resamples of the
    layouts, and differs from resampling the 4 scenarios as if independent."""
    import itertools

    import numpy as np

    spec = [("p", 9, 1, 0), ("p-s1", 8, 2, 1), ("q", 2, 8, 5), ("r", 6, 4, 2)]
    summary = _summary(spec)
    sums = {"p": [0, 0, 0], "q": [0, 0, 0], "r": [0, 0, 0]}
    for unit in summary["per_scenario"]:
        tp, fp, fn = summary["per_scenario"][unit]["counts"]["0.2"]
        layout = unit.split("-s")[0]
        sums[layout] = [sums[layout][0] + tp, sums[layout][1] + fp, sums[layout][2] + fn]

    def f1(draw):
        tp, fp, fn = np.sum([sums[u] for u in draw], axis=0)
        return 2 * tp / (2 * tp + fp + fn)

    exact = np.std([f1(d) for d in itertools.product(sums, repeat=3)], ddof=0)
    assert summary["standard_errors"]["f1"]["0.2"] == pytest.approx(exact, rel=0.08)
    per_scene = np.asarray([summary["per_scenario"][u]["counts"]["0.2"] for u in sorted(summary["per_scenario"])])
    scenes = np.std([(lambda c: 2 * c[0] / (2 * c[0] + c[1] + c[2]))(per_scene[list(d)].sum(axis=0))
                     for d in itertools.product(range(4), repeat=4)])
    assert abs(scenes - exact) > 0.1 * exact  # the unit matters: scenarios as if independent give another figure


def test_hidden_but_seen_recall_and_paired_differences():
    a = _summary([("a", 2, 8, 0), ("b", 9, 1, 0), ("c", 5, 5, 0)])
    for summary in (a,):  # the visible ones are hits here; hidden ones are the misses (visible 0, seen elsewhere)
        assert summary["per_scenario"]["a"]["hidden_seen"]["0.2"] == [0, 8]
    hidden = _summary([("a", 0, 10, 0), ("b", 0, 10, 0), ("c", 0, 10, 0)])
    assert figure_se([hidden], hidden_recall_of("0.2")) == pytest.approx(0.0, abs=1e-12)  # 0 found everywhere
    assert difference_se(a, a, f1_of, "0.2") == pytest.approx(0.0, abs=1e-12)  # paired: a row minus itself
    b = _summary([("a", 3, 7, 1), ("b", 8, 2, 0), ("c", 5, 5, 3)])
    assert 0 < difference_se(a, b, f1_of, "0.2") < figure_se([a], f1_of("0.2")) + figure_se([b], f1_of("0.2"))
    assert difference_se(a, _summary([("x", 1, 1, 0), ("y", 1, 1, 0)]), f1_of, "0.2") is None  # other scenarios


def test_chance_comes_from_a_single_view_scored_on_the_same_objects(tmp_path, capsys):
    """``pnyolo-eval --chance-from``: the single view's hidden-but-seen recall on the same objects is the chance the
    model's is set against; without it no chance is named; options may come before, between or after the
    positionals."""
    import json

    from test_pnyolo_common import TINY, make_dataset, tiny

    from pnyolo.cli import eval_main, train_main

    ds = make_dataset(tmp_path / "ds", n_scenarios=2)
    for kind, sets in (("mv", TINY), ("sv", tiny("model.kind=single-view"))):
        args = sum((["--set", s] for s in sets + ["train.max_steps=2", "train.epochs=1"]), [])
        assert train_main([str(ds), "--out", str(tmp_path / kind), "--quiet", *args]) == 0
    assert eval_main(["--split", "train", str(tmp_path / "mv" / "latest.pt"), "--conf", "0.05", str(ds),
                      "--every-camera", "--chance-from", str(tmp_path / "sv" / "latest.pt"), "--out",
                      str(tmp_path / "e"), "--quiet"]) == 0
    assert "F1@0.2 (strict)" in capsys.readouterr().out
    metrics = json.loads((tmp_path / "e" / "metrics.json").read_text())
    chance, hidden = metrics["against_chance"], metrics["recall_by_visibility"]["0.2"]["hidden here, seen in another view"]
    assert chance["chance_source"] == "single-view (chance) on the same objects" and chance["n"] == hidden["n"] > 0
    assert chance["above"] == pytest.approx(chance["recall"] - chance["chance"]) and chance["recall"] == hidden["recall"]
    assert "against chance (single-view (chance) on the same objects)" in (tmp_path / "e" / "metrics.md").read_text()
    assert eval_main([str(tmp_path / "mv" / "latest.pt"), str(ds), "--split", "train", "--out", str(tmp_path / "f"),
                      "--quiet", "--chance-from", str(tmp_path / "mv" / "latest.pt")]) == 2
    assert "reads the other cameras" in capsys.readouterr().err


def test_a_target_passes_only_beyond_its_margin_by_one_standard_error():
    """Issue 85 item 3: a target on a difference passes only when the difference minus its standard error (layouts
    resampled) reaches the margin: a primary model 0.01 above its baseline on noisy layouts is no PASS, one well
    above on steady layouts is; with one layout the figure alone decides, and the line says n/a."""
    from dataclasses import replace as dc_replace

    from pnyolo.bench.presets import load_preset
    from pnyolo.bench.record import Result
    from pnyolo.bench.targets import beyond, bench_targets
    from pnyolo.evaluation.evaluate import Entry

    assert beyond(0.30, 0.05, 0.2) and not beyond(0.22, 0.05, 0.2) and beyond(0.22, None, 0.2)
    assert beyond(None, 0.1, 0.2) is None
    preset = dc_replace(load_preset("smoke"), primary="bev", baseline="single-view")
    noisy_a = _summary([("a", 9, 1, 0), ("b", 2, 8, 5), ("c", 6, 4, 2), ("d", 5, 5, 1)])
    noisy_b = _summary([("a", 9, 1, 1), ("b", 2, 8, 5), ("c", 6, 4, 2), ("d", 5, 5, 1)])
    for a, b, passes in ((noisy_a, noisy_b, False),
                         (_summary([(u, 9, 1, 0) for u in "abcd"]), _summary([(u, 5, 5, 3) for u in "abcd"]), True)):
        results = {"bev": Result(Entry("bev"), a), "single-view": Result(Entry("single-view"), b)}
        ok, text = bench_targets(preset, results, {})["bev F1@0.2 > single-view F1@0.2"]
        assert ok is passes and "±" in text, text
