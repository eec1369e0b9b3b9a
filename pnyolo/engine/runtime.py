"""What a run takes from the machine: its device, its seed, and how many torch CPU threads it uses.

    device = pick_device("auto")        # cuda, mps or cpu; one-line errors for an unknown or missing one

    n, why = choose_threads(0)          # 0: the usable cores (shared by the processes), never the idle ones
    n, line = apply_threads(cfg.train.threads, processes=2)   # sets torch's threads; line: how many, why

The count comes from the config and the machine's cores only: the same command, seed and machine give the same
figures however busy the machine is (a float sum's order depends on the thread count). On a busy machine set
``train.threads`` lower; the run says how many it took.
"""
from __future__ import annotations

import contextlib

import os
import random
import sys

import numpy as np
import torch

from dataset_spec.cli_support import UserError


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity), whatever other work keeps them busy."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def choose_threads(setting: int, processes: int = 1) -> tuple[int, str]:
    """(threads per process, why): ``setting`` when > 0 (capped at the cores), else the usable cores shared by
    ``processes``. Never what is idle at the moment: the thread count changes a float sum's order, so a figure
    measured under load would differ from the same command's on an idle machine."""
    cores = usable_cores()
    if setting > 0:
        if setting > cores:  # more threads than cores only spin against each other
            print(f"pnyolo: warning: train.threads {setting} is more than the {cores} cores here; using {cores}",
                  file=sys.stderr)
            return cores, f"train.threads {setting}, capped at the {cores} cores"
        return setting, "train.threads"
    return max(1, cores // max(1, processes)), f"train.threads 0: the {cores} usable cores"


def apply_threads(setting: int, processes: int = 1) -> tuple[int, str]:
    """Set torch's CPU threads by ``choose_threads``; returns (count, a line saying so)."""
    n, why = choose_threads(setting, processes)
    torch.set_num_threads(n)
    return n, f"{n} torch thread{'s' if n > 1 else ''}{' per process' if processes > 1 else ''} ({why})"


def pick_device(name: str) -> torch.device:
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        if getattr(torch.backends, "mps", None) and torch.backends.mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError, ValueError):
        raise UserError(f"unknown device {name!r} (auto | cpu | cuda[:N] | mps)") from None
    if dev.type == "cpu":
        return dev
    backend = {"cuda": torch.cuda, "mps": getattr(torch.backends, "mps", None)}.get(dev.type)
    if backend is None:  # a device type torch names but the project does not run on (meta, xpu, ...)
        raise UserError(f"device {name!r}: the models run on auto | cpu | cuda[:N] | mps")
    if not backend.is_available():
        raise UserError(f"device {name!r} requested but {dev.type.upper()} is not available on this machine")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise UserError(f"device {name!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return dev


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


@contextlib.contextmanager
def deterministic_mode(on: bool):
    """``train.deterministic``: deterministic algorithms (the samplers switch to gather arithmetic), cuDNN's too,
    and cuBLAS's workspace setting, for the run; the process's earlier settings afterwards. An operation without a
    deterministic kernel (a plugin kind's) is a one-line error naming it."""
    if not on:
        yield
        return
    was = (torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.benchmark,
           torch.backends.cudnn.deterministic)
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")  # read when cuBLAS starts: before any CUDA work
    torch.use_deterministic_algorithms(True)
    torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic = False, True
    try:
        yield
    except RuntimeError as exc:
        if "deterministic" not in str(exc):
            raise
        raise UserError(f"train.deterministic: {str(exc).splitlines()[0][:200]} (set train.deterministic false)") from None
    finally:
        torch.use_deterministic_algorithms(was[0])
        torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic = was[1:]
