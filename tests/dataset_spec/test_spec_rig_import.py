"""Wildtrack- and MultiviewX-format folders imported as datasets: fixtures written in the formats' exact
layout (intrinsics with cv2.FileStorage, Wildtrack's plain-text extrinsics in centimetres, MultiviewX's
FileStorage extrinsics in metres, annotation JSON with -1 for "not in this view", boxes projected with
cv2.projectPoints), checked against OpenCV, the validator and the bad inputs users meet."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dataset_spec import Dataset
from dataset_spec.cli import main as spec_main
from dataset_spec.cli_support import UserError
from dataset_spec.ground_grid import GRIDS
from dataset_spec.rig_import import PERSON_HEIGHT_M, PERSON_RADIUS_M, import_rig
from dataset_spec.validate import validate
from rig_fixtures import H, K, W, write_fixture

@pytest.mark.parametrize("fmt_name, z_up", [("wildtrack", True), ("multiviewx", False)])
def test_imported_cameras_project_as_opencv_and_people_stand_where_the_grid_says(tmp_path, fmt_name, z_up):
    src = tmp_path / "src"
    made = write_fixture(src, fmt_name, z_up=z_up, frames=tuple(range(0, 50, 5)))
    summary = import_rig(fmt_name, src, tmp_path / "ds")
    assert summary["z_turned"] == (not z_up) and summary["box_error_px"] < 1e-6  # boxes are the cylinders
    assert summary["frames"] == 10 and summary["splits"] == {"train": 9, "val": 0, "test": 1}  # the datasets' 90/10
    ds = Dataset.open(tmp_path / "ds")
    assert ds.info.absent == ["depth", "instance"] and ds.split("test") == ["frame_" + "45".zfill(made["fmt"].annotation_digits)]
    turn = np.array(ds.info.extras["source"]["world_from_source"])
    assert np.allclose(turn, np.eye(4) if z_up else np.diag([1, -1, -1, 1]))
    scn = ds.scenario(ds.scenario_names()[0])
    unit = made["fmt"].metres_per_unit
    rng = np.random.default_rng(0)
    world_src = rng.uniform([-2, -2, -1], [10, 14, 2], size=(50, 3))  # metres, the source's axes
    for k, cam in enumerate(scn.cameras):
        expected = cv2.projectPoints(world_src / unit, made["rvecs"][k], made["tvecs"][k], K, np.zeros(5))[0].reshape(-1, 2)
        ours = (turn[:3, :3] @ world_src.T).T
        uv, depth = cam.project(ours)
        front = depth > 0.1
        assert front.sum() > 10 and np.abs(uv[front] - expected[front]).max() < 1e-6
    # each person: a pedestrian on its grid cell, standing up (z up here), labelled as annotated
    grid = GRIDS[fmt_name]
    positions = sorted(a.extras["positionID"] for a in scn.actors)
    assert positions == sorted(made["people"][0].tolist())
    for a in scn.actors:
        xy = grid.world_of_xy(grid.xy_of_position([a.extras["positionID"]]))[0]
        assert np.allclose(a.box.center, [xy[0], xy[1] * turn[1, 1], PERSON_HEIGHT_M / 2])
        assert a.cls == "pedestrian" and np.allclose(a.box.size, [2 * PERSON_RADIUS_M] * 2 + [PERSON_HEIGHT_M])
    raw = json.loads(sorted((src / "annotations_positions").glob("*.json"))[0].read_text())
    for k, cam in enumerate(scn.cameras):
        labels = {o.instance_id: o for o in ds.read_labels(scn.name, cam.name).objects}
        for e in raw:
            v = e["views"][k]
            if v["xmin"] == -1:
                assert e["personID"] + 1 not in labels
                continue
            o = labels[e["personID"] + 1]
            assert o.extras["annotated_box"] == [v["xmin"], v["ymin"], v["xmax"], v["ymax"]]
            assert np.allclose(o.box, np.clip([v["xmin"], v["ymin"], v["xmax"], v["ymax"]], -0.5, [W - .5, H - .5] * 2))
            assert o.visible_fraction is None and o.visible_pixels is None and 0 < o.in_frame_fraction <= 1
    errors = [p for p in validate(tmp_path / "ds") if p.severity == "error"]
    assert not errors, errors


def test_the_import_cli_reports_the_calibration_check_and_consumers_say_what_is_absent(tmp_path, capsys):
    write_fixture(tmp_path / "src", "wildtrack")
    assert spec_main(["import", "wildtrack", str(tmp_path / "src"), "--out", str(tmp_path / "ds"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "3 frames of 3 cameras" in out and "0.0 px from the annotated boxes" in out
    ds = Dataset.open(tmp_path / "ds")
    name = ds.scenario_names()[0]
    with pytest.raises(Exception, match="no depth maps"):
        ds.read_depth(name, ds.scenario(name).cameras[0].name)
    assert ds.view_is_complete(name, ds.scenario(name).cameras[0].name, ["original"])
    # a second import into the same folder is refused, the first kept
    assert spec_main(["import", "wildtrack", str(tmp_path / "src"), "--out", str(tmp_path / "ds"), "--quiet"]) == 2
    assert "not empty" in capsys.readouterr().err


def _no_camera_matrix(src: Path):
    p = next((src / "calibrations" / "intrinsic_zero").glob("*.xml"))
    p.write_text('<?xml version="1.0"?>\n<opencv_storage>\n</opencv_storage>\n')
    return p.name


def _outside_grid(src: Path):
    p = sorted((src / "annotations_positions").glob("*.json"))[1]
    entries = json.loads(p.read_text())
    entries[0]["positionID"] = 480 * 1440 + 5
    p.write_text(json.dumps(entries))
    return p.name


def _wrong_size(src: Path):
    p = sorted((src / "Image_subsets" / "C2").glob("*.png"))[2]
    cv2.imwrite(str(p), np.zeros((90, 160, 3), np.uint8))
    return p.name


def _no_calibrations(src: Path):
    import shutil

    shutil.rmtree(src / "calibrations")
    return "calibrations"


def _truncated(src: Path):  # a valid header, the rest cut: only decoding finds it
    p = sorted((src / "Image_subsets" / "C3").glob("*.png"))[2]
    p.write_bytes(p.read_bytes()[:80])
    return p.name


def _grey(src: Path):
    p = sorted((src / "Image_subsets" / "C1").glob("*.png"))[1]
    cv2.imwrite(str(p), np.zeros((H, W), np.uint8))
    return p.name


def _one_camera_resized(src: Path):  # one camera's frames at half the calibration's size
    for p in (src / "Image_subsets" / "C2").glob("*.png"):
        cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p)), (W // 2, H // 2)))
    return "C2"


def _resized(src: Path):  # every frame at half the calibration's size
    for p in (src / "Image_subsets").rglob("*.png"):
        cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p)), (W // 2, H // 2)))
    return "principal point"


@pytest.mark.parametrize("break_it, says", [(_no_calibrations, "folder is missing"),
                                            (_no_camera_matrix, "no <camera_matrix>"),
                                            (_outside_grid, "outside the 480 x 1440 ground grid"),
                                            (_wrong_size, "160x90"), (_truncated, "not a readable PNG"),
                                            (_grey, "8-bit 3-channel"), (_resized, "does not fit the camera's 160x90"),
                                            (_one_camera_resized, "needs the same image size")])
def test_bad_folders_get_one_line_naming_the_file_and_nothing_is_written(tmp_path, capsys, break_it, says):
    write_fixture(tmp_path / "src", "wildtrack")
    name = break_it(tmp_path / "src")
    assert spec_main(["import", "wildtrack", str(tmp_path / "src"), "--out", str(tmp_path / "ds"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and name in err and says in err, err
    assert not (tmp_path / "ds").exists() and not list(tmp_path.glob(".ds.tmp-*"))  # nothing written, nothing left


def test_a_failed_import_leaves_an_empty_out_folder_empty(tmp_path, capsys):
    write_fixture(tmp_path / "src", "wildtrack")
    _truncated(tmp_path / "src")
    (tmp_path / "ds").mkdir()
    assert spec_main(["import", "wildtrack", str(tmp_path / "src"), "--out", str(tmp_path / "ds"), "--quiet"]) == 2
    assert list((tmp_path / "ds").iterdir()) == []


DIST = np.array([-0.058, 0.050, 0.0004, -0.0003, 0.0])  # of the order of the real MultiviewX's Camera1


def test_a_multiviewx_folder_with_lens_distortion_and_jpeg_frames_imports_either_way(tmp_path, capsys):
    write_fixture(tmp_path / "src", "multiviewx", z_up=False, dist=DIST, suffix=".jpg")
    assert spec_main(["import", "multiviewx", str(tmp_path / "src"), "--out", str(tmp_path / "as_is"), "--quiet"]) == 0
    note = capsys.readouterr().out.splitlines()[-1]
    shift = float(note.split("up to ")[1].split(" px")[0])
    corners = np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]], np.float64)
    expected = np.linalg.norm(cv2.undistortPoints(corners[:, None], K, DIST, P=K).reshape(-1, 2) - corners, axis=1).max()
    assert note.startswith("note: lens distortion ignored") and abs(shift - expected) < 0.06, note
    ignored = import_rig("multiviewx", tmp_path / "src", tmp_path / "ignored")
    undone = import_rig("multiviewx", tmp_path / "src", tmp_path / "undistorted", distortion="undistort")
    assert undone["box_error_px"] < 0.5 * ignored["box_error_px"]  # boxes fit the cylinders again
    a, b = Dataset.open(tmp_path / "ignored"), Dataset.open(tmp_path / "undistorted")
    name = a.scenario_names()[0]
    cam_a, cam_b = a.scenario(name).cameras[0], b.scenario(name).cameras[0]
    assert np.allclose(cam_a.K, K) and not np.allclose(cam_b.K, K)
    assert cam_a.extras["distortion"] == pytest.approx(DIST.tolist())
    src = cv2.cvtColor(cv2.imread(str(sorted((tmp_path / "src" / "Image_subsets" / "C1").glob("*.jpg"))[0])),
                       cv2.COLOR_BGR2RGB)
    maps = cv2.initUndistortRectifyMap(K, DIST, None, cam_b.K, (W, H), cv2.CV_32FC1)
    assert np.array_equal(b.read_rgb(name, cam_b.name, "original"), cv2.remap(src, *maps, cv2.INTER_LINEAR))
    assert np.array_equal(a.read_rgb(name, cam_a.name, "original"), src)
    assert not [p for p in validate(tmp_path / "undistorted") if p.severity == "error"]


@pytest.mark.parametrize("grid", ["10,x", "nan,10", "10,10,inf", "10,10,0.1,nan,0"])
def test_grid_option_is_checked_before_anything_is_read(tmp_path, capsys, grid):
    assert spec_main(["import", "multiviewx", str(tmp_path / "nowhere"), "--out", str(tmp_path / "ds"),
                      "--grid", grid]) == 2
    err = capsys.readouterr().err
    assert f"--grid {grid}" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(UserError, match="no such folder"):
        import_rig("multiviewx", tmp_path / "nowhere", tmp_path / "ds")


def test_the_validator_holds_camera_data_to_what_it_declares(tmp_path):
    write_fixture(tmp_path / "src", "wildtrack")
    import_rig("wildtrack", tmp_path / "src", tmp_path / "ds")
    ds = Dataset.open(tmp_path / "ds")
    name = ds.scenario_names()[0]
    cam = ds.scenario(name).cameras[0].name
    labels = ds.read_labels(name, cam)
    labels.objects[0].visible_fraction = 0.5  # a figure nothing could have measured
    ds.write_labels(labels)
    assert any("visible fraction without instance maps" in p.message for p in validate(tmp_path / "ds"))
    info = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    info["absent"] = ["rgb"]
    (tmp_path / "ds" / "dataset.json").write_text(json.dumps(info))
    assert any("absent" in p.message for p in validate(tmp_path / "ds"))
    info["absent"], info["spec_version"] = [], "1.0"  # a 1.0 file: every map required, so these views lack them
    (tmp_path / "ds" / "dataset.json").write_text(json.dumps(info))
    assert any("depth.exr" in str(p.path) for p in validate(tmp_path / "ds"))


def _misleading_jpeg(real_wh: tuple[int, int], fake_wh: tuple[int, int]) -> bytes:
    """A JPEG whose real frame header (``real_wh``) follows a 0xFF fill byte, as libjpeg allows, and whose COM
    segment holds a fake frame header (``fake_wh``) exactly where a walk that reads the fill byte as a marker
    lands (issue 62, item 3: the check saw 320x180 while OpenCV decoded 12000x9000)."""
    ok, buf = cv2.imencode(".jpg", np.full((real_wh[1], real_wh[0], 3), 90, np.uint8))
    data = bytes(buf)
    sof = data.index(b"\xff\xc0")
    length = int.from_bytes(data[sof + 2:sof + 4], "big")
    end = sof + 2 + length
    # a walk that takes FF FF as a marker reads C0 00 as its length: it skips 0xC000 - 2 bytes after the length
    landing = sof + 4 + 0xC000 - 2  # offset (in the new file) of the fake header: the fill byte is at sof
    fake = b"\xff\xc0\x00\x11\x08" + fake_wh[1].to_bytes(2, "big") + fake_wh[0].to_bytes(2, "big") + data[sof + 9:end]
    com_start = end + 1  # after the fill byte, the real SOF, then the COM segment
    pad = landing - (com_start + 4)
    payload = bytes(pad) + fake + bytes(16)
    com = b"\xff\xfe" + (len(payload) + 2).to_bytes(2, "big") + payload
    return data[:sof] + b"\xff" + data[sof:end] + com + data[end:]


def test_a_jpeg_whose_header_would_mislead_is_sized_as_the_decoder_sizes_it(tmp_path):
    from dataset_spec.images import jpeg_size, read_rgb

    path = tmp_path / "0000.jpg"
    path.write_bytes(_misleading_jpeg((640, 360), (W, H)))
    assert cv2.imread(str(path)).shape[:2] == (360, 640)  # what OpenCV decodes
    assert jpeg_size(path) == (360, 640)  # the header walk agrees with it
    assert read_rgb(path).shape == (360, 640, 3)


def test_an_import_with_a_misleading_jpeg_is_refused_before_anything_is_written(tmp_path, capsys):
    write_fixture(tmp_path / "src", "multiviewx", suffix=".jpg")
    first = sorted((tmp_path / "src" / "Image_subsets" / "C2").glob("*.jpg"))[1]
    first.write_bytes(_misleading_jpeg((640, 360), (W, H)))  # the header check used to see W x H
    assert spec_main(["import", "multiviewx", str(tmp_path / "src"), "--out", str(tmp_path / "out"), "--quiet"]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "640x360" in err and first.name in err
    assert not (tmp_path / "out").exists()


def test_an_image_that_decodes_to_another_size_than_its_header_is_refused(tmp_path, monkeypatch):
    from dataset_spec import images
    from dataset_spec.errors import SpecError

    path = tmp_path / "a.png"
    images.write_rgb(path, np.zeros((48, 64, 3), np.uint8))
    monkeypatch.setattr(images, "image_size", lambda p: (18, 32))  # a header reader the decoder disagrees with
    with pytest.raises(SpecError, match="decodes to 64x48 while its header says 32x18"):
        images.read_rgb(path)
