"""Our renders in the MultiviewX layout and back: the toy scene exported (project-labels --export
multiviewx), imported again (dataset-spec import) with the same cameras and people within a grid
cell, and the ground-plane model trained on the import scored the field's way (MODA on the grid)."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from dataset_spec import Dataset
from dataset_spec.cli import main as spec_main
from dataset_spec.ground_grid import GroundGrid
from tools.projection_cli import main as labels_main


@pytest.fixture(scope="module")
def toy_export(tmp_path_factory):
    """The toy scene at 192x128 (2 cameras, 2 pedestrians, noon and overcast), exported and imported back."""
    pytest.importorskip("bpy")
    from blender_tools.cli import main as render_main

    root = tmp_path_factory.mktemp("mvx")
    assert render_main(["render", "--scene", "toy", "--hdr", "noon,overcast", "--resolution", "192x128", "--samples",
                        "4", "--out", str(root / "toy"), "--no-progress"]) == 0
    assert labels_main([str(root / "toy"), "--no-labelling", "--export", "multiviewx", "--out", str(root / "exp"),
                        "--quiet"]) == 0
    folder = root / "exp" / "multiviewx" / "toy"
    grid = re.search(r"--grid (\d+),(\d+)", (folder / "README.md").read_text())
    assert spec_main(["import", "multiviewx", str(folder), "--out", str(root / "back"), "--grid",
                      f"{grid[1]},{grid[2]}", "--quiet"]) == 0
    return root, folder, (int(grid[1]), int(grid[2]))


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_export_then_import_gives_back_the_cameras_and_the_people_within_a_grid_cell(toy_export):
    root, folder, (nx, ny) = toy_export
    src, back = Dataset.open(root / "toy"), Dataset.open(root / "back")
    scn = src.scenario("toy")
    shift = re.search(r"moved by \((\S+), (\S+)\) m", (folder / "README.md").read_text())
    move = np.array([float(shift[1]), float(shift[2]), 0.0])
    frames = back.scenario_names()
    assert len(frames) == 2 and back.info.absent == ["depth", "instance"]  # noon and overcast: two frames
    for name in frames:
        got = back.scenario(name)
        assert len(got.cameras) == len(scn.cameras) == 2
        for a, b in zip(scn.cameras, got.cameras):
            assert np.allclose(b.K, a.K, atol=1e-9) and (b.width, b.height) == (a.width, a.height)
            assert np.allclose(b.camera_to_world[:3, :3], a.camera_to_world[:3, :3], atol=1e-9)
            assert np.allclose(b.camera_to_world[:3, 3], a.camera_to_world[:3, 3] + move, atol=1e-9)
        people = {a.id: a.box.center for a in scn.actors if a.cls == "pedestrian"}
        assert sorted(a.extras["personID"] for a in got.actors) == sorted(people)
        for a in got.actors:
            off = a.box.center[:2] - (people[a.extras["personID"]][:2] + move[:2])
            assert np.abs(off).max() <= 0.0125 + 1e-9  # the nearest 2.5 cm cell
    # gt.txt holds every person in every frame on the stated grid; the visibility file has our labels
    rows = np.loadtxt(folder / "gt.txt").reshape(-1, 3)
    assert len(rows) == 2 * len(people) and rows[:, 1].max() < nx and rows[:, 2].max() < ny
    vis = json.loads((folder / "visibility" / "00000.json").read_text())
    labels = {c.name: {o.instance_id: o for o in src.read_labels("toy", c.name).objects} for c in scn.cameras}
    for person in vis:
        for v in person["views"]:
            lab = labels[scn.cameras[v["viewNum"]].name][person["personID"]]
            assert v["visible_fraction"] == pytest.approx(lab.visible_fraction)
    assert GroundGrid(nx, ny, 0.025).xy_of_world(np.zeros((1, 2))).tolist() == [[0, 0]]


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_the_ground_plane_model_overfits_the_import_to_the_fields_moda(toy_export, tmp_path, capsys):
    from pnyolo.cli import eval_main, train_main

    root, _, (nx, ny) = toy_export
    bounds = f"[0,0,{nx * 0.025:g},{ny * 0.025:g}]"
    assert train_main([str(root / "back"), "--config", "configs/cpu.yaml", "--model", "bev", "--set",
                       "data.num_views=2", "--set", f"model.bev.bounds={bounds}", "--set", "model.bev.cell_m=0.2",
                       "--set", "train.max_steps=200", "--set", "train.epochs=1000", "--set", "data.hflip=false",
                       "--set", "data.color_jitter=false", "--out", str(tmp_path / "bev"), "--quiet"]) == 0
    capsys.readouterr()
    assert eval_main([str(tmp_path / "bev" / "latest.pt"), str(root / "back"), "--split", "train", "--examples", "0",
                      "--out", str(tmp_path / "ev"), "--quiet"]) == 0
    metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())["ground_plane"]
    assert metrics["frames"] == 2 and metrics["n_gt"] == 4 and metrics["moda"] >= 0.8, metrics
    assert "ground plane (2 frames, 0.5 m): MODA" in capsys.readouterr().out
    assert len(np.loadtxt(tmp_path / "ev" / "gt.txt").reshape(-1, 3)) == 4  # the benchmarks' files, beside the report
    report = (tmp_path / "ev" / "metrics.md").read_text()
    assert "Visibility was not measured" in report and "ground-plane evaluation (2 frames" in report


def test_every_consumer_takes_camera_data_without_inventing_visibility(tmp_path, capsys):
    # an imported Wildtrack-format fixture: exports carry boxes (no masks, visibility null), the
    # labeller and a depth-trained model refuse in one line, the detector's items carry nan visibility
    from pnyolo.cli import train_main
    from pnyolo.config import load_config
    from pnyolo.data.dataset import MultiViewDataset
    from rig_fixtures import write_fixture

    write_fixture(tmp_path / "src", "wildtrack")
    assert spec_main(["import", "wildtrack", str(tmp_path / "src"), "--out", str(tmp_path / "ds"), "--quiet"]) == 0
    assert labels_main([str(tmp_path / "ds"), "--no-labelling", "--export", "coco,yolo,kitti", "--out",
                        str(tmp_path / "exp"), "--quiet"]) == 0
    coco = json.loads((tmp_path / "exp" / "coco" / "annotations" / "instances_train.json").read_text())
    assert coco["annotations"] and all(a["visible_fraction"] is None and "segmentation" not in a
                                       and a["area"] == pytest.approx(a["bbox"][2] * a["bbox"][3])
                                       for a in coco["annotations"])
    assert labels_main([str(tmp_path / "ds"), "--quiet"]) == 2
    assert "no instance maps to label from" in capsys.readouterr().err
    cfg = load_config("configs/cpu.yaml", ["model.kind=single-view"])
    item = MultiViewDataset(tmp_path / "ds", "train", cfg, training=False)[0]
    assert all(np.isnan(g.visible_fraction).all() and len(g.visible_fraction) for g in item.gt)
    assert train_main([str(tmp_path / "ds"), "--config", "configs/cpu.yaml", "--model", "pixelnerf-yolo", "--set",
                       "model.loss.surface_depth=0.5", "--set", "model.surface_depth=true", "--out", str(tmp_path / "r")]) == 2
    assert "has no depth maps" in capsys.readouterr().err


def test_other_tools_ground_rows_are_scored_on_the_imported_grid(tmp_path, capsys):
    # an MVDet-style prediction file: one person found exactly, one 10 cells (25 cm) off, one missed,
    # one false alarm; a row of a frame outside the split is not counted
    from pnyolo.cli import eval_main
    from rig_fixtures import write_fixture

    made = write_fixture(tmp_path / "src", "wildtrack", frames=tuple(range(0, 50, 5)))
    assert spec_main(["import", "wildtrack", str(tmp_path / "src"), "--out", str(tmp_path / "ds"), "--quiet"]) == 0
    grid = made["fmt"].grid
    people = grid.xy_of_position(made["people"][45])  # the test frame: the last 10 %
    pred = [[45, *people[0]], [45, people[1][0] + 10, people[1][1]], [45, *people[2]], [45, 5, 5], [0, *people[0]]]
    np.savetxt(tmp_path / "pred.txt", np.array(pred), fmt="%d")
    assert eval_main(["--results", str(tmp_path / "pred.txt"), str(tmp_path / "ds"), "--out", str(tmp_path / "ev")]) == 0
    g = json.loads((tmp_path / "ev" / "metrics.json").read_text())["ground_plane"]
    assert (g["tp"], g["fp"], g["fn"], g["n_gt"]) == (3, 1, 1, 4) and g["frames"] == 1
    assert g["moda"] == pytest.approx(1 - 2 / 4) and g["modp"] == pytest.approx((1 + 0.5 + 1) / 3)
    assert np.loadtxt(tmp_path / "ev" / "gt.txt").reshape(-1, 3)[:, 1:].tolist() == people.tolist()
    capsys.readouterr()
    assert eval_main(["--results", str(tmp_path / "pred.txt"), "tests", "--out", str(tmp_path / "e2")]) == 2
    # issue 84 item 6: extras.source (a dataset is a file from others) checked where it is read: one line each
    doc = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    for change, words in ((lambda s: s["grid"].pop("cell_m"), "cell_m a number of metres"),
                          (lambda s: s.update(world_from_source=[[0.0] * 4] * 4), "a rigid transform"),
                          (lambda s: s["grid"].update(nx=10 ** 9), "at most"),
                          (lambda s: s.update(frames=[1, 2]), "frames: a mapping")):
        bad = json.loads(json.dumps(doc))
        change(bad["extras"]["source"])
        (tmp_path / "ds" / "dataset.json").write_text(json.dumps(bad))
        capsys.readouterr()
        assert eval_main(["--results", str(tmp_path / "pred.txt"), str(tmp_path / "ds"), "--out",
                          str(tmp_path / "e3")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "extras.source." in err[0] and words in err[0], err


def test_cars_go_into_the_export_when_asked_each_entry_naming_its_class(toy_export, tmp_path):
    from tools.exporters import export_multiviewx

    root = toy_export[0]
    ds = Dataset.open(root / "toy")
    export_multiviewx(ds, tmp_path, classes=("pedestrian", "car"))
    entries = json.loads((tmp_path / "toy" / "annotations_positions" / "00000.json").read_text())
    want = sorted(a.cls for a in ds.scenario("toy").actors if a.cls in ("pedestrian", "car"))
    assert sorted(e["class"] for e in entries) == want and "car" in want


def test_a_rig_of_more_cameras_exports_the_first_that_mvdet_s_loaders_list(tmp_path, capsys):
    """Issue 83 item 5: MVDet's and GMVD's loaders list intr_Camera1..6 / extr_Camera1..6 and Image_subsets/C1..6,
    so a rig of more cameras (a procedural layout has up to 8) is exported as its first six by default; here the
    same rule with --multiviewx-cameras 2 on a 3-camera rig: exactly the files such a loader lists for 2 cameras,
    each entry with 2 views, the README saying which; 'all' keeps every camera; a bad count is one line."""
    from dataset_spec.synthetic import write_synthetic_dataset
    from tools.exporters.multiviewx import MVDET_CAMERAS
    from tools.projection import label_dataset

    assert MVDET_CAMERAS == 6
    ds = write_synthetic_dataset(tmp_path / "ds")
    label_dataset(ds, progress=False)
    for count, want in (("2", 2), ("all", 3), (None, 3)):  # the default (six) keeps a 3-camera rig whole
        out = tmp_path / f"exp_{count}"
        assert labels_main([str(ds), "--no-labelling", "--export", "multiviewx", "--out", str(out), "--quiet",
                            *(["--multiviewx-cameras", count] if count else [])]) == 0
        folder = out / "multiviewx" / "toy_01"
        listed = {f"calibrations/intrinsic/intr_Camera{k + 1}.xml" for k in range(want)} | \
                 {f"calibrations/extrinsic/extr_Camera{k + 1}.xml" for k in range(want)}
        written = {str(p.relative_to(folder)) for p in (folder / "calibrations").rglob("*.xml")}
        assert written == listed  # what the loader opens for `want` cameras, nothing more
        assert sorted(p.name for p in (folder / "Image_subsets").iterdir()) == [f"C{k + 1}" for k in range(want)]
        entries = json.loads(next((folder / "annotations_positions").iterdir()).read_text())
        assert entries and all(len(e["views"]) == want for e in entries)
        assert json.loads((folder / "config.json").read_text())["num_cam"] == want
        assert ("the first 2 of the rig's 3" in (folder / "README.md").read_text()) == (count == "2")
    for bad in ("0", "x", "-1"):
        assert labels_main([str(ds), "--no-labelling", "--export", "multiviewx", "--multiviewx-cameras", bad,
                            "--out", str(tmp_path / "bad")]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--multiviewx-cameras" in err[0] and not (tmp_path / "bad").exists()
