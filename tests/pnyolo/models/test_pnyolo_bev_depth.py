"""bev's depth-aware lift (``model.surface_depth``, issue 87's placement): a depth map per view trained on the rendered
depth, and each pillar point's place relative to the surface its views see. Flat pillars give every point along a
view's ray the same features; the cue tells them apart."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_pnyolo_common import make_dataset, tiny

from dataset_spec.cli_support import UserError
from pnyolo.components.geometry import pixel_rays, project_to_views
from pnyolo.components.surface_depth import surface_cue
from pnyolo.config import load_config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.training.train import train
from pnyolo.models import build_model
from pnyolo.models.bev import BASE_STRIDE, sample_maps

SURFACE = ("model.surface_depth=true", "model.loss.surface_depth=0.5")
BEV_DEPTH = tiny("model.kind=bev", *SURFACE)


@pytest.fixture(scope="module")
def item(tmp_path_factory):
    root = make_dataset(tmp_path_factory.mktemp("bev_depth") / "ds", n_scenarios=1, width=160, height=120)
    return MultiViewDataset(root, "train", load_config(None, BEV_DEPTH), views=[0, 1, 2])[0]


def test_items_carry_the_rendered_depth_and_the_options_go_together(item):
    assert item.surface_depth is not None and item.surface_depth.shape == (3, item.grid.height, item.grid.width)
    for half in SURFACE:
        with pytest.raises(UserError, match="go together"):
            load_config(None, tiny("model.kind=bev", half))


def test_the_cue_tells_apart_two_points_on_one_ray_that_flat_pillars_cannot(item):
    cfg = load_config(None, BEV_DEPTH)
    torch.manual_seed(0)
    model = build_model(cfg, 2).eval()
    K, c2w, g = item.K, item.camera_to_world, item.grid
    with torch.no_grad():
        maps = model.image_maps(item.images)
        origin, direction = pixel_rays(K[0], c2w[0], torch.tensor([[g.width / 2, g.height * 0.7]]))
        points = origin + direction * torch.tensor([[4.0], [12.0]])  # (2, 3) on view 0's ray through one pixel
        uv = project_to_views(K, c2w, points, g.width, g.height)[0]
        f, depth = model.point_features(maps, K, c2w, points, uv)
    C = cfg.model.bev.channels
    assert depth.shape == (3, *maps[BASE_STRIDE].shape[-2:]) and (depth > 0).all()
    torch.testing.assert_close(f[0, :C, 0], f[0, :C, 1])  # one pixel: the features alone cannot tell them apart
    z = project_to_views(K, c2w, points, g.width, g.height)[2][0]
    torch.testing.assert_close(z / z[0], torch.tensor([1.0, 3.0]))  # on one ray: depths in proportion
    seen = sample_maps(depth[:1, None], uv[:1], BASE_STRIDE)[0, 0]  # the surface view 0 sees at that pixel
    torch.testing.assert_close(f[0, C:].T, surface_cue(z, seen))
    assert not torch.allclose(f[0, C:, 0], f[0, C:, 1])  # the cue can


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_the_depth_head_learns_the_rendered_depth_and_the_detector_still_trains(tmp_path):
    root = make_dataset(tmp_path / "ds", n_scenarios=2)
    sets = [*BEV_DEPTH, "train.max_steps=40", "train.epochs=100", "train.lr=3e-3"]
    train(root, load_config(None, sets), tmp_path / "run", quiet=True)
    steps = [r for r in map(json.loads, (tmp_path / "run" / "log.jsonl").read_text().splitlines()) if r["event"] == "step"]
    depth, loss = [r["surface_depth"] for r in steps], [r["loss"] for r in steps]
    assert len(depth) == 40 and all(np.isfinite(depth)) and all(np.isfinite(loss))
    assert np.mean(depth[-8:]) < 0.6 * np.mean(depth[:8])
