"""Shared helpers for the pnyolo tests: small datasets with 2D labels, small configs."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dataset_spec import Dataset, Label2D, LabelThresholds, ViewLabels
from dataset_spec.camera import pixel_rays
from dataset_spec.synthetic import GROUND_ID, ray_box_distances, write_synthetic_dataset

torch.set_num_threads(2)

# A tiny model configuration for fast tests (seconds per run on 2 CPU cores).
TINY = ["model.encoder.backbone=resnet18", "model.encoder.num_layers=2", "model.encoder.norm=frozen_batch",
        "model.mlp.hidden=32", "model.mlp.num_blocks=2", "model.mlp.combine_layer=1", "model.sampler.num_samples=8",
        "model.sampler.far=30", "data.image_scale=1.0", "data.cell_px=8", "train.threads=2", "train.val_every=0",
        "model.head.anchors=[[0.08,0.12],[0.2,0.3],[0.4,0.3]]"]


def write_labels_from_raycast(root: Path) -> None:
    """2D labels for a synthetic dataset: amodal box from ray-casting each actor alone, visible
    fraction from the instance mask. Used while (or where) the projection tool is unavailable."""
    try:
        from tools.projection import label_dataset  # the project's labelling tool, once it lands
    except ImportError:
        label_dataset = None
    if label_dataset is not None:
        label_dataset(root, progress=False)
        return
    ds = Dataset.open(root)
    for name in ds.scenario_names():
        scn = ds.scenario(name)
        for cam in scn.cameras:
            inst = ds.read_instance(name, cam.name)
            h, w = inst.shape
            v, u = np.mgrid[0:h, 0:w]
            uv = np.stack([u, v], -1).reshape(-1, 2).astype(np.float64)
            o, d = pixel_rays(cam.K, cam.camera_to_world, uv)
            objs = []
            for a in scn.actors:
                if a.id == GROUND_ID:
                    continue
                amodal = np.isfinite(ray_box_distances(o, d, a.box.center, a.box.size, a.box.yaw)).reshape(h, w)
                if amodal.sum() == 0:
                    continue
                ys, xs = np.nonzero(amodal)
                box = np.array([xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5])
                visible = int((inst == a.id).sum())
                objs.append(Label2D(a.id, a.cls, box, 1.0, visible / amodal.sum(),
                                    float(np.linalg.norm(a.box.center - cam.camera_to_world[:3, 3])),
                                    visible, int(amodal.sum())))
            ds.write_labels(ViewLabels(name, cam.name, w, h, LabelThresholds(), objs))


def make_dataset(root: Path, n_scenarios: int = 1, width: int = 64, height: int = 48, labels: bool = True) -> Path:
    write_synthetic_dataset(root, n_scenarios=n_scenarios, width=width, height=height)
    if labels:
        write_labels_from_raycast(root)
    return root


def small_config(**overrides):
    from pnyolo.config import load_config

    sets = ["model.encoder.backbone=resnet18", "model.encoder.num_layers=3", "model.encoder.norm=frozen_batch",
            "model.mlp.hidden=64", "model.mlp.num_blocks=3", "model.mlp.combine_layer=2",
            "model.sampler.num_samples=16", "model.sampler.far=30", "model.sampler.slab_clip=true",
            "model.sampler.height_cap=2.5", "eval.nms_iou=0.3", "data.image_scale=1.0", "data.cell_px=8", "train.threads=2",
            "model.head.anchors=[[0.08,0.12],[0.2,0.3],[0.4,0.3]]", "data.color_jitter=false"]
    sets += [f"{k}={v}" for k, v in overrides.items()]
    return load_config(None, sets)


def test_helpers_make_labels(tmp_path):
    root = make_dataset(tmp_path / "ds")
    ds = Dataset.open(root)
    scn = ds.scenario(ds.scenario_names()[0])
    kept = ds.read_labels(scn.name, scn.cameras[0].name).kept()
    assert kept and all(0 <= k.visible_fraction <= 1 for k in kept)
