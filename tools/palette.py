"""Deterministic colours for integer ids that keep neighbouring ids far apart.

Id ``k`` gets hue ``frac(k * 0.618...)`` (golden-ratio stepping: consecutive ids are ~137.5 degrees
apart on the hue circle, and no two of the first few hundred ids share a hue) and a value that cycles
over three levels, so ids 13 and 14 never look alike. Id 0 (nothing / sky) is black.

Usage::

    rgb = colourise(instance)         # (H, W) ints -> (H, W, 3) uint8
    id_colour(13), id_colour(14)      # (3,) uint8 each, clearly different
"""
from __future__ import annotations

import colorsys

import numpy as np

GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0  # 0.618...
_VALUES = (1.0, 0.78, 0.9)
_SATURATIONS = (0.85, 0.65)
BACKGROUND = np.array([0, 0, 0], dtype=np.uint8)


def id_colour(i: int, offset: float = 0.0) -> np.ndarray:
    """(3,) uint8 RGB colour of id ``i`` (``offset`` shifts all hues, e.g. for class maps)."""
    if i == 0:
        return BACKGROUND.copy()
    hue = (i * GOLDEN + offset) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, _SATURATIONS[i % 2], _VALUES[i % 3])
    return np.round(np.array([r, g, b]) * 255).astype(np.uint8)


def palette(ids, offset: float = 0.0) -> dict[int, np.ndarray]:
    """Colours of several ids: ``{id: (3,) uint8}``."""
    return {int(i): id_colour(int(i), offset) for i in ids}


def colourise(ids: np.ndarray, offset: float = 0.0) -> np.ndarray:
    """(H, W) integer id map -> (H, W, 3) uint8 RGB with ``id_colour`` per id."""
    ids = np.asarray(ids)
    present, inverse = np.unique(ids, return_inverse=True)
    table = np.stack([id_colour(int(i), offset) for i in present]) if present.size else np.zeros((0, 3), np.uint8)
    return table[inverse.reshape(ids.shape)]


def colour_distance(a, b) -> float:
    """Euclidean distance of two RGB colours in 0..255 units (a rough perceptual gap)."""
    return float(np.linalg.norm(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)))
