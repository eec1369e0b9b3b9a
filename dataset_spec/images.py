"""Readers and atomic writers for per-camera image files.

=============  ==========================  =====================================
file           on disk                     in memory (reader's return value)
=============  ==========================  =====================================
RGB            8-bit PNG, 3 channels       (H, W, 3) uint8, RGB order
instance       16-bit PNG, 1 channel       (H, W) uint16, 0 = no object
semantic       derived from instance       (H, W) uint8 class ids, 0 = nothing
depth          single-part float32 EXR,    (H, W) float32 planar depth in metres,
               channel ``Z``               0.0 where no surface (sky)
=============  ==========================  =====================================

Every reader raises ``SpecError`` naming the file for missing, truncated or malformed
input; writers check dtype/shape and write atomically.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .atomic import atomic_path
from .errors import SpecError

DEPTH_CHANNEL = "Z"
DEPTH_BACKGROUND = 0.0


def check_resolution(path: str | Path, shape, expected) -> None:
    """SpecError naming ``path`` when an image's (H, W) ``shape`` is not the camera's ``expected`` (H, W)."""
    if tuple(shape) != tuple(expected):
        raise SpecError(path, f"shape {tuple(shape)} differs from camera resolution {tuple(expected)}")


def png_size(path: str | Path) -> tuple[int, int]:
    """(height, width) from a PNG's header, without decoding it; SpecError for a missing or non-PNG file."""
    path = Path(path)
    if not path.is_file():
        raise SpecError(path, "file is missing")
    with open(path, "rb") as fh:
        head = fh.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise SpecError(path, "not a readable PNG (corrupt or truncated)")
    return int.from_bytes(head[20:24], "big"), int.from_bytes(head[16:20], "big")


def _read_png(path: Path, flags: int) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise SpecError(path, "file is missing")
    data = np.fromfile(path, dtype=np.uint8)
    if data.size == 0:
        raise SpecError(path, "file is empty")
    try:
        img = cv2.imdecode(data, flags)
    except cv2.error as exc:  # pragma: no cover - OpenCV rarely raises here
        raise SpecError(path, f"not a readable PNG ({exc})") from None
    if img is None:
        raise SpecError(path, "not a readable PNG (corrupt or truncated)")
    return img


def read_rgb(path: str | Path) -> np.ndarray:
    img = _read_png(Path(path), cv2.IMREAD_UNCHANGED)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] not in (3, 4):
        raise SpecError(path, f"RGB must be an 8-bit 3-channel PNG, got {img.dtype} {img.shape}")
    return np.ascontiguousarray(cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB))


def write_rgb(path: str | Path, rgb: np.ndarray) -> None:
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"RGB must be (H, W, 3) uint8, got {rgb.dtype} {rgb.shape}")
    _write_png(path, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def read_instance(path: str | Path) -> np.ndarray:
    img = _read_png(Path(path), cv2.IMREAD_UNCHANGED)
    if img.dtype != np.uint16 or img.ndim != 2:
        raise SpecError(path, f"instance segmentation must be a 16-bit 1-channel PNG, got {img.dtype} {img.shape}")
    return img


def write_instance(path: str | Path, instance: np.ndarray) -> None:
    instance = np.asarray(instance)
    if instance.dtype != np.uint16 or instance.ndim != 2:
        raise ValueError(f"instance ids must be (H, W) uint16, got {instance.dtype} {instance.shape}")
    _write_png(path, instance)


def _write_png(path: str | Path, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    with atomic_path(path) as tmp:
        buf.tofile(tmp)


def semantic_from_instance(instance: np.ndarray, class_of_instance: dict[int, int]) -> np.ndarray:
    """Map instance ids to class ids through a lookup table; unknown ids map to 0."""
    lut = np.zeros(max(class_of_instance, default=0) + 1, dtype=np.uint8)
    for inst, cls in class_of_instance.items():
        lut[inst] = cls
    inst = np.asarray(instance).astype(np.int64)
    return np.where(inst < lut.size, lut[np.minimum(inst, lut.size - 1)], 0).astype(np.uint8)


def _read_exr_channels(path: str | Path) -> dict[str, np.ndarray]:
    """All channels of an EXR file as arrays; SpecError for a missing or unreadable file."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise SpecError(path, "file is missing")
    try:
        with OpenEXR.File(str(path)) as exr:
            return {name: np.array(ch.pixels) for name, ch in exr.channels().items()}
    except Exception as exc:  # OpenEXR raises RuntimeError/ValueError/... on bad files
        raise SpecError(path, f"not a readable EXR ({exc})") from None


def read_depth(path: str | Path) -> np.ndarray:
    channels = _read_exr_channels(path)
    if DEPTH_CHANNEL not in channels:
        raise SpecError(path, f"depth EXR has no '{DEPTH_CHANNEL}' channel (has {sorted(channels)})")
    depth = channels[DEPTH_CHANNEL]
    if depth.dtype != np.float32 or depth.ndim != 2:
        raise SpecError(path, f"depth must be a float32 (32-bit) single channel, got {depth.dtype} {depth.shape}")
    return depth


def write_depth(path: str | Path, depth: np.ndarray) -> None:
    import OpenEXR

    depth = np.asarray(depth)
    if depth.dtype != np.float32 or depth.ndim != 2:
        raise ValueError(f"depth must be (H, W) float32, got {depth.dtype} {depth.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, {DEPTH_CHANNEL: np.ascontiguousarray(depth)}) as exr:
            exr.write(str(tmp))


def read_exr_rgb(path: str | Path) -> np.ndarray:
    """Read an RGB(A) float EXR (e.g. an HDR environment map) as (H, W, 3) float32."""
    ch = _read_exr_channels(path)
    for packed in ("RGB", "RGBA"):
        if packed in ch and ch[packed].ndim == 3:
            return ch[packed][..., :3].astype(np.float32)
    if all(c in ch for c in "RGB"):
        return np.stack([ch[c].astype(np.float32) for c in "RGB"], axis=-1)
    raise SpecError(path, f"EXR has no RGB channels (has {sorted(ch)})")


def write_exr_rgb(path: str | Path, rgb: np.ndarray) -> None:
    import OpenEXR

    rgb = np.ascontiguousarray(np.asarray(rgb, dtype=np.float32))
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"RGB EXR must be (H, W, 3), got {rgb.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, {"RGB": rgb}) as exr:
            exr.write(str(tmp))
