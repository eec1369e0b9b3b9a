"""The detectors on sequences: an item is (scenario, frame, lighting, views); splits stay by layout, so no
frame of a test layout is ever in training; training, evaluation and prediction read every frame."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY

from dataset_spec import Dataset
from dataset_spec.synthetic import write_synthetic_dataset
from pnyolo.cli import eval_main, train_main
from pnyolo.config import load_config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.predict_cli import main as predict_main
from tools.exporters.coco import export_coco
from tools.projection import label_dataset

torch.set_num_threads(2)


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    root = tmp_path_factory.mktemp("pnseq") / "ds"
    write_synthetic_dataset(root, n_scenarios=3, frames=3, fps=2.0)
    label_dataset(root, progress=False)
    return root


def test_items_are_frames_of_the_split_s_layouts_only(sequences):
    ds = Dataset.open(sequences)
    cfg = load_config(None, TINY)
    seen = {}
    for split in ("train", "val", "test"):
        data = MultiViewDataset(sequences, split, cfg, training=split == "train")
        seen[split] = {it.scenario for it in data.items}
        assert seen[split] == set(ds.split(split))
        for s in seen[split]:  # every frame under every lighting
            assert sorted({(it.frame, it.variant) for it in data.items if it.scenario == s}) == \
                [(f, v) for f in range(3) for v in ("dusk", "noon")]
    assert not seen["train"] & (seen["test"] | seen["val"])
    data = MultiViewDataset(sequences, "test", cfg)
    at2 = data.load(data.items[0].scenario, "noon", [0, 1, 2], frame=2)
    at0 = data.load(data.items[0].scenario, "noon", [0, 1, 2], frame=0)
    assert at2.frame == 2 and not torch.equal(at2.images, at0.images)  # the road users moved
    assert not torch.equal(at2.boxes_3d, at0.boxes_3d)
    truth = ds.scenario_at(at2.scenario, 2)
    walker = next(a for a in truth.actors if a.name == "ped_a")
    row = at2.actor_ids.index(walker.id)
    np.testing.assert_allclose(at2.boxes_3d[row, :3].numpy(), walker.box.center, atol=1e-5)


def test_train_eval_and_predict_run_on_sequences(sequences, tmp_path, capsys):
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=3", "train.epochs=1"]), [])
    assert train_main([str(sequences), "--out", str(tmp_path / "run"), "--quiet", *sets]) == 0
    assert eval_main([str(tmp_path / "run" / "latest.pt"), str(sequences), "--split", "test", "--out",
                      str(tmp_path / "eval"), "--quiet"]) == 0
    export_coco(Dataset.open(sequences), tmp_path / "coco", variant="all")
    assert predict_main([str(tmp_path / "run" / "latest.pt"), str(sequences), "--split", "test", "--variant", "all",
                         "--conf", "0.001", "--out", str(tmp_path / "pred"), "--quiet"]) == 0
    views = sorted(p.name for p in (tmp_path / "pred" / "views").rglob("*.json"))
    assert len(views) == 3 * 3 * 2 and "cam_0__f0002__noon.json" in views  # cameras x frames x lightings
    rec = json.loads(next((tmp_path / "pred" / "views").rglob("cam_0__f0002__noon.json")).read_text())
    assert rec["frame"] == 2
    gt = json.loads((tmp_path / "coco" / "annotations" / "instances_test.json").read_text())
    rows = json.loads((tmp_path / "pred" / "results_test.json").read_text())
    assert {r["image_id"] for r in rows} <= {im["id"] for im in gt["images"]}
