"""The field's ground-plane evaluation: MODA / MODP / precision / recall from ``frame grid_x grid_y``
files, hand-computed cases, the Wildtrack and MultiviewX grids, and agreement with metrics_3d."""
from __future__ import annotations

import numpy as np
import pytest

from dataset_spec.cli_support import UserError
from dataset_spec.ground_grid import GRIDS
from pnyolo.evaluation.ground_moda import clear_mod, read_rows, write_rows
from pnyolo.evaluation.metrics import ViewDetections, ViewGroundTruth
from pnyolo.evaluation.metrics_3d import metrics_3d


def test_hand_computed_frames_match_the_published_definition():
    gt = [[0, 0, 0], [0, 100, 0], [1, 50, 50]]
    pred = [[0, 10, 0],     # 10 cells from (0, 0): a match, 1 - 10/20 = 0.5
            [0, 100, 20],   # exactly at the threshold: a match, closeness 0
            [0, 300, 300],  # near nothing: a false positive
            [2, 0, 0]]      # a frame without ground truth: a false positive
    s = clear_mod(np.array(gt), np.array(pred), 20)
    assert (s["tp"], s["fp"], s["fn"], s["n_gt"]) == (2, 2, 1, 3)  # frame 1's person missed
    assert s["moda"] == pytest.approx(1 - 3 / 3) and s["modp"] == pytest.approx(0.25)
    assert s["precision"] == pytest.approx(0.5) and s["recall"] == pytest.approx(2 / 3)


def test_matching_is_one_to_one_and_minimum_cost_not_greedy():
    # P1 is 15 from both people, P2 5 from A and 35 from B: nearest-first would give P1 to A and
    # leave P2 and B unmatched; the minimum-cost assignment matches both.
    s = clear_mod(np.array([[0, 0, 0], [0, 30, 0]]), np.array([[0, 15, 0], [0, -5, 0]]), 20)
    assert (s["tp"], s["fp"], s["fn"]) == (2, 0, 0)
    assert s["modp"] == pytest.approx(((1 - 15 / 20) + (1 - 5 / 20)) / 2)
    twice = clear_mod(np.array([[0, 0, 0]]), np.array([[0, 1, 0], [0, 2, 0]]), 20)  # one person, two detections
    assert (twice["tp"], twice["fp"]) == (1, 1)


def test_rows_files_round_trip_in_the_benchmarks_text_format(tmp_path):
    rows = np.array([[0, 120, 455], [0, 3, 7], [5, 479, 1439]])
    write_rows(tmp_path / "pred.txt", rows)
    assert (tmp_path / "pred.txt").read_text() == "0 120 455\n0 3 7\n5 479 1439\n"
    np.testing.assert_array_equal(read_rows(tmp_path / "pred.txt"), rows)
    (tmp_path / "gt.txt").write_text("0,120,455\n\n0 3 7 0.9\n")  # commas, a blank line, a score column
    np.testing.assert_array_equal(read_rows(tmp_path / "gt.txt"), rows[:2])
    (tmp_path / "bad.txt").write_text("0 1 2\n0 x 2\n")
    with pytest.raises(UserError, match="bad.txt:2"):
        read_rows(tmp_path / "bad.txt")
    with pytest.raises(UserError, match="does not exist"):
        read_rows(tmp_path / "none.txt")


def test_wildtrack_and_multiviewx_grids_round_trip_positions_and_metres():
    w = GRIDS["wildtrack"]
    xy = w.xy_of_position([0, 479, 480, 480 * 1440 - 1])
    np.testing.assert_array_equal(xy, [[0, 0], [479, 0], [0, 1], [479, 1439]])
    np.testing.assert_allclose(w.world_of_xy(xy), [[-3.0, -9.0], [-3.0 + 479 * 0.025, -9.0],
                                                   [-3.0, -9.0 + 0.025], [8.975, 26.975]])
    np.testing.assert_array_equal(w.xy_of_world(w.world_of_xy(xy)), xy)
    np.testing.assert_array_equal(w.position_of_xy(xy), [0, 479, 480, 480 * 1440 - 1])
    assert w.cells(0.5) == pytest.approx(20)
    m = GRIDS["multiviewx"]
    np.testing.assert_allclose(m.world_of_xy(m.xy_of_position([1000 * 3 + 40])), [[1.0, 0.075]])  # x / 40, y / 40
    with pytest.raises(UserError, match="positionID 640000 is outside the 1000 x 640"):
        m.xy_of_position([640000])


def test_the_3d_metrics_moda_agrees_with_the_fields_evaluation():
    rng = np.random.default_rng(3)
    records, gt_rows, pred_rows = [], [], []
    for frame in range(6):
        g = rng.uniform(0, 10, (4, 2))
        p = np.concatenate([g[:3] + rng.normal(0, 0.3, (3, 2)), rng.uniform(0, 10, (1, 2))])
        p[0] = g[0] + [0.5, 0.0]  # exactly at the threshold
        gt_rows += [[frame, *xy] for xy in g]
        pred_rows += [[frame, *xy] for xy in p]
        centres = lambda xy: np.concatenate([xy, np.zeros((len(xy), 1))], 1)  # noqa: E731
        records.append((ViewDetections(np.zeros((len(p), 4)), np.ones(len(p)), np.zeros(len(p), int),
                                       centres=centres(p)),
                        ViewGroundTruth(np.zeros((len(g), 4)), np.zeros(len(g), int), centres=centres(g))))
    ours = metrics_3d(records, ["pedestrian"])
    field = clear_mod(np.array(gt_rows), np.array(pred_rows), 0.5)
    assert ours["moda"] == pytest.approx(field["moda"]) and ours["modp"] == pytest.approx(field["modp"])
    assert ours["counts"] == {k: field[k] for k in ("tp", "fp", "fn")} and field["tp"] >= 6
