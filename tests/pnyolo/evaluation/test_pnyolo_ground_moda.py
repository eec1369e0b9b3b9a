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
from repo_paths import TESTS


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


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """A Wildtrack-format fixture imported as a dataset, and a MultiviewX-format one (another grid)."""
    import sys

    sys.path.insert(0, str(TESTS))
    from rig_fixtures import write_fixture

    from dataset_spec.rig_import import import_rig

    tmp = tmp_path_factory.mktemp("rows")
    write_fixture(tmp / "wt", "wildtrack", frames=tuple(range(0, 50, 5)))
    import_rig("wildtrack", tmp / "wt", tmp / "ds")
    return tmp


def _eval(imported, rows: bytes | str, capsys):
    from pnyolo.cli import eval_main

    path = imported / "pred.txt"
    path.write_bytes(rows if isinstance(rows, bytes) else rows.encode())
    rc = eval_main(["--results", str(path), str(imported / "ds"), "--out", str(imported / "eval")])
    return rc, capsys.readouterr()


@pytest.mark.parametrize("rows, says", [
    (b"\x89PNG\r\n\x1a\n\x00\xff\xfe", "not a text file"),
    ("45 10 10\n45 480 10\n", "pred.txt:2: position (480, 10) is outside the dataset's 480 x 1440"),
    ("45 10 10\n46 10 10\n", "pred.txt:2: frame 46 is not a frame of the dataset"),
    ("45 nan 10\n", "pred.txt:1: numbers must be finite"),
    ("45 10 inf\n", "pred.txt:1: numbers must be finite"),
    ("45.5 10 10\n", "pred.txt:1: frame 45.5 is not a whole number"),
])
def test_a_results_file_that_does_not_fit_the_dataset_is_refused_naming_the_line(imported, capsys, rows, says):
    rc, out = _eval(imported, rows, capsys)
    assert rc == 2 and says in out.err and len(out.err.strip().splitlines()) == 1, out.err


def test_the_gt_of_another_dataset_is_refused_and_the_own_gt_scores_perfectly(imported, capsys):
    import json

    rc, _ = _eval(imported, "45 10 10\n", capsys)  # a frame of the test split: scored
    assert rc == 0
    gt = (imported / "eval" / "gt.txt").read_text()
    rc, out = _eval(imported, gt, capsys)
    assert rc == 0 and json.loads((imported / "eval" / "metrics.json").read_text())["ground_plane"]["moda"] == 1.0
    other = "0 900 600\n1 950 630\n"  # MultiviewX frames 0, 1 on its 1000 x 640 grid
    rc, out = _eval(imported, other, capsys)
    assert rc == 2 and ("outside the dataset's 480 x 1440" in out.err or "not a frame of the dataset" in out.err)


def test_a_report_with_nothing_to_measure_says_dash_as_metrics_json_says_null():
    from pnyolo.evaluation.metrics import MetricAccumulator
    from pnyolo.evaluation.report import markdown_table

    empty = {"moda": -0.0, "modp": None, "precision": None, "recall": 0.0, "frames": 2, "threshold_m": 0.5}
    summary = {**MetricAccumulator((0.2,), 1, ["pedestrian"]).summary(), "ground_plane": empty}
    line = next(ln for ln in markdown_table(summary).splitlines() if "ground-plane evaluation" in ln)
    assert "MODP -, precision -, recall 0.0000" in line, line


def test_a_frame_outside_the_dataset_is_named_with_the_frames_it_has(tmp_path):
    from dataset_spec.cli_support import UserError
    from pnyolo.evaluation.ground_moda import frame_ranges, read_rows

    assert frame_ranges({0, 5}) == "0, 5" and frame_ranges([3, 0, 1, 2, 7]) == "0..3, 7"
    assert frame_ranges(range(0, 30, 2)).endswith(", ...")
    rows = tmp_path / "rows.txt"
    rows.write_text("3 1 1\n")
    with pytest.raises(UserError, match=r"frame 3 is not a frame of the dataset \(its frames: 0, 5\)"):
        read_rows(rows, frames={0, 5})
