"""Exports and pictures of sequences: MOTChallenge scored against itself by motmetrics (and one id swap
counted), MultiviewX with the real frames read back by ``dataset-spec import``, COCO's video fields,
one YOLO image per frame, a moving rig refused, the viewer per frame and over time, the top-down plot."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from dataset_spec import Dataset
from dataset_spec.cli import main as spec_main
from dataset_spec.synthetic import write_synthetic_dataset
from tools.projection import label_dataset
from tools.projection_cli import main as labels_main


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """Two synthetic 4-frame sequences (2 fps), labelled and exported to every format."""
    root = tmp_path_factory.mktemp("seqexp")
    ds = write_synthetic_dataset(root / "ds", n_scenarios=2, frames=4, fps=2.0)
    label_dataset(ds, progress=False)
    assert labels_main([str(ds), "--no-labelling", "--export", "yolo,coco,kitti,pixelnerf,multiviewx,mot",
                        "--out", str(root / "exp"), "--quiet"]) == 0
    return ds, root / "exp"


def _mot_folder(exp, scenario="toy_01", camera="cam_0"):
    return next((exp / "mot").glob(f"OCC-*/{scenario}__{camera}"))


def test_the_mot_export_scores_perfectly_against_itself_and_counts_an_id_swap(exported):
    mm = pytest.importorskip("motmetrics")
    _, exp = exported
    folder = _mot_folder(exp)
    info = (folder / "seqinfo.ini").read_text()
    assert "seqLength=4" in info and "frameRate=2" in info and "imExt=.png" in info
    assert sorted(p.name for p in (folder / "img1").iterdir()) == ["000001.png", "000002.png", "000003.png",
                                                                  "000004.png"]
    gt = mm.io.loadtxt(str(folder / "gt" / "gt.txt"), fmt="mot15-2D", min_confidence=1)
    assert sorted(gt.index.get_level_values("FrameId").unique()) == [1, 2, 3, 4]
    metrics = mm.metrics.create()
    same = metrics.compute(mm.utils.compare_to_groundtruth(gt, gt, "iou", distth=0.5),
                           metrics=["mota", "idf1", "num_switches"], name="self")
    assert same.loc["self", "mota"] == 1.0 and same.loc["self", "idf1"] == 1.0
    hyp = gt.reset_index()
    a, b = sorted(hyp.Id.unique())[:2]
    late = hyp.FrameId >= 3
    swap = hyp.Id.copy()
    swap[late & (hyp.Id == a)], swap[late & (hyp.Id == b)] = b, a
    hyp = hyp.assign(Id=swap).set_index(["FrameId", "Id"])
    swapped = metrics.compute(mm.utils.compare_to_groundtruth(gt, hyp, "iou", distth=0.5),
                              metrics=["mota", "idf1", "num_switches"], name="swap")
    assert swapped.loc["swap", "num_switches"] == 2 and swapped.loc["swap", "idf1"] < 1.0


def test_mot_rows_are_the_labels_of_each_frame_with_track_ids_and_mot_classes(exported):
    from tools.exporters.mot import read_mot_gt

    ds_root, exp = exported
    ds = Dataset.open(ds_root)
    rows = read_mot_gt(_mot_folder(exp) / "gt" / "gt.txt")
    for frame in ds.frames("toy_01"):
        labels = ds.read_labels("toy_01", "cam_0", frame).objects
        mine = rows[rows[:, 0] == frame + 1]
        assert sorted(mine[:, 1].astype(int)) == sorted(o.instance_id for o in labels)
        for o in labels:
            row = mine[mine[:, 1] == o.instance_id][0]
            np.testing.assert_allclose(row[2:4], np.asarray(o.box[:2]) + 1.5, atol=0.006)  # centre 0 -> [1, 2)
            assert row[7] == {"car": 3, "pedestrian": 1}[o.cls]


def test_mot_boxes_are_the_coco_export_boxes_in_one_based_pixels_box_for_box(exported):
    from tools.exporters.mot import read_mot_gt

    _, exp = exported
    compared = 0
    for doc in (json.loads(p.read_text()) for p in (exp / "coco" / "annotations").glob("*.json")):
        videos = {v["id"]: v["name"] for v in doc["videos"]}
        frames = {im["id"]: im["frame_id"] for im in doc["images"]}
        for a in doc["annotations"]:
            folder = next((exp / "mot").glob(f"OCC-*/{videos[a['video_id']]}"))
            rows = read_mot_gt(folder / "gt" / "gt.txt")
            row = rows[(rows[:, 0] == frames[a["image_id"]] + 1) & (rows[:, 1] == a["instance_id"])]
            assert len(row) == 1, a
            np.testing.assert_allclose(row[0, 2:6], np.asarray(a["bbox"]) + [1, 1, 0, 0], atol=0.006)
            assert row[0, 6] == (0 if a["iscrowd"] else 1)  # left-out road users: MOT's ignore, COCO's crowd
            compared += 1
    assert compared > 50


def test_trackeval_finds_the_export_with_its_default_layout(exported, tmp_path):
    """TrackEval's MOTChallenge reader without --SKIP_SPLIT_FOL or --SEQ_INFO: GT_FOLDER/seqmaps/OCC-<split>.txt
    names the sequences of GT_FOLDER/OCC-<split>/ (read with TrackEval itself where it is installed)."""
    _, exp = exported
    root = exp / "mot"
    for seqmap in sorted((root / "seqmaps").glob("OCC-*.txt")):
        lines = seqmap.read_text().splitlines()
        assert lines[0] == "name" and lines[1:] == sorted(p.name for p in (root / seqmap.stem).iterdir())
        for seq in lines[1:]:
            assert (root / seqmap.stem / seq / "gt" / "gt.txt").is_file()
    trackeval = pytest.importorskip("trackeval")  # numpy 2 only on the registry: installed by hand, --no-deps
    trackers = tmp_path / "trackers" / "OCC-train" / "gt_itself" / "data"  # the ground truth's pedestrians as a tracker
    trackers.mkdir(parents=True)
    for seq in (root / "OCC-train").iterdir():
        rows = [r for r in (seq / "gt" / "gt.txt").read_text().splitlines() if r.split(",")[6:8] == ["1", "1"]]
        (trackers / f"{seq.name}.txt").write_text("".join(r + "\n" for r in rows))
    data = trackeval.datasets.MotChallenge2DBox({"GT_FOLDER": str(root), "TRACKERS_FOLDER": str(tmp_path / "trackers"),
                                                 "BENCHMARK": "OCC", "SPLIT_TO_EVAL": "train", "PRINT_CONFIG": False})
    assert sorted(data.seq_list) == sorted(p.name for p in (root / "OCC-train").iterdir())
    quiet = {k: False for k in ("USE_PARALLEL", "PRINT_RESULTS", "PRINT_CONFIG", "OUTPUT_SUMMARY", "PLOT_CURVES",
                                "OUTPUT_DETAILED", "TIME_PROGRESS")}
    res, _ = trackeval.Evaluator(quiet).evaluate([data], [trackeval.metrics.CLEAR(), trackeval.metrics.Identity()])
    got = res["MotChallenge2DBox"]["gt_itself"]["COMBINED_SEQ"]["pedestrian"]
    assert got["CLEAR"]["MOTA"] == 1.0 and got["Identity"]["IDF1"] == 1.0


def test_the_multiviewx_export_has_the_real_frames_and_imports_back_in_order(exported, tmp_path):
    ds_root, exp = exported
    ds = Dataset.open(ds_root)
    folder = exp / "multiviewx" / "toy_01__noon"
    config = json.loads((folder / "config.json").read_text())
    grid = re.search(r"--grid (\d+),(\d+)", (folder / "README.md").read_text())
    nx, ny = int(grid[1]), int(grid[2])
    assert config["num_frames"] == 4 and config["num_cam"] == 3 and config["grid_shape"] == [ny, nx]
    assert config["img_shape"] == [48, 64] and config["grid_cell"] == 0.025
    assert spec_main(["import", "multiviewx", str(folder), "--out", str(tmp_path / "back"), "--grid", f"{nx},{ny}",
                      "--quiet"]) == 0
    back = Dataset.open(tmp_path / "back")
    shift = re.search(r"moved by \((\S+), (\S+)\) m", (folder / "README.md").read_text())
    move = np.array([float(shift[1]), float(shift[2])])
    names = sorted(back.scenario_names())
    assert len(names) == 4
    for frame, name in enumerate(names):  # frame_00000 ... in the sequence's order
        now = ds.scenario_at("toy_01", frame)
        people = {a.id: a.box.center[:2] for a in now.actors if a.cls == "pedestrian"}
        for a in back.scenario(name).actors:
            off = a.box.center[:2] - (people[a.extras["personID"]] + move)
            assert np.abs(off).max() <= 0.0125 + 1e-9  # within one 2.5 cm cell


def test_coco_has_its_video_fields_and_yolo_an_image_per_frame(exported):
    ds_root, exp = exported
    docs = [json.loads(p.read_text()) for p in (exp / "coco" / "annotations").glob("*.json")]
    videos = [v for d in docs for v in d["videos"]]
    assert len(videos) == 2 * 3 and all(v["fps"] == 2.0 for v in videos)  # a video per (scenario, camera)
    for d in docs:
        ids = {v["id"] for v in d["videos"]}
        assert all(im["video_id"] in ids and 0 <= im["frame_id"] < 4 for im in d["images"])
        assert all(a["video_id"] in ids for a in d["annotations"])
        by_video = {}
        for im in d["images"]:
            by_video.setdefault(im["video_id"], []).append(im["frame_id"])
        assert all(sorted(f) == [0, 1, 2, 3] for f in by_video.values())
    images = sorted(p.name for p in (exp / "yolo" / "images").rglob("*.png"))
    assert len(images) == 2 * 3 * 4 and "toy_01__cam_0__f0003.png" in images
    assert len(list((exp / "kitti").rglob("calib/*.txt"))) == 2 * 3 * 4


def test_a_one_frame_export_keeps_its_names_and_has_no_video_fields(synthetic_dataset, tmp_path):
    assert labels_main([str(synthetic_dataset), "--export", "coco,yolo", "--out", str(tmp_path / "exp"),
                        "--quiet"]) == 0
    doc = json.loads(next((tmp_path / "exp" / "coco" / "annotations").glob("*.json")).read_text())
    assert "videos" not in doc and all("frame_id" not in im for im in doc["images"])
    assert all("__f" not in p.name for p in (tmp_path / "exp" / "yolo").rglob("*.png"))


def test_a_sequence_whose_cameras_move_is_refused_by_multiviewx_before_any_work(exported, tmp_path, capsys):
    import shutil

    ds_root, _ = exported
    root = shutil.copytree(ds_root, tmp_path / "ds")
    path = root / "scenarios" / "toy_01" / "frames.json"
    doc = json.loads(path.read_text())
    doc["frames"][2]["cameras"][0]["camera_to_world"][0][3] += 1.0
    path.write_text(json.dumps(doc))
    assert labels_main([str(root), "--export", "multiviewx", "--out", str(tmp_path / "exp"), "--quiet"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "move" in err[0] and "calibration" in err[0]
    assert not (tmp_path / "exp" / "multiviewx").exists()


def test_the_viewer_shows_a_frame_and_each_camera_over_time(exported, tmp_path, capsys):
    from PIL import Image

    from tools.viewer_cli import main as viewer_main

    ds_root, _ = exported
    assert viewer_main([str(ds_root), "--scenario", "toy_01", "--frame", "2", "--no-html", "--out",
                        str(tmp_path / "v"), "--quiet"]) == 0
    files = sorted(p.name for p in (tmp_path / "v" / "toy_01").iterdir())
    assert "contact_sheet_f0002.png" in files and "cam_0_instance_side_f0002.png" in files
    gif = Image.open(tmp_path / "v" / "toy_01" / "cam_0_strip.gif")
    assert gif.n_frames == 4
    assert viewer_main([str(ds_root), "--frame", "9", "--out", str(tmp_path / "w")]) != 0
    assert "frames 0..3" in capsys.readouterr().err


def test_info_reports_frames_and_tracks_and_draws_each_sequence_from_above(exported, tmp_path, capsys):
    ds_root, _ = exported
    assert spec_main(["info", str(ds_root), "--plots", str(tmp_path / "plots")]) == 0
    out = capsys.readouterr().out
    assert "4 frames at 2 fps (1.5 s), 5 tracks" in out
    picture = tmp_path / "plots" / "trajectories_toy_01.png"
    assert picture.stat().st_size > 10_000
    stats = json.loads((tmp_path / "plots" / "statistics.json").read_text())
    assert stats["scenarios"]["toy_01"]["frames"] == 4


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_a_long_sequence_s_strip_shows_a_bounded_number_of_frames_spread_over_it(tmp_path):
    """Issue 62, item 7: a strip and its GIF once held every frame in memory (849 MB for 16 MB of files)."""
    from PIL import Image

    from tools.viewer import STRIP_FRAMES, strip_frames
    from tools.viewer_cli import main as viewer_main

    assert strip_frames(4) == [0, 1, 2, 3]
    shown = strip_frames(10_000)
    assert len(shown) == STRIP_FRAMES and shown[0] == 0 and shown[-1] == 9_999
    ds = write_synthetic_dataset(tmp_path / "ds", n_scenarios=1, frames=STRIP_FRAMES + 12, fps=10.0)
    label_dataset(ds, progress=False)
    assert viewer_main([str(ds), "--frame", "all", "--no-html", "--sheet-only", "--out", str(tmp_path / "v"),
                        "--quiet"]) == 0
    gif = Image.open(next((tmp_path / "v").rglob("*_strip.gif")))
    assert gif.n_frames == STRIP_FRAMES


def test_the_multiviewx_export_has_a_rectangles_pom_whose_boxes_hold_the_people(exported):
    """Issue 63, item 3: GMVD's varying-camera evaluation reads rectangles.pom beside config.json."""
    from tools.exporters.pom import read_pom

    _, exp = exported
    folder = exp / "multiviewx" / "toy_01__noon"
    pom = read_pom(folder / "rectangles.pom")
    config = json.loads((folder / "config.json").read_text())
    assert pom and all(set(cams) == set(range(config["num_cam"])) for cams in pom.values())  # every camera listed
    assert max(pom) < config["grid_shape"][0] * config["grid_shape"][1]
    checked = 0
    for person in json.loads((folder / "annotations_positions" / "00000.json").read_text()):
        for view in person["views"]:
            if view["xmin"] == -1:
                continue
            box = pom[person["positionID"]][view["viewNum"]]
            assert box is not None  # an annotated person's position is seen by that camera
            cx, foot = (view["xmin"] + view["xmax"]) / 2, view["ymax"]
            assert box[0] - 3 <= cx <= box[2] + 3 and abs(box[3] - foot) <= 0.25 * (foot - view["ymin"]) + 3
            checked += 1
    assert checked > 0
