"""Cycles rendering: presets, HDR world, the data pass (depth + Object Index) and RGB passes.

Per camera the data pass runs once (1 sample, pixel filter 0.01 px, so depth and ids are the
values at pixel centres) and writes depth and Object Index through the Blender 5 compositor
(File Output node, multi-layer float32 EXR). Then one RGB render per lighting variant; only the
world changes between them, and persistent data keeps the scene synced between renders.

Blender outputs are converted to the spec: depth background 1e10 -> 0.0, Object Index (float)
-> uint16 instance ids, RGB PNG -> ``Dataset.write_rgb``.
"""
from __future__ import annotations

import contextlib
import math
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ._bpy import require_bpy

PRESETS = {
    # name: resolution, samples, denoise
    "preview": dict(width=320, height=180, samples=8, denoise=False),
    "default": dict(width=480, height=270, samples=16, denoise=True),
    "final": dict(width=1920, height=1080, samples=128, denoise=True),
}
DEPTH_BACKGROUND_BLENDER = 1e9  # Blender writes 1e10 where no surface; anything above this is sky


@dataclass
class RenderSettings:
    width: int = 480
    height: int = 270
    samples: int = 16
    denoise: bool = False
    device: str = "cpu"  # 'cpu' | 'gpu'
    threads: int = 0  # 0 = all cores
    max_bounces: int = 4

    @classmethod
    def from_preset(cls, quality: str, **overrides) -> "RenderSettings":
        if quality not in PRESETS:
            raise ValueError(f"unknown quality {quality!r} (known: {', '.join(PRESETS)})")
        values = dict(PRESETS[quality])
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)

    def to_dict(self) -> dict:
        return asdict(self)


@contextlib.contextmanager
def quiet_stdout():
    """Silence Blender's C-level prints (``Fra:1 Mem:...``) on fd 1 for the duration."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no fd 1 (unusual embedding): nothing to silence
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def _enable_gpu() -> str:
    bpy = require_bpy()
    prefs = bpy.context.preferences.addons["cycles"].preferences
    for kind in ("OPTIX", "CUDA", "HIP", "METAL", "ONEAPI"):
        try:
            prefs.compute_device_type = kind
        except TypeError:
            continue
        prefs.refresh_devices()
        devices = [d for d in prefs.devices if d.type == kind]
        if devices:
            for d in prefs.devices:
                d.use = d.type == kind
            return kind
    raise RuntimeError("--device gpu: Cycles found no GPU (OPTIX/CUDA/HIP/METAL/ONEAPI); use --device cpu")


class Renderer:
    """Owns the render setup of the current Blender scene."""

    def __init__(self, settings: RenderSettings, tmpdir: str | Path):
        self.bpy = require_bpy()
        self.settings = settings
        self.tmpdir = Path(tmpdir)
        self.scene = self.bpy.context.scene
        self.render_seconds = 0.0  # time spent inside bpy.ops.render.render
        self._setup()

    # ------------------------------------------------------------------ setup
    def _setup(self):
        s, scene = self.settings, self.scene
        scene.render.engine = "CYCLES"
        cy = scene.cycles
        if s.device == "gpu":
            _enable_gpu()
            cy.device = "GPU"
        else:
            cy.device = "CPU"
        r = scene.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = s.width, s.height, 100
        r.use_persistent_data = True
        r.threads_mode = "FIXED" if s.threads > 0 else "AUTO"
        if s.threads > 0:
            r.threads = s.threads
        r.film_transparent = False
        r.use_motion_blur = False
        cy.use_adaptive_sampling = True
        cy.adaptive_threshold = 0.05
        cy.max_bounces = s.max_bounces
        cy.diffuse_bounces = 2
        cy.glossy_bounces = 2
        cy.transmission_bounces = 2
        cy.transparent_max_bounces = 4
        cy.volume_bounces = 0
        cy.caustics_reflective = cy.caustics_refractive = False
        cy.seed = 0
        cy.denoiser = "OPENIMAGEDENOISE"
        scene.view_settings.view_transform = "AgX"
        vl = scene.view_layers[0]
        vl.use_pass_z = True
        vl.use_pass_object_index = True
        # compositor: Render Layers -> File Output (Depth, Object Index) as 32-bit multi-layer EXR
        ng = self.bpy.data.node_groups.new("data_pass", "CompositorNodeTree")
        scene.compositing_node_group = ng
        rl = ng.nodes.new("CompositorNodeRLayers")
        fo = ng.nodes.new("CompositorNodeOutputFile")
        fo.format.media_type = "MULTI_LAYER_IMAGE"
        fo.format.file_format = "OPEN_EXR_MULTILAYER"
        fo.format.color_depth = "32"
        fo.format.exr_codec = "ZIP"
        fo.directory = str(self.tmpdir)
        for name in ("Depth", "Object Index"):
            fo.file_output_items.new("FLOAT", name)
            ng.links.new(rl.outputs[name], fo.inputs[name])
        self.file_output = fo
        # world: TexCoord -> Mapping -> Environment Texture -> Background -> World Output
        world = self.bpy.data.worlds.new("hdr_world")
        scene.world = world
        nt = world.node_tree
        for n in list(nt.nodes):
            nt.nodes.remove(n)
        tc = nt.nodes.new("ShaderNodeTexCoord")
        self.mapping = nt.nodes.new("ShaderNodeMapping")
        self.env = nt.nodes.new("ShaderNodeTexEnvironment")
        self.background = nt.nodes.new("ShaderNodeBackground")
        out = nt.nodes.new("ShaderNodeOutputWorld")
        nt.links.new(tc.outputs["Generated"], self.mapping.inputs["Vector"])
        nt.links.new(self.mapping.outputs["Vector"], self.env.inputs["Vector"])
        nt.links.new(self.env.outputs["Color"], self.background.inputs["Color"])
        nt.links.new(self.background.outputs["Background"], out.inputs["Surface"])
        r.image_settings.file_format = "PNG"
        r.image_settings.color_mode = "RGB"
        r.image_settings.color_depth = "8"

    def set_lighting(self, hdr_path: str | Path, strength: float = 1.0, rotation_deg: float = 0.0) -> None:
        img = self.bpy.data.images.load(str(hdr_path), check_existing=True)
        self.env.image = img
        self.background.inputs["Strength"].default_value = strength
        self.mapping.inputs["Rotation"].default_value[2] = math.radians(rotation_deg)

    # ------------------------------------------------------------------ renders
    def _render(self, write_still: bool):
        t = time.perf_counter()
        with quiet_stdout():
            self.bpy.ops.render.render(write_still=write_still)
        self.render_seconds += time.perf_counter() - t

    def render_data(self, camera_obj) -> tuple[np.ndarray, np.ndarray]:
        """(planar depth (H, W) float32 with 0 = no surface, instance ids (H, W) uint16)."""
        scene, cy = self.scene, self.scene.cycles
        scene.camera = camera_obj
        saved = (cy.samples, cy.filter_width, cy.use_denoising, cy.use_adaptive_sampling)
        cy.samples, cy.filter_width, cy.use_denoising, cy.use_adaptive_sampling = 1, 0.01, False, False
        scene.render.use_compositing = True
        name = f"data_{os.getpid()}"
        self.file_output.file_name = name
        path = self.tmpdir / f"{name}.exr"
        if path.exists():
            path.unlink()
        try:
            self._render(write_still=False)
        finally:
            cy.samples, cy.filter_width, cy.use_denoising, cy.use_adaptive_sampling = saved
            scene.render.use_compositing = False
        if not path.is_file():
            raise RuntimeError(f"the compositor wrote no data pass file ({path})")
        depth, index = read_data_exr(path)
        path.unlink()
        return depth, index

    def render_rgb(self, camera_obj) -> np.ndarray:
        import cv2

        s, scene, cy = self.settings, self.scene, self.scene.cycles
        scene.camera = camera_obj
        cy.samples, cy.filter_width, cy.use_denoising = s.samples, 1.5, s.denoise
        scene.render.use_compositing = False
        path = self.tmpdir / f"rgb_{os.getpid()}.png"
        scene.render.filepath = str(path)
        self._render(write_still=True)
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise RuntimeError(f"Blender wrote no RGB image ({path})")
        path.unlink()
        return np.ascontiguousarray(img[..., ::-1])


def read_data_exr(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read Blender's multi-part data EXR -> (depth float32 with 0 = sky, instance uint16)."""
    import OpenEXR

    channels = {}
    with OpenEXR.File(str(path)) as exr:
        for part in exr.parts:
            for key, ch in part.channels.items():
                channels[key] = np.array(ch.pixels)
    depth = next(v for k, v in channels.items() if k.startswith("Depth"))
    index = next(v for k, v in channels.items() if k.startswith("Object Index"))
    if depth.dtype != np.float32:
        raise RuntimeError(f"{path}: depth pass is {depth.dtype}, expected float32 (32-bit EXR)")
    depth = np.where((depth >= DEPTH_BACKGROUND_BLENDER) | ~np.isfinite(depth), 0.0, depth).astype(np.float32)
    inst = np.rint(index).astype(np.int64)
    if inst.min() < 0 or inst.max() > 65535 or not np.allclose(index, inst, atol=1e-3):
        raise RuntimeError(f"{path}: Object Index pass is not integer ids")
    return depth, inst.astype(np.uint16)
