"""Pose noise for the cooperative setting: the other cars' poses move by the requested spread, the
target car, the ground truth and the images never, runs repeat with a seed, and zero noise changes
nothing."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset, tiny

from pnyolo.config import load_config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.cooperation.pose_noise import PoseNoise, car_of, perturb, pivot_of

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
        assert torch.equal(seen.camera_to_world[0], item.camera_to_world[0])  # the target's own car
        assert seen.images is item.images and seen.gt is item.gt and seen.K is item.K
        for v in (1, 2):
            offset, yaw = noise.error(item, car_of(item, v))
            offsets.append(offset)
            yaws.append(np.degrees(yaw))
            expected = perturb(item.camera_to_world[v].double().numpy(), offset, yaw, pivot_of(item, v))
            assert np.allclose(seen.camera_to_world[v].double().numpy(), expected, atol=1e-5)
    offsets, yaws = np.array(offsets), np.array(yaws)
    assert np.abs(offsets.mean(axis=0)).max() < 0.03 and np.allclose(offsets.std(axis=0), 0.2, atol=0.02)
    assert abs(yaws.mean()) < 0.06 and yaws.std() == pytest.approx(0.5, abs=0.05)
    assert PoseNoise(0.2, 0.5, 3).item_for_target(item, 1).camera_to_world.equal(
        PoseNoise(0.2, 0.5, 3).item_for_target(item, 1).camera_to_world)  # seeded: the same again
    assert not PoseNoise(0.2, 0.5, 3).item_for_target(item, 1).camera_to_world.equal(
        PoseNoise(0.2, 0.5, 4).item_for_target(item, 1).camera_to_world)
    assert PoseNoise(0.0, 0.0).item_for_target(item, 1) is item


def test_a_senders_detections_move_as_its_wrong_pose_places_them(item):
    """A point fixed in the sender's camera frame lands where the perturbed camera puts it."""
    noise = PoseNoise(0.4, 2.0, 1)
    local = np.array([1.5, -0.3, 12.0, 1.0])  # camera frame (OpenCV axes), homogeneous
    c2w = item.camera_to_world[1].double().numpy()
    world = (c2w @ local)[:3]
    box = np.array([[*world, 4.0, 2.0, 1.5, 0.3]])
    moved = noise.boxes_from(item, 1, box, receiver=0)
    wrong = noise.item_for_target(item, 0).camera_to_world[1].double().numpy()
    assert np.allclose(moved[0, :3], (wrong @ local)[:3], atol=1e-4)
    assert moved[0, 6] == pytest.approx(0.3 + noise.error(item, car_of(item, 1))[1])
    assert np.array_equal(noise.boxes_from(item, 1, box, receiver=1), box)  # its own car knows its pose


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_eval_with_pose_noise_zero_equals_without_and_noise_is_recorded(tmp_path, capsys):
    from pnyolo.cli import eval_main, train_main

    ds = make_dataset(tmp_path / "ds", n_scenarios=3)
    sets = sum((["--set", s] for s in tiny("train.max_steps=2", "train.epochs=1", "model.kind=bev")), [])
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


def _dets(rows):
    from pnyolo.decoding.world import WorldDetections

    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 9)
    return WorldDetections(rows[:, :7], rows[:, 7], rows[:, 8].astype(np.int64))


def test_messages_round_trip_at_a_fixed_size_and_refuse_what_is_broken():
    from pnyolo.cooperation.message import (DETECTION_BYTES, HEADER_BYTES, CarMessage, MessageError, decode, encode)

    dets = _dets([[10.25, -3.5, 0.8, 4.2, 1.8, 1.5, 0.3, 0.91, 0], [22.0, 7.125, 0.9, 0.6, 0.6, 1.8, -2.0, 0.55, 1]])
    vel, vcov = np.array([[8.5, -0.25], [0.0, 1.25]]), np.array([[0.5, 0.125, 0.75], [0.25, 0.0, 0.25]])
    msg = CarMessage(7, 12.5, (1.0, 2.0, 0.5, 0.25), (0.2, 0.1, 0.2), dets, velocities=vel, velocity_covariances=vcov)
    data = encode(msg)
    assert len(data) == HEADER_BYTES + 2 * DETECTION_BYTES == 48 + 2 * 68  # format version 2
    back = decode(data)
    assert (back.sender, back.timestamp) == (7, 12.5)
    assert np.allclose(back.pose, msg.pose, rtol=1e-7) and np.allclose(back.pose_sigma, msg.pose_sigma, rtol=1e-7)
    assert np.allclose(back.detections.boxes, dets.boxes, rtol=1e-7, atol=1e-6)
    assert np.allclose(back.detections.scores, dets.scores, rtol=1e-7) and back.detections.classes.tolist() == [0, 1]
    assert np.allclose(back.covariances, msg.covariance(), rtol=1e-6)
    assert np.allclose(back.velocities, vel) and np.allclose(back.velocity_covariances, vcov)
    assert len(encode(CarMessage(1, 0.0, (0, 0, 0, 0), (0, 0, 0), _dets([])))) == HEADER_BYTES
    old = decode(encode(msg, version=1))  # a version-1 sender: no velocity, 48 bytes a detection
    assert len(encode(msg, version=1)) == 48 + 2 * 48 and old.velocities is None
    assert np.allclose(old.detections.boxes, dets.boxes, atol=1e-6) and np.allclose(old.velocity()[0], 0.0)
    wrong_version = data[:4] + (3).to_bytes(2, "little") + data[6:]
    nan = encode(CarMessage(7, 12.5, (1.0, 2.0, 0.5, float("nan")), (0.2, 0.1, 0.2), dets))
    for broken, words in ((wrong_version, "version 3"), (data[:-5], "truncated"), (data[:20], "shorter than"),
                          (nan, "NaN"), (b"JUNK" + data[4:], "not a detection message")):
        with pytest.raises(MessageError, match=words) as err:
            decode(broken)
        assert "\n" not in str(err.value)


def test_a_late_detection_moved_by_its_velocity_lands_on_the_true_position():
    from pnyolo.cooperation.message import CarMessage

    # a car at 10 m/s along x seen at t = 1.0 s at x = 20 (a hand-made track); the message is read at t = 1.3 s
    dets = _dets([[20.0, 3.0, 0.75, 4.2, 1.8, 1.5, 0.0, 0.9, 0]])
    msg = CarMessage(3, 1.0, (0, 0, 0, 0), (0, 0, 0), dets, velocities=np.array([[10.0, 0.0]]),
                     velocity_covariances=np.array([[0.25, 0.0, 0.25]]))
    now = msg.at(1.3)
    assert np.allclose(now.detections.boxes[0, :3], [23.0, 3.0, 0.75]) and now.timestamp == 1.3
    assert np.allclose(now.covariance()[0], msg.covariance()[0] + np.array([0.25, 0.0, 0.25]) * 0.09)
    assert np.allclose(msg.at(1.0).detections.boxes, dets.boxes)  # no time passed: where it was


def test_covariance_weighted_fusion_lands_nearer_the_more_certain_car():
    """Two cars see one road user 1 m apart: car A's covariance is 0.1 m^2 in x, car B's 0.4 m^2, so
    the fused x is (x_a / 0.1 + x_b / 0.4) / (1 / 0.1 + 1 / 0.4) = 0.2 (hand-computed), with B's
    higher score keeping the box's other values."""
    from pnyolo.cooperation.message import CarMessage, fuse_weighted, position_covariance

    a = CarMessage(1, 0.0, (0, 0, 0, 0), (0, 0, 0), _dets([[0.0, 5.0, 0.9, 4, 2, 1.5, 0.1, 0.6, 0]]),
                   np.array([[0.1, 0.0, 0.1]]))
    b = CarMessage(2, 0.0, (0, 0, 0, 0), (0, 0, 0), _dets([[1.0, 5.0, 0.9, 4, 2, 1.5, 0.2, 0.8, 0]]),
                   np.array([[0.4, 0.0, 0.4]]))
    fused = fuse_weighted([a, b], radius=2.0)
    assert len(fused) == 1 and fused.boxes[0, 0] == pytest.approx(0.2) and fused.boxes[0, 1] == pytest.approx(5.0)
    assert fused.scores[0] == pytest.approx(0.8) and fused.boxes[0, 6] == pytest.approx(0.2)
    assert len(fuse_weighted([a, b], radius=0.5)) == 2  # too far apart to be one road user
    # the yaw error widens a far detection's covariance sideways, not along the line of sight
    cov = position_covariance(np.array([[0.0, 20.0, 0, 4, 2, 1.5, 0]]), (0, 0, 0, 0), (0.0, 0.0, 1.0), floor_m=0.0)
    assert cov[0, 0] == pytest.approx((20 * np.radians(1.0)) ** 2) and cov[0, 2] == pytest.approx(0.0)


def test_training_with_pose_noise_moves_all_cars_but_the_steps_ego(item, tmp_path):
    from pnyolo.training.train import train
    from pnyolo.cooperation.pose_noise import training_poses

    assert training_poses(item, None, 5) is item
    a, b = training_poses(item, [0.2, 0.2], 4), training_poses(item, [0.2, 0.2], 4)
    assert a.camera_to_world.equal(b.camera_to_world)  # a resumed run draws the same
    ego = 4 % 3
    assert a.camera_to_world[ego].equal(item.camera_to_world[ego])
    assert all(not a.camera_to_world[v].equal(item.camera_to_world[v]) for v in range(3) if v != ego)
    assert not training_poses(item, [0.2, 0.2], 7).camera_to_world[2].equal(a.camera_to_world[2])
    ds = make_dataset(tmp_path / "ds", n_scenarios=2)
    summary = train(ds, load_config(None, TINY + ["train.max_steps=2", "train.epochs=1", "train.pose_noise=[0.2,0.2]"]),
                    tmp_path / "run", quiet=True)
    assert summary["steps"] == 2 and np.isfinite(summary["last_loss"])


def test_a_hostile_car_s_message_is_refused_or_cannot_move_a_fused_detection_far():
    """Issue 62, item 8: a non-positive-definite covariance once moved a fused detection to x = 9998 m, a zero one
    raised LinAlgError, and class 255 and score -5 decoded."""
    from pnyolo.cooperation.message import CarMessage, MessageError, decode, encode, fuse_weighted

    honest = CarMessage(1, 0.0, (0, 0, 0, 0), (0.2, 0.1, 0.2), _dets([[10.0, 0.0, 0.8, 4.2, 1.8, 1.5, 0.0, 0.9, 0]]))
    for cov, cls, score, words in (([[1.0, 2.0, 1.0]], 0, 0.9, "not positive definite"),
                                   ([[0.0, 0.0, 0.0]], 0, 0.9, "not positive definite"),
                                   ([[0.1, 0.0, 0.1]], 255, 0.9, "class 255"),
                                   ([[0.1, 0.0, 0.1]], 0, -5.0, "score outside")):
        dets = _dets([[10.5, 0.0, 0.8, 4.2, 1.8, 1.5, 0.0, score, cls]])
        hostile = CarMessage(2, 0.0, (5, 5, 0, 0), (0.2, 0.1, 0.2), dets, covariances=np.array(cov, np.float64))
        with pytest.raises(MessageError, match=words):
            decode(encode(hostile))
        if cls == 0 and score == 0.9:  # what fusion does if such a message reached it anyway
            fused = fuse_weighted([honest, hostile], radius=2.0)
            assert len(fused) == 1 and 10.0 - 1e-9 <= fused.boxes[0, 0] <= 10.5 + 1e-9 and abs(fused.boxes[0, 1]) < 0.5
    with pytest.raises(MessageError, match="classes 0..1"):
        decode(encode(CarMessage(2, 0.0, (0, 0, 0, 0), (0.2, 0.1, 0.2), _dets([[1, 1, 1, 1, 1, 1, 0, 0.5, 2]]))),
               num_classes=2)
