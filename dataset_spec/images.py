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
input, and reads the image's size from its header before decoding it (``image_size``): an image
over ``MAX_PIXELS`` is refused unread (a small file can declare a huge image); writers check
dtype/shape and write atomically.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .errors import SpecError

DEPTH_CHANNEL = "Z"
DEPTH_BACKGROUND = 0.0
MAX_PIXELS = 1 << 26  # 8192 x 8192: larger images are refused from their header, before decoding
# The decoder enforces the same cap itself (OpenCV reads it once, at its first decode in a process), so a header
# that misleads the check above still cannot make it allocate more.
if int(os.environ.get("OPENCV_IO_MAX_IMAGE_PIXELS", MAX_PIXELS + 1)) > MAX_PIXELS:
    os.environ["OPENCV_IO_MAX_IMAGE_PIXELS"] = str(MAX_PIXELS)
import cv2  # noqa: E402 - after the cap is set


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


def _next_marker(fh) -> int | None:
    """The next marker code as libjpeg finds it (``next_marker``): bytes before an 0xFF skipped, repeated 0xFF
    fill bytes swallowed, a stuffed 0xFF 0x00 passed over; None at the end of the file."""
    while True:
        c = fh.read(1)
        while c and c != b"\xff":
            c = fh.read(1)
        while c == b"\xff":
            c = fh.read(1)
        if not c:
            return None
        if c != b"\x00":
            return c[0]


def jpeg_size(path: str | Path) -> tuple[int, int]:
    """(height, width) from a JPEG's frame header (its SOF marker), without decoding it: the markers are walked
    as libjpeg walks them, so the size is the one the decoder will use."""
    path = Path(path)
    if not path.is_file():
        raise SpecError(path, "file is missing")
    with open(path, "rb") as fh:
        if fh.read(2) != b"\xff\xd8":
            raise SpecError(path, "not a readable JPEG (corrupt or truncated)")
        while True:
            marker = _next_marker(fh)
            if marker is None or marker in (0xD8, 0xD9, 0xDA):  # a second SOI, the end or the scan: no frame first
                raise SpecError(path, "not a readable JPEG (no frame header)")
            if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
                continue
            length = int.from_bytes(fh.read(2), "big")
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                head = fh.read(5)
                if len(head) < 5:
                    raise SpecError(path, "not a readable JPEG (truncated frame header)")
                return int.from_bytes(head[1:3], "big"), int.from_bytes(head[3:5], "big")
            if length < 2:
                raise SpecError(path, "not a readable JPEG (bad segment length)")
            fh.seek(length - 2, 1)


MAX_EXR_CHANNELS = 8  # the dataset's EXR files hold one (depth) to four (an HDR's RGBA) channels
MAX_EXR_BYTES = 1 << 28  # what decoding one EXR may take: channels x pixels x 4 bytes (a full-size depth map's)


def exr_size(path: str | Path) -> tuple[int, int]:
    """(height, width) of an OpenEXR file, from its header only. The dataset's EXR files are single-part with at most
    ``MAX_EXR_CHANNELS`` channels: a file of several parts or more channels is refused here, before any decoding
    (the decoder reads every part and channel, the size only the first)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise SpecError(path, "file is missing")
    try:
        with OpenEXR.File(str(path), header_only=True) as exr:
            parts = len(exr.parts)
            head = exr.header()
            channels, (lo, hi) = len(head.get("channels") or []), head["dataWindow"]
    except Exception as exc:  # OpenEXR raises RuntimeError/ValueError/... on bad files
        raise SpecError(path, f"not a readable EXR ({exc.__class__.__name__}: {exc})") from None
    if parts != 1:
        raise SpecError(path, f"is an EXR of {parts} parts (the dataset's are single-part)")
    if channels > MAX_EXR_CHANNELS:
        raise SpecError(path, f"is an EXR of {channels} channels (at most {MAX_EXR_CHANNELS} are read)")
    h, w = int(hi[1]) - int(lo[1]) + 1, int(hi[0]) - int(lo[0]) + 1
    if h * w <= MAX_PIXELS and channels * max(h, 0) * max(w, 0) * 4 > MAX_EXR_BYTES:  # what decoding would take
        # (a size beyond MAX_PIXELS is the pixel check's to refuse; here the channels that multiply a legal size)
        raise SpecError(path, f"is an EXR of {channels} channels of {w}x{h}: decoding it takes more than "
                              f"{MAX_EXR_BYTES >> 20} MiB")
    return h, w


def image_size(path: str | Path) -> tuple[int, int]:
    """(height, width) of a PNG, JPEG or EXR file from its header (by the file's suffix)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".exr":
        return exr_size(path)
    if suffix in (".jpg", ".jpeg"):
        return jpeg_size(path)
    return png_size(path)


def check_size_limit(path: str | Path, hw: tuple[int, int]) -> None:
    """SpecError when a header declares more than ``MAX_PIXELS`` (checked before decoding)."""
    if hw[0] <= 0 or hw[1] <= 0 or hw[0] * hw[1] > MAX_PIXELS:
        raise SpecError(path, f"declares a {hw[1]}x{hw[0]} image (at most {MAX_PIXELS} pixels are read)")


def _kind(path: Path) -> str:
    return "JPEG" if path.suffix.lower() in (".jpg", ".jpeg") else "PNG"


def _read_png(path: Path, flags: int) -> np.ndarray:
    path = Path(path)
    hw = image_size(path)
    check_size_limit(path, hw)  # also: missing, or not the format its name says
    data = np.fromfile(path, dtype=np.uint8)
    if data.size == 0:
        raise SpecError(path, "file is empty")
    try:
        img = cv2.imdecode(data, flags)
    except cv2.error as exc:  # pragma: no cover - OpenCV rarely raises here
        raise SpecError(path, f"not a readable {_kind(path)} ({exc})") from None
    if img is None:
        raise SpecError(path, f"not a readable {_kind(path)} (corrupt or truncated)")
    if img.shape[:2] != hw:  # the header and the decoder disagree: a file made to mislead the size check
        raise SpecError(path, f"decodes to {img.shape[1]}x{img.shape[0]} while its header says {hw[1]}x{hw[0]}")
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
    check_size_limit(path, exr_size(path))
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
