"""Camera export and the labeller against Blender itself (no rendering)."""
from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.blender
bpy = pytest.importorskip("bpy")

from dataset_spec.camera import project_points  # noqa: E402


@pytest.mark.parametrize("fit,shift,res,aspect", [
    ("AUTO", (0.0, 0.0), (96, 64), (1, 1)),
    ("AUTO", (0.1, -0.05), (64, 96), (1, 1)),
    ("HORIZONTAL", (-0.2, 0.1), (120, 50), (1, 1)),
    ("VERTICAL", (0.05, 0.15), (80, 60), (1, 1)),
    ("AUTO", (0.1, 0.1), (100, 60), (1, 2)),
    ("VERTICAL", (0.0, -0.1), (90, 70), (3, 2)),
])
def test_K_and_extrinsics_match_world_to_camera_view(fit, shift, res, aspect):
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    from blender_tools.build import reset_blender
    from blender_tools.export import camera_info

    reset_blender()
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = res
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = aspect
    data = bpy.data.cameras.new("c")
    data.lens, data.sensor_width, data.sensor_height, data.sensor_fit = 28.0, 36.0, 20.0, fit
    data.shift_x, data.shift_y = shift
    cam = bpy.data.objects.new("c", data)
    scene.collection.objects.link(cam)
    cam.location = (3.0, -7.0, 1.4)
    cam.rotation_euler = (1.45, 0.05, 0.4)
    bpy.context.view_layer.update()
    info = camera_info(cam, scene, None)
    rng = np.random.default_rng(0)
    c2w_bl = np.array(cam.matrix_world)
    pts_cam = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(-2, 2, 50), -rng.uniform(2, 30, 50)])
    pts = pts_cam @ c2w_bl[:3, :3].T + c2w_bl[:3, 3]
    uv, z = project_points(info.K, info.camera_to_world, pts)
    W, H = res
    for p, (u, v), zz in zip(pts, uv, z):
        ndc = world_to_camera_view(scene, cam, Vector(p))
        assert abs(ndc.x * W - 0.5 - u) < 0.01 and abs((1 - ndc.y) * H - 0.5 - v) < 0.01
        assert abs(ndc.z - zz) < 1e-6 * max(1.0, zz)  # planar depth (float32 in mathutils)


def test_model_cameras_match_blender_matrices():
    from blender_tools.build import build_scene, reset_blender
    from blender_tools.scenarios import build_model

    reset_blender()
    model = build_model("toy", 0)
    build_scene(model)
    for rig in model.cameras:
        assert np.allclose(np.array(bpy.data.objects[rig.name].matrix_world), model.camera_to_world_blender(rig),
                           atol=1e-5)


def test_labeller_on_a_user_style_scene():
    from blender_tools.build import reset_blender
    from blender_tools.labeller import label_scene

    reset_blender()
    scene = bpy.context.scene

    def coll(name, parent=None):
        c = bpy.data.collections.new(name)
        (parent or scene.collection).children.link(c) if parent is None else parent.children.link(c)
        return c

    def cube(name, c, parent=None):
        o = bpy.data.objects.new(name, bpy.data.meshes.new(name))
        o.data.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
        c.objects.link(o)
        o.parent = parent
        return o

    cars = coll("Cars")
    sedans = bpy.data.collections.new("Sedans")
    cars.children.link(sedans)  # nested collection under Cars
    peds = coll("Pedestrians")
    misc = coll("Props")
    body = cube("sedan_body", sedans)
    wheel = cube("sedan_wheel", misc, parent=body)  # child in another collection: still the car
    cube("walker", peds)
    cube("sedan_driver", peds, parent=body)  # class conflict inside one actor: reported
    lonely = cube("car_lonely", misc)  # name prefix -> car (an actor of its own)
    cube("Person statue", misc)  # suspicious name -> reported, 'other'
    odd = cube("odd", misc)
    odd["label_class"] = "truck"
    forced = cube("bus_stop", misc)
    forced["label_class"] = "pedestrian"
    forced["label_id"] = 40
    cam = bpy.data.objects.new("dashcam", bpy.data.cameras.new("dashcam"))
    misc.objects.link(cam)
    cam.parent = body
    res = label_scene(scene)
    by_name = {a.name: a for a in res.actors}
    assert set(by_name) == {"sedan_body", "walker", "car_lonely", "Person statue", "odd", "bus_stop"}
    assert body.pass_index == wheel.pass_index == by_name["sedan_body"].id
    assert [by_name[n].cls for n in ("sedan_body", "walker", "car_lonely", "Person statue", "odd", "bus_stop")] == \
           ["car", "pedestrian", "car", "other", "other", "pedestrian"]
    assert by_name["bus_stop"].id == 40
    assert lonely.pass_index == by_name["car_lonely"].id != by_name["sedan_body"].id
    assert len({a.id for a in res.actors}) == len(res.actors)
    assert res.cameras == [(cam, by_name["sedan_body"].id)]
    text = "\n".join(res.problems)
    assert "Person statue" in text and "truck" in text and "sedan_driver" in text and "sedan_wheel" not in text
