"""Shared helpers for the pnyolo tests: small datasets with 2D labels, small configs."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from dataset_spec import Dataset
from dataset_spec.synthetic import write_synthetic_dataset
from pnyolo.registry import config_class
from tools.projection import label_dataset

torch.set_num_threads(2)

# A tiny model configuration for fast tests (seconds per run on 2 CPU cores).
TINY = ["model.encoder.backbone=resnet18", "model.encoder.num_layers=2", "model.encoder.norm=frozen_batch",
        "model.mlp.hidden=32", "model.mlp.num_blocks=2", "model.mlp.combine_layer=1", "model.sampler.num_samples=8",
        "model.sampler.far=30", "data.image_scale=1.0", "data.cell_px=8", "train.threads=2", "train.val_every=0",
        "model.head.anchors=[[0.08,0.12],[0.2,0.3],[0.4,0.3]]"]
def for_kind(base: list[str], extra: list[str]) -> list[str]:
    """``base`` + ``extra``, leaving out ``base``'s model settings in parts the kind ``extra`` picks does not have
    (the ray settings for a kind without rays, the encoder's for a kind without one)."""
    kind = next((e.split("=", 1)[1] for e in reversed(extra) if e.startswith("model.kind=")), "pixelnerf-yolo")
    parts = {f.name for f in dataclasses.fields(config_class(kind))}
    keep = [b for b in base if not b.startswith("model.") or b.split(".")[1] in parts]
    return keep + list(extra)


def tiny(*extra: str) -> list[str]:
    """TINY for the kind ``extra`` names (pixelnerf-yolo by default), then ``extra``."""
    return for_kind(TINY, list(extra))


def make_dataset(root: Path, n_scenarios: int = 1, width: int = 64, height: int = 48, labels: bool = True) -> Path:
    write_synthetic_dataset(root, n_scenarios=n_scenarios, width=width, height=height)
    if labels:
        label_dataset(root, progress=False)
    return root


def small_config(**overrides):
    from pnyolo.config import load_config

    sets = ["model.encoder.backbone=resnet18", "model.encoder.num_layers=3", "model.encoder.norm=frozen_batch",
            "model.mlp.hidden=64", "model.mlp.num_blocks=3", "model.mlp.combine_layer=2",
            "model.sampler.num_samples=16", "model.sampler.far=30", "model.sampler.slab_clip=true",
            "model.sampler.height_cap=2.5", "eval.nms_iou=0.3", "data.image_scale=1.0", "data.cell_px=8", "train.threads=2",
            "model.head.anchors=[[0.08,0.12],[0.2,0.3],[0.4,0.3]]", "data.color_jitter=false"]
    return load_config(None, for_kind(sets, [f"{k}={v}" for k, v in overrides.items()]))


def test_helpers_make_labels(tmp_path):
    root = make_dataset(tmp_path / "ds")
    ds = Dataset.open(root)
    scn = ds.scenario(ds.scenario_names()[0])
    kept = ds.read_labels(scn.name, scn.cameras[0].name).kept()
    assert kept and all(0 <= k.visible_fraction <= 1 for k in kept)


def smooth_frame(width=64, height=48, views=3):
    """Smooth random images and cameras on a line 1.5 m up looking along +x, at the images' own size."""
    rng = np.random.default_rng(0)
    small = rng.integers(0, 256, (views, height // 8, width // 8, 3)).astype(np.uint8)
    images = np.stack([np.kron(s, np.ones((8, 8, 1), np.uint8)) for s in small])
    K = np.array([[width * 0.8, 0, width / 2 - 0.5], [0, width * 0.8, height / 2 - 0.5], [0, 0, 1.0]])
    c2ws = []
    for v in range(views):
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = [[0, 0, 1.0], [-1, 0, 0], [0, -1, 0]], [0.0, 2.0 * v, 1.5]
        c2ws.append(c2w)
    return images, np.stack([K] * views), np.stack(c2ws)
