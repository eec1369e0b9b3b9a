"""The validator catches each class of corruption, naming the offending path; readers never crash."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dataset_spec import Dataset, SpecError
from dataset_spec import images, meshes
from dataset_spec.dataset import read_json
from dataset_spec.labels2d import ViewLabels
from dataset_spec.schema import DatasetInfo, Scenario
from dataset_spec.validate import validate


@pytest.fixture
def ds_copy(synthetic_dataset, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(synthetic_dataset, root)
    return root


def _edit_json(path, fn):
    obj = json.loads(path.read_text())
    fn(obj)
    path.write_text(json.dumps(obj))


def _errors(root):
    return [p for p in validate(root) if p.severity == "error"]


def _scn(root):
    return root / "scenarios" / "toy_01" / "scenario.json"


def _view(root, cam="cam_0"):
    return root / "scenarios" / "toy_01" / "views" / cam


CORRUPTIONS = {
    "not a dataset": (lambda r: (r / "dataset.json").unlink(), "not a dataset folder"),
    "bad dataset json": (lambda r: (r / "dataset.json").write_text("{oops"), "invalid JSON"),
    "future version": (lambda r: _edit_json(r / "dataset.json", lambda o: o.update(spec_version="9.9")), "unsupported version"),
    "leaky split": (lambda r: _edit_json(r / "dataset.json", lambda o: o["splits"]["test"].append("toy_01")), "in both"),
    "split names missing scenario": (lambda r: _edit_json(r / "dataset.json", lambda o: o["splits"]["val"].append("nope")), "does not exist"),
    "missing field": (lambda r: _edit_json(_scn(r), lambda o: o["actors"][1].pop("class")), "actors[1].class: missing"),
    "unknown class": (lambda r: _edit_json(_scn(r), lambda o: o["actors"][1].update({"class": "tram"})), "unknown class"),
    "K not triangular": (lambda r: _edit_json(_scn(r), lambda o: o["cameras"][0]["K"][1].__setitem__(0, 3.0)), "upper-triangular"),
    "K wrong shape": (lambda r: _edit_json(_scn(r), lambda o: o["cameras"][0].update(K=[[1, 0], [0, 1]])), "expected shape (3, 3)"),
    "rotation not orthonormal": (lambda r: _edit_json(_scn(r), lambda o: o["cameras"][1]["camera_to_world"][0].__setitem__(0, 2.0)), "orthonormal"),
    "actor beyond the world's bound": (lambda r: _edit_json(_scn(r), lambda o: o["actors"][2]["box"].update(
        center=[5000.0, 5000.0, 0.5])), "world coordinates beyond 1000 m"),  # issue 84 item 5: sizes from coordinates
    "camera beyond the world's bound": (lambda r: _edit_json(_scn(r), lambda o: o["cameras"][1]["camera_to_world"][0]
                                                                          .__setitem__(3, -2000.0)), "beyond 1000 m"),
    "corners disagree": (lambda r: _edit_json(_scn(r), lambda o: o["actors"][2]["box"].update(yaw=1.0)), "corners"),
    "duplicate ids": (lambda r: _edit_json(_scn(r), lambda o: o["actors"][2].update(id=o["actors"][1]["id"])), "duplicate actor id"),
    "bad mounted_on": (lambda r: _edit_json(_scn(r), lambda o: o["cameras"][0].update(mounted_on=999)), "mounted_on"),
    "missing depth": (lambda r: (_view(r) / "depth.exr").unlink(), "depth.exr: file is missing"),
    "truncated depth": (lambda r: (_view(r) / "depth.exr").write_bytes((_view(r) / "depth.exr").read_bytes()[:100]), "not a readable EXR"),
    "16-bit depth": (lambda r: _half_depth(_view(r) / "depth.exr"), "float32"),
    "depth wrong shape": (lambda r: images.write_depth(_view(r) / "depth.exr", np.ones((5, 5), np.float32)), "differs from camera resolution"),
    "truncated instance": (lambda r: (_view(r) / "instance.png").write_bytes((_view(r) / "instance.png").read_bytes()[:60]), "not a readable PNG"),
    "8-bit instance": (lambda r: images._write_png(_view(r) / "instance.png", np.zeros((48, 64), np.uint8)), "16-bit"),
    "unknown instance id": (lambda r: images.write_instance(_view(r) / "instance.png", np.full((48, 64), 999, np.uint16)), "not in the actor table"),
    "missing rgb variant": (lambda r: (_view(r) / "rgb" / "dusk.png").unlink(), "dusk.png: file is missing"),
    "rgb wrong size": (lambda r: images.write_rgb(_view(r) / "rgb" / "noon.png", np.zeros((3, 3, 3), np.uint8)), "differs from camera resolution"),
    "missing view": (lambda r: shutil.rmtree(_view(r, "cam_2")), "view folder is missing"),
    "truncated mesh": (lambda r: _truncate(r / "scenarios" / "toy_01" / "meshes" / "00002.ply"), "truncated"),
    "bad labels": (lambda r: (_view(r) / "labels.json").write_text('{"spec_version": "1.0"}'), "labels.json"),
}


def _half_depth(path):
    import OpenEXR

    with OpenEXR.File({"type": OpenEXR.scanlineimage}, {"Z": np.ones((48, 64), np.float16)}) as f:
        f.write(str(path))


def _truncate(path):
    path.write_bytes(path.read_bytes()[:-7])


@pytest.mark.parametrize("name", sorted(CORRUPTIONS))
def test_validator_catches(ds_copy, name):
    corrupt, expected = CORRUPTIONS[name]
    corrupt(ds_copy)
    errors = _errors(ds_copy)
    assert errors, f"{name}: not detected"
    assert any(expected in str(p) for p in errors), f"{name}: got {[str(p) for p in errors]}"
    assert all(str(ds_copy) in str(p.path) for p in errors)  # every problem names a path in the dataset


def test_validator_warns_about_leftovers_unsplit_scenarios_and_views_without_labels(ds_copy):
    from tools.projection import label_dataset

    label_dataset(ds_copy, progress=False)
    assert validate(ds_copy) == []
    (_view(ds_copy) / ".depth.tmp-1-0.exr").write_bytes(b"partial")
    _edit_json(ds_copy / "dataset.json", lambda o: o["splits"].update(train=[]))
    (_view(ds_copy) / "labels.json").unlink()
    probs = validate(ds_copy)
    assert not [p for p in probs if p.severity == "error"]
    assert {p.severity for p in probs} == {"warning"} and len(probs) == 3
    no_labels = [p for p in probs if p.path.name == "labels.json"]
    assert len(no_labels) == 1 and f"project-labels {ds_copy}" in no_labels[0].message  # says how to make them


def test_cli_validate_exit_codes(ds_copy):
    ok = subprocess.run([sys.executable, "-m", "dataset_spec.cli", "validate", str(ds_copy)], capture_output=True, text=True)
    assert ok.returncode == 0 and "valid" in ok.stdout
    (_view(ds_copy) / "depth.exr").unlink()
    bad = subprocess.run([sys.executable, "-m", "dataset_spec.cli", "validate", str(ds_copy)], capture_output=True, text=True)
    assert bad.returncode == 1 and "depth.exr" in bad.stdout and "Traceback" not in bad.stderr
    nodir = subprocess.run([sys.executable, "-m", "dataset_spec.cli", "info", str(ds_copy / "nope")], capture_output=True, text=True)
    assert nodir.returncode == 2 and len(nodir.stderr.strip().splitlines()) == 1 and "Traceback" not in nodir.stderr


# ------------------------------------------------------------------ fuzzing the readers
_fuzz = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@_fuzz
@given(st.binary(max_size=400))
def test_image_readers_never_crash_on_garbage(tmp_path_factory, blob):
    d = tmp_path_factory.mktemp("fuzz")
    for name, reader in (("a.png", images.read_rgb), ("b.png", images.read_instance), ("c.exr", images.read_depth),
                         ("d.ply", meshes.read_mesh)):
        (d / name).write_bytes(blob)
        try:
            reader(d / name)
        except SpecError as exc:
            assert name in str(exc)


@_fuzz
@given(st.integers(min_value=0, max_value=2000), st.integers(min_value=0, max_value=255))
def test_readers_never_crash_on_truncated_or_flipped_files(synthetic_dataset, tmp_path_factory, cut, flip):
    d = tmp_path_factory.mktemp("trunc")
    view = synthetic_dataset / "scenarios" / "toy_01" / "views" / "cam_0"
    for src, reader in ((view / "depth.exr", images.read_depth), (view / "instance.png", images.read_instance),
                        (view / "rgb" / "noon.png", images.read_rgb),
                        (synthetic_dataset / "scenarios" / "toy_01" / "meshes" / "00002.ply", meshes.read_mesh)):
        data = bytearray(src.read_bytes())
        if cut < len(data):
            data[cut] ^= flip
        for blob in (bytes(data), bytes(data[: min(cut, len(data) - 1)])):
            (d / src.name).write_bytes(blob)
            try:
                reader(d / src.name)
            except SpecError:
                pass


json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=5),
                           lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
                           max_leaves=20)


@_fuzz
@given(st.data())
def test_json_records_reject_mutations_cleanly(synthetic_dataset, data):
    """Replace one field anywhere in a real record with random JSON: parsing returns or raises SpecError."""
    base = read_json(synthetic_dataset / "scenarios" / "toy_01" / "scenario.json")
    obj = json.loads(json.dumps(base))
    node = obj
    for _ in range(data.draw(st.integers(0, 5))):
        if isinstance(node, dict) and node:
            key = data.draw(st.sampled_from(sorted(node)))
        elif isinstance(node, list) and node:
            key = data.draw(st.integers(0, len(node) - 1))
        else:
            break
        if not isinstance(node[key], (dict, list)):
            break
        node = node[key]
    if isinstance(node, dict) and node:
        node[data.draw(st.sampled_from(sorted(node)))] = data.draw(json_values)
    elif isinstance(node, list) and node:
        node[data.draw(st.integers(0, len(node) - 1))] = data.draw(json_values)
    for parse in (Scenario.from_dict, DatasetInfo.from_dict, ViewLabels.from_dict):
        try:
            parse(obj, "x.json")
        except SpecError:
            pass


def test_open_reports_missing_scenario(synthetic_dataset):
    ds = Dataset.open(synthetic_dataset)
    with pytest.raises(SpecError, match="no scenario 'nope'"):
        ds.scenario("nope")
    with pytest.raises(SpecError, match="no 2D labels"):
        ds.read_labels("toy_01", "cam_0")
