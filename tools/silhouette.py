"""Vectorised triangle-mesh silhouettes: near-plane clipping, scanline spans, pixel counts.

A pixel belongs to a silhouette when its centre lies inside (or on the edge of) at least one
projected triangle -- the same rule a ray-cast segmentation follows, so counts are comparable
with ``instance.png``. Pixel (u, v) has its centre at continuous coords (u, v) (spec convention).

Everything works on *spans*: for each triangle and each pixel row it covers, the inclusive
integer column range ``[x0, x1]`` of pixel centres inside it. The union of many triangles is
computed per (group, row) by sorting spans, so cost grows with the rows a mesh covers, not
with its area, and no per-object canvas has to be allocated.

Usage::

    s = measure_silhouettes(tris_cam, group, n_groups, K, width, height, near=0.1)
    s.image_pixels        # (G,) silhouette pixels inside the image, full resolution
    mask = rasterise_mask(project_camera_points(K, tris_cam), width, height)   # (H, W) bool
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dataset_spec.camera import project_camera_points

# Most spans one chunk of triangles may produce (bounds temporary memory to ~100 MB).
_MAX_SPANS_PER_CHUNK = 1_500_000


def _min3(a: np.ndarray) -> np.ndarray:
    """Minimum over axis 1 of an (N, 3, ...) array (much faster than ``a.min(axis=1)`` for 3)."""
    return np.minimum(np.minimum(a[:, 0], a[:, 1]), a[:, 2])


def _max3(a: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])


def _cross_near(a: np.ndarray, b: np.ndarray, near: float) -> np.ndarray:
    """Points (N, 3) where segments a-b (N, 3) cross the plane z = near (one end on each side)."""
    t = (near - a[:, 2]) / (b[:, 2] - a[:, 2])
    return a + t[:, None] * (b - a)


def clip_triangles_near(tris: np.ndarray, near: float) -> tuple[np.ndarray, np.ndarray]:
    """Clip camera-space triangles (T, 3, 3) to the half-space ``z >= near``.

    A triangle with one vertex in front becomes one smaller triangle, one with two vertices in
    front becomes a quad split into two triangles, one with none is dropped.

    Returns ``(clipped (T', 3, 3), source index (T',))``.
    """
    tris = np.asarray(tris, dtype=np.float64).reshape(-1, 3, 3)
    inside = tris[:, :, 2] >= near
    n_in = inside.sum(axis=1)
    index = np.arange(len(tris))
    out, src = [tris[n_in == 3]], [index[n_in == 3]]

    one = np.flatnonzero(n_in == 1)
    if one.size:
        i = np.argmax(inside[one], axis=1)  # the vertex in front
        vi, vj, vk = (tris[one, (i + s) % 3] for s in range(3))
        out.append(np.stack([vi, _cross_near(vi, vj, near), _cross_near(vi, vk, near)], axis=1))
        src.append(one)

    two = np.flatnonzero(n_in == 2)
    if two.size:
        i = np.argmin(inside[two], axis=1)  # the vertex behind
        vi, vj, vk = (tris[two, (i + s) % 3] for s in range(3))
        pji, pki = _cross_near(vj, vi, near), _cross_near(vk, vi, near)
        out += [np.stack([vj, vk, pki], axis=1), np.stack([vj, pki, pji], axis=1)]
        src += [two, two]
    return np.concatenate(out), np.concatenate(src)


def triangle_row_spans(tris_px: np.ndarray, row_lo: float = -np.inf, row_hi: float = np.inf):
    """Scanline spans of 2D triangles (T, 3, 2) over pixel rows ``row_lo..row_hi``.

    Returns ``(tri (S,), row (S,), x0 (S,), x1 (S,))``, all int64: for triangle ``tri`` the pixel
    centres ``(x, row)`` with ``x0 <= x <= x1`` lie inside it. Degenerate triangles give no spans.
    """
    tris_px = np.asarray(tris_px, dtype=np.float64).reshape(-1, 3, 2)
    ys = tris_px[:, :, 1]
    y_lo = np.maximum(np.ceil(_min3(ys)), row_lo)
    y_hi = np.minimum(np.floor(_max3(ys)), row_hi)
    n_rows = np.clip(y_hi - y_lo + 1, 0, None).astype(np.int64)
    total = int(n_rows.sum())
    empty = np.zeros(0, dtype=np.int64)
    if total == 0:
        return empty, empty, empty, empty
    tri = np.repeat(np.arange(len(tris_px)), n_rows)
    first = np.cumsum(n_rows) - n_rows
    row = y_lo[tri] + (np.arange(total) - np.repeat(first, n_rows))

    a = tris_px[tri]  # (S, 3, 2) edge starts
    b = np.roll(a, -1, axis=1)  # edge ends
    ay, by = a[:, :, 1], b[:, :, 1]
    y = row[:, None]
    spans_edge = (np.minimum(ay, by) <= y) & (y <= np.maximum(ay, by)) & (ay != by)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (y - ay) / (by - ay)
        x = a[:, :, 0] + t * (b[:, :, 0] - a[:, :, 0])
    x_min = _min3(np.where(spans_edge, x, np.inf))
    x_max = _max3(np.where(spans_edge, x, -np.inf))
    ok = np.isfinite(x_min) & np.isfinite(x_max)
    # A tiny tolerance keeps pixel centres exactly on an edge despite rounding.
    x0 = np.ceil(x_min[ok] - 1e-9)
    x1 = np.floor(x_max[ok] + 1e-9)
    keep = x1 >= x0
    return (tri[ok][keep], row[ok][keep].astype(np.int64), x0[keep].astype(np.int64), x1[keep].astype(np.int64))


@dataclass
class SpanUnion:
    """Per-group union of spans: pixel counts and tight pixel-centre bounds (NaN when empty)."""

    pixels: np.ndarray  # (G,) int64
    bounds: np.ndarray  # (G, 4) float: min x, min row, max x, max row of covered pixel centres


def union_spans(group: np.ndarray, row: np.ndarray, x0: np.ndarray, x1: np.ndarray, n_groups: int) -> SpanUnion:
    """Count the distinct pixels covered by the spans of each group (overlaps counted once).

    Inputs are (S,) int64 arrays; spans of one group and row may overlap in any way.
    """
    pixels = np.zeros(n_groups, dtype=np.int64)
    bounds = np.full((n_groups, 4), np.nan)
    if len(group) == 0:
        return SpanUnion(pixels, bounds)
    order = np.lexsort((x0, row, group))
    g, r, a, b = group[order], row[order], x0[order], x1[order]
    new_line = np.concatenate([[True], (g[1:] != g[:-1]) | (r[1:] != r[:-1])])
    line = np.cumsum(new_line) - 1
    offset = a.min()
    a, b = a - offset, b - offset
    stride = int(b.max()) + 2
    # Running maximum of span ends within a line: a larger line index dominates, so the
    # maximum restarts at every new line without a Python loop.
    running = np.maximum.accumulate(line * stride + b)
    prev_end = np.concatenate([[-1], running[:-1]]) - line * stride  # < 0 at a line's first span
    start = np.maximum(a, prev_end + 1)
    pixels += np.bincount(g, weights=np.clip(b - start + 1, 0, None), minlength=n_groups).astype(np.int64)

    first = np.flatnonzero(np.concatenate([[True], g[1:] != g[:-1]]))
    ids = g[first]
    bounds[ids, 0] = np.minimum.reduceat(a, first) + offset
    bounds[ids, 1] = r[first]  # sorted by row within a group
    bounds[ids, 2] = np.maximum.reduceat(b, first) + offset
    bounds[ids, 3] = np.maximum.reduceat(r, first)
    return SpanUnion(pixels, bounds)


def _chunks(tris_px: np.ndarray, row_lo: float, row_hi: float):
    """Triangle index ranges whose span count stays under ``_MAX_SPANS_PER_CHUNK``."""
    ys = tris_px[:, :, 1]
    rows = np.clip(np.minimum(np.floor(_max3(ys)), row_hi) - np.maximum(np.ceil(_min3(ys)), row_lo) + 1, 0, None)
    cum = np.cumsum(rows)
    start = 0
    while start < len(tris_px):
        base = cum[start - 1] if start else 0.0
        stop = int(np.searchsorted(cum, base + _MAX_SPANS_PER_CHUNK, side="right"))
        stop = max(stop, start + 1)
        yield start, stop
        start = stop


def group_spans(tris_px: np.ndarray, tri_group: np.ndarray, row_lo: float = -np.inf, row_hi: float = np.inf,
                col_lo: float = -np.inf, col_hi: float = np.inf):
    """Spans of triangles (T, 3, 2) labelled with their group (T,), clipped to a pixel window.

    Returns ``(group, row, x0, x1)`` (S,) int64 arrays (see ``triangle_row_spans``).
    """
    parts = []
    for lo, hi in _chunks(tris_px, row_lo, row_hi):
        tri, row, x0, x1 = triangle_row_spans(tris_px[lo:hi], row_lo, row_hi)
        x0 = np.maximum(x0, col_lo).astype(np.int64)
        x1 = np.minimum(x1, col_hi).astype(np.int64)
        keep = x1 >= x0
        parts.append((tri_group[lo:hi][tri[keep]], row[keep], x0[keep], x1[keep]))
    if not parts:
        z = np.zeros(0, dtype=np.int64)
        return z, z, z, z
    return tuple(np.concatenate(p) for p in zip(*parts))


@dataclass
class Silhouettes:
    """Amodal silhouettes of G objects in one camera (arrays indexed by group)."""

    image_pixels: np.ndarray  # (G,) int64, silhouette pixels inside the image (full resolution)
    image_bounds: np.ndarray  # (G, 4) float, [x0, y0, x1, y1] box around those pixels (pixel edges), NaN if none


def measure_silhouettes(tris_cam: np.ndarray, tri_group: np.ndarray, n_groups: int, K: np.ndarray, width: int,
                        height: int, near: float) -> Silhouettes:
    """Rasterise grouped camera-space triangles inside the image and measure each group's silhouette.

    Args:
        tris_cam: (T, 3, 3) triangles in camera coordinates (OpenCV axes).
        tri_group: (T,) int group (object) index of each triangle, in ``0..n_groups-1``.
        K: (3, 3) intrinsics. width, height: image size in pixels.
        near: clipping plane (metres); geometry in front of it is cut away before projection.
    """
    tris, src = clip_triangles_near(tris_cam, near)
    group = np.asarray(tri_group, dtype=np.int64)[src]
    pix = project_camera_points(K, tris)  # (T', 3, 2)
    inside = union_spans(*group_spans(pix, group, 0, height - 1, 0, width - 1), n_groups)
    return Silhouettes(inside.pixels, inside.bounds + np.array([-0.5, -0.5, 0.5, 0.5]))


def rasterise_mask(tris_px: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool mask of pixel centres covered by any 2D triangle (T, 3, 2)."""
    tris_px = np.asarray(tris_px, dtype=np.float64).reshape(-1, 3, 2)
    _, row, x0, x1 = group_spans(tris_px, np.zeros(len(tris_px), dtype=np.int64), 0, height - 1, 0, width - 1)
    diff = np.zeros((height, width + 1), dtype=np.int32)
    np.add.at(diff, (row, x0), 1)
    np.add.at(diff, (row, x1 + 1), -1)
    return np.cumsum(diff, axis=1)[:, :width] > 0
