"""What a ray-rendering model passes between its steps, as values rather than long parameter lists (the shape
nerfstudio gives ``RayBundle`` / ``RaySamples``)::

    views = ViewBundle(K, camera_to_world, width, height, feats, surface)    # the source views, once per forward
    rays = RayBundle(origins, dirs, view, cell, drop_own, spread)            # (R,) rays, sliced into chunks
    coarse = CoarseSamples(t, valid, t_near, t_far)                          # (R, S) samples along them
    rays[a:b], coarse[a:b], views.select(v)                                  # a chunk; one view alone

Frozen: a step reads them and makes new ones (``replace``), never changes what another step holds.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

from torch import Tensor


@dataclass(frozen=True)
class ViewBundle:
    """The source views the rays sample: cameras at the encoded size, the encoder's maps, predicted depth maps."""

    K: Tensor  # (V, 3, 3)
    camera_to_world: Tensor  # (V, 4, 4)
    width: int  # encoded image size, pixels
    height: int
    feats: list[Tensor]  # the encoder's maps, each (V, C, H_f, W_f)
    surface: Tensor | None = None  # (V, H_s, W_s) planar depth (model.surface_depth), metres; None without

    def __len__(self) -> int:
        return self.K.shape[0]

    def select(self, v: int) -> "ViewBundle":
        """View ``v`` alone, as if the others were not there."""
        return ViewBundle(self.K[v:v + 1], self.camera_to_world[v:v + 1], self.width, self.height,
                          [f[v:v + 1] for f in self.feats], None if self.surface is None else self.surface[v:v + 1])


@dataclass(frozen=True)
class _Sliced:
    """Per-ray tensors on a leading axis, sliced and indexed together."""

    def __getitem__(self, index) -> "_Sliced":
        return replace(self, **{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def __len__(self) -> int:
        return getattr(self, fields(self)[0].name).shape[0]


@dataclass(frozen=True)
class RayBundle(_Sliced):
    """Rays (R,): a cell's ``cell_rays``^2 rays consecutive."""

    origins: Tensor  # (R, 3) world
    dirs: Tensor  # (R, 3) world, unit
    view: Tensor  # (R,) long: the ray's target view, an index into the ViewBundle
    cell: Tensor  # (R,) long: the ray's cell among the item's V * S_h * S_w cells
    drop_own: Tensor  # (R,) bool: the target view's image features withheld from this ray
    spread: Tensor  # (R,) the ray's cell half-width per metre along it (its frustum's cross-section)


@dataclass(frozen=True)
class CoarseSamples(_Sliced):
    """The coarse samples along rays (R, S) and each ray's interval."""

    t: Tensor  # (R, S) metres along the ray
    valid: Tensor  # (R, S) bool
    t_near: Tensor  # (R,)
    t_far: Tensor  # (R,)
