"""blender-gen render --ray: a local Ray cluster renders the toy scene like local workers do,
retries a task whose process dies, and a killed driver resumes without losing or redoing files."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dataset_spec import Dataset
from dataset_spec.validate import validate
from repo_paths import REPO

pytest.importorskip("bpy")
pytest.importorskip("ray")

ROOT = REPO
VARIANTS = ["noon", "dusk"]


def _cli(args: list[str], **env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "blender_tools.cli", *map(str, args)], capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(ROOT), **env}, timeout=900)


def _view_files(root: Path, scenario: str) -> list[Path]:
    ds = Dataset.open(root)
    lay = ds.layout
    return [p for cam in ds.scenario(scenario).cameras
            for p in (lay.depth(scenario, cam.name), lay.instance(scenario, cam.name),
                      *(lay.rgb(scenario, cam.name, v) for v in VARIANTS))]


def _assert_same_render(a: Path, b: Path, scenario: str) -> None:
    da, db = Dataset.open(a), Dataset.open(b)
    sa, sb = da.scenario(scenario), db.scenario(scenario)
    assert [c.name for c in sa.cameras] == [c.name for c in sb.cameras]
    assert [x.id for x in sa.actors] == [x.id for x in sb.actors]
    assert [v.name for v in sa.lighting] == [v.name for v in sb.lighting]
    for cam in sa.cameras:
        assert np.array_equal(da.read_depth(scenario, cam.name), db.read_depth(scenario, cam.name))
        assert np.array_equal(da.read_instance(scenario, cam.name), db.read_instance(scenario, cam.name))
        for v in VARIANTS:  # Cycles with a different thread count: equal up to sampling noise
            ra = da.read_rgb(scenario, cam.name, v).astype(np.float32)
            rb = db.read_rgb(scenario, cam.name, v).astype(np.float32)
            assert ra.shape == rb.shape and np.abs(ra - rb).mean() < 2.0, (cam.name, v)


@pytest.mark.parametrize("shared", [False, True], ids=["object-store", "shared-out"])
@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_ray_render_equals_a_local_worker_render(blender_toy_dataset, tmp_path, shared):
    from conftest import BLENDER_TOY_ARGS

    out = tmp_path / "ds"
    res = _cli(["render", *BLENDER_TOY_ARGS, "--out", out, "--ray", "local", "--no-progress",
                *(["--shared-out"] if shared else [])])
    assert res.returncode == 0, res.stderr
    assert "ray: 1 units, 0 retries, 6 files" in res.stdout
    assert list(validate(out)) == []
    _assert_same_render(blender_toy_dataset, out, "toy")
    assert Dataset.open(out).info.splits["train"] == ["toy"]
    assert "occlusion" in Dataset.open(out).scenario("toy").extras


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_a_task_whose_process_dies_is_retried(tmp_path):
    from conftest import BLENDER_TOY_ARGS

    out = tmp_path / "ds"
    res = _cli(["render", *BLENDER_TOY_ARGS, "--out", out, "--ray", "local", "--no-progress"],
               BLENDER_TOOLS_FAIL_ONCE=str(tmp_path / "markers"))
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "markers" / "toy.failed").is_file(), "the first attempt did die"
    assert "ray: 1 units, 1 retries, 6 files" in res.stdout
    assert list(validate(out)) == []


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_a_killed_driver_resumes_with_nothing_lost_or_rendered_twice(tmp_path):
    out = tmp_path / "ds"
    args = ["render", "--scene", "toy,toy-s1", "--hdr", ",".join(VARIANTS), "--resolution", "96x64", "--samples", "4",
            "--out", out, "--ray", "local", "--ray-cpus", "2", "--no-progress"]  # 2 CPUs a task: one at a time
    proc = subprocess.Popen([sys.executable, "-m", "blender_tools.cli", *map(str, args)], start_new_session=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)},
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def complete() -> list[str]:  # Ray runs the two tasks in either order
        done = []
        for scenario in ("toy", "toy-s1"):
            try:
                if Dataset.open(out).view_is_complete(scenario, "cam_b", VARIANTS) and all(
                        p.is_file() for p in _view_files(out, scenario)):
                    done.append(scenario)
            except Exception:  # noqa: BLE001 - not written yet
                pass
        return done

    deadline = time.time() + 600
    while time.time() < deadline and not complete() and proc.poll() is None:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # the driver and the Ray processes it started
    proc.wait()
    done = complete()
    assert len(done) == 1, f"killed after one scenario was complete, before the other: {done}"
    first, second = done[0], ({"toy", "toy-s1"} - set(done)).pop()
    kept = {p: p.stat().st_mtime_ns for p in _view_files(out, first)}
    res = _cli(args)
    assert res.returncode == 0, res.stderr
    assert f"{first}: 0 files rendered" in res.stdout, res.stdout
    assert f"{second}: 6 files rendered" in res.stdout, res.stdout
    assert "ray: 2 units, 0 retries, 6 files" in res.stdout
    assert {p: p.stat().st_mtime_ns for p in kept} == kept, "complete files are not rendered again"
    assert list(validate(out)) == []
    assert sorted(sum(Dataset.open(out).info.splits.values(), [])) == ["toy", "toy-s1"]
