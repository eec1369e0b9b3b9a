"""A preset's targets on the 3D state and the tracks (issues 87, 88): names checked when the preset loads, each
figure read where the test stage put it, "at most" for the devkit's errors, and a figure with a standard error
passing only beyond it."""
from __future__ import annotations

from pathlib import Path

import pytest

from dataset_spec.cli_support import UserError
from pnyolo.bench.presets import load_preset, preset_from_dict
from pnyolo.bench.state_targets import check_state_targets, figure, state_lines

METRICS = {"devkit_detection_eval": {"car_pedestrian": {
    "nds": 0.42, "map": 0.3, "errors": {"trans_err": 0.5, "scale_err": 0.2, "orient_err": 0.4, "vel_err": 0.9,
                                        "attr_err": 0.2},
    "ap": {"car": {0.5: 0.36, 1.0: 0.5}, "pedestrian": {"0.5": 0.1, "1.0": 0.26}}}},
    "3d": {"moda": 0.25, "per_view": {"ap": {"1": {"mean": 0.45}}}}}
TRACKS = {"mota": 0.35, "idf1": 0.55, "standard_errors": {"mota": 0.08, "idf1": 0.02, "layouts": 3},
          "devkit_tracking_eval": {"amota": 0.1, "car_pedestrian": {"amota": 0.31}}}


def test_each_figure_is_read_where_the_test_stage_puts_it():
    assert figure("car_ap_0.5", METRICS, None)[0] == 0.36 and figure("pedestrian_ap_1", METRICS, None)[0] == 0.26
    assert figure("mate", METRICS, None)[0] == 0.5 and figure("ground_ap_1", METRICS, None)[0] == 0.45
    assert figure("amota", METRICS, TRACKS)[0] == 0.31  # over car and pedestrian, not the four-class 0.1
    assert figure("mota", METRICS, TRACKS) == (0.35, 0.08, 3)
    assert figure("amota", METRICS, None)[0] is None and figure("nds", {}, None)[0] is None


def test_lines_judge_at_least_at_most_and_beyond_one_standard_error():
    lines = state_lines("bev", METRICS, TRACKS, {"nds": 0.40, "mate": 0.45, "mave": 0.8, "maae": 0.3, "mota": 0.3,
                                                 "idf1": 0.5, "car_ap_0.5": 0.35, "amota": 0.3})
    got = {k.split(": ", 1)[1]: v[0] for k, v in lines.items()}
    assert got == {"DetectionEval NDS (car, pedestrian) >= 0.4": True, "DetectionEval mATE, m (car, pedestrian) <= 0.45": False,
                   "DetectionEval mAVE, m/s (car, pedestrian) <= 0.8": False,
                   "DetectionEval mAAE (car, pedestrian) <= 0.3": True,
                   "MOTA of its tracks >= 0.3": False,  # 0.35 is within one standard error (0.08) of 0.3
                   "IDF1 of its tracks >= 0.5": True, "DetectionEval car AP within 0.5 m >= 0.35": True,
                   "TrackingEval AMOTA (car, pedestrian) >= 0.3": True}
    assert lines["bev: MOTA of its tracks >= 0.3"][1] == "0.350 ± 0.080 (target >= 0.3)"
    assert "no standard error" in lines["bev: DetectionEval NDS (car, pedestrian) >= 0.4"][1]
    unmeasured = state_lines("bev", {}, None, {"nds": 0.4})
    assert unmeasured == {"bev: DetectionEval NDS (car, pedestrian) >= 0.4": (None, "n/a (not measured)")}


@pytest.mark.parametrize("value, match", [({"ndss": 0.4}, "unknown figure"), ({"bus_ap_1": 0.4}, "unknown figure"),
                                          ({"car_ap_3": 0.4}, "unknown figure"), ({"nds": "high"}, "a number"),
                                          ({"nds": float("nan")}, "a number"), ([0.4], "a mapping")])
def test_a_preset_s_state_targets_are_checked_in_one_line(value, match):
    with pytest.raises(UserError, match=match):
        check_state_targets(value, "preset x")
    raw = {"description": "x", "splits": {"train": ["intersection_01"], "val": ["intersection_02"],
                                          "test": ["intersection_03"]}, "render": [], "models": ["bev"],
           "state_targets": value}
    with pytest.raises(UserError, match=match):
        preset_from_dict(raw, Path("configs/bench/x.yaml"))


def test_the_issue_targets_are_the_presets():
    assert load_preset("cpu_seq").state_targets == {"nds": 0.40, "car_ap_0.5": 0.35, "pedestrian_ap_1": 0.25,
                                                     "mate": 0.45, "maoe": 0.5, "mave": 0.8, "maae": 0.3,
                                                     "amota": 0.30, "mota": 0.3, "idf1": 0.5}
    assert load_preset("cpu").state_targets == {"moda": 0.2, "ground_ap_1": 0.5}
