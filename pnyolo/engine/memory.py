"""Process memory: keep glibc's allocator from holding on to freed activations of chunked rendering.

When a step's rays do not fit one chunk (``model.chunk_memory_mb``), rendering allocates and frees
blocks of a few megabytes once per chunk. glibc's malloc raises its mmap threshold to the largest
block freed (up to 32 MiB), so those blocks then come from the heap, where fragmentation keeps them
resident. Measured at 960x540, 128 samples per ray, 192 chunks: 8.6 GB resident for 0.12 GB live.
A fixed 4 MiB threshold hands such blocks back to the system when freed (0.8 GB there), but costs
about 10 % step time on the cpu preset, whose steps fit one chunk: it is set only for chunked models.

    chunked = limit_heap_retention(model, num_views=3, cells=3 * grid.grid_h * grid.grid_w)
"""
from __future__ import annotations

import ctypes
import ctypes.util

M_MMAP_THRESHOLD = -3  # mallopt parameter (glibc malloc.h)
MMAP_THRESHOLD_BYTES = 4 << 20


def fix_mmap_threshold(nbytes: int = MMAP_THRESHOLD_BYTES) -> bool:
    """Fix glibc's mmap threshold (disables its dynamic raise); False where there is no glibc."""
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        return bool(libc.mallopt(M_MMAP_THRESHOLD, int(nbytes)))
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to do
        return False


def limit_heap_retention(model, num_views: int, cells: int) -> bool:
    """``fix_mmap_threshold`` when ``model`` renders a step's ``cells`` grid cells (all views) in
    more than one chunk; True when set."""
    if model.render_chunks(num_views, cells) <= 1:
        return False
    return fix_mmap_threshold()
