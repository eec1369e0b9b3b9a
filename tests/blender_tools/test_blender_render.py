"""End-to-end: the toy scene rendered by blender-gen (session fixture), checked against geometry."""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from dataset_spec import Dataset
from dataset_spec.camera import pixel_rays, project_points
from dataset_spec.validate import validate
from repo_paths import REPO

pytestmark = pytest.mark.blender
ROOT = REPO


def _errors(root):
    return [p for p in validate(root) if p.severity == "error"]


def raycast_meshes(ds: Dataset, scn, origins, dirs, skip=()):
    """Nearest hit (distance, actor id) per ray over every actor mesh (Moller-Trumbore, numpy)."""
    best_t = np.full(len(origins), np.inf)
    best_id = np.zeros(len(origins), dtype=np.int64)
    for actor in scn.actors:
        if actor.id in skip:
            continue
        v, f = ds.read_mesh(scn.name, actor.id)
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        e1, e2 = b - a, c - a
        p = np.cross(dirs[:, None, :], e2[None])  # (R, T, 3)
        det = np.einsum("rtk,tk->rt", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = origins[:, None, :] - a[None]
            u = np.einsum("rtk,rtk->rt", s, p) * inv
            q = np.cross(s, e1[None])
            w = np.einsum("rk,rtk->rt", dirs, q) * inv
            t = np.einsum("tk,rtk->rt", e2, q) * inv
        ok = (np.abs(det) > 1e-12) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 1e-4)
        t = np.where(ok, t, np.inf).min(axis=1)
        closer = t < best_t
        best_t[closer], best_id[closer] = t[closer], actor.id
    return best_t, best_id


def test_toy_dataset_is_valid(blender_toy_dataset):
    assert _errors(blender_toy_dataset) == []


def test_actor_table_matches_model_and_segmentation(blender_toy_dataset):
    from blender_tools.scenarios import build_model

    ds = Dataset.open(blender_toy_dataset)
    scn = ds.scenario("toy")
    model = build_model("toy", 0)
    assert {(a.id, a.name, a.cls) for a in scn.actors} == {(a.id, a.name, a.cls) for a in model.actors}
    table = {a.id: a.cls for a in scn.actors}
    for cam in scn.cameras:
        ids = set(np.unique(ds.read_instance("toy", cam.name)).tolist()) - {0}
        assert ids <= set(table), "every labelled id is in the actor table"
        assert cam.mounted_on not in ids, "a camera does not see its own car"
        assert table[cam.mounted_on] == "car"
    seen = set().union(*(set(np.unique(ds.read_instance("toy", c.name)).tolist()) for c in scn.cameras))
    assert {"car", "pedestrian", "other"} <= {table[i] for i in seen - {0}}


def test_depth_matches_ray_cast_of_exported_meshes(blender_toy_dataset):
    ds = Dataset.open(blender_toy_dataset)
    scn = ds.scenario("toy")
    rng = np.random.default_rng(0)
    for cam in scn.cameras:
        depth, inst = ds.read_depth("toy", cam.name), ds.read_instance("toy", cam.name)
        assert depth.dtype == np.float32
        assert np.all((depth == 0) == (inst == 0)), "sky has no depth and no id"
        # interior pixels: same id in the 3x3 neighbourhood (pixel centre well inside one surface)
        pad = np.pad(inst, 1, mode="edge")
        same = np.ones_like(inst, dtype=bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                same &= pad[1 + dy:1 + dy + inst.shape[0], 1 + dx:1 + dx + inst.shape[1]] == inst
        vs, us = np.nonzero(same & (inst > 0))
        pick = rng.choice(len(vs), size=min(120, len(vs)), replace=False)
        uv = np.column_stack([us[pick], vs[pick]]).astype(np.float64)
        origins, dirs = pixel_rays(cam.K, cam.camera_to_world, uv)
        # the camera's own car is hidden from its camera (Blender: visible_camera off for that view)
        t, hit = raycast_meshes(ds, scn, origins, dirs, skip={cam.mounted_on})
        planar = t * (dirs @ cam.camera_to_world[:3, 2])
        d = depth[vs[pick], us[pick]].astype(np.float64)
        agree = np.abs(planar - d) < 1e-3 * np.maximum(d, 1.0)
        assert agree.mean() > 0.97, f"{cam.name}: depth/ray-cast agreement {agree.mean():.3f}"
        assert (hit == inst[vs[pick], us[pick]]).mean() > 0.97


def test_object_centres_project_into_their_segments(blender_toy_dataset):
    ds = Dataset.open(blender_toy_dataset)
    scn = ds.scenario("toy")
    checked = 0
    for cam in scn.cameras:
        inst = ds.read_instance("toy", cam.name)
        for a in scn.actors:
            if a.cls == "other":
                continue
            vs, us = np.nonzero(inst == a.id)
            if len(vs) < 40:
                continue
            uv, z = project_points(cam.K, cam.camera_to_world, a.box.center[None])
            u, v = uv[0]
            assert z[0] > 0
            assert us.min() - 1 <= u <= us.max() + 1 and vs.min() - 1 <= v <= vs.max() + 1, (cam.name, a.name)
            checked += 1
    assert checked >= 2


def test_depth_and_ids_shared_by_variants_rgb_differs(blender_toy_dataset):
    ds = Dataset.open(blender_toy_dataset)
    scn = ds.scenario("toy")
    assert [v.name for v in scn.lighting] == ["dusk", "noon"]
    lay = ds.layout
    for cam in scn.cameras:
        # one depth and one instance file per camera (not per variant)
        assert sorted(p.name for p in lay.view_dir("toy", cam.name).iterdir() if p.is_file()) \
            == sorted({"depth.exr", "instance.png"} | ({"labels.json"} & {p.name for p in lay.view_dir("toy", cam.name).iterdir()}))
        noon, dusk = (ds.read_rgb("toy", cam.name, v).astype(float) for v in ("noon", "dusk"))
        assert np.abs(noon - dusk).mean() > 5
        assert noon.mean() > dusk.mean()


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def _cli(args, **kw):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "blender_tools.cli", *args], capture_output=True, text=True,
                          env=env, **kw)


def test_resume_redoes_only_missing_files_with_same_depth_and_ids(blender_toy_dataset, tmp_path):
    from conftest import BLENDER_TOY_ARGS

    root = _copy(blender_toy_dataset, tmp_path / "ds")
    ds = Dataset.open(root)
    lay = ds.layout
    depth_b, inst_b = ds.read_depth("toy", "cam_b"), ds.read_instance("toy", "cam_b")
    lay.depth("toy", "cam_b").unlink()  # as if killed after this view's RGB of an earlier run
    lay.rgb("toy", "cam_a", "dusk").unlink()
    stray = lay.view_dir("toy", "cam_a") / ".depth.tmp-999-0.exr"  # what a kill mid-write leaves
    stray.write_bytes(b"partial")
    assert not ds.view_is_complete("toy", "cam_b", ["noon", "dusk"])
    mtime = lay.rgb("toy", "cam_a", "noon").stat().st_mtime_ns
    res = _cli(["render", *BLENDER_TOY_ARGS, "--out", str(root), "--no-progress"])
    assert res.returncode == 0, res.stderr
    # cam_b: data pass + its 2 RGB (new data pass => RGB redone for consistency); cam_a: 1 RGB
    assert "toy: 4 files rendered" in res.stdout
    assert lay.rgb("toy", "cam_a", "noon").stat().st_mtime_ns == mtime, "complete files are kept"
    assert not stray.exists()
    assert np.array_equal(ds.read_depth("toy", "cam_b"), depth_b), "data pass is deterministic"
    assert np.array_equal(ds.read_instance("toy", "cam_b"), inst_b)
    assert [p for p in validate(root)] == []


def test_rerun_renders_again_what_does_not_read_back(blender_toy_dataset, tmp_path):
    from conftest import BLENDER_TOY_ARGS

    root = _copy(blender_toy_dataset, tmp_path / "ds")
    lay = Dataset.open(root).layout
    depth = lay.depth("toy", "cam_a")
    depth.write_bytes(depth.read_bytes()[: depth.stat().st_size // 2])  # a disk error: truncated
    lay.rgb("toy", "cam_b", "dusk").write_bytes(b"\x89PNG\r\n\x1a\ngarbage")  # a bad copy
    assert not Dataset.open(root).view_is_complete("toy", "cam_a", ["noon", "dusk"])
    res = _cli(["render", *BLENDER_TOY_ARGS, "--out", str(root), "--no-progress"])
    assert res.returncode == 0, res.stderr
    assert "toy: 4 files rendered" in res.stdout  # cam_a: data pass + both RGB; cam_b: dusk only
    assert [p for p in validate(root)] == []


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_killed_render_resumes_to_a_valid_dataset(tmp_path):
    from conftest import BLENDER_TOY_ARGS

    out = tmp_path / "ds"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "blender_tools.cli", "render", *BLENDER_TOY_ARGS,
                             "--out", str(out), "--no-progress"], env=env, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    lay = Dataset(out, None).layout
    deadline = time.time() + 120
    while time.time() < deadline and not lay.instance("toy", "cam_a").exists():
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # the whole process group: CLI and its render worker
    proc.wait()
    assert lay.instance("toy", "cam_a").exists()
    assert not Dataset.open(out).view_is_complete("toy", "cam_b", ["noon", "dusk"])
    res = _cli(["render", *BLENDER_TOY_ARGS, "--out", str(out), "--no-progress"])
    assert res.returncode == 0, res.stderr
    assert _errors(out) == []
    ds = Dataset.open(out)
    assert all(ds.view_is_complete("toy", c.name, ["noon", "dusk"]) for c in ds.scenario("toy").cameras)
    assert ds.info.splits["train"] == ["toy"]


@pytest.fixture(scope="module")
def no_camera_blend(tmp_path_factory):
    import bpy

    from blender_tools.build import reset_blender

    reset_blender()
    mesh = bpy.data.meshes.new("cube")
    mesh.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("cube", mesh))
    path = tmp_path_factory.mktemp("blend") / "nocam.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


def test_bad_input_gives_one_line_errors(tmp_path, no_camera_blend):
    (tmp_path / "fake.blend").write_text("not a blend file")
    (tmp_path / "afile").write_text("x")
    (tmp_path / "empty_hdrs").mkdir()
    cases = [
        (["--scene", "intersection_99"], "unknown scenario"),
        (["--scene", "intersection_01-s0"], "unknown scenario"),
        (["--scene", "toy", "--hdr", "noon,moonlight"], "unknown HDR variant"),
        (["--scene", "toy", "--hdr", str(tmp_path / "missing.exr")], "does not exist"),
        (["--scene", "toy", "--hdr-dir", str(tmp_path / "nope")], "no such directory"),
        (["--scene", "toy", "--hdr-dir", str(tmp_path / "empty_hdrs")], "no .hdr or .exr"),
        (["--blend", str(tmp_path / "fake.blend")], "not a readable .blend"),
        (["--blend", str(tmp_path / "missing.blend")], "no such file"),
        (["--blend", str(no_camera_blend), "--hdr", "noon"], "no cameras"),
        (["--scene", "toy", "--out", str(tmp_path / "afile" / "ds")], "is a file, so no folder"),
        (["--scene", "toy", "--resolution", "big"], "expected WxH"),
        (["--scene", "toy", "--quality", "ultra"], "invalid choice"),
    ]
    for args, needle in cases:
        out = [] if "--out" in args else ["--out", str(tmp_path / "out")]
        res = _cli(["render", *args, *out, "--no-progress"])
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        assert res.returncode != 0, args
        assert len(lines) == 1 and needle in lines[0] and "Traceback" not in res.stderr, (args, res.stderr)
    assert not (tmp_path / "out").exists(), "a refused or failed render leaves no (empty) dataset folder"


def test_user_blend_with_two_workers(tmp_path):
    """A user-style .blend (collections only, no label properties) rendered by 2 worker processes."""
    import bpy

    from blender_tools.build import build_scene, reset_blender
    from blender_tools.scenarios import build_model

    reset_blender()
    model = build_model("toy", 0)
    build_scene(model)
    for obj in bpy.data.objects:
        for key in ("label_id", "label_class"):
            if key in obj:
                del obj[key]
    blend = tmp_path / "my_street.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    out = tmp_path / "ds"
    res = _cli(["render", "--blend", str(blend), "--hdr", "noon", "--resolution", "48x32", "--samples", "2",
                "--workers", "2", "--out", str(out), "--no-progress"])
    assert res.returncode == 0, res.stderr
    assert _errors(out) == []
    scn = Dataset.open(out).scenario("my_street")
    assert {a.name: a.cls for a in scn.actors} == {a.name: a.cls for a in model.actors}
    assert {c.name for c in scn.cameras} == {"cam_a", "cam_b"}
    by_name = {a.name: a.id for a in scn.actors}
    assert {c.mounted_on for c in scn.cameras} == {by_name["car_cam_a"], by_name["car_cam_b"]}


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_random_lighting_renders_each_scene_under_its_drawn_variant_and_resumes(tmp_path):
    from blender_tools.hdri import drawn_variant

    out = tmp_path / "ds"
    args = ["render", "--scene", "toy,toy-s1,toy-s2", "--hdr", "random:noon,dusk", "--resolution", "32x24",
            "--samples", "1", "--denoise", "off", "--seed", "5", "--out", str(out), "--no-progress"]
    res = _cli(args)
    assert res.returncode == 0, res.stderr
    ds = Dataset.open(out)
    for name in ("toy", "toy-s1", "toy-s2"):
        scn = ds.scenario(name)
        want = drawn_variant(["noon", "dusk"], name, 5)
        assert [v.name for v in scn.lighting] == [want]
        assert sorted(p.stem for p in (out / "scenarios" / name / "views" / scn.cameras[0].name / "rgb").iterdir()) \
            == [want]
    again = _cli(args)
    assert again.returncode == 0 and " 0 files rendered" in again.stdout, again.stdout
    assert _errors(out) == []


def test_junction_centre_is_lit_from_above(tmp_path, monkeypatch):
    """The ground-level surfaces of an intersection (road arms overlapping at the junction, the
    junction disc, the ground) under the noon sky, seen from straight above: the junction centre is
    as bright as a single road arm. It rendered pure black when two arms' top faces coincided."""
    import bpy

    from blender_tools.build import build_scene, reset_blender
    from blender_tools.hdri import builtin_path
    from blender_tools.render import Renderer, RenderSettings
    from blender_tools.scenarios import build_model
    from blender_tools.scene_model import ActorModel, CameraRig, Part, SceneModel

    monkeypatch.setenv("BLENDER_TOOLS_CACHE", str(tmp_path / "cache"))
    full = build_model("intersection_07", 0)
    actors = [a for a in full.actors if a.name in ("ground", "road")]
    actors.append(ActorModel(32000, "far_car", "car", [Part("box", (1, 1, 1), (0, 0, 0.5))], location=(500, 0, 0)))
    reset_blender()
    build_scene(SceneModel("junction", 0, actors, [CameraRig("far_cam", "far_car")]))
    data = bpy.data.cameras.new("top")
    data.type, data.ortho_scale = "ORTHO", 40.0  # 40 m wide, centred on the junction
    top = bpy.data.objects.new("top", data)
    bpy.context.scene.collection.objects.link(top)
    top.location = (0.0, 0.0, 30.0)  # looking straight down, image x = world x
    renderer = Renderer(RenderSettings(width=40, height=40, samples=2), tmp_path)
    renderer.set_lighting(builtin_path("noon"))
    img = renderer.render_rgb(top).astype(float).mean(axis=2)
    centre, arm = img[18:22, 18:22].mean(), img[18:22, 34:38].mean()  # (0, 0) m and (+15, 0) m
    assert arm > 60, "a lit road arm"
    assert centre > 0.7 * arm, f"junction centre {centre:.0f} vs road arm {arm:.0f} (black: coincident faces)"
