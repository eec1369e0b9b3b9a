"""Every tensor on its input's device, tested without a GPU: each registered kind (and the guide's example kind)
runs ``forward`` with its rig constants on PyTorch's ``meta`` device, where a tensor made on the CPU and mixed
with the model's raises a device mismatch (issue 64: bev's rig constants and the example kind's grid were built on
the CPU and crashed on CUDA). Data-dependent steps (the grid's extent, NMS) stay outside, as on a GPU they run
from host values."""
from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from test_pnyolo_common import tiny

from pnyolo.config import load_config
from pnyolo.data.frame import frame_item
from pnyolo.models import build_model, register_model, rig_constants_on_device
from pnyolo.registry import kinds, unregister_model
from repo_paths import TESTS

EXAMPLE = TESTS / "example_kind"


def _frame(width=64, height=48, views=3):
    K = np.array([[width * 0.8, 0, width / 2 - 0.5], [0, width * 0.8, height / 2 - 0.5], [0, 0, 1.0]])
    cams = []
    for v in range(views):
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = [[0, 0, 1.0], [-1, 0, 0], [0, -1, 0]], [0.0, 2.0 * v, 1.5]
        cams.append((K, c2w))
    return [np.zeros((height, width, 3), np.uint8)] * views, cams


@pytest.fixture(scope="module")
def every_kind():
    added = "ground-mean" not in kinds()  # asked before the import, which registers the kind itself
    sys.path.insert(0, str(EXAMPLE))
    import ground_mean_kind

    if "ground-mean" not in kinds():
        register_model("ground-mean")(ground_mean_kind.GroundMean)
    yield sorted(kinds())
    if added:  # later tests see the registry as they would without this module
        unregister_model("ground-mean")
    sys.path.remove(str(EXAMPLE))


def test_every_kind_runs_forward_and_its_rig_constants_on_the_meta_device(every_kind):
    images, cams = _frame()
    assert {"bev", "pixelnerf-yolo", "single-view", "ground-mean"} <= set(every_kind)
    options = {"bev": ["model.bev.range_m=30"]}
    variants = [(kind, options.get(kind, [])) for kind in every_kind]
    variants.append(("bev", ["model.bev.range_m=30", "model.surface_depth=true", "model.loss.surface_depth=0.5"]))
    variants.append(("pixelnerf-yolo", ["model.sampler.footprint=evidence", "model.sampler.fine_samples=2"]))
    for kind, extra in variants:
        cfg = load_config(None, tiny(f"model.kind={kind}", *extra))
        item, _ = frame_item(images, cams, cfg.data, ["car", "pedestrian"])
        model = build_model(cfg, 2).eval().to("meta")
        constants = rig_constants_on_device(model, item)  # computed from the item's values, moved to the model's device
        assert all(t.device.type == "meta" for t in _tensors(constants)), kind
        out = model(**model.inputs(item, "meta"), **model.eval_options(cfg.eval), **constants)
        assert all(t.device.type == "meta" for t in _tensors(vars(out))), kind


def test_a_tensor_made_on_the_cpu_in_forward_is_caught_on_the_meta_device(every_kind):
    """The check has teeth: the example kind as it was (its view sets made without a device) fails there."""
    images, cams = _frame()
    cfg = load_config(None, tiny("model.kind=ground-mean"))
    item, _ = frame_item(images, cams, cfg.data, ["car", "pedestrian"])
    model = build_model(cfg, 2).eval().to("meta")
    constants = rig_constants_on_device(model, item)
    stray = torch.ones(1, 3, dtype=torch.bool)  # made on the CPU, as the example's forward once made it
    with pytest.raises((RuntimeError, NotImplementedError)):
        model.heads(*(model.inputs(item, "meta")[k] for k in ("images", "K", "camera_to_world")),
                    model.points(constants["ground"]).to("meta"), stray, 64, 48)
    model.heads(*(model.inputs(item, "meta")[k] for k in ("images", "K", "camera_to_world")),
                model.points(constants["ground"]).to("meta"), stray.to("meta"), 64, 48)  # on the device: runs


def _tensors(value):
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, dict):
        for v in value.values():
            yield from _tensors(v)
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _tensors(v)
