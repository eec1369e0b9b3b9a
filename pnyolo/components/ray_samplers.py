"""Where along each camera ray the model queries 3D points (nerfstudio's ray samplers).

    t, valid = sample_along_rays(origins, dirs, 16, 2.0, 42.0, slab=(0.0, 3.5))   # (R, S), (R, S)
    points = origins[:, None] + t[..., None] * dirs[:, None]                      # (R, S, 3)

Distances ``t`` are metres along unit rays; ``valid`` marks samples inside the sampled interval.
"""
from __future__ import annotations

import torch
from torch import Tensor


def slab_interval(origins: Tensor, dirs: Tensor, near: float, far: float, ground_z: float,
                  height_cap: float) -> tuple[Tensor, Tensor, Tensor]:
    """Clip each ray's [near, far] to the slab ground_z <= z <= height_cap (world z).

    Returns (t_near (R,), t_far (R,), nonempty (R,) bool). Rays that never enter the slab
    between near and far are empty (their samples get valid=False).
    """
    oz, dz = origins[..., 2], dirs[..., 2]
    flat = dz.abs() < 1e-9
    safe = torch.where(flat, torch.ones_like(dz), dz)
    t0 = (ground_z - oz) / safe
    t1 = (height_cap - oz) / safe
    lo, hi = torch.minimum(t0, t1), torch.maximum(t0, t1)
    inside = (oz >= ground_z) & (oz <= height_cap)
    lo = torch.where(flat, torch.where(inside, torch.full_like(lo, -torch.inf), torch.full_like(lo, torch.inf)), lo)
    hi = torch.where(flat, torch.where(inside, torch.full_like(hi, torch.inf), torch.full_like(hi, -torch.inf)), hi)
    t_near = torch.clamp(lo, min=near)
    t_far = torch.clamp(hi, max=far)
    nonempty = t_far > t_near
    t_near = torch.where(nonempty, t_near, torch.full_like(t_near, near))
    t_far = torch.where(nonempty, t_far, torch.full_like(t_far, far))
    return t_near, t_far, nonempty


def sample_along_rays(origins: Tensor, dirs: Tensor, num_samples: int, near: float, far: float, *,
                      stratified: bool = False, slab: tuple[float, float] | None = None,
                      generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """Distances t (R, S) along unit rays (R, 3) and a validity mask (R, S).

    Samples are bin centres of S equal bins in [near, far] (or the slab-clipped interval),
    jittered inside their bins when ``stratified``.
    """
    R = origins.shape[0]
    if slab is not None:
        t_near, t_far, ok = slab_interval(origins, dirs, near, far, slab[0], slab[1])
    else:
        t_near = torch.full((R,), near, device=origins.device, dtype=origins.dtype)
        t_far = torch.full((R,), far, device=origins.device, dtype=origins.dtype)
        ok = torch.ones(R, dtype=torch.bool, device=origins.device)
    if stratified:
        u = torch.rand(R, num_samples, device=origins.device, dtype=origins.dtype, generator=generator)
    else:
        u = torch.full((R, num_samples), 0.5, device=origins.device, dtype=origins.dtype)
    frac = (torch.arange(num_samples, device=origins.device, dtype=origins.dtype) + u) / num_samples
    t = t_near[:, None] + (t_far - t_near)[:, None] * frac
    return t, ok[:, None].expand(R, num_samples)
