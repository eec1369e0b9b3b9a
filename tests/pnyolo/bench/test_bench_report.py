"""Pieces of the benchmark report that need neither Blender nor training."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dataset_spec.cli_support import UserError
from pnyolo.bench.new_layouts import is_new_layout, new_layout_names
from pnyolo.bench.presets import builtin_presets, load_preset, preset_from_dict
from pnyolo.bench.report import _one_per_scenario_first
from pnyolo.bench.selection import hidden_target_point, select_threshold
from pnyolo.bench.record import BenchRun
from pnyolo.bench.stages import configure, model_config
from pnyolo.evaluation.metrics import MetricAccumulator, ViewDetections, ViewGroundTruth

MULTI, SINGLE = "pixelnerf-yolo", "single-view"


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
    assert builtin_presets() == ["cpu", "cpu_hires", "cpu_pretrained", "cpu_seq", "cpu_variety", "demo", "gpu",
                                 "gpu_quick", "smoke"]
    for name in builtin_presets():
        preset = load_preset(name)
        train, val, test = ({base(s) for s in split} for split in (preset.train, preset.val, preset.test))
        assert not (train & test) and not (train & val) and not (val & test), preset.name
    cpu = load_preset("cpu")
    layouts = {base(s) for s in cpu.scenarios if not is_new_layout(s)}
    assert layouts == {f"intersection_{i:02d}" for i in range(1, 13)}  # every built-in layout in one split
    assert len(cpu.train) == 12 * 7 and len(cpu.val) == 3 * 2 + 12 and len(cpu.test) == 2 * 3 + 24  # and new layouts
    assert "intersection_01-s11" in cpu.train and "intersection_07-s1" in cpu.test
    assert [s for s in cpu.test if is_new_layout(s)] == new_layout_names("test", 24)
    variety = load_preset("cpu_variety")  # run 58: 84 distinct training scenes, one drawn lighting each (the cpu's since)
    built_in = lambda split: [s for s in split if not is_new_layout(s)]  # noqa: E731 - run 58 had no new layouts
    assert (variety.train, variety.val, variety.test, variety.steps) == (cpu.train, built_in(cpu.val),
                                                                         built_in(cpu.test), cpu.steps)
    assert variety.split_render == cpu.split_render == {"train": ["--hdr", "random"]} and variety.hdr == cpu.hdr == "all"
    pretrained = load_preset("cpu_pretrained")  # run 49's scenes, as published: 21 training scenes, every lighting
    assert len(pretrained.train) == 3 * 7 and set(pretrained.train) < set(cpu.train) and not pretrained.split_render


def _preset_dict(**changes) -> dict:
    raw = {"description": "d", "splits": {"train": ["intersection_01"], "val": ["intersection_02"],
                                          "test": {"layouts": ["intersection_03"], "redraws": 1}},
           "render": ["--quality", "preview"], "config": "../cpu.yaml", "models": [MULTI, SINGLE]}
    return {**raw, **changes}


def test_a_preset_file_is_validated_field_by_field(tmp_path):
    from pnyolo.bench.presets import PRESET_DIR

    where = PRESET_DIR / "mine.yaml"  # config paths resolve against the preset file's folder
    preset = preset_from_dict(_preset_dict(steps=12, conf_grid=[0.2, 0.5]), where)
    assert (preset.name, preset.steps, preset.conf_grid) == ("mine", 12, (0.2, 0.5))
    assert preset.test == ["intersection_03", "intersection_03-s1"] and preset.config == "configs/cpu.yaml"
    for bad, words in [(_preset_dict(step=3), "unknown key"), (_preset_dict(steps="many"), "steps"),
                       (_preset_dict(steps=0), "steps must be >= 1"), (_preset_dict(conf_grid=[1.5]), "conf_grid"),
                       (_preset_dict(config="nowhere.yaml"), "does not exist"),
                       (_preset_dict(model_overrides={"bev2": ["model.loss.iou=1"]}), "unknown model kind"),
                       (_preset_dict(models=[]), "models must list distinct model kinds"),
                       (_preset_dict(baseline="lidar"), "primary, baseline and late_sender name a kind"),
                       (_preset_dict(late_sender="single-view"), "late_sender single-view is not one of the models "
                                                                 "with 3D detections"),
                       (_preset_dict(fusion=[MULTI]), "fusion two kinds"),
                       (_preset_dict(splits={"train": ["intersection_01"], "val": ["intersection_01-s1"],
                                             "test": ["intersection_03"]}), "both train and val"),
                       ({k: v for k, v in _preset_dict().items() if k != "render"}, "missing key 'render'")]:
        with pytest.raises(UserError, match=words):
            preset_from_dict(bad, where)
    path = tmp_path / "user.yaml"
    path.write_text("description: [unclosed\n")
    with pytest.raises(UserError, match="invalid YAML"):
        load_preset(path)
    with pytest.raises(UserError, match="unknown benchmark preset 'cpuu'"):
        load_preset("cpuu")


def test_a_preset_takes_what_it_does_not_give_from_its_base(tmp_path):
    # cpu_hires is cpu_pretrained rendered at 480x270 in two lightings: every other field inherited
    pre, hires = load_preset("cpu_pretrained"), load_preset("cpu_hires")
    assert (hires.name, hires.hdr, hires.render[-2:]) == ("cpu_hires", "noon,dusk", ["--resolution", "480x270"])
    assert replace(hires, name=pre.name, description=pre.description, render=pre.render, hdr=pre.hdr) == pre
    # a user's file beside its own base file: config stays relative to the file that gave it
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "base.yaml").write_text("description: b\nsplits: {train: [intersection_01], val: [intersection_02], "
                                                "test: [intersection_03]}\nrender: [--quality, preview]\n"
                                                "models: [single-view]\n"
                                                f"config: {load_preset('cpu').config_path}\nsteps: 9\n")
    (tmp_path / "cfg" / "child.yaml").write_text("base: base.yaml\nsteps: 4\n")
    child = load_preset(tmp_path / "cfg" / "child.yaml")
    assert (child.name, child.description, child.steps, child.config) == ("child", "b", 4, "configs/cpu.yaml")
    (tmp_path / "cfg" / "base.yaml").write_text("base: child.yaml\n")
    with pytest.raises(UserError, match="leads back to itself"):
        load_preset(tmp_path / "cfg" / "child.yaml")
    (tmp_path / "cfg" / "child.yaml").write_text("base: nowhere.yaml\n")
    with pytest.raises(UserError, match="nowhere.yaml does not exist"):
        load_preset(tmp_path / "cfg" / "child.yaml")


def test_an_explicit_training_seed_wins_for_its_model_but_kind_and_budget_do_not_move():
    # The bench's --seed seeds both models unless an override names train.seed for one of them
    # (a seed check of one model, the other reused); kind and step budget stay the bench's.
    cpu = load_preset("cpu")
    preset = replace(cpu, anchors=0, steps=123, overrides=[*cpu.overrides, "train.max_steps=7", "model.kind=single-view"],
                     model_overrides={MULTI: ["train.seed=1"]})
    multi, single = (model_config(preset, kind, seed=5) for kind in (MULTI, SINGLE))
    assert (multi.train.seed, single.train.seed) == (1, 5)
    assert (multi.model.kind, single.model.kind) == (MULTI, SINGLE)
    assert multi.train.max_steps == single.train.max_steps == 123


def test_frozen_efficientnet_models_share_one_feature_cache_in_the_run_folder(tmp_path):
    # cpu_pretrained freezes the pretrained backbone: every model reads one cache under OUT (the same
    # weights, the same entries); a preset that trains its encoder gets none
    cpu = replace(load_preset("cpu_pretrained"), anchors=0)
    run = BenchRun(cpu, tmp_path / "bench", seed=0)
    configure(run)
    assert {m.config.model.encoder.feature_cache for m in run.models.values()} == {str(tmp_path / "bench" / "feature_cache")}
    assert all(not m.config.data.color_jitter and m.config.data.shift_px == 0 for m in run.models.values())  # hits
    run = BenchRun(replace(cpu, overrides=[*cpu.overrides, "model.encoder.freeze=false"]), tmp_path / "b2", seed=0)
    configure(run)
    assert {m.config.model.encoder.feature_cache for m in run.models.values()} == {None}

def _sweep(item_counts_per_threshold: dict[float, list[tuple[int, int, int]]]) -> list[dict]:
    rows = []
    for t, items in item_counts_per_threshold.items():
        tp, fp, fn = np.sum(items, axis=0)
        rows.append({"threshold": t, "f1": 2 * tp / (2 * tp + fp + fn), "layout_counts": [list(c) for c in items]})
    return rows


def test_one_standard_error_rule_prefers_recall_within_noise_but_not_beyond():
    # 12 noisy items: the best F1 (0.9) barely beats 0.6, well within one standard error -> 0.6 (more recall)
    rng = np.random.default_rng(1)
    noisy = {t: [(int(rng.integers(3, 12)), int(rng.integers(5, 15)), int(rng.integers(5, 15))) for _ in range(12)]
             for t in (0.3, 0.6, 0.9)}
    noisy[0.9] = [(tp + (k < 3), fp, fn - (k < 3)) for k, (tp, fp, fn) in enumerate(noisy[0.6])]  # 3 more hits
    noisy[0.3] = [(tp // 3, fp * 3, fn * 2) for tp, fp, fn in noisy[0.6]]  # much worse
    pick = select_threshold(_sweep(noisy))
    assert pick["best_threshold"] == 0.9 and pick["threshold"] == 0.6
    assert pick["best_val_f1"] - pick["val_f1"] <= pick["val_f1_se"] and pick["val_f1_se"] > 0
    # the same F1 gap on hundreds of consistent items is no longer noise -> the best threshold
    steady = {0.6: [(4, 6, 6)] * 400, 0.9: [(5, 6, 5)] * 400}
    pick = select_threshold(_sweep(steady))
    assert pick["threshold"] == pick["best_threshold"] == 0.9 and pick["val_f1_se"] == pytest.approx(0.0)
    # one item: no spread to estimate -> the best (ties: the lower threshold); deterministic
    assert select_threshold(_sweep({0.3: [(1, 2, 2)], 0.6: [(2, 2, 1)], 0.9: [(1, 0, 2)]}))["threshold"] == 0.6
    assert select_threshold(_sweep({0.3: [(2, 2, 2)], 0.6: [(2, 2, 2)]}))["threshold"] == 0.3
    assert select_threshold(_sweep(noisy), seed=3) == select_threshold(_sweep(noisy), seed=3)


def test_hidden_target_point_is_the_most_precise_threshold_reaching_the_target_on_validation():
    def rows(pairs):  # threshold -> (F1, hidden-but-seen recall)
        return [{"threshold": t, "f1": f, "hidden_seen_recall": h} for t, (f, h) in pairs.items()]
    val = rows({0.1: (0.30, 0.62), 0.45: (0.36, 0.51), 0.75: (0.40, 0.49), 0.9: (0.38, 0.20)})
    test = rows({0.1: (0.31, 0.58), 0.45: (0.37, 0.47), 0.75: (0.41, 0.44), 0.9: (0.39, 0.25)})
    point = hidden_target_point(val, test, target=0.5)
    # 0.45 is the highest threshold with validation recall >= 0.5; test's own figures there, not test's choice
    assert point.threshold == 0.45 and point.target == 0.5
    assert (point.val_f1, point.val_hidden_recall) == (0.36, 0.51)
    assert (point.test_f1, point.test_hidden_recall) == (0.37, 0.47)
    assert point.as_json()["test_hidden_recall"] == 0.47
    assert hidden_target_point(val, test, target=0.6).threshold == 0.1
    missed = hidden_target_point(val, test, target=0.7)
    assert missed.threshold is None and missed.best_val_recall == 0.62 and missed.test_f1 is None
    assert missed.as_json() == {"target": 0.7, "threshold": None, "best_val_recall": 0.62}  # report.json: no figures
    # no hidden-but-seen objects on validation: nothing to choose
    assert hidden_target_point(rows({0.1: (0.3, None)}), rows({0.1: (0.3, None)}), 0.5).best_val_recall is None


def test_per_view_counts_add_up_to_the_totals():
    acc = MetricAccumulator([0.5])
    box = np.array([[0.0, 0.0, 10.0, 10.0]])
    far = np.array([[50.0, 50.0, 60.0, 60.0]])
    gt = ViewGroundTruth(box, np.array([0]), np.array([1.0]), np.array([False]))
    acc.add(ViewDetections(box, np.array([0.9]), np.array([0])), gt)  # TP
    acc.add(ViewDetections(far, np.array([0.9]), np.array([0])), gt)  # FP + FN
    acc.add(ViewDetections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64)), gt)  # FN
    per_view = acc.per_view_counts(0.5)
    assert per_view.tolist() == [[1, 0, 0], [0, 1, 1], [0, 0, 1]]
    c = acc.counts(0.5)
    assert (c["tp"], c["fp"], c["fn"]) == tuple(per_view.sum(axis=0))


def test_a_rows_figures_are_its_metrics_typed():
    """``Result.figures``: what the report reads of a row, the same numbers as its report.json entry."""
    from pnyolo.bench.record import Figures, Result, Share
    from pnyolo.evaluation.evaluate import Entry
    from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE

    acc = MetricAccumulator([0.2, 0.5])
    boxes = np.array([[0.0, 0.0, 10.0, 10.0], [20.0, 20.0, 30.0, 30.0], [40.0, 0.0, 50.0, 10.0]])
    gt = ViewGroundTruth(boxes, np.array([0, 0, 1]), np.array([1.0, 0.0, 0.0]), np.array([False, True, False]),
                         distances=np.array([10.0, 20.0, 30.0]))
    acc.add(ViewDetections(boxes[:2], np.array([0.9, 0.8]), np.array([0, 0]), np.array([11.0, 20.5])), gt)
    metrics = acc.summary() | {"bytes_per_car_frame": 80.0}
    figures = Result(Entry("m"), metrics).figures
    assert figures == Figures.of(metrics)
    assert figures.f1 == {"0.2": metrics["strict"]["0.2"]["f1"], "0.5": metrics["strict"]["0.5"]["f1"]}
    hidden = metrics["recall_by_visibility"]["0.2"][HIDDEN_SEEN_ELSEWHERE]
    assert figures.recall("0.2") == Share(hidden["recall"], hidden["n"]) == Share(1.0, 1)  # the hidden one, found
    assert figures.recall("0.2", "no such group") == Share(None, 0)
    assert figures.distance_error_m == pytest.approx(0.75) and figures.bytes_per_car_frame == 80.0
    ceiling = metrics["single_view_ceiling"]
    assert (figures.view_ceiling.recall_ceiling, figures.view_ceiling.n, figures.view_ceiling.fully_hidden) == (
        ceiling["recall_ceiling"], ceiling["n"], ceiling["fully_hidden"]) == (pytest.approx(1 / 3), 3, 2)
    assert figures.within_1m is None  # no world boxes: no ground-plane figures


def test_threshold_sweep_counts_per_scenario_over_its_lightings(tmp_path):
    """The bootstrap unit is the scenario: its lighting variants' counts are summed, and the
    per-scenario counts add up to the sweep's totals."""
    from pnyolo.bench.selection import threshold_sweep
    from pnyolo.engine.predict import Condition, predict
    from pnyolo.config import load_config
    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.models import build_model
    from test_pnyolo_common import TINY, make_dataset

    root = make_dataset(tmp_path / "ds", n_scenarios=2)
    cfg = load_config(None, TINY)
    ds = MultiViewDataset(root, "test", cfg, training=False, views=[0, 1, 2], scenarios=["toy_01", "toy_02"])
    items = [ds[k] for k in range(len(ds))]
    assert len(items) == 4 and len({i.scenario for i in items}) == 2  # 2 scenarios x 2 lightings
    model = build_model(cfg, len(ds.class_names))
    rows = threshold_sweep(predict(model, ds, cfg.eval), cfg.eval, (0.0, 1.01))
    for row in rows:
        counts = np.asarray(row["layout_counts"])
        assert counts.shape == (2, 3)
        tp, fp, fn = counts.sum(axis=0)
        assert row["recall"] == pytest.approx(tp / max(tp + fn, 1)) and row["f1"] == pytest.approx(
            2 * tp / max(2 * tp + fp + fn, 1))
    # above every confidence nothing is detected: each scenario misses all its objects, in both lightings
    gt_per_scenario = {}
    for i in items:
        gt_per_scenario[i.scenario] = gt_per_scenario.get(i.scenario, 0) + sum(len(g.classes) for g in i.gt)
    assert rows[1]["layout_counts"] == [[0, 0, n] for n in gt_per_scenario.values()]
    assert sum(c[1] for c in rows[0]["layout_counts"]) > 0  # at confidence 0 everything is a detection
    # the selection predicts each item once at the most depth peaks and decodes every setting from those outputs
    assert threshold_sweep(predict(model, ds, cfg.eval, Condition(peaks=3)), cfg.eval, (0.0, 1.01)) == rows


def test_the_time_budget_counts_reused_training_at_the_time_it_took():
    from pnyolo.bench.targets import cached_time as _cached_time

    timings = {"render (blender-gen)": 30.0, "labels (project-labels)": 3.0, "total": 999.0,
               f"train {MULTI}": {"reused": True, "trained_seconds": 1400.0}, f"train {SINGLE}": 600.0,
               "evaluate (every model, fusion, ablations)": 200.0}
    assert _cached_time(timings) == pytest.approx(2203.0)  # rendering and the total left out
    timings[f"train {SINGLE}"] = {"reused": True, "trained_seconds": None}  # no record of it
    assert _cached_time(timings) is None


def test_hidden_but_seen_recall_is_stated_against_the_single_views_on_the_same_objects_or_not_at_all():
    """Issue 76: chance is the single view's recall on the same objects, its margin with a paired bootstrap standard
    error; without a single view scored no chance is named (a floor from other data is not this data's)."""
    from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE
    from pnyolo.evaluation.report import against_chance, chance_markdown

    def summary(found: list[int], n: list[int]):
        per = {f"s{k}": {"counts": {}, "hidden_seen": {"0.2": [f, m]}} for k, (f, m) in enumerate(zip(found, n))}
        return {"recall_by_visibility": {"0.2": {HIDDEN_SEEN_ELSEWHERE: {"recall": sum(found) / sum(n), "n": sum(n)}}},
                "per_scenario": per, "standard_errors": {"scenarios": len(n)}}

    rows = {"single-view": summary([3, 3, 6], [10, 10, 20]), "bev": summary([5, 4, 9], [10, 10, 20]),
            "pixelnerf-yolo": summary([3, 4, 6], [10, 10, 20])}
    got = against_chance(rows, "0.2", "single-view")
    assert set(got) == {"bev", "pixelnerf-yolo"}  # the single view is the chance level, not a row
    assert got["bev"]["chance"] == 0.30 and got["bev"]["above"] == pytest.approx(0.15)
    assert got["pixelnerf-yolo"]["above"] == pytest.approx(0.025)
    assert 0 < got["bev"]["above_se"] < 0.15 and got["bev"]["chance_source"] == "single-view on the same objects"
    assert "| bev | 0.450 (40) | 0.300 | +0.150 ± " in chance_markdown(rows, "0.2", "single-view")
    assert against_chance({"bev": rows["bev"]}, "0.2", None) == {}  # no single view scored: no chance at all
    assert chance_markdown({"bev": rows["bev"]}, "0.2", None) == ""
    one = {"single-view": summary([3], [10]), "bev": summary([5], [10])}  # one scene: its standard error says so
    assert "+0.200 n/a (one layout)" in chance_markdown(one, "0.2", "single-view")
