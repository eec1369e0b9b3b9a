"""The toy scene rendered as a 3-frame sequence at tiny resolution: ids persist, velocities are the
displacement over time, the renders show the walker where frames.json puts it, labels per frame, a
killed render resumes at the missing frames, and the sequence options' bad input is one line."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from dataset_spec import Dataset
from dataset_spec.camera import project_points
from dataset_spec.validate import validate
from repo_paths import REPO

pytestmark = pytest.mark.blender
ROOT = REPO
ARGS = ["--scene", "toy", "--hdr", "noon", "--resolution", "96x64", "--samples", "1", "--frames", "3", "--fps", "2"]


def _cli(args):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "blender_tools.cli", *args], env=env, capture_output=True, text=True)


@pytest.fixture(scope="module")
def toy_sequence(tmp_path_factory):
    pytest.importorskip("bpy")
    from blender_tools.cli import main

    root = tmp_path_factory.mktemp("toyseq") / "ds"
    assert main(["render", *ARGS, "--out", str(root), "--no-progress"]) == 0
    return root


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_the_toy_sequence_keeps_its_ids_and_moves_its_walker_at_its_velocity(toy_sequence):
    assert [p for p in validate(toy_sequence) if p.severity == "error"] == []
    ds = Dataset.open(toy_sequence)
    scn, seq = ds.scenario("toy"), ds.sequence("toy")
    assert (scn.frames, scn.fps, len(seq.frames)) == (3, 2.0, 3)
    walker = next(a for a in scn.actors if a.name == "ped_open")
    track = np.array([f.actors[walker.id].center for f in seq.frames])
    step = np.diff(track, axis=0)
    assert np.linalg.norm(step[0, :2]) > 0.3  # it walks (1.0-1.6 m/s for 0.5 s)
    np.testing.assert_allclose(step * seq.fps, [seq.frames[k].actors[walker.id].velocity for k in range(2)], atol=1e-9)
    parked = next(a for a in scn.actors if a.name == "van")
    assert np.allclose([f.actors[parked.id].center for f in seq.frames], parked.box.center)
    for frame in range(3):  # the walker's segment in the render is where frames.json puts its box
        now = ds.scenario_at("toy", frame)
        for cam in now.cameras:
            inst = ds.read_instance("toy", cam.name, frame)
            ys, xs = np.nonzero(inst == walker.id)
            if len(xs) < 5:
                continue
            uv, _ = project_points(cam.K, cam.camera_to_world, now.actor(walker.id).box.center[None])
            u, v = uv[0]
            assert abs(np.median(xs) - u) < 6 and abs(np.median(ys) - v) < 10, (frame, cam.name)
            labels = {o.instance_id for o in ds.read_labels("toy", cam.name, frame).objects}
            assert walker.id in labels and labels <= {a.id for a in scn.actors}


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_a_killed_sequence_render_resumes_at_the_missing_frames(tmp_path):
    out = tmp_path / "ds"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "blender_tools.cli", "render", *ARGS, "--out", str(out),
                             "--no-progress"], env=env, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    lay = Dataset(out, None).layout
    deadline = time.time() + 180
    while time.time() < deadline and not lay.rgb("toy", "cam_a", "noon", 1).exists():
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert lay.rgb("toy", "cam_a", "noon", 1).exists() and not lay.rgb("toy", "cam_b", "noon", 2).exists()
    kept = lay.rgb("toy", "cam_a", "noon", 0).stat().st_mtime_ns
    res = _cli(["render", *ARGS, "--out", str(out), "--no-progress"])
    assert res.returncode == 0, res.stderr
    assert lay.rgb("toy", "cam_a", "noon", 0).stat().st_mtime_ns == kept  # frame 0 was not rendered again
    ds = Dataset.open(out)
    assert all(ds.view_is_complete("toy", c.name, ["noon"], f) for f in range(3) for c in ds.scenario("toy").cameras)
    assert [p for p in validate(out) if p.severity == "error"] == []


@pytest.mark.parametrize("args, words", [
    (["--frames", "0"], "--frames must be 1.."),
    (["--frames", "3", "--fps", "0"], "--fps must be a number > 0"),
    (["--moving-cameras", "1"], "--moving-cameras goes with --frames"),
    (["--frames", "3", "--moving-cameras", "5"], "toy has 2 camera cars"),
])
def test_bad_sequence_options_are_one_line_errors(tmp_path, args, words):
    res = _cli(["render", "--scene", "toy", "--hdr", "noon", *args, "--out", str(tmp_path / "o")])
    lines = res.stderr.strip().splitlines()
    assert res.returncode != 0 and len(lines) == 1 and words in lines[0], res.stderr
    assert not (tmp_path / "o").exists()


def test_rendering_another_frame_count_into_a_sequence_needs_force(toy_sequence):
    res = _cli(["render", "--scene", "toy", "--hdr", "noon", "--out", str(toy_sequence)])
    assert res.returncode != 0 and "holds 3 frames at 2 fps" in res.stderr and "--force" in res.stderr
