"""Which rays the model casts and where along them it queries 3D points (nerfstudio's ray samplers).

    uv = cell_ray_pixels(grid, rays_per_side=2)                                   # (S_h, S_w, 4, 2)
    t, valid = sample_along_rays(origins, dirs, 16, 2.0, 42.0, slab=(0.0, 3.5))   # (R, S), (R, S)
    t_fine = sample_from_weights(t_near, t_far, weights, 8)                       # (R, 8): hierarchical
    points = origins[:, None] + t[..., None] * dirs[:, None]                      # (R, S, 3)

Distances ``t`` are metres along unit rays; ``valid`` marks samples inside the sampled interval.
Coarse samples stand for equal bins of the interval (stratified: one uniform draw in each); fine
samples are drawn from the piecewise-constant density the coarse pass's confidences give those
bins, as NeRF's hierarchical sampling does, with a uniform floor so every bin keeps a chance.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class SamplerConfig:
    num_samples: int = 128  # samples per ray, one in each of as many equal bins
    near: float = 1.0  # metres along the (unit) ray where sampling starts
    far: float = 13.0  # metres along the ray where sampling ends
    stratified: bool = True  # jitter samples in training
    slab_clip: bool = False  # clip rays to the slab data.ground_z <= z <= height_cap
    height_cap: float = 3.0  # slab_clip: the slab's top, world z in metres (above data.ground_z)
    # Hierarchical sampling (not in the paper; 0: off): this many more samples per ray drawn where
    # the coarse samples' confidence is (pnyolo.components.ray_samplers.sample_from_weights); the MLP
    # is told each sample's bin half-width (0 for these points), as coarse samples stand for a bin.
    fine_samples: int = 0
    # Rays per cell side (not in the paper; 1: one ray through the cell's centre): k x k rays
    # through a regular sub-grid of the cell, their samples aggregated together as one thick ray,
    # so a road user narrower than a cell is met by a ray wherever in the cell it stands. k^2 times
    # the MLP work of one ray.
    cell_rays: int = 1
    # What a coarse sample reads from each source view (not in the paper): "point", the features at its point (the
    # paper's); "frustum", the maximum of every map over the projected footprint of the cell's frustum segment the
    # sample stands for (pnyolo.components.footprints), so a road user anywhere in the cell between the bin's depths
    # is read, however thin; "both", the two side by side (where the point is and what its segment covers), fine
    # samples then reading their point's own small footprint. Fine samples stay points otherwise. "evidence": where
    # along its segment the source views agree (pnyolo.components.segment_evidence, issue 89), read at
    # evidence_points sub-points: each view's features there, the place and the agreement as inputs; fine samples are
    # drawn from the coarse confidence times that place within each bin.
    footprint: str = "point"
    footprint_levels: int = 4  # frustum: the coarsest pooling of a map, 2^levels of its features a side
    evidence_points: int = 8  # evidence: sub-points a coarse segment is read at
    # How fine samples are drawn (fine_samples > 0): "max", from the coarse confidence, the maximum over the
    # anchors; "per_anchor", each anchor's confidence along the ray normalised to its own peak, summed, so a weak
    # anchor's peak (a pedestrian behind a bus another view shows) gets as many fine samples as the occluder's
    fine_weights: str = "max"


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


def ray_interval(origins: Tensor, dirs: Tensor, near: float, far: float, slab: tuple[float, float] | None = None
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """Each ray's sampled interval: (t_near (R,), t_far (R,), nonempty (R,) bool), [near, far]
    clipped to the ground..height-cap slab when ``slab`` is given (``slab_interval``)."""
    if slab is not None:
        return slab_interval(origins, dirs, near, far, slab[0], slab[1])
    R = origins.shape[0]
    return (torch.full((R,), near, device=origins.device, dtype=origins.dtype),
            torch.full((R,), far, device=origins.device, dtype=origins.dtype),
            torch.ones(R, dtype=torch.bool, device=origins.device))


def sample_along_rays(origins: Tensor, dirs: Tensor, num_samples: int, near: float, far: float, *,
                      stratified: bool = False, slab: tuple[float, float] | None = None,
                      generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """Distances t (R, S) along unit rays (R, 3) and a validity mask (R, S).

    Samples are bin centres of S equal bins in [near, far] (or the slab-clipped interval),
    jittered inside their bins when ``stratified``.
    """
    t_near, t_far, ok = ray_interval(origins, dirs, near, far, slab)
    return bin_samples(t_near, t_far, num_samples, stratified, generator), ok[:, None].expand(-1, num_samples)


def bin_samples(t_near: Tensor, t_far: Tensor, num: int, stratified: bool = False,
                generator: torch.Generator | None = None) -> Tensor:
    """(R, num) distances: one per equal bin of each ray's [t_near, t_far] (R,), at the bin's centre
    or, ``stratified``, at a uniform random point of it."""
    R = t_near.shape[0]
    if stratified:
        u = torch.rand(R, num, device=t_near.device, dtype=t_near.dtype, generator=generator)
    else:
        u = torch.full((R, num), 0.5, device=t_near.device, dtype=t_near.dtype)
    frac = (torch.arange(num, device=t_near.device, dtype=t_near.dtype) + u) / num
    return t_near[:, None] + (t_far - t_near)[:, None] * frac


FINE_FLOOR = 0.1  # share of the fine samples' density spread evenly over the interval


def sample_from_weights(t_near: Tensor, t_far: Tensor, weights: Tensor, num: int, stratified: bool = False,
                        generator: torch.Generator | None = None) -> Tensor:
    """``num`` distances per ray (R, num), sorted, drawn from the density of the coarse bins.

    Args:
        t_near, t_far: (R,) each ray's interval, cut into S equal bins.
        weights: (R, S) non-negative weight of each bin (the coarse pass's confidence there).
        stratified: one uniform draw in each of ``num`` equal quantile strata (training); else
            the strata's middles (evaluation: deterministic).
    """
    R, S = weights.shape
    w = weights.clamp_min(0)
    total = w.sum(dim=1, keepdim=True)
    pdf = torch.where(total > 0, w / total.clamp_min(1e-12), torch.full_like(w, 1.0 / S))
    pdf = (1 - FINE_FLOOR) * pdf + FINE_FLOOR / S
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), pdf.cumsum(dim=1)], dim=1)  # (R, S + 1)
    cdf[:, -1] = 1.0
    u = torch.rand(R, num, device=weights.device, dtype=weights.dtype, generator=generator) if stratified \
        else torch.full((R, num), 0.5, device=weights.device, dtype=weights.dtype)
    u = (torch.arange(num, device=weights.device, dtype=weights.dtype) + u) / num  # (R, num) in [0, 1)
    # bin of each draw: how many cdf values are <= u (searchsorted right=True, which ONNX lacks)
    k = (cdf[:, None, :] <= u[:, :, None]).sum(dim=2).clamp(1, S) - 1
    lo, hi = cdf.gather(1, k), cdf.gather(1, k + 1)
    frac = torch.where(hi > lo, (u - lo) / (hi - lo).clamp_min(1e-12), torch.full_like(u, 0.5))
    width = ((t_far - t_near) / S)[:, None]
    return t_near[:, None] + (k.to(u.dtype) + frac) * width


def cell_ray_pixels(grid_h: int, grid_w: int, width: int, height: int, rays_per_side: int = 1, device=None) -> Tensor:
    """Pixels (grid_h, grid_w, rays_per_side**2, 2) the rays of each YOLO cell go through.

    The cells split the image extent [-0.5, W-0.5] evenly (``geometry.grid_cell_centres``); a cell's
    rays go through the centres of a regular rays_per_side x rays_per_side sub-grid of it (one ray:
    the cell's centre).
    """
    k = rays_per_side
    cw, ch = width / grid_w, height / grid_h
    sub = (torch.arange(k, device=device, dtype=torch.float32) + 0.5) / k  # sub-cell centres in (0, 1)
    sv, su = torch.meshgrid(sub, sub, indexing="ij")
    cols = torch.arange(grid_w, device=device, dtype=torch.float32)[None, :, None]
    rows = torch.arange(grid_h, device=device, dtype=torch.float32)[:, None, None]
    u = (cols + su.reshape(1, 1, -1)) * cw - 0.5  # (1, S_w, k^2)
    v = (rows + sv.reshape(1, 1, -1)) * ch - 0.5  # (S_h, 1, k^2)
    return torch.stack(torch.broadcast_tensors(u, v), dim=-1)


def cell_spread(K: Tensor, grid, rays_per_side: int = 1) -> Tensor:
    """(V,) each view's cell half-width per metre along a ray: half a cell (of one of its ``rays_per_side``^2 rays)
    over the focal length, the wider of the two axes (a frustum segment's cross-section at distance t is this
    times t either side of the ray)."""
    cw, ch = grid.width / grid.grid_w / rays_per_side, grid.height / grid.grid_h / rays_per_side
    return torch.maximum(cw / (2 * K[:, 0, 0]), ch / (2 * K[:, 1, 1]))


def fine_weights(confidence: Tensor, rule: str = "max") -> Tensor:
    """(R, S) weights of the coarse bins for the fine samples from the coarse confidences (R, S, A):
    ``max``, the most confident anchor's; ``per_anchor``, each anchor's confidence over its own peak along the
    ray, summed over the anchors (``SamplerConfig.fine_weights``)."""
    if rule == "max":
        return confidence.max(dim=-1).values
    return (confidence / confidence.max(dim=1, keepdim=True).values.clamp_min(1e-6)).sum(dim=-1)
