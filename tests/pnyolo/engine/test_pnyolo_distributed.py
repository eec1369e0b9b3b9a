"""Data-parallel training (torch.distributed, gloo on CPU): two processes equal one that accumulates
the same items' gradients, and a two-process run killed and resumed continues exactly."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from test_pnyolo_common import TINY, make_dataset

from pnyolo.engine.checkpoint import read_checkpoint
from repo_paths import REPO

ROOT = REPO
# No randomness in a step (no colour jitter, every ray, samples at bin centres): the two runs differ
# only in how the gradients of a step's two items are summed.
FIXED = ["data.color_jitter=false", "train.background_rays=1.0", "model.sampler.stratified=false",
         "train.tensorboard=false", "train.epochs=9"]


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("ddp") / "ds", n_scenarios=4)


def _command(ds, out, sets, nproc=1, resume=False):
    args = [sys.executable, "-m", "pnyolo.cli", "train", str(ds), "--out", str(out), "--quiet",
            *sum((["--set", s] for s in TINY + sets), [])]
    if nproc > 1:
        args += ["--nproc", str(nproc)]
    if resume:
        args.append("--resume")
    return args, {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}


def _train(ds, out, sets, nproc=1, resume=False):
    args, env = _command(ds, out, sets, nproc, resume)
    res = subprocess.run(args, capture_output=True, text=True, env=env, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    return read_checkpoint(out / "latest.pt")


def _close(a: dict, b: dict) -> bool:
    return all(torch.allclose(a[k].float(), b[k].float(), atol=1e-5, rtol=1e-4) for k in a if a[k].is_floating_point())


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_two_processes_equal_one_accumulating_the_same_items(ds, tmp_path):
    import tempfile

    elastic = set(Path(tempfile.gettempdir()).glob("torchelastic_*"))
    two = _train(ds, tmp_path / "two", FIXED + ["train.max_steps=3", "train.threads=1"], nproc=2)
    assert set(Path(tempfile.gettempdir()).glob("torchelastic_*")) == elastic, "torchrun's scratch left behind"
    one = _train(ds, tmp_path / "one", FIXED + ["train.max_steps=3", "train.threads=1", "train.items_per_step=2"])
    assert two["train_state"]["step"] == one["train_state"]["step"] == 3
    assert len(two["rng_ranks"]) == 2 and len(one["rng_ranks"]) == 1
    assert _close(two["model"], one["model"])
    start = {k: v for k, v in read_checkpoint(tmp_path / "one" / "latest.pt")["model"].items()}
    assert start  # and the runs did train: the weights moved from their initial values
    fresh = _train(ds, tmp_path / "zero", FIXED + ["train.max_steps=1", "train.threads=1", "train.items_per_step=2"])
    assert not _close(fresh["model"], one["model"])


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_two_process_run_killed_and_resumed_continues_exactly(ds, tmp_path):
    sets = ["train.threads=1", "train.tensorboard=false", "train.epochs=9", "train.max_steps=6",
            "train.checkpoint_every=2"]  # with augmentation and sampling noise
    straight = _train(ds, tmp_path / "a", sets, nproc=2)
    args, env = _command(ds, tmp_path / "b", sets, nproc=2)
    proc = subprocess.Popen(args, env=env, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    latest, deadline = tmp_path / "b" / "latest.pt", time.time() + 600
    while time.time() < deadline and not latest.is_file() and proc.poll() is None:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # the launcher and both ranks, mid-run
    proc.wait()
    assert read_checkpoint(latest)["train_state"]["step"] < 6, "killed before the end"
    resumed = _train(ds, tmp_path / "b", sets, nproc=2, resume=True)
    assert resumed["train_state"]["step"] == 6
    assert all(torch.equal(straight["model"][k], resumed["model"][k]) for k in straight["model"])
    log = (tmp_path / "b" / "log.jsonl").read_text()
    assert log.count('"event": "resume"') == 1 and '"processes": 2' in log


def test_more_processes_than_gpus_is_refused_in_one_line(tmp_path, monkeypatch, capsys):
    """Issue 64, item 4: --nproc 2 --device cuda on a one-GPU machine died in NCCL ("Duplicate GPU detected")."""
    import torch

    from pnyolo.cli import train_main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # a machine with one GPU, simulated
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    out = tmp_path / "run"
    assert train_main([str(tmp_path / "no_dataset_needed"), "--nproc", "2", "--set", "train.device=cuda",
                       "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--nproc 2: CUDA sees 1 GPU(s)" in err[0] and not out.exists()
