"""pixelNeRF-YOLO's point sampling reproduces the outputs it gave before the 3D state and the segment evidence
existed (issue 89): outputs recorded at commit 0df8554 by this module run as a script (``python
tests/pnyolo/models/test_pnyolo_point_sampling.py OUT.npz`` there), the same model weights by construction (each
weight drawn from its own name's seed), compared to float rounding (they were equal to the bit on the machine that
recorded them: different CPUs may round a sum differently)."""
from __future__ import annotations

import sys
import zlib
from pathlib import Path

import numpy as np
import torch

RECORDED = Path(__file__).parent / "fixtures" / "point_sampling_0df8554.npz"
OPTIONS = {"point": [], "fine": ["model.sampler.fine_samples=4", "eval.depth_peaks=2"]}
FIELDS = ("ray_confidence", "box", "class_logits", "depth")


def outputs() -> dict[str, np.ndarray]:
    """The smooth frame's outputs of a tiny pixelNeRF-YOLO with point sampling, without and with fine samples."""
    from test_pnyolo_common import smooth_frame, tiny

    from pnyolo.config import load_config
    from pnyolo.data.frame import frame_item
    from pnyolo.models import build_model, predict_item

    arrays = {}
    images, K, c2w = smooth_frame()
    for name, extra in OPTIONS.items():
        cfg = load_config(None, tiny("model.kind=pixelnerf-yolo", *extra))
        model = build_model(cfg, 2).eval()
        with torch.no_grad():
            for key, p in model.named_parameters():  # each weight drawn from its name's seed
                p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(zlib.crc32(key.encode()))) * 0.05)
        item, _ = frame_item(list(images), list(zip(K, c2w)), cfg.data, ["car", "pedestrian"])
        with torch.no_grad():
            out = predict_item(model, item, "cpu", cfg.eval)
        arrays.update({f"{name}.{f}": getattr(out, f).numpy() for f in FIELDS})
    return arrays


def test_the_point_sampling_reproduces_the_outputs_recorded_before_the_state_and_the_evidence():
    recorded, now = np.load(RECORDED), outputs()
    assert sorted(recorded.files) == sorted(now)
    for key in recorded.files:
        np.testing.assert_allclose(now[key], recorded[key], rtol=0, atol=1e-5, err_msg=key)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # test_pnyolo_common
    np.savez_compressed(sys.argv[1], **outputs())
