"""Spec 1.2 sequences: frames.json read and written, the validator's rules for time, tracks, speeds and the
rig, per-frame view files, and a dataset of one frame (1.1) unchanged."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from dataset_spec import Dataset
from dataset_spec.errors import SpecError
from dataset_spec.layout import frame_name
from dataset_spec.sequence import Sequence, velocities
from dataset_spec.synthetic import SYNTHETIC_VELOCITIES, write_synthetic_dataset
from dataset_spec.validate import validate


@pytest.fixture(scope="module")
def sequence_dataset(tmp_path_factory):
    """Two synthetic scenarios as 4-frame sequences at 2 fps (64x48), labelled."""
    from tools.projection import label_dataset

    root = write_synthetic_dataset(tmp_path_factory.mktemp("seq") / "ds", n_scenarios=2, frames=4, fps=2.0)
    label_dataset(root, progress=False)
    return root


def _errors(problems) -> list:
    return [p for p in problems if p.severity == "error"]


def _copy(root, tmp_path):
    return shutil.copytree(root, tmp_path / "ds")


def test_a_sequence_reads_back_with_its_tracks_times_and_velocities(sequence_dataset):
    ds = Dataset.open(sequence_dataset)
    scn = ds.scenario("toy_01")
    seq = ds.sequence("toy_01")
    assert (scn.frames, scn.fps, ds.frames("toy_01")) == (4, 2.0, [0, 1, 2, 3])
    assert [f.time_s for f in seq.frames] == [0.0, 0.5, 1.0, 1.5] and seq.seconds == 1.5
    road = sorted(a.id for a in scn.actors if a.cls in ("car", "pedestrian"))
    assert seq.tracks == road and all(sorted(f.actors) == road for f in seq.frames)
    car = next(a for a in scn.actors if a.name == "car_a")
    centres = np.array([f.actors[car.id].center for f in seq.frames])
    # the velocity is the displacement over the frame interval
    np.testing.assert_allclose(np.diff(centres, axis=0) * seq.fps, [f.actors[car.id].velocity for f in seq.frames[:-1]])
    np.testing.assert_allclose(seq.frames[2].actors[car.id].velocity, SYNTHETIC_VELOCITIES["car_a"])
    np.testing.assert_allclose(velocities(centres, 2.0), [f.actors[car.id].velocity for f in seq.frames])
    # a frame's scenario moves the road users; the mesh moves with its box
    at2 = ds.scenario_at("toy_01", 2)
    np.testing.assert_allclose(at2.actor(car.id).box.center, centres[2])
    v0, _ = ds.read_mesh("toy_01", car.id)
    v2, _ = ds.read_mesh("toy_01", car.id, frame=2)
    np.testing.assert_allclose(v2 - v0, np.broadcast_to(centres[2] - centres[0], v0.shape), atol=1e-9)


def test_frame_zero_lies_where_a_one_frame_scenario_s_files_lie(sequence_dataset):
    lay = Dataset.open(sequence_dataset).layout
    assert lay.rgb("toy_01", "cam_0", "noon", 0) == lay.rgb("toy_01", "cam_0", "noon")
    assert lay.rgb("toy_01", "cam_0", "noon", 3).parent.parent == lay.view_dir("toy_01", "cam_0") / "frames" / "0003"
    for frame in range(4):
        labels = Dataset.open(sequence_dataset).read_labels("toy_01", "cam_1", frame)
        assert labels.frame == frame
    with pytest.raises(ValueError):
        frame_name(-1)


def test_labels_follow_the_road_users_from_frame_to_frame(sequence_dataset):
    ds = Dataset.open(sequence_dataset)
    walker = next(a.id for a in ds.scenario("toy_01").actors if a.name == "ped_a")
    boxes = []
    for frame in ds.frames("toy_01"):
        found = [o.box for o in ds.read_labels("toy_01", "cam_0", frame).objects if o.instance_id == walker]
        boxes.append(found[0] if found else None)
    moved = [b for b in boxes if b is not None]
    assert len(moved) >= 2 and not np.allclose(moved[0], moved[-1])


def test_the_sequence_validates_and_each_broken_rule_is_named(sequence_dataset, tmp_path):
    assert not _errors(validate(sequence_dataset))
    root = _copy(sequence_dataset, tmp_path)
    path = root / "scenarios" / "toy_01" / "frames.json"
    good = json.loads(path.read_text())

    def problems(doc) -> str:
        path.write_text(json.dumps(doc))
        return " | ".join(str(e) for e in _errors(validate(root, check_images=False)))

    doc = json.loads(json.dumps(good))
    doc["frames"][2]["time_s"] = doc["frames"][1]["time_s"]
    assert "does not increase" in problems(doc)
    doc = json.loads(json.dumps(good))
    doc["frames"][3]["actors"] = doc["frames"][3]["actors"][1:]
    assert "track ids differ" in problems(doc)
    doc = json.loads(json.dumps(good))
    doc["frames"][3]["actors"][0]["center"][0] += 40.0  # 40 m in half a second
    assert "faster than" in problems(doc)
    doc = json.loads(json.dumps(good))
    doc["frames"][1]["cameras"][0]["camera_to_world"][0][3] += 2.0  # a camera on no car moves
    assert "mounted on no car" in problems(doc)
    doc = json.loads(json.dumps(good))
    doc["frames"] = doc["frames"][:3]
    assert "holds 3 frames" in problems(doc)
    doc = json.loads(json.dumps(good))
    doc["fps"] = 2 * good["fps"]  # scenario.json says otherwise
    assert f"fps {2 * good['fps']:g} contradicts scenario.json's {good['fps']:g}" in problems(doc)
    path.write_text(json.dumps(good))
    (root / "scenarios" / "toy_01" / "views" / "cam_2" / "frames" / "0002" / "instance.png").unlink()
    assert any("instance.png" in str(e) for e in _errors(validate(root)))


def test_a_frames_json_that_is_not_a_sequence_is_a_one_line_spec_error(tmp_path):
    with pytest.raises(SpecError, match="fps"):
        Sequence.from_dict({"spec_version": "1.2", "fps": 0, "frames": []}, tmp_path / "frames.json")
    with pytest.raises(SpecError, match="index"):
        Sequence.from_dict({"spec_version": "1.2", "fps": 2.0, "frames": [
            {"index": 1, "time_s": 0.0, "actors": [], "cameras": []}]}, tmp_path / "frames.json")


def test_a_one_frame_dataset_is_written_as_before_and_reads_as_a_sequence_of_one(synthetic_dataset):
    ds = Dataset.open(synthetic_dataset)
    name = ds.scenario_names()[0]
    assert not ds.layout.frames_json(name).exists()
    assert "sequence" not in json.loads(ds.layout.scenario_json(name).read_text())
    seq = ds.sequence(name)
    assert len(seq.frames) == 1 and ds.frames(name) == [0]
    assert all(not s.velocity.any() for s in seq.frames[0].actors.values())
    assert ds.scenario_at(name, 0) is ds.scenario(name)


def test_a_1_1_dataset_still_validates(synthetic_dataset, tmp_path):
    root = _copy(synthetic_dataset, tmp_path)
    for path in root.rglob("*.json"):
        doc = json.loads(path.read_text())
        if isinstance(doc, dict) and doc.get("spec_version") == "1.2":
            doc["spec_version"] = "1.1"
            path.write_text(json.dumps(doc))
    assert not _errors(validate(root)), _errors(validate(root))[:3]
    assert Dataset.open(root).scenario(Dataset.open(root).scenario_names()[0]).frames == 1
