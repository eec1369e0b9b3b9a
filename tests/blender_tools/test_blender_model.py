"""Scene model, catalog and HDR skies: no Blender needed."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from blender_tools import hdri
from blender_tools.scenarios import build_model, list_scenarios
from blender_tools.scene_model import ActorModel, Part, coincident_faces, oriented_box, part_mesh


def test_catalog_has_toy_and_twelve_intersections():
    names = [n for n, _ in list_scenarios()]
    assert "toy" in names
    assert [n for n in names if n.startswith("intersection_")] == [f"intersection_{i:02d}" for i in range(1, 13)]


@pytest.mark.parametrize("name", ["toy"] + [f"intersection_{i:02d}" for i in range(1, 13)])
def test_scenarios_are_deterministic_and_sane(name):
    a, b = build_model(name, 0), build_model(name, 0)
    assert [(x.id, x.name, x.cls, x.location, x.yaw) for x in a.actors] == \
           [(x.id, x.name, x.cls, x.location, x.yaw) for x in b.actors]
    a.check()
    classes = {x.cls for x in a.actors}
    assert {"car", "pedestrian", "other"} <= classes
    if name != "toy":
        assert 3 <= len(a.cameras) <= 8
    for rig in a.cameras:
        c2w = a.camera_to_world_blender(rig)
        assert 1.3 <= c2w[2, 3] <= 1.5, "driver eye height"
        fwd = -c2w[:3, 2]  # Blender cameras look down -z
        car = a.actor(rig.mounted_on)
        assert fwd @ np.array([np.cos(car.yaw), np.sin(car.yaw), 0]) > 0.95, "forward facing"


def test_other_seed_changes_the_scene():
    a, b = build_model("intersection_01", 0), build_model("intersection_01", 1)
    assert [x.location for x in a.actors] != [x.location for x in b.actors]


def _layout(model):
    return [(x.id, x.name, x.cls, x.location, x.yaw) for x in model.actors], [r.mounted_on for r in model.cameras]


def test_variant_is_the_layout_redrawn_with_an_offset_seed():
    v = build_model("intersection_03-s2", 5)
    assert v.name == "intersection_03-s2" and v.seed == 7
    assert _layout(v) == _layout(build_model("intersection_03", 7))
    assert _layout(v) != _layout(build_model("intersection_03", 5))
    assert _layout(build_model("toy-s1", 0)) == _layout(build_model("toy", 1))


@pytest.mark.parametrize("name", ["intersection_03-s0", "intersection_03-s", "intersection_03-sx", "intersection_99-s1",
                                  "intersection_03-s01", "-s1"])
def test_bad_variant_names_are_unknown(name):
    with pytest.raises(KeyError, match="unknown scenario"):
        build_model(name, 0)


def test_part_mesh_is_closed_and_box_fits():
    for shape in ("box", "cylinder", "sphere", "cone"):
        v, f = part_mesh(Part(shape, (2.0, 1.0, 3.0), (1, 2, 3)))
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        assert np.all(counts == 2), f"{shape} mesh is not closed"
        assert np.allclose(v.min(0), [0, 1.5, 1.5], atol=0.05) and np.allclose(v.max(0)[2], 4.5)
    actor = ActorModel(3, "a", "car", [Part("box", (4, 2, 1.5), (0, 0, 0.75))], location=(5, 1, 0), yaw=0.7)
    center, size = oriented_box(actor.world_mesh()[0], actor.yaw)
    assert np.allclose(center, [5, 1, 0.75]) and np.allclose(size, [4, 2, 1.5])


def test_part_mesh_faces_point_outward():
    for shape in ("box", "cylinder", "sphere", "cone"):
        part = Part(shape, (16.8, 16.8, 0.04), (1, 2, -0.005))  # flat, like the junction disc
        v, f = part_mesh(part)
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n = n[np.linalg.norm(n, axis=1) > 1e-9]  # the cone's apex triangles are degenerate
        tri = tri[np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) > 1e-9]
        outward = np.einsum("md,md->m", n, tri.mean(axis=1) - np.asarray(part.location))
        assert np.all(outward > 0), f"{shape}: inward triangles"
        assert (n[:, 2] > 0).any() and (n[:, 2] < 0).any(), f"{shape}: caps must face up and down"


def test_coincident_faces_found_and_cleared_by_a_height_step():
    def road(z1):
        return [ActorModel(1, "road", "other", [Part("box", (20, 4, 0.04), (5, 0, 0)),
                                                Part("box", (4, 20, 0.04), (0, 5, z1))], yaw=0.3)]

    found = coincident_faces(road(0.0))
    assert [(a, b) for a, b, *_ in found] == [(("road", 0), ("road", 1))] * 2
    assert [(normal, offset) for _, _, normal, offset in found] == [((0, 0, -1), 0.02), ((0, 0, 1), 0.02)]
    assert coincident_faces(road(-0.001)) == []
    touching = [ActorModel(1, "a", "other", [Part("box", (2, 2, 1), (0, 0, 0.5))]),
                ActorModel(2, "b", "other", [Part("box", (2, 2, 1), (2, 0, 0.5))])]
    assert coincident_faces(touching) == [], "side by side (shared edge) is not an overlap"


def test_coincident_vertical_faces_found_and_cleared_by_a_stagger():
    """Two buildings' roof slabs (0.15 m overhang) overlapping across a 5 cm gap: coplanar street
    fronts are found; fronts a few cm apart are not."""
    def row(dy):  # the slabs of a 10 m and a 10.2 m tall building, 10 m long, in a row along yaw 0.4
        d = np.array([np.cos(0.4), np.sin(0.4), 0.0])
        return [ActorModel(i + 1, f"b{i}", "other", [Part("box", (10.3, 8.3, 0.3), (0, y, h + 0.15))],
                           location=tuple(x * d), yaw=0.4) for i, (x, y, h) in enumerate(((0, 0, 10), (10.05, dy, 10.2)))]

    assert {(a, b) for a, b, *_ in coincident_faces(row(0.0))} == {(("b0", 0), ("b1", 0))}
    assert coincident_faces(row(0.03)) == []


@pytest.mark.parametrize("seed", [0, 1])
def test_no_coincident_faces_in_scenarios(seed):
    """Overlapping parts with faces in one plane facing the same way render black in Cycles (every
    shadow and bounce ray from one face hits the other at distance 0): the junction centre was black
    where the road arms overlapped, facades and roof edges where buildings in a row overlapped, walls
    placed on walls, stop lines flush with the road's sides. Depth and ids hid it (camera rays only).
    Any orientation, every scenario."""
    bad = {}
    names = [n for n, _ in list_scenarios() if n != "procedural-K"] + [f"procedural-{k}" for k in range(0, 40, 4)]
    for name in names:  # the catalog's and procedural draws
        found = coincident_faces(build_model(name, seed).actors)
        if found:
            bad[name] = found[:3]
    assert bad == {}


def test_hdri_skies(tmp_path, monkeypatch):
    monkeypatch.setenv("BLENDER_TOOLS_CACHE", str(tmp_path))
    for name in hdri.BUILTIN:
        sky = hdri.make_sky(name, size=(64, 128))
        assert sky.shape == (64, 128, 3) and sky.dtype == np.float32
        assert np.all(np.isfinite(sky)) and sky.min() >= 0
    noon = hdri.make_sky("noon")
    assert noon.max() > 100 * np.median(noon), "noon needs a bright sun for hard shadows"
    upper = hdri.make_sky("overcast")[:128]
    assert upper.max() < 5 * np.median(upper), "overcast: no sun"
    variants = hdri.resolve_variants("noon,dusk")
    assert [lm.name for lm, _ in variants] == ["noon", "dusk"] and all(p.is_file() for _, p in variants)


def test_random_lighting_is_one_variant_per_scene_drawn_by_its_name_and_seed():
    assert hdri.random_spec("random") == (True, "all")
    assert hdri.random_spec("random:noon,dusk") == (True, "noon,dusk")
    assert hdri.random_spec("noon,dusk") == (False, "noon,dusk")
    with pytest.raises(hdri.HdrError, match="after the colon"):
        hdri.random_spec("random:")
    names = list(hdri.BUILTIN)
    scenes = [f"intersection_{i:02d}-s{k}" for i in range(1, 8) for k in range(1, 13)]
    drawn = [hdri.drawn_variant(names, s, 0) for s in scenes]
    assert drawn == [hdri.drawn_variant(names, s, 0) for s in scenes]  # a seeded draw reproduces
    counts = {n: drawn.count(n) for n in names}
    assert min(counts.values()) >= 10, counts  # 84 scenes: every variant drawn, none left out
    other_seed = [hdri.drawn_variant(names, s, 1) for s in scenes]
    assert sum(a != b for a, b in zip(drawn, other_seed)) > 30  # the seed matters
    assert hdri.drawn_variant(["dusk"], scenes[0], 0) == "dusk"


def test_hdri_bad_input(tmp_path):
    with pytest.raises(hdri.HdrError, match="unknown HDR variant"):
        hdri.resolve_variants("noonish")
    with pytest.raises(hdri.HdrError, match="no such directory"):
        hdri.resolve_variants("all", tmp_path / "nope")
    with pytest.raises(hdri.HdrError, match="no .hdr or .exr"):
        hdri.resolve_variants("all", tmp_path)
    with pytest.raises(hdri.HdrError, match="does not exist"):
        hdri.resolve_variants(str(tmp_path / "missing.hdr"))
    (tmp_path / "street.exr").write_bytes(b"x")  # garbage: Blender would render magenta and say nothing
    with pytest.raises(hdri.HdrError, match="street.exr: not a readable EXR"):
        hdri.resolve_variants("all", tmp_path)
    (tmp_path / "street.hdr").write_bytes(b"#?RADIANCE\ngarbage")
    with pytest.raises(hdri.HdrError, match="street.hdr: not a readable Radiance"):
        hdri.resolve_variants(str(tmp_path / "street.hdr"))
    from dataset_spec.images import write_exr_rgb

    write_exr_rgb(tmp_path / "street.exr", np.full((8, 16, 3), 0.5, np.float32))
    cv2.imwrite(str(tmp_path / "street.hdr"), np.full((8, 16, 3), 0.5, np.float32))
    names = [lm.name for lm, _ in hdri.resolve_variants("all", tmp_path)]
    assert "street" in names and "noon" in names
