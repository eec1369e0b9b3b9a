"""Evaluation that scores every camera of a scenario once (``every_camera``): pnyolo-bench's
validation and test, ``pnyolo-eval --every-camera``."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset

from dataset_spec import Dataset
from dataset_spec.cli_support import UserError
from pnyolo.bench.selection import threshold_sweep
from pnyolo.cli import eval_main
from pnyolo.config import load_config
from pnyolo.data.dataset import MultiViewDataset, camera_groups
from pnyolo.training.train import train
from pnyolo.engine.predict import predict
from pnyolo.evaluation.evaluate import item_name, score
from pnyolo.models import build_model

torch.set_num_threads(2)


@pytest.fixture(scope="module")
def tiny_ds(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("every") / "ds", n_scenarios=2)


def _cfg(num_views: int, *extra: str):
    return load_config(None, TINY + [f"data.num_views={num_views}", *extra])


def test_camera_groups_score_every_camera_once():
    assert camera_groups(5, 3) == [([0, 1, 2], [0, 1, 2]), ([3, 4, 0], [0, 1])]
    assert camera_groups(6, 3) == [([0, 1, 2], [0, 1, 2]), ([3, 4, 5], [0, 1, 2])]
    for n in range(1, 10):
        for size in range(1, n + 1):
            groups = camera_groups(n, size)
            assert all(len(views) == len(set(views)) == size for views, _ in groups)
            assert [views[j] for views, scored in groups for j in scored] == list(range(n))
    with pytest.raises(ValueError):
        camera_groups(2, 3)


def _all_scenarios(root):
    return Dataset.open(root).scenario_names()


def test_every_camera_items_score_each_view_once(tiny_ds):
    scenarios = _all_scenarios(tiny_ds)
    ds = MultiViewDataset(tiny_ds, "test", _cfg(2), scenarios=scenarios, every_camera=True)
    scored, names = [], set()
    for k in range(len(ds)):
        item = ds[k]
        names.add(item_name(item))
        assert len(item.views) == 2 and item.scored
        for v in item.scored:
            scored.append((item.scenario, item.variant, item.camera_names[v]))
        if item.scored != [0, 1]:  # the wrapped group: its second camera is a source view only
            assert item.scored == [0] and item.views == [2, 0]
    dataset = Dataset.open(tiny_ds)
    expected = [(s, var.name, cam.name) for s in scenarios for var in dataset.scenario(s).lighting
                for cam in dataset.scenario(s).cameras]
    assert len(scored) == len(set(scored)) and set(scored) == set(expected)
    assert len(names) == len(ds)  # example pictures of one scene's camera groups do not overwrite each other
    # a plain evaluation dataset is unchanged: the same views for every item, all of them scored
    plain = MultiViewDataset(tiny_ds, "test", _cfg(2), scenarios=scenarios)
    assert len(plain) == len(expected) // 3 and plain[0].views == [0, 1] and plain[0].scored == [0, 1]
    with pytest.raises(UserError):
        MultiViewDataset(tiny_ds, "test", _cfg(2), scenarios=scenarios, views=[0, 1], every_camera=True)


def test_evaluation_counts_each_camera_once(tiny_ds):
    """Scored in pairs with a wrapped last pair, the ground truth is that of all three cameras
    scored together: a view serving only as a source is not counted again."""
    scenarios = _all_scenarios(tiny_ds)
    cfg = _cfg(2, "eval.conf_threshold=0.0")
    torch.manual_seed(0)
    model = build_model(cfg, 2).eval()
    every = MultiViewDataset(tiny_ds, "test", cfg, scenarios=scenarios, every_camera=True)
    together = MultiViewDataset(tiny_ds, "test", _cfg(3), scenarios=scenarios)
    n_gt = sum(len(gt.boxes) for k in range(len(together)) for gt in together[k].gt)
    preds = predict(model, every, cfg.eval)
    summary = score(preds, cfg.eval).summary()
    assert summary["ground_truth"] == n_gt > 0
    assert summary["views"] == 3 * len(together)
    for row in threshold_sweep(preds, cfg.eval, (0.0, 0.5)):  # the bench's validation sweep too
        counts = np.asarray(row["layout_counts"])
        assert counts[:, 0].sum() + counts[:, 2].sum() == n_gt


def test_eval_cli_every_camera(tiny_ds, tmp_path, capsys):
    cfg = _cfg(2, "train.max_steps=1", "train.epochs=1")
    train(tiny_ds, cfg, tmp_path / "mv", quiet=True)
    ckpt = str(tmp_path / "mv" / "latest.pt")
    rc = eval_main([ckpt, str(tiny_ds), "--split", "train", "--every-camera", "--out", str(tmp_path / "ev")])
    assert rc == 0
    report = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    dataset = Dataset.open(tiny_ds)
    cameras = sum(len(dataset.scenario(s).cameras) * len(dataset.scenario(s).lighting) for s in dataset.split("train"))
    assert report["views"] == cameras and report["source_views"] == "every camera"
    capsys.readouterr()
    rc = eval_main([ckpt, str(tiny_ds), "--every-camera", "--views", "0,1"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "--every-camera" in err
