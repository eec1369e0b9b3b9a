"""The samples a ray-casting model queries as one frozen value (nerfstudio's ``Frustums``): each sample a segment of
its ray, ``t`` +- ``half`` along it (a point: half 0) and, with ``model.sampler.footprint`` frustum, ``lateral``
either side of it (None: read at the ray, a point across it)::

    coarse = Frustums(origins, dirs, t, half, lateral)          # rays (R, 3); t, half, lateral (R, S)
    both = coarse.then(fine)                                   # the same rays' samples, coarse then fine
    coarse.points()                                             # (R, S, 3) world centres
    coarse.radius()                                             # (R, S) the sphere holding each segment
    Frustums.cat([a, b])                                        # more rays (the leading axis)
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pnyolo.components.footprints import segment_radius


@dataclass(frozen=True)
class Frustums:
    origins: Tensor  # (R, 3) world
    dirs: Tensor  # (R, 3) unit, world
    t: Tensor  # (R, S) metres along the ray: each segment's centre
    half: Tensor  # (R, S) metres: the segment is t +- half along the ray (0: a point)
    lateral: Tensor | None = None  # (R, S) metres either side of the ray (None: every sample a point across it)

    def points(self) -> Tensor:
        """(R, S, 3) world positions of the segments' centres."""
        return self.origins[:, None] + self.t[..., None] * self.dirs[:, None]

    def radius(self) -> Tensor:
        """(R, S) the radius of the sphere holding each segment (``footprints.segment_radius``); needs ``lateral``."""
        return segment_radius(self.half, self.lateral)

    def then(self, other: "Frustums") -> "Frustums":
        """These rays' samples followed by ``other``'s (the same rays), along the sample axis."""
        lateral = None if self.lateral is None else torch.cat([self.lateral, other.lateral], dim=1)
        return Frustums(self.origins, self.dirs, torch.cat([self.t, other.t], dim=1),
                        torch.cat([self.half, other.half], dim=1), lateral)

    @staticmethod
    def cat(parts: list["Frustums"]) -> "Frustums":
        """The rays of ``parts`` one after another (the leading axis)."""
        lateral = None if parts[0].lateral is None else torch.cat([p.lateral for p in parts])
        return Frustums(*(torch.cat([getattr(p, f) for p in parts]) for f in ("origins", "dirs", "t", "half")), lateral)
