"""What a run takes from the machine: its device, its seed, and how many torch CPU threads it uses
(never more than the cores other work leaves idle).

    device = pick_device("auto")        # cuda, mps or cpu; one-line errors for an unknown or missing one

    n, why = choose_threads(0)          # auto: the cores not already busy, at least 1
    n, line = apply_threads(cfg.train.threads, processes=2)   # sets torch's threads; line: how many, why

On a busy 2-core machine two torch threads spin against each other and a step can take ten times
as long as with one, so ``train.threads: 0`` (the default) measures how busy the cores are over a
short window (``/proc/stat``; the 1-minute load average where there is none) and takes the rest.
"""
from __future__ import annotations

import contextlib

import os
import random
import sys
import time

import numpy as np
import torch

from dataset_spec.cli_support import UserError


def _cpu_times() -> tuple[float, float] | None:
    """(busy, total) jiffies of all CPUs since boot, or None where /proc/stat is missing."""
    try:
        with open("/proc/stat", encoding="ascii") as fh:
            fields = [float(v) for v in fh.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0.0)  # idle + iowait
    return sum(fields) - idle, sum(fields)


def busy_cores(window_s: float = 0.25) -> float:
    """How many cores other processes keep busy now (this process is idle while it measures)."""
    cores = os.cpu_count() or 1
    first = _cpu_times()
    if first is None:
        return min(float(cores), os.getloadavg()[0]) if hasattr(os, "getloadavg") else 0.0
    time.sleep(window_s)
    second = _cpu_times()
    total = second[1] - first[1]
    return cores * (second[0] - first[0]) / total if total > 0 else 0.0


def usable_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def choose_threads(setting: int, processes: int = 1) -> tuple[int, str]:
    """(threads per process, why): ``setting`` when > 0, else the idle cores shared by ``processes``."""
    if setting > 0:
        cores = usable_cores()
        if setting > cores:  # more threads than cores only spin against each other
            print(f"pnyolo: warning: train.threads {setting} is more than the {cores} cores here; using {cores}",
                  file=sys.stderr)
            return cores, f"train.threads {setting}, capped at the {cores} cores"
        return setting, "train.threads"
    cores, busy = usable_cores(), busy_cores()
    idle = max(1, cores - round(busy))
    return max(1, idle // max(1, processes)), f"auto: {cores} cores, {busy:.1f} busy"


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
