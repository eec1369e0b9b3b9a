"""Training on a share of the background rays (train.background_rays, pnyolo.components.ray_selection)."""
from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch
from test_pnyolo_common import TINY, make_dataset, small_config, tiny

from dataset_spec.boxes import box_to_yolo
from dataset_spec.cli_support import UserError
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.data.targets import IGNORE, OBJ, TARGET_CHANNELS, unseen_elsewhere_cells
from pnyolo.components.ray_selection import ignore_unrendered, own_view_dropout_mask, training_ray_mask
from pnyolo.models import build_model
from pnyolo.models import predict_item


def _targets(V=2, H=12, W=16, A=3):
    t = torch.zeros(V, H, W, A, TARGET_CHANNELS)
    t[0, 5, 7, 1, 0] = OBJ
    t[1, 0, 0, 2, 0] = OBJ  # a corner: its neighbourhood is clipped at the border
    t[1, 9, 3, 0, 0] = IGNORE  # an ignored cell (e.g. a road user left out of the ground truth) needs no ray
    return t


def test_mask_keeps_target_cells_and_their_neighbours_and_a_share_of_the_rest():
    t = _targets()
    g = torch.Generator().manual_seed(0)
    always = torch.zeros(2, 12, 16, dtype=torch.bool)
    always[0, 4:7, 6:9] = True
    always[1, 0:2, 0:2] = True
    # a share of almost 0 leaves exactly the target cells and their 8 neighbours
    assert torch.equal(training_ray_mask(t, 1e-9, generator=g), always)
    assert torch.equal(training_ray_mask(t, 1e-9, neighbourhood=0, generator=g), (t[..., 0] == OBJ).any(-1))
    assert training_ray_mask(t, 1.0, generator=g).all()
    shares = []
    for _ in range(50):
        m = training_ray_mask(t, 0.3, generator=g)
        assert m[always].all()
        shares.append(m[~always].float().mean())
    assert abs(float(torch.stack(shares).mean()) - 0.3) < 0.02  # independent draws of the given share
    assert not torch.equal(training_ray_mask(t, 0.3, generator=g), training_ray_mask(t, 0.3, generator=g))


def test_unrendered_cells_are_ignored_by_the_loss_targets():
    t = _targets()
    mask = training_ray_mask(t, 0.2, generator=torch.Generator().manual_seed(1))
    out = ignore_unrendered(t, mask)
    assert (out[..., 0][~mask] == IGNORE).all()
    assert torch.equal(out[mask], t[mask])
    assert (t[..., 0] == IGNORE).sum() == 1  # the input is left as it was


@pytest.fixture(scope="module")
def tiny_ds(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("rays") / "ds", n_scenarios=2)


def test_rendering_a_subset_of_rays_gives_those_rays_unchanged(tiny_ds):
    cfg = small_config()
    torch.manual_seed(0)
    model = build_model(cfg, 2).eval()  # evaluation: fixed samples along each ray
    item = MultiViewDataset(tiny_ds, "train", cfg, views=[0, 1, 2])[0]
    mask = training_ray_mask(model.targets(item), 0.3, generator=torch.Generator().manual_seed(2))
    assert 0 < mask.sum() < mask.numel()
    with torch.no_grad():
        full = predict_item(model, item, "cpu")
        part = predict_item(model, item, "cpu", ray_mask=mask)
    for name in ("ray_confidence", "box", "class_logits", "depth"):
        a, b = getattr(full, name), getattr(part, name)
        assert a.shape == b.shape
        torch.testing.assert_close(b[mask], a[mask], rtol=1e-5, atol=1e-6)
    assert (part.ray_confidence[~mask] == 0).all() and part.depth[~mask].isnan().all()
    with torch.no_grad():  # an empty selection (a view grid without targets, a tiny share) is no error
        none = predict_item(model, item, "cpu", ray_mask=torch.zeros_like(mask))
    assert none.ray_confidence.shape == full.ray_confidence.shape and (none.ray_confidence == 0).all()


def _model_whose_outputs_follow_the_features(tiny_ds):
    """A multi-view model in evaluation mode and a 3-view toy item. Frozen batch norm: a view's
    features do not depend on the views encoded with it."""
    cfg = small_config()
    torch.manual_seed(0)
    model = build_model(cfg, 2).eval()
    torch.nn.init.normal_(model.mlp.lin_out.weight, std=0.1)  # outputs that depend visibly on the features
    return model, MultiViewDataset(tiny_ds, "train", cfg, views=[0, 1, 2])[0]


def test_own_view_only_gives_each_view_what_it_alone_would_give(tiny_ds):
    model, item = _model_whose_outputs_follow_the_features(tiny_ds)
    with torch.no_grad():
        full = predict_item(model, item, "cpu")
        own = predict_item(model, item, "cpu", own_view_only=True)
        alone = [model(item.images[v:v + 1], item.K[v:v + 1], item.camera_to_world[v:v + 1], item.grid)
                 for v in range(3)]
    for name in ("ray_confidence", "box", "class_logits", "depth"):
        for v in range(3):
            torch.testing.assert_close(getattr(own, name)[v], getattr(alone[v], name)[0], rtol=1e-5, atol=1e-6)
    # the toy views overlap: with the other source views the outputs differ
    assert (full.ray_confidence - own.ray_confidence).abs().max() > 1e-3
    with pytest.raises(ValueError, match="ray_mask"):
        predict_item(model, item, "cpu", ray_mask=torch.ones(model.targets(item).shape[:3], dtype=torch.bool),
                     own_view_only=True)
    single = build_model(small_config(**{"model.kind": "single-view"}), 2).eval()
    with torch.no_grad():  # each view of the single-view model is its own view already
        assert torch.equal(predict_item(single, item, "cpu", own_view_only=True).ray_confidence,
                           predict_item(single, item, "cpu").ray_confidence)


def test_own_view_dropout_draws_a_share_of_the_rendered_rays_but_never_a_road_user_only_its_view_sees():
    unseen = torch.zeros(2, 12, 16, dtype=torch.bool)
    unseen[0, 5, 7] = unseen[1, 2:4, 3] = True
    rendered = training_ray_mask(_targets(), 0.5, generator=torch.Generator().manual_seed(3))
    g = torch.Generator().manual_seed(4)
    assert own_view_dropout_mask(unseen, 0.0, rendered, generator=g) is None
    shares = []
    for _ in range(50):
        drop = own_view_dropout_mask(unseen, 0.3, rendered, generator=g)
        assert not drop[unseen].any() and not drop[~rendered].any()
        shares.append(drop[rendered & ~unseen].float().mean())
    assert abs(float(torch.stack(shares).mean()) - 0.3) < 0.02
    assert own_view_dropout_mask(unseen, 0.9999, generator=g).sum() == unseen.numel() - unseen.sum()


def test_unseen_elsewhere_cells_are_the_cells_of_road_users_no_other_view_sees(tiny_ds):
    cfg = small_config()
    counts = {True: 0, False: 0}
    pairs = [MultiViewDataset(tiny_ds, "train", cfg, views=views) for views in ([0, 1], [1, 2], [0, 2])]
    for item in (ds[k] for ds in pairs for k in range(len(ds))):
        g = item.grid
        for v, gt in enumerate(item.gt):
            cells = unseen_elsewhere_cells(gt, g)
            centres = [(int(cy * g.grid_h), int(cx * g.grid_w))  # pixel centres: see dataset_spec.boxes
                       for cx, cy, _, _ in (box_to_yolo(b, g.width, g.height) for b in gt.boxes)]
            unseen_at = {c for c, s in zip(centres, gt.seen_elsewhere) if not s}
            assert {tuple(c) for c in cells.nonzero().tolist()} == unseen_at
            for s in gt.seen_elsewhere:
                counts[bool(s)] += 1
    assert counts[True] and counts[False]  # two views of the toy scene: both kinds


def test_dropping_its_own_view_makes_a_ray_blind_to_that_image_alone(tiny_ds):
    model, item = _model_whose_outputs_follow_the_features(tiny_ds)
    other = replace(item, images=item.images.clone())
    other.images[0] = torch.rand(other.images[0].shape, generator=torch.Generator().manual_seed(5))
    drop = torch.zeros(model.targets(item).shape[:3], dtype=torch.bool)
    drop[0, ::2] = True  # every other row of view 0's grid
    with torch.no_grad():
        full = predict_item(model, item, "cpu")
        a = predict_item(model, item, "cpu", drop_own_view=drop)
        b = predict_item(model, other, "cpu", drop_own_view=drop)
        none = predict_item(model, item, "cpu", drop_own_view=torch.zeros_like(drop))
        mask = training_ray_mask(model.targets(item), 0.3, generator=torch.Generator().manual_seed(2))
        part = predict_item(model, item, "cpu", ray_mask=mask, drop_own_view=drop)
    for name in ("ray_confidence", "box", "class_logits", "depth"):
        fa, fb = getattr(a, name), getattr(b, name)
        # the dropped rays do not see view 0's image: another image there changes nothing
        torch.testing.assert_close(fa[drop], fb[drop], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(fa[~drop], getattr(full, name)[~drop], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(getattr(none, name), getattr(full, name), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(getattr(part, name)[mask], fa[mask], rtol=1e-5, atol=1e-6)
    keep = ~drop
    keep[1:] = False  # view 0's rays that keep their own view: its image matters to them
    assert (a.ray_confidence[keep] - b.ray_confidence[keep]).abs().max() > 1e-3
    assert (a.ray_confidence[drop] - full.ray_confidence[drop]).abs().max() > 1e-3
    with pytest.raises(ValueError, match="drop_own_view"):
        predict_item(model, item, "cpu", own_view_only=True, drop_own_view=drop)
    single = build_model(small_config(**{"model.kind": "single-view"}), 2).eval()
    with pytest.raises(ValueError, match="cannot drop"):
        predict_item(single, item, "cpu", drop_own_view=drop)


def _steps(run):
    return [r for r in map(json.loads, (run / "log.jsonl").read_text().splitlines()) if r["event"] == "step"]


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_training_on_a_share_of_the_background_rays_learns(tiny_ds, tmp_path):
    """Over a short run that renders about a third of the rays per step the loss falls about as
    far as with every ray (measured: 1.58 -> 1.16 vs 1.75 -> 1.08, means of the first and last 10
    steps), and the log records the share rendered; the single-view model refuses the option. A run
    that also withholds their own view's features from 30 % of the rendered rays learns too."""
    from pnyolo.config import load_config
    from pnyolo.training.train import train

    def run(name, *extra):
        cfg = load_config(None, TINY + ["train.max_steps=60", "train.epochs=100", "train.lr=3e-3",
                                        "data.color_jitter=false", *extra])
        train(tiny_ds, cfg, tmp_path / name, quiet=True)
        return _steps(tmp_path / name)

    def mean(xs):
        return sum(xs) / len(xs)

    share = run("share", "train.background_rays=0.25")
    every = run("every")
    dropped = run("dropped", "train.background_rays=0.25", "train.own_view_dropout=0.3")
    first, last = mean([s["loss"] for s in share[:10]]), mean([s["loss"] for s in share[-10:]])
    assert last < 0.8 * first
    assert last < 1.25 * mean([s["loss"] for s in every[-10:]])
    assert all(0 < s["rays"] < 0.8 for s in share) and all(s["rays"] == 1.0 for s in every)
    # a share of the rendered rays without their own view's features: it still learns
    assert mean([s["loss"] for s in dropped[-10:]]) < 0.8 * mean([s["loss"] for s in dropped[:10]])
    assert all(s["own_view_dropped"] == 0 for s in share)
    assert 0.05 < mean([s["own_view_dropped"] / s["rays"] for s in dropped]) < 0.3
    with pytest.raises(UserError, match="single-view model casts no rays"):  # refused, not ignored
        load_config(None, tiny("model.kind=single-view", "train.background_rays=0.25"))
