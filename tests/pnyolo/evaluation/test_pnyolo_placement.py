"""The placement probe (issue 87, item 1): a ground-plane error split along the nearest camera's line of sight and
across it, matched as the devkit matches its true-positive errors; and benchmarks/placement_errors.py on a dataset
whose results are its own boxes moved by a known amount."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_pnyolo_common import make_dataset

from pnyolo.evaluation.placement import decompose, duplicates, greedy_matches, placement_rows
from repo_paths import REPO

ROOT = REPO


def test_an_error_along_the_ray_is_radial_and_one_across_it_lateral():
    cams = np.array([[0.0, 0.0], [100.0, 100.0]])  # the second camera is far: the first is the nearest
    gt = np.array([[10.0, 0.0], [10.0, 0.0], [0.0, 20.0]])
    pred = np.array([[11.0, 0.0], [10.0, 1.0], [0.0, 19.5]])
    radial, lateral, distance = decompose(pred, gt, cams)
    np.testing.assert_allclose(radial, [1.0, 0.0, -0.5], atol=1e-12)  # the third placed nearer than it is
    np.testing.assert_allclose(lateral, [0.0, 1.0, 0.0], atol=1e-12)  # +y is left of a ray along +x
    np.testing.assert_allclose(distance, [10.0, 10.0, 20.0])


def test_the_nearest_camera_defines_the_ray():
    radial, lateral, _ = decompose([[5.0, 1.0]], [[5.0, 0.0]], [[0.0, 0.0], [5.0, -3.0]])
    assert radial[0] == pytest.approx(1.0) and lateral[0] == pytest.approx(0.0)  # camera 2 looks along +y at it


def test_matching_follows_the_score_and_the_radius():
    gt = np.array([[0.0, 0.0], [10.0, 0.0]])
    pred = np.array([[0.5, 0.0], [0.2, 0.0], [13.0, 0.0]])
    scores = np.array([0.9, 0.5, 0.8])
    # the best-scored takes the first ground truth though the second prediction is nearer; the third is 3 m off
    assert greedy_matches(pred, scores, gt, radius=2.0) == [(0, 0)]
    assert greedy_matches(pred, scores, gt, radius=3.0) == [(0, 0), (2, 1)]
    assert greedy_matches(pred[:0], scores[:0], gt, 2.0) == [] and greedy_matches(pred, scores, gt[:0], 2.0) == []


def test_rows_give_the_share_along_the_ray_and_its_error_over_layouts():
    radial = np.array([1.0, -1.0, 2.0, 0.0])
    lateral = np.array([0.0, 0.0, 0.0, 1.0])
    distance = np.array([5.0, 15.0, 25.0, 35.0])
    rows = {r["bin"]: r for r in placement_rows(radial, lateral, distance, np.array(["a", "a", "b", "b"]))}
    assert [rows[b]["n"] for b in ("0-10 m", "10-20 m", "20-30 m", "30+ m", "all")] == [1, 1, 1, 1, 4]
    assert rows["all"]["radial_share"] == pytest.approx(6 / 7)
    assert rows["all"]["mean_radial_m"] == pytest.approx(0.5)
    assert rows["all"]["rms_lateral_m"] == pytest.approx(0.5)
    assert rows["all"]["radial_share_se"] > 0  # two layouts with different shares (2/2 and 4/5)
    assert rows["0-10 m"]["radial_share_se"] is None  # one layout: nothing to resample


def test_duplicates_are_the_lower_scored_within_the_radius():
    xy = np.array([[0.0, 0.0], [0.5, 0.0], [3.0, 0.0], [3.2, 0.0]])
    assert duplicates(xy, np.array([0.9, 0.5, 0.4, 0.8]), radius=1.0) == 2
    assert duplicates(xy, np.array([0.9, 0.5, 0.4, 0.8]), radius=0.1) == 0


def _moved_results(ds: Path, tmp: Path, dx: float) -> Path:
    """The export's own boxes of the test split (buses and trucks as cars), every centre moved ``dx`` metres in x."""
    from nuscenes.nuscenes import NuScenes

    from dataset_spec.nuscenes_format import VERSION, detection_name
    from pnyolo.evaluation.devkit_eval import export_split, split_samples

    export = export_split(ds, "test", tmp / "exp", "all", refined=False)
    nusc = NuScenes(version=VERSION, dataroot=str(export), verbose=False)
    results = {t: [] for t in split_samples(export, "test")}
    for a in nusc.sample_annotation:
        name = detection_name(nusc.get("category", nusc.get("instance", a["instance_token"])["category_token"])["name"])
        if a["sample_token"] in results:
            results[a["sample_token"]].append({
                "sample_token": a["sample_token"], "translation": [a["translation"][0] + dx, *a["translation"][1:]],
                "size": a["size"], "rotation": a["rotation"], "velocity": [0.0, 0.0], "detection_name": name,
                "detection_score": 0.5, "attribute_name": ""})
    path = tmp / f"moved_{dx}.json"
    path.write_text(json.dumps({"meta": {"use_camera": True, "use_lidar": False}, "results": results}))
    return path


def test_the_probe_measures_a_known_displacement_on_a_dataset(tmp_path):
    pytest.importorskip("nuscenes")
    ds = make_dataset(tmp_path / "ds", n_scenarios=3, width=96, height=72)
    moved, exact = _moved_results(ds, tmp_path, 0.5), _moved_results(ds, tmp_path, 0.0)
    out = tmp_path / "probe"
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "placement_errors.py"), str(ds), "--results",
                          f"moved={moved}", "--results", f"exact={exact}", "--out", str(out)],
                         capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
    figures = json.loads((out / "placement.json").read_text())
    assert (out / "placement.png").stat().st_size > 0 and "## moved, car" in (out / "placement.md").read_text()
    for c in ("car", "pedestrian"):
        every = {m: next(r for r in figures[m][c]["rows"] if r["bin"] == "all") for m in ("moved", "exact")}
        if not figures["moved"][c]["ground_truth"]:
            continue
        assert figures["moved"][c]["matches"] == figures["moved"][c]["ground_truth"]  # each box finds its own
        assert every["moved"]["median_error_m"] == pytest.approx(0.5, abs=1e-3)
        assert np.hypot(every["moved"]["rms_radial_m"], every["moved"]["rms_lateral_m"]) == pytest.approx(0.5, abs=1e-3)
        assert every["exact"]["median_error_m"] == pytest.approx(0.0, abs=1e-3)
    assert figures["moved"]["car"]["ground_truth"] > 0


def test_the_probe_refuses_a_missing_results_file_in_one_line(tmp_path):
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "placement_errors.py"), str(tmp_path),
                          "--results", f"bev={tmp_path / 'none.json'}"], capture_output=True, text=True, timeout=120)
    assert res.returncode != 0 and res.stderr.count("\n") == 1 and "none.json" in res.stderr
