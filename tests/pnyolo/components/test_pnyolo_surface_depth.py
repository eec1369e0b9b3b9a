"""The surface-depth option (model.surface_depth): depth maps in items, the cue, the head's training."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset, small_config

from dataset_spec import Dataset
from dataset_spec.camera import unproject_depth
from dataset_spec.cli_support import UserError
from pnyolo.components.geometry import project_points
from pnyolo.components.surface_depth import surface_cue
from pnyolo.config import load_config
from pnyolo.data.augment import shift_image
from pnyolo.data.dataset import SKY_DEPTH_M, Draw, MultiViewDataset
from pnyolo.training.train import train

SURFACE = {"model.surface_depth": "true", "model.loss.surface_depth": "0.5"}


def test_surface_cue_signs():
    z = torch.tensor([5.0, 10.0, 20.0])
    cue = surface_cue(z, torch.tensor([10.0, 10.0, 10.0]))
    assert cue.shape == (3, 2)
    assert (cue[0] < 0).all() and cue[1].abs().max() == 0 and (cue[2] > 0).all()  # in front, on, behind
    torch.testing.assert_close(cue[2], torch.tanh(torch.tensor([10 / 2, 10 / 8])))


def test_surface_points_one_view_sees_are_never_in_front_of_what_another_sees(tmp_path):
    """Each item's depth maps follow its images through mirroring and shifts: points on the
    surfaces view 0 sees, projected into view 1, lie on or behind the surface view 1's map holds
    there (never in free space), and many lie on it; with view 1's map not mirrored or not
    shifted, some would lie in free space."""
    root = make_dataset(tmp_path / "ds", width=128, height=96)
    mvd = MultiViewDataset(root, None, small_config(**SURFACE, **{"data.shift_px": "4", "data.hflip": "true"}),
                           training=True, scenarios=Dataset.open(root).scenario_names())
    scenario, variant = mvd.items[0].scenario, mvd.items[0].variant
    item = mvd.load(scenario, variant, [0, 1, 2], draw=Draw(mirror=True, shifts=[(3, -2), (-4, 1), (0, 0)]))
    depth, K, c2w, g = item.surface_depth, item.K, item.camera_to_world, item.grid
    assert depth.shape == (3, g.height, g.width)
    # the shifts' uncovered borders: view 0 moved right 3 and up 2, view 1 left 4 and down 1
    assert torch.isnan(depth[0, :, :3]).all() and torch.isnan(depth[0, -2:]).all()
    assert torch.isnan(depth[1, :, -4:]).all() and torch.isnan(depth[1, :1]).all()
    assert torch.isfinite(depth[0, :-2, 3:]).all() and torch.isfinite(depth[2]).all()
    assert (depth[torch.isfinite(depth)] > 0).all() and (depth == SKY_DEPTH_M).any()  # sky is far, not 0

    # the surface points view 0 sees (its sky and shift border as "no surface": depth 0), in view 1
    surface0 = (torch.isfinite(depth[0]) & (depth[0] < SKY_DEPTH_M)).numpy()
    depth0 = np.where(surface0, depth[0].numpy(), 0.0)
    points = unproject_depth(K[0].double().numpy(), c2w[0].double().numpy(), depth0)[surface0]
    pix, z = project_points(K[1].double(), c2w[1].double(), torch.from_numpy(points))

    def dz_in_view1(d1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # The nearest of the 3x3 pixels around: at this size one pixel of ground spans metres, and
        # bilinear values blend the depths on both sides of a silhouette.
        px = pix.round().long()
        inside = (z > 0) & (px[:, 0] >= 1) & (px[:, 1] >= 1) & (px[:, 0] < g.width - 1) & (px[:, 1] < g.height - 1)
        px = px[inside]
        nb = torch.stack([d1[px[:, 1] + dy, px[:, 0] + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], -1)
        ok = torch.isfinite(nb).all(-1)
        dz = z[inside, None] - nb
        return dz.max(-1).values[ok], dz.abs().min(-1).values[ok]  # in front of all / nearest to one

    dz, off = dz_in_view1(depth[1])
    assert len(dz) > 100
    assert (dz < -0.5).float().mean() < 0.001
    assert (off < 0.2).float().mean() > 0.1
    # the check can fail: view 1's map left unmirrored, or unshifted, puts points in free space
    unmirrored, _ = dz_in_view1(depth[1].flip(-1))
    unshifted, _ = dz_in_view1(torch.from_numpy(shift_image(depth[1].numpy(), 4, -1, np.nan)))
    assert (unmirrored < -0.5).float().mean() > 0.02 and (unshifted < -0.5).float().mean() > 0.003


def test_model_with_surface_depth_learns_the_depth_maps(tmp_path):
    root = make_dataset(tmp_path / "ds", n_scenarios=2)
    sets = [*TINY, *(f"{k}={v}" for k, v in SURFACE.items()), "train.max_steps=40", "train.epochs=100", "train.lr=3e-3"]
    train(root, load_config(None, sets), tmp_path / "run", quiet=True)
    steps = [r for r in map(json.loads, (tmp_path / "run" / "log.jsonl").read_text().splitlines()) if r["event"] == "step"]
    depth = [r["surface_depth"] for r in steps]
    assert len(depth) == 40 and all(np.isfinite(depth))
    assert np.mean(depth[-8:]) < 0.6 * np.mean(depth[:8])


def test_surface_depth_options_are_checked():
    with pytest.raises(UserError, match="go together"):
        load_config(None, ["model.surface_depth=true"])
    with pytest.raises(UserError, match="go together"):
        load_config(None, ["model.loss.surface_depth=0.5"])
    with pytest.raises(UserError, match="single-view"):
        load_config(None, ["model.kind=single-view", "model.surface_depth=true", "model.loss.surface_depth=0.5"])
