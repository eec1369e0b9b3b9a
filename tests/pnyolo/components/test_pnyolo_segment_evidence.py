"""Where along a frustum segment the source views agree (pnyolo.components.segment_evidence): an object on a segment is
found where the target view's ray and another view's ray through it cross, not at the segment's middle."""
from __future__ import annotations

import math

import pytest
import torch

from pnyolo.components.encoder import index_features
from pnyolo.components.geometry import Cameras
from pnyolo.components.segment_evidence import NO_AGREEMENT, segment_evidence, sub_points

W, H, C = 64, 48, 8
Tensor = torch.Tensor


def _looking(at, heading: float) -> Tensor:
    """An OpenCV camera_to_world at ``at`` looking level along world heading ``heading``."""
    forward = torch.tensor([math.cos(heading), math.sin(heading), 0.0])
    right = torch.tensor([math.sin(heading), -math.cos(heading), 0.0])
    c2w = torch.eye(4)
    c2w[:3, :3] = torch.stack([right, torch.linalg.cross(forward, right), forward], dim=1)
    c2w[:3, 3] = torch.tensor(at)
    return c2w


def _scene(target_m: float, side_sees: bool = True, views: int = 2):
    """Views of one object ``target_m`` metres along view 0's optical axis: view 0 from behind it, view 1 from
    the side (or, with ``side_sees`` False, looking away), a third from the other side; every map is noise, except a
    3-pixel blob of one feature vector where each view sees the object."""
    gen = torch.Generator().manual_seed(0)
    K = torch.tensor([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]]).expand(views, 3, 3)
    side = math.pi / 2 if side_sees else -math.pi / 2
    c2w = torch.stack([_looking((0.0, 0.0, 0.0), 0.0), _looking((target_m, -10.0, 0.0), side),
                       _looking((target_m + 1.0, 9.0, 0.0), -math.pi / 2)][:views])
    cams = Cameras(K, c2w, W, H)
    maps = torch.randn(views, C, H, W, generator=gen)
    obj = torch.randn(C, generator=gen) * 3
    uv, _, _, valid = cams.project(torch.tensor([[target_m, 0.0, 0.0]]))
    for v in range(views):
        if valid[v, 0]:
            u, w = (int(round(x)) for x in uv[v, 0].tolist())
            maps[v, :, w - 1:w + 2, u - 1:u + 2] = obj[:, None, None]
    return cams, maps


def _evidence(cams: Cameras, maps: Tensor, t: float, half: float, m: int):
    origin, direction = torch.zeros(3), torch.tensor([1.0, 0.0, 0.0])  # view 0's optical axis
    ts = sub_points(torch.tensor([t]), torch.tensor([half]), m)  # (1, m)
    points = origin + ts[..., None] * direction  # (1, m, 3)
    uv, _, _, valid = cams.project(points)
    feats = index_features([maps], uv.reshape(2, -1, 2), [1]).reshape(2, 1, m, C)
    return segment_evidence(feats, valid.reshape(2, 1, m), sharpness=4.0), ts


def test_a_segments_evidence_peaks_where_two_views_rays_cross_an_object_on_it():
    for target in (8.7, 10.5, 11.6):  # anywhere in the 8-12 m segment, not only its middle
        cams, maps = _scene(target)
        ev, ts = _evidence(cams, maps, 10.0, 2.0, 16)
        best = float(ts[0, ev.weights[0].argmax()])
        assert abs(best - target) <= 0.13, (target, best)  # the sub-point nearest the object (0.25 m apart)
        placed = 10.0 + 2.0 * float(ev.offset[0])
        assert abs(placed - target) < 0.3, (target, placed)
        assert float(ev.weights[0].max()) > 0.3  # a peak, not a spread
        # what the views see there: view 1's averaged features are the object's, not its noise
        assert torch.nn.functional.cosine_similarity(ev.features[1, 0], ev.features[0, 0], dim=0) > 0.9


def test_the_model_reads_a_segment_with_its_own_view_left_out_of_the_agreement():
    """pixelNeRF-YOLO's read (``read_segments``): the target view sees one pixel all along its ray, so the other two
    views' agreement places the object; with only one other view there is nothing to agree about."""
    from pnyolo.components.frustums import Frustums
    from pnyolo.components.segment_evidence import read_segments

    for views, placed in ((3, True), (2, False)):
        cams, maps = _scene(9.3, views=views)
        segment = Frustums(torch.zeros(1, 3), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([[10.0]]),
                           torch.tensor([[2.0]]))
        own = torch.arange(views)[:, None] == 0
        ev, seen = read_segments(segment, cams, [maps], [1], 16, own)
        assert seen.shape == (views, 1, 1) and bool(seen.all())
        if placed:
            assert abs(10.0 + 2.0 * float(ev.offset[0]) - 9.3) < 0.3
        else:
            assert float(ev.agreement[0]) == NO_AGREEMENT


def test_a_segment_no_second_view_sees_has_no_place_and_no_agreement():
    cams, maps = _scene(10.5, side_sees=False)
    ev, _ = _evidence(cams, maps, 10.0, 2.0, 16)
    assert float(ev.agreement[0]) == NO_AGREEMENT
    torch.testing.assert_close(ev.weights[0], torch.full((16,), 1 / 16))
    assert abs(float(ev.offset[0])) < 1e-6


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_pixelnerf_yolo_reads_segment_evidence_and_learns_from_it_and_its_3d_state(tmp_path):
    from test_pnyolo_common import make_dataset, small_config

    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.models import build_model

    cfg = small_config(**{"model.sampler.footprint": "evidence", "model.sampler.evidence_points": 4,
                          "model.sampler.fine_samples": 4})
    ds = MultiViewDataset(make_dataset(tmp_path / "ds"), None, cfg, training=True, scenarios=["toy_01"])
    item = ds[0]
    torch.manual_seed(0)
    model = build_model(cfg, len(ds.class_names)).train()
    targets = model.targets(item)
    out = model(**model.inputs(item, "cpu"), return_samples=True)
    loss, terms = model.loss(out, item, targets, "cpu")
    assert torch.isfinite(loss) and {"size", "heading", "front"} <= set(terms)  # the 3D state's terms
    loss.backward()
    point_inputs = model.mlp.lin_in.weight.grad[:, -2:]  # the segment's place and agreement (the last inputs)
    assert point_inputs.abs().sum() > 0
    assert model.mlp.lin_state.weight.grad.abs().sum() > 0
    n_coarse, n_fine = cfg.model.sampler.num_samples, cfg.model.sampler.fine_samples
    assert out.samples.frustums.t.shape[1] == n_coarse + n_fine
