"""A cell's samples cover its frustum (issue 72, ``model.sampler.footprint frustum``): a segment's footprint holds
the projection of every point of the segment, the maps' maximum is read over it, a thin road user inside a cell's
frustum but off its centre ray is met by a segment, and the old sampling is the old model."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from test_pnyolo_common import small_config

from pnyolo.components.footprints import index_footprints, segment_footprints, segment_radius
from pnyolo.components.occupancy import segments_meet_boxes

torch.set_num_threads(2)


def test_a_segments_footprint_holds_the_projection_of_every_point_of_the_segment():
    gen = torch.Generator().manual_seed(0)
    n = 400
    centres = torch.stack([torch.rand(n, generator=gen) * 40 - 20, torch.rand(n, generator=gen) * 20 - 10,
                           torch.rand(n, generator=gen) * 40 + 1.5], dim=-1).double()
    half, lateral = torch.rand(n, generator=gen).double() * 1.5, torch.rand(n, generator=gen).double() * 1.0
    radius = segment_radius(half, lateral)
    fx, fy = torch.tensor([230.0], dtype=torch.float64), torch.tensor([210.0], dtype=torch.float64)
    box, front = segment_footprints(centres[None], radius, fx, fy)
    centre_uv = torch.stack([fx * centres[:, 0] / centres[:, 2], fy * centres[:, 1] / centres[:, 2]], dim=-1)
    checked = 0
    for _ in range(50):  # points of each segment's bounding sphere (its surface: the farthest ones)
        d = torch.randn(n, 3, generator=gen, dtype=torch.float64)
        p = centres + radius[:, None] * d / d.norm(dim=-1, keepdim=True)
        uv = torch.stack([fx * p[:, 0] / p[:, 2], fy * p[:, 1] / p[:, 2]], dim=-1)
        inside = ((uv - centre_uv).abs() <= box[0] + 1e-9).all(dim=-1)
        assert inside[front[0]].all()
        checked += int(front[0].sum())
    assert checked > 15000 and not front[0][centres[:, 2] - radius <= 0.05].any()  # behind or at the camera: none


def test_the_maximum_of_a_map_anywhere_in_a_footprint_is_what_it_reads():
    gen = torch.Generator().manual_seed(1)
    H, W, stride = 45, 80, 4  # a stride-4 map of a 320x180 image
    for _ in range(200):
        half = torch.rand(2, generator=gen) * 24 + 0.5  # up to 49 px wide: every pooling level
        uv = torch.rand(2, generator=gen) * torch.tensor([320.0, 180.0])
        fmap = torch.zeros(1, 1, H, W)
        lo = ((uv - half) / stride).ceil().clamp(min=0).long()  # a feature whose centre lies in the footprint
        hi = ((uv + half) / stride).floor().long().clamp(max=torch.tensor([W - 1, H - 1]))
        if (hi < lo).any():
            continue
        j = [int(torch.randint(int(lo[a]), int(hi[a]) + 1, (1,), generator=gen)) for a in range(2)]
        fmap[0, 0, j[1], j[0]] = 1.0
        got = index_footprints([fmap], uv[None, None], half[None, None], [stride], levels=4)
        assert float(got) == 1.0


def test_a_thin_road_user_in_a_cells_frustum_but_off_its_centre_ray_is_met_by_a_segment():
    """A 0.2 m pole 25 m down a ray, 0.6 m beside it: no point of the ray lies in it, the frustum segment of the
    bin there meets it (a cell 1 m wide there: lateral 0.5 m at the ray's 0.02 m per metre); the others do not."""
    origins, dirs = torch.zeros(1, 3, dtype=torch.float64), torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    t = torch.arange(1.25, 40, 2.5, dtype=torch.float64)[None]  # 16 bins of 2.5 m
    half = torch.full_like(t, 1.25)
    lateral = 0.02 * (t + half)
    pole = torch.tensor([[25.0, 0.6, 0.0, 0.2, 0.2, 3.0, 0.0]], dtype=torch.float64)
    met = segments_meet_boxes(origins, dirs, t, half, lateral, pole)[0, :, 0]
    assert met.tolist() == [abs(float(c) - 25.0) <= 1.25 + 0.1 for c in t[0]]  # the bins reaching 25 m +- 0.1
    assert not segments_meet_boxes(origins, dirs, t, half, torch.zeros_like(t), pole).any()  # the ray alone: no


def test_the_point_sampling_is_the_old_model_and_frustum_reads_footprints():
    """``footprint: point`` queries the features at the points (the old code path, bit for bit: the same weights
    give the same outputs as without the option); ``frustum`` differs and keeps its segments' widths."""
    from dataset_spec.synthetic import toy_scenario
    from pnyolo.data.grid import grid_for
    from pnyolo.models import build_model

    scn = toy_scenario(width=96, height=64)
    K = torch.tensor(np.stack([c.K for c in scn.cameras]), dtype=torch.float32)
    T = torch.tensor(np.stack([c.camera_to_world for c in scn.cameras]), dtype=torch.float32)
    grid, images = grid_for(96, 64, 1.0, 8), torch.rand(3, 3, 64, 96, generator=torch.Generator().manual_seed(0))
    outs = {}
    for footprint in ("point", "frustum", "both"):
        torch.manual_seed(0)
        model = build_model(small_config(**{"model.sampler.footprint": footprint,
                                            "model.sampler.fine_samples": 4}), 2).eval()
        with torch.no_grad():
            outs[footprint] = model(images, K, T, grid, return_samples=True)
    point, frustum, both = outs["point"], outs["frustum"], outs["both"]
    fp, ff, fb = (o.samples.frustums for o in (point, frustum, both))
    assert fp.lateral is None and ff.lateral is not None
    coarse = ff.half > 0
    assert (ff.lateral[coarse] > 0).all() and (ff.lateral[~coarse] == 0).all()
    assert torch.equal(fb.lateral, ff.lateral)  # the same segments, read twice over
    assert not torch.equal(point.ray_confidence, frustum.ray_confidence)
    assert not torch.equal(both.ray_confidence, frustum.ray_confidence)
    with pytest.raises(Exception, match="surface_depth"):
        small_config(**{"model.sampler.footprint": "frustum", "model.surface_depth": True,
                        "model.loss.surface_depth": 0.5})
