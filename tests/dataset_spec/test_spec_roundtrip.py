"""Round trips through the dataset contract: what is written is what is read."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from dataset_spec import Dataset, DatasetInfo, LabelThresholds, Label2D, Scenario, ViewLabels, make_splits
from dataset_spec import images, meshes
from dataset_spec.atomic import atomic_path, atomic_write_json
from dataset_spec.synthetic import BOX_FACES, raycast, toy_scenario, write_synthetic_dataset
from dataset_spec.validate import validate


def test_synthetic_dataset_is_valid_and_reads_back(synthetic_dataset):
    problems = validate(synthetic_dataset)  # valid; only the views' missing labels.json are warned about
    assert problems and all(p.severity == "warning" and p.path.name == "labels.json" for p in problems)
    ds = Dataset.open(synthetic_dataset)
    assert ds.scenario_names() == ["toy_01", "toy_02", "toy_03"]
    scn = ds.scenario("toy_01")
    assert Scenario.from_dict(json.loads(json.dumps(scn.to_dict()))).to_dict() == scn.to_dict()  # JSON round trip
    cam = scn.cameras[0]
    depth, inst, _ = raycast(scn, cam)
    np.testing.assert_array_equal(ds.read_instance("toy_01", cam.name), inst)
    np.testing.assert_array_equal(ds.read_depth("toy_01", cam.name), depth)
    rgb = ds.read_rgb("toy_01", cam.name, "noon")
    assert rgb.shape == (cam.height, cam.width, 3) and rgb.dtype == np.uint8
    sem = ds.read_semantic("toy_01", cam.name)
    cars = [a.id for a in scn.actors if a.cls == "car"]
    assert np.all(sem[np.isin(inst, cars)] == ds.info.class_id("car"))
    assert np.all(sem[inst == 0] == 0)


def test_image_roundtrips_exact(tmp_path):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (7, 5, 3), dtype=np.uint8)
    inst = rng.integers(0, 65536, (7, 5), dtype=np.uint16)
    depth = rng.uniform(0, 500, (7, 5)).astype(np.float32)
    images.write_rgb(tmp_path / "a.png", rgb)
    images.write_instance(tmp_path / "b.png", inst)
    images.write_depth(tmp_path / "c.exr", depth)
    np.testing.assert_array_equal(images.read_rgb(tmp_path / "a.png"), rgb)
    np.testing.assert_array_equal(images.read_instance(tmp_path / "b.png"), inst)
    np.testing.assert_array_equal(images.read_depth(tmp_path / "c.exr"), depth)  # 32-bit, lossless


def test_writers_reject_wrong_dtypes(tmp_path):
    with pytest.raises(ValueError):
        images.write_instance(tmp_path / "x.png", np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError):
        images.write_depth(tmp_path / "x.exr", np.zeros((4, 4), np.float16))
    with pytest.raises(ValueError):
        images.write_rgb(tmp_path / "x.png", np.zeros((4, 4), np.uint8))
    assert not any(tmp_path.iterdir())


def test_mesh_roundtrip_and_trimesh_reads_it(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    scn = toy_scenario()
    corners = scn.actors[1].box.corners
    meshes.write_mesh(tmp_path / "m.ply", corners, BOX_FACES)
    v, f = meshes.read_mesh(tmp_path / "m.ply")
    np.testing.assert_allclose(v, corners, atol=1e-5)
    np.testing.assert_array_equal(f, BOX_FACES)
    tm = trimesh.load(tmp_path / "m.ply", process=False)
    assert tm.is_watertight and tm.is_winding_consistent
    assert tm.volume == pytest.approx(np.prod(scn.actors[1].box.size), rel=1e-4)  # outward faces


def test_labels_roundtrip_and_thresholds_reapply():
    objs = [Label2D(2, "car", np.array([1, 2, 30, 20.0]), 1.0, 0.0, 12.0),
            Label2D(3, "pedestrian", np.array([5, 5, 9, 20.0]), 0.5, 0.6, 45.0),
            Label2D(4, "car", np.array([5, 5, 6, 6.0]), 0.1, 1.0, 5.0)]
    t = LabelThresholds(min_in_frame=0.25, min_visible=0.0, per_class={"pedestrian": {"max_distance": 40.0}})
    labels = ViewLabels("s", "c", 64, 48, t, objs)
    back = ViewLabels.from_dict(json.loads(json.dumps(labels.to_dict())))
    assert [o.instance_id for o in back.kept()] == [2]
    assert [o.instance_id for o in back.kept(LabelThresholds(min_in_frame=0.0, min_box_pixels=0))] == [2, 3, 4]
    assert [o.instance_id for o in back.kept(LabelThresholds(min_visible=0.5))] == [3]  # 4 is too small


def test_make_splits_is_by_scenario_deterministic_and_disjoint():
    names = [f"intersection_{i:02d}" for i in range(1, 13)]
    a, b = make_splits(names, seed=3), make_splits(list(reversed(names)), seed=3)
    assert a == b
    assert sorted(sum(a.values(), [])) == names
    assert all(a[s] for s in ("train", "val", "test"))


def test_dataset_create_keeps_existing_info(tmp_path):
    ds = Dataset.create(tmp_path / "d", DatasetInfo(name="first"))
    ds.set_splits({"train": ["x"], "val": [], "test": []})
    again = Dataset.create(tmp_path / "d", DatasetInfo(name="second"))
    assert again.info.name == "first" and again.info.splits["train"] == ["x"]


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.json"
    atomic_write_json(target, {"a": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert json.loads(target.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]


def test_two_scenarios_written_separately_share_one_dataset(tmp_path):
    root = write_synthetic_dataset(tmp_path / "d", n_scenarios=2, width=16, height=12)
    assert [p for p in validate(root) if p.severity == "error"] == []
    assert Dataset.open(root).info.all_split_scenarios == ["toy_01", "toy_02"] or \
        sorted(Dataset.open(root).info.all_split_scenarios) == ["toy_01", "toy_02"]


def test_stale_temporaries_of_dead_writers_are_removed_and_live_ones_kept(tmp_path):
    import subprocess
    import sys

    from dataset_spec.atomic import remove_stale_temporaries

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (tmp_path / "views").mkdir()
    stale = tmp_path / "views" / f".labels.tmp-{int(dead.stdout)}-3.json"
    live = tmp_path / f".dataset.tmp-{os.getpid()}-0.json"  # a write in progress
    for p in (stale, live, tmp_path / "dataset.json"):
        p.write_text("{}")
    assert remove_stale_temporaries(tmp_path) == 1
    assert not stale.exists() and live.exists() and (tmp_path / "dataset.json").exists()
