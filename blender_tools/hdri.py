"""Lighting variants: procedural equirectangular HDR skies (numpy) and the user's own HDR files.

Built-in variants are generated once and cached as float EXR files (``dataset_spec.images.
write_exr_rgb``) under ``$BLENDER_TOOLS_CACHE`` (default ``~/.cache/occluded-road-users/hdri``):

* ``noon``     clear sky, sun 58 deg high, strong sun -> hard shadows
* ``overcast`` CIE-like overcast sky, no sun, soft light
* ``sunset``   sun 4 deg above the horizon, warm, long shadows
* ``dusk``     sun below the horizon, dim blue sky with a warm glow

Equirectangular mapping (Blender's Environment Texture): row 0 is the zenith, the middle row
the horizon; column ``c`` has azimuth ``phi = 2 pi (c + 0.5) / W - pi`` with direction
``(-cos phi, sin phi, .)`` -- so a sun at ``phi = 0`` lights the scene from -X.

Example::

    variants = resolve_variants("noon,sunset", hdr_dir=None)   # [LightingModel, ...]
    draw, spec = random_spec("random:noon,dusk")               # (True, "noon,dusk"): one drawn per scene
    drawn_variant(["noon", "dusk"], "intersection_01-s3", 0)   # the same name for the same scene and seed
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from dataset_spec.names import check_name, excerpt

from .scene_model import LightingModel

HDRI_VERSION = 1
HDRI_SIZE = (256, 512)  # (H, W)
# name: (sun elevation deg, sun azimuth deg, sun irradiance, sun colour, zenith, horizon, ground, strength)
BUILTIN = {
    "noon": dict(sun_elev=58.0, sun_az=35.0, sun_E=14.0, sun_rgb=(1.0, 0.96, 0.9), zenith=(0.18, 0.35, 0.85),
                 horizon=(0.75, 0.85, 1.0), ground=(0.25, 0.23, 0.2), scale=1.0, strength=1.0),
    "overcast": dict(sun_elev=None, zenith=(0.9, 0.92, 0.95), horizon=(0.55, 0.57, 0.6), ground=(0.15, 0.15, 0.15),
                     scale=1.1, strength=1.0),
    "sunset": dict(sun_elev=4.0, sun_az=-60.0, sun_E=6.0, sun_rgb=(1.0, 0.45, 0.15), zenith=(0.12, 0.15, 0.4),
                   horizon=(1.0, 0.55, 0.3), ground=(0.1, 0.08, 0.07), scale=0.8, strength=1.0),
    "dusk": dict(sun_elev=-5.0, sun_az=120.0, sun_E=0.0, sun_rgb=(1.0, 0.4, 0.2), zenith=(0.03, 0.05, 0.14),
                 horizon=(0.35, 0.22, 0.2), ground=(0.02, 0.02, 0.025), scale=0.6, strength=1.0),
}
USER_SUFFIXES = (".hdr", ".exr")


def cache_dir() -> Path:
    return Path(os.environ.get("BLENDER_TOOLS_CACHE", Path.home() / ".cache" / "occluded-road-users")) / "hdri"


def _directions(h: int, w: int):
    elev = (0.5 - (np.arange(h) + 0.5) / h) * np.pi
    phi = 2 * np.pi * (np.arange(w) + 0.5) / w - np.pi
    el, ph = np.meshgrid(elev, phi, indexing="ij")
    d = np.stack([-np.cos(ph) * np.cos(el), np.sin(ph) * np.cos(el), np.sin(el)], axis=-1)
    solid_angle = np.cos(el) * (np.pi / h) * (2 * np.pi / w)
    return d, el, solid_angle


def sun_direction(elev_deg: float, az_deg: float) -> np.ndarray:
    el, ph = np.radians(elev_deg), np.radians(az_deg)
    return np.array([-np.cos(ph) * np.cos(el), np.sin(ph) * np.cos(el), np.sin(el)])


def make_sky(name: str, size=HDRI_SIZE) -> np.ndarray:
    """A built-in variant's equirectangular radiance (H, W, 3) float32."""
    p = BUILTIN[name]
    h, w = size
    d, el, omega = _directions(h, w)
    up = np.clip(np.sin(el), 0, 1)[..., None]
    zen, hor, gnd = (np.asarray(p[k], dtype=np.float64) for k in ("zenith", "horizon", "ground"))
    sky = hor + (zen - hor) * up ** 0.6
    if name == "overcast":
        sky = sky * ((1 + 2 * up) / 3) * 1.4
    img = np.where((el >= 0)[..., None], sky, gnd * np.ones_like(sky))
    if p.get("sun_elev") is not None:
        s = sun_direction(p["sun_elev"], p["sun_az"])
        cosang = np.clip(d @ s, -1, 1)
        ang = np.degrees(np.arccos(cosang))
        # glow around the sun (also below the horizon at dusk)
        glow = np.exp(-ang / 25.0)[..., None] * np.asarray(p["sun_rgb"]) * (0.6 if name != "noon" else 0.25)
        img = img + np.where((el >= -0.02)[..., None], glow, 0)
        if p["sun_E"] > 0:
            disc = (ang < 1.6) & (el > 0)
            E = float((omega * disc).sum())
            if E > 0:
                img[disc] += np.asarray(p["sun_rgb"]) * (p["sun_E"] / E)
    return (img * p["scale"]).astype(np.float32)


def builtin_path(name: str) -> Path:
    """Generate (once) and return the cached EXR of a built-in variant."""
    from dataset_spec.images import write_exr_rgb

    path = cache_dir() / f"{name}_v{HDRI_VERSION}.exr"
    if not path.is_file():
        write_exr_rgb(path, make_sky(name))
    return path


class HdrError(ValueError):
    """Bad --hdr / --hdr-dir input (reported as a one-line user error)."""


def user_hdr_files(hdr_dir: str | Path) -> dict[str, Path]:
    d = Path(hdr_dir)
    if d.is_file():
        raise HdrError(f"--hdr-dir {d}: is a file; expected a folder of .hdr/.exr files")
    if not d.is_dir():
        raise HdrError(f"--hdr-dir {d}: no such directory")
    found = {p.stem: p for p in sorted(d.iterdir()) if p.suffix.lower() in USER_SUFFIXES and p.is_file()}
    if not found:
        raise HdrError(f"--hdr-dir {d}: no .hdr or .exr files in it")
    return found


def check_hdr_file(path: Path) -> None:
    """HdrError unless ``path`` loads as an image: Blender would render a missing or unreadable
    environment map as its magenta missing-texture colour and say nothing."""
    from dataset_spec.errors import SpecError
    from dataset_spec.images import read_exr_rgb

    if path.suffix.lower() == ".exr":
        try:
            img = read_exr_rgb(path)
        except SpecError as exc:
            raise HdrError(f"HDR file {path}: {exc.message}") from None
    else:
        import cv2

        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise HdrError(f"HDR file {path}: not a readable Radiance .hdr image")
    if img.ndim != 3 or min(img.shape[:2]) < 2 or not np.isfinite(img).all():
        raise HdrError(f"HDR file {path}: expected an RGB image with finite values, got shape {img.shape}")


RANDOM = "random"


def random_spec(spec: str) -> tuple[bool, str]:
    """``--hdr random`` (every variant) or ``random:A,B`` (those): (True, the variants to draw from);
    any other value: (False, it unchanged)."""
    head, sep, rest = spec.partition(":")
    if head.strip() != RANDOM:
        return False, spec
    if sep and not rest.strip():
        raise HdrError("--hdr random:...: name the variants to draw from after the colon (e.g. random:noon,dusk)")
    return True, rest if sep else "all"


def drawn_variant(names: list[str], scenario: str, seed: int) -> str:
    """The one variant of ``names`` a scene is rendered under with ``--hdr random``: drawn by the scene's
    name and the run's seed (a hash, the same on every machine and Python), so a re-run draws it again."""
    digest = hashlib.sha256(f"{scenario}/{seed}".encode()).digest()
    return names[int.from_bytes(digest[:8], "big") % len(names)]


def resolve_variants(spec: str, hdr_dir: str | Path | None = None) -> list[tuple[LightingModel, Path]]:
    """``--hdr`` value -> [(LightingModel, file path)].

    ``spec``: ``all`` (built-ins plus every file of ``hdr_dir``), or a comma list of built-in names,
    names of files in ``hdr_dir`` (without suffix) and paths to ``.hdr``/``.exr`` files.
    """
    available: dict[str, Path | None] = {n: None for n in BUILTIN}
    if hdr_dir is not None:
        available.update(user_hdr_files(hdr_dir))
    items = [s.strip() for s in spec.split(",") if s.strip()]
    if not items:
        raise HdrError("--hdr is empty")
    chosen: dict[str, Path | None] = {}
    for item in items:
        if item == "all":
            chosen.update(available)
        elif item in available:
            chosen[item] = available[item]
        elif item.lower().endswith(USER_SUFFIXES) or os.sep in item:
            p = Path(item)
            if not p.is_file():
                raise HdrError(f"HDR file {item} does not exist")
            chosen[p.stem] = p
        else:
            raise HdrError(f"unknown HDR variant {item!r} (built-in: {', '.join(BUILTIN)}"
                           + (f"; in --hdr-dir: {', '.join(n for n in available if n not in BUILTIN)}" if hdr_dir else "")
                           + "; or give a path to a .hdr/.exr file)")
    out = []
    for name, path in chosen.items():
        if (why := check_name(name)) is not None:
            raise HdrError(f"HDR variant name {excerpt(name)} {why} (rename the file)")
        if path is None:
            path = builtin_path(name)
            strength = BUILTIN[name]["strength"]
        else:
            check_hdr_file(Path(path))
            strength = 1.0
        out.append((LightingModel(name, Path(path).name, strength, 0.0), Path(path)))
    return out
