"""Blender scene -> dataset_spec records: cameras (K, extrinsics), actors (boxes, world meshes).

* K comes from ``dataset_spec.camera.intrinsics_from_blender`` (sensor fit, shift, pixel aspect).
* ``camera_to_world`` is Blender's ``matrix_world`` converted to OpenCV camera axes.
* An actor's box is the smallest box with the actor's yaw (its root object's local +X projected on
  the ground plane) that contains all evaluated vertices of its objects, in world space.
* Meshes: every object of the actor, evaluated (modifiers applied), triangulated, in world space.
* Names are the objects' names made legal (``dataset_spec.names.safe_name``: "Car 01" -> "Car_01").
"""
from __future__ import annotations

import math

import numpy as np

from dataset_spec.camera import blender_to_opencv_camera_to_world, intrinsics_from_blender
from dataset_spec.names import safe_name
from dataset_spec.schema import Actor, Box3D, CameraInfo

from ._bpy import require_bpy
from .labeller import LabelResult
from .scene_model import oriented_box


def camera_intrinsics(cam_obj, scene) -> np.ndarray:
    r = scene.render
    w = int(round(r.resolution_x * r.resolution_percentage / 100))
    h = int(round(r.resolution_y * r.resolution_percentage / 100))
    d = cam_obj.data
    return intrinsics_from_blender(lens_mm=d.lens, sensor_width_mm=d.sensor_width, sensor_height_mm=d.sensor_height,
                                   sensor_fit=d.sensor_fit, shift_x=d.shift_x, shift_y=d.shift_y, width=w, height=h,
                                   pixel_aspect=r.pixel_aspect_y / r.pixel_aspect_x)


def camera_info(cam_obj, scene, mounted_on: int | None) -> CameraInfo:
    if cam_obj.data.type != "PERSP":
        raise ValueError(f"camera {cam_obj.name}: only perspective cameras are supported (got {cam_obj.data.type})")
    r = scene.render
    w = int(round(r.resolution_x * r.resolution_percentage / 100))
    h = int(round(r.resolution_y * r.resolution_percentage / 100))
    c2w = blender_to_opencv_camera_to_world(np.array(cam_obj.matrix_world))
    # remove any scale from the camera matrix (a scaled parent) so the transform stays rigid
    c2w[:3, :3] /= np.linalg.norm(c2w[:3, :3], axis=0, keepdims=True)
    return CameraInfo(safe_name(cam_obj.name), w, h, camera_intrinsics(cam_obj, scene), c2w, mounted_on,
                      near=float(cam_obj.data.clip_start), far=float(cam_obj.data.clip_end),
                      extras={"lens_mm": cam_obj.data.lens, "sensor_fit": cam_obj.data.sensor_fit})


def object_world_mesh(obj, depsgraph) -> tuple[np.ndarray, np.ndarray]:
    ev = obj.evaluated_get(depsgraph)
    mesh = ev.to_mesh()
    try:
        mesh.calc_loop_triangles()
        nv, nt = len(mesh.vertices), len(mesh.loop_triangles)
        co = np.empty(nv * 3, dtype=np.float64)
        mesh.vertices.foreach_get("co", co)
        tris = np.empty(nt * 3, dtype=np.int64)
        mesh.loop_triangles.foreach_get("vertices", tris)
    finally:
        ev.to_mesh_clear()
    M = np.array(ev.matrix_world)
    verts = co.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]
    return verts, tris.reshape(-1, 3)


def actor_yaw(root) -> float:
    fwd = np.array(root.matrix_world)[:3, 0]
    if math.hypot(fwd[0], fwd[1]) < 1e-6:
        return 0.0
    return float(math.atan2(fwd[1], fwd[0]))


def export_actors(labels: LabelResult, scene, write_mesh=None) -> list[Actor]:
    """Actor records; ``write_mesh(actor_id, verts, faces) -> relpath`` stores the world mesh."""
    bpy = require_bpy()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    out = []
    for a in labels.actors:
        verts, faces, n = [], [], 0
        for obj in a.objects:
            v, f = object_world_mesh(obj, depsgraph)
            verts.append(v)
            faces.append(f + n)
            n += len(v)
        V = np.concatenate(verts) if verts else np.zeros((0, 3))
        F = np.concatenate(faces) if faces else np.zeros((0, 3), int)
        yaw = actor_yaw(a.root)
        if len(V):
            center, size = oriented_box(V, yaw)
        else:
            center, size = np.array(a.root.matrix_world.translation), np.full(3, 0.01)
        mesh = write_mesh(a.id, V, F) if (write_mesh is not None and len(F)) else None
        out.append(Actor(a.id, safe_name(a.name), a.cls, Box3D(center, size, yaw), mesh,
                         extras={"objects": [o.name for o in a.objects]}))
    return out
