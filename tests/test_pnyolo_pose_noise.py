"""Pose noise for the cooperative setting: the other cars' poses move by the requested spread, the
target car, the ground truth and the images never, runs repeat with a seed, and zero noise changes
nothing."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset

from pnyolo.config import load_config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.evaluation.pose_noise import PoseNoise, car_of, perturb, pivot_of

torch.set_num_threads(2)


@pytest.fixture(scope="module")
def item(tmp_path_factory):
    ds = make_dataset(tmp_path_factory.mktemp("noise") / "ds", n_scenarios=2)
    return MultiViewDataset(ds, "train", load_config(None, TINY), training=False, views=[0, 1, 2])[0]


def test_other_cars_move_by_the_requested_spread_and_the_target_never(item):
    offsets, yaws = [], []
    for seed in range(400):
        noise = PoseNoise(0.2, 0.5, seed)
        seen = noise.item_for_target(item, 0)
        assert torch.equal(seen["camera_to_world"][0], item["camera_to_world"][0])  # the target's own car
        assert seen["images"] is item["images"] and seen["gt"] is item["gt"] and seen["K"] is item["K"]
        for v in (1, 2):
            offset, yaw = noise.error(item, car_of(item, v))
            offsets.append(offset)
            yaws.append(np.degrees(yaw))
            expected = perturb(item["camera_to_world"][v].double().numpy(), offset, yaw, pivot_of(item, v))
            assert np.allclose(seen["camera_to_world"][v].double().numpy(), expected, atol=1e-5)
    offsets, yaws = np.array(offsets), np.array(yaws)
    assert np.abs(offsets.mean(axis=0)).max() < 0.03 and np.allclose(offsets.std(axis=0), 0.2, atol=0.02)
    assert abs(yaws.mean()) < 0.06 and yaws.std() == pytest.approx(0.5, abs=0.05)
    assert PoseNoise(0.2, 0.5, 3).item_for_target(item, 1)["camera_to_world"].equal(
        PoseNoise(0.2, 0.5, 3).item_for_target(item, 1)["camera_to_world"])  # seeded: the same again
    assert not PoseNoise(0.2, 0.5, 3).item_for_target(item, 1)["camera_to_world"].equal(
        PoseNoise(0.2, 0.5, 4).item_for_target(item, 1)["camera_to_world"])
    assert PoseNoise(0.0, 0.0).item_for_target(item, 1) is item


def test_a_senders_detections_move_as_its_wrong_pose_places_them(item):
    """A point fixed in the sender's camera frame lands where the perturbed camera puts it."""
    noise = PoseNoise(0.4, 2.0, 1)
    local = np.array([1.5, -0.3, 12.0, 1.0])  # camera frame (OpenCV axes), homogeneous
    c2w = item["camera_to_world"][1].double().numpy()
    world = (c2w @ local)[:3]
    box = np.array([[*world, 4.0, 2.0, 1.5, 0.3]])
    moved = noise.boxes_from(item, 1, box, receiver=0)
    wrong = noise.item_for_target(item, 0)["camera_to_world"][1].double().numpy()
    assert np.allclose(moved[0, :3], (wrong @ local)[:3], atol=1e-4)
    assert moved[0, 6] == pytest.approx(0.3 + noise.error(item, car_of(item, 1))[1])
    assert np.array_equal(noise.boxes_from(item, 1, box, receiver=1), box)  # its own car knows its pose


def test_eval_with_pose_noise_zero_equals_without_and_noise_is_recorded(tmp_path, capsys):
    from pnyolo.cli import eval_main, train_main

    ds = make_dataset(tmp_path / "ds", n_scenarios=3)
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=2", "train.epochs=1", "model.kind=bev"]), [])
    assert train_main([str(ds), "--out", str(tmp_path / "run"), "--quiet", *sets]) == 0
    ckpt = str(tmp_path / "run" / "latest.pt")
    common = [ckpt, str(ds), "--every-camera", "--late-fusion", "--conf", "0.01", "--quiet"]
    assert eval_main([*common, "--out", str(tmp_path / "exact")]) == 0
    assert eval_main([*common, "--pose-noise", "0,0", "--out", str(tmp_path / "zero")]) == 0
    assert eval_main([*common, "--pose-noise", "0.8,0.8", "--seed", "2", "--out", str(tmp_path / "noisy")]) == 0
    exact, zero, noisy = (json.loads((tmp_path / n / "comparison.json").read_text()) for n in ("exact", "zero", "noisy"))
    assert exact["models"] == zero["models"]
    assert noisy["pose_noise"] == {"sigma_m": 0.8, "sigma_deg": 0.8, "seed": 2}
    assert noisy["models"]["bev"]["ground_truth"] == exact["models"]["bev"]["ground_truth"]
    capsys.readouterr()
    assert eval_main([*common, "--pose-noise", "0.2"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--pose-noise '0.2': expected SIGMA_M,SIGMA_DEG" in err
