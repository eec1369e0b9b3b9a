"""Blender adapter: ``SceneModel`` -> Blender objects, materials, collections, cameras.

Collection convention (shared with user ``.blend`` files, see ``labeller``): car actors go to
``Cars``, pedestrians to ``Pedestrians``, everything else to ``Other``; cameras to ``Cameras``,
parented to the root object of the car that carries them. Each actor's root object carries the
custom properties ``label_id`` (its instance id) and ``label_class``.
"""
from __future__ import annotations

import numpy as np

from ._bpy import require_bpy
from .scene_model import ActorModel, SceneModel, part_mesh, rotation_xyz

COLLECTIONS = {"car": "Cars", "pedestrian": "Pedestrians", "other": "Other"}


def reset_blender() -> None:
    """Empty the Blender session (frees the previous scene's data; keeps memory flat)."""
    bpy = require_bpy()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.data.orphans_purge(do_recursive=True)


# ----------------------------------------------------------------------------- materials
class Materials:
    """One Blender material per (kind, colour), created on first use."""

    def __init__(self):
        self.bpy = require_bpy()
        self.cache: dict = {}

    def get(self, kind: str, color) -> "object":
        key = (kind, tuple(round(float(c), 3) for c in color))
        if key not in self.cache:
            self.cache[key] = self._make(kind, key[1])
        return self.cache[key]

    def _make(self, kind: str, color):
        bpy = self.bpy
        mat = bpy.data.materials.new(f"{kind}_{len(self.cache):03d}")
        nt = mat.node_tree
        bsdf = next(n for n in nt.nodes if n.type == "BSDF_PRINCIPLED")
        rgba = (*color, 1.0)
        bsdf.inputs["Base Color"].default_value = rgba
        rough = {"paint": 0.3, "glass": 0.05, "rubber": 0.9, "metal": 0.35, "asphalt": 0.95, "concrete": 0.9,
                 "plaster": 0.85, "grass": 1.0, "foliage": 0.9, "bark": 0.95, "marking": 0.7, "skin": 0.6,
                 "cloth": 0.95, "light": 0.4, "pavement": 0.9, "facade": 0.8, "brick": 0.9}[kind]
        bsdf.inputs["Roughness"].default_value = rough
        if kind in ("metal", "paint"):
            bsdf.inputs["Metallic"].default_value = 1.0 if kind == "metal" else 0.35
        if kind == "light":
            bsdf.inputs["Emission Color"].default_value = rgba
            bsdf.inputs["Emission Strength"].default_value = 3.0
        if kind in ("facade", "brick"):
            self._facade(nt, bsdf, rgba, brick=kind == "brick")
        mat.diffuse_color = rgba
        return mat

    @staticmethod
    def _facade(nt, bsdf, wall_rgba, brick: bool):
        """Window grid (UV in metres: u along the facade, v = height) over a plain or brick wall."""
        uv = nt.nodes.new("ShaderNodeTexCoord")
        win = nt.nodes.new("ShaderNodeTexBrick")
        win.offset, win.squash = 0.0, 1.0
        glass = (0.05, 0.07, 0.09, 1.0)
        win.inputs["Color1"].default_value = glass
        win.inputs["Color2"].default_value = (0.08, 0.09, 0.1, 1.0)
        win.inputs["Scale"].default_value = 1.0
        win.inputs["Mortar Size"].default_value = 0.9
        win.inputs["Brick Width"].default_value = 2.6
        win.inputs["Row Height"].default_value = 3.2
        win.inputs["Mortar"].default_value = wall_rgba
        nt.links.new(uv.outputs["UV"], win.inputs["Vector"])
        if brick:
            small = nt.nodes.new("ShaderNodeTexBrick")
            small.inputs["Scale"].default_value = 1.0
            small.inputs["Brick Width"].default_value = 0.25
            small.inputs["Row Height"].default_value = 0.08
            small.inputs["Mortar Size"].default_value = 0.012
            small.inputs["Color1"].default_value = wall_rgba
            small.inputs["Color2"].default_value = tuple(c * 0.8 for c in wall_rgba[:3]) + (1.0,)
            small.inputs["Mortar"].default_value = (0.6, 0.6, 0.58, 1.0)
            nt.links.new(uv.outputs["UV"], small.inputs["Vector"])
            nt.links.new(small.outputs["Color"], win.inputs["Mortar"])
        nt.links.new(win.outputs["Color"], bsdf.inputs["Base Color"])
        rough = nt.nodes.new("ShaderNodeMath")
        rough.operation = "MULTIPLY_ADD"
        nt.links.new(win.outputs["Fac"], rough.inputs[0])
        rough.inputs[1].default_value = 0.75
        rough.inputs[2].default_value = 0.1
        nt.links.new(rough.outputs[0], bsdf.inputs["Roughness"])


# ----------------------------------------------------------------------------- geometry
def _facade_uvs(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-corner UVs in metres: vertical faces (horizontal distance, height), others (x, y)."""
    tri = verts[faces]  # (M, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    t = np.stack([-n[:, 1], n[:, 0], np.zeros(len(n))], axis=1)
    t /= np.linalg.norm(t, axis=1, keepdims=True) + 1e-12
    vertical = np.abs(n[:, 2]) < 0.7
    u = np.where(vertical[:, None], np.einsum("mkd,md->mk", tri, t), tri[:, :, 0])
    v = np.where(vertical[:, None], tri[:, :, 2], tri[:, :, 1])
    return np.stack([u, v], axis=-1).reshape(-1, 2)


def make_mesh_object(name: str, actor: ActorModel, group: str, materials: Materials):
    bpy = require_bpy()
    verts, faces, slots, mats = [], [], [], []
    n = 0
    smooth = []
    for part in actor.parts:
        if part.group != group:
            continue
        v, f = part_mesh(part)
        mat = materials.get(part.material, part.color)
        if mat not in mats:
            mats.append(mat)
        verts.append(v)
        faces.append(f + n)
        slots += [mats.index(mat)] * len(f)
        if part.shape == "sphere":
            smooth += [True] * len(f)
        elif part.shape in ("cylinder", "cone"):  # smooth sides, flat caps
            zs = np.round((v[f] - part.location) @ rotation_xyz(*part.rotation)[:, 2], 6)
            smooth += list(np.ptp(zs, axis=1) > 1e-6)
        else:
            smooth += [False] * len(f)
        n += len(v)
    verts_a, faces_a = np.concatenate(verts), np.concatenate(faces)
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts_a.tolist(), [], faces_a.tolist())
    for m in mats:
        mesh.materials.append(m)
    mesh.polygons.foreach_set("material_index", np.asarray(slots, dtype=np.int32))
    mesh.polygons.foreach_set("use_smooth", np.asarray(smooth, dtype=bool))
    uv = mesh.uv_layers.new(name="UVMap")
    uv.data.foreach_set("uv", _facade_uvs(verts_a, faces_a).astype(np.float32).ravel())
    mesh.update()
    return bpy.data.objects.new(name, mesh)


def build_scene(model: SceneModel) -> dict:
    """Create ``model`` in the current (empty) Blender scene. Returns {actor name: root object}."""
    bpy = require_bpy()
    model.check()
    scene = bpy.context.scene
    colls = {}
    for key, cname in list(COLLECTIONS.items()) + [("camera", "Cameras")]:
        coll = bpy.data.collections.get(cname) or bpy.data.collections.new(cname)
        if coll.name not in scene.collection.children:
            scene.collection.children.link(coll)
        colls[key] = coll
    materials = Materials()
    roots = {}
    for actor in model.actors:
        root = None
        for gi, group in enumerate(actor.groups()):
            obj = make_mesh_object(actor.name if gi == 0 else f"{actor.name}.{group}", actor, group, materials)
            colls[actor.cls].objects.link(obj)
            if root is None:
                root = obj
                root["label_id"] = actor.id
                root["label_class"] = actor.cls
                root.matrix_world = _matrix(actor.pose)
            else:
                obj.parent = root  # local coordinates are the actor frame
        roots[actor.name] = root
    for rig in model.cameras:
        data = bpy.data.cameras.new(rig.name)
        data.lens, data.sensor_width, data.sensor_height = rig.lens_mm, rig.sensor_width_mm, rig.sensor_height_mm
        data.sensor_fit, data.shift_x, data.shift_y = rig.sensor_fit, rig.shift_x, rig.shift_y
        data.clip_start, data.clip_end = rig.clip_start, rig.clip_end
        cam = bpy.data.objects.new(rig.name, data)
        colls["camera"].objects.link(cam)
        cam.parent = roots[rig.mounted_on]
        cam.matrix_basis = _matrix(rig.local_matrix())
    bpy.context.view_layer.update()
    return roots


def _matrix(m: np.ndarray):
    from mathutils import Matrix

    return Matrix(np.asarray(m, dtype=np.float64).tolist())
