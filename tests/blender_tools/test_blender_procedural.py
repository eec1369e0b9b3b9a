"""Procedural intersections (issue 73): ``procedural-K`` draws a layout from a distribution by K alone, every draw a
legal scene recorded in its extras, redraws keep the layout, splits keep a layout's draws together, and a few draws
render, validate and label at the procedural toy scale."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from blender_tools.motion import Footprint
from blender_tools.procedural import MIN_CAMERAS, draw_layout, is_procedural
from blender_tools.scenarios import build_model, list_scenarios, split_variant
from blender_tools.street import Street, overlap


def test_a_draw_is_the_same_layout_on_every_call_and_its_redraw_keeps_it():
    a, b = build_model("procedural-5", 0), build_model("procedural-5", 0)
    assert [(x.name, x.location) for x in a.actors] == [(x.name, x.location) for x in b.actors]
    redraw = build_model("procedural-5-s2", 0)
    assert redraw.extras["arms_deg"] == a.extras["arms_deg"] and redraw.extras["procedural"]["k"] == 5
    assert [x.location for x in redraw.actors if x.cls == "car"] != [x.location for x in a.actors if x.cls == "car"]
    assert split_variant("procedural-5-s2") == ("procedural-5", 2) and is_procedural("procedural-0")
    assert not is_procedural("procedural-01") and not is_procedural("procedural-x")
    assert any(name == "procedural-K" for name, _ in list_scenarios())
    layouts = {tuple(draw_layout(k).arms) for k in range(30)}
    assert len(layouts) > 25 and {len(arms) for arms in layouts} == {3, 4, 5}  # scenes without end, 3-5 arms


@pytest.mark.parametrize("k", range(0, 60, 3))
def test_every_draw_is_a_legal_scene_and_says_what_was_drawn(k):
    """Rule: nobody overlaps anybody, every camera car is on an incoming lane facing the junction, every road
    user stands on a road or a sidewalk, and the draw's parameters are in the scene's extras."""
    model = build_model(f"procedural-{k}", 0)
    drawn = model.extras["procedural"]
    assert set(drawn) >= {"arms", "lanes", "roundabout", "parking", "crosswalks", "sidewalk", "setback", "cameras",
                          "pedestrians", "moving", "parked", "big", "trees", "walls", "brick", "k"}
    assert len(model.cameras) >= MIN_CAMERAS
    arms = sorted(drawn["arms"])
    assert min((b - a) % 360 for a, b in zip(arms, arms[1:] + arms[:1])) >= 50.0
    street = Street(draw_layout(k))
    users = [a for a in model.actors if a.cls in ("car", "pedestrian")]
    feet = {a.name: Footprint.of(a).quad(a.location[:2], a.yaw) for a in users}
    names = list(feet)
    assert not any(overlap(feet[p], feet[q]) for i, p in enumerate(names) for q in names[i + 1:])
    assert all(street.in_roads(np.asarray([a.location[:2]]), 0.3) for a in users)
    for rig in model.cameras:
        car = model.actor(rig.mounted_on)
        heading = np.array([np.cos(car.yaw), np.sin(car.yaw)])
        assert car.extras["drive"] == "camera" and heading @ -np.asarray(car.location[:2]) > 0


def test_a_layouts_draws_stay_in_one_split(tmp_path):
    import yaml

    from dataset_spec.cli_support import UserError
    from pnyolo.bench.presets import load_preset

    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump({"base": "smoke", "splits": {"train": ["procedural-3"], "val": ["procedural-3-s1"],
                                                               "test": ["intersection_03"]}}))
    with pytest.raises(UserError, match="procedural-3"):
        load_preset(path)


@pytest.mark.blender
@pytest.mark.slow
def test_a_few_draws_render_validate_and_label(tmp_path):
    pytest.importorskip("bpy")
    from dataset_spec import Dataset
    from dataset_spec.validate import validate
    from tools.projection import label_dataset

    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "blender_tools.cli", "render", "--scene", "procedural-1,procedural-12", "--hdr",
           "noon", "--resolution", "96x54", "--samples", "1", "--denoise", "off", "--out", str(out), "--no-progress"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-2000:]
    assert not [p for p in validate(out) if p.severity == "error"]
    assert label_dataset(out, progress=False) > 0
    ds = Dataset.open(out)
    extras = json.loads((out / "scenarios" / "procedural-12" / "scenario.json").read_text())["extras"]
    assert extras["procedural"]["k"] == 12 and ds.scenario("procedural-1").cameras
