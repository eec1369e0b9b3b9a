"""Data-parallel training with torch.distributed: one process per rank, started by torchrun.

    torchrun --nproc_per_node 2 -m pnyolo.cli train out/dataset --config configs/cpu.yaml --out runs/ddp
    pnyolo-train out/dataset --config configs/cpu.yaml --out runs/ddp --nproc 2     # the same, launched for you

``init_from_env`` reads torchrun's ``RANK`` / ``WORLD_SIZE`` / ``LOCAL_RANK`` and joins the group
(gloo on CPU, nccl on CUDA); without them (a plain ``pnyolo-train``) nothing is initialised and
``Dist()`` is the one-process group. Rank 0 alone logs, validates and writes checkpoints; every rank
trains on its own share of each step's items (``pnyolo.training.train``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as tdist


@dataclass
class Dist:
    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def active(self) -> bool:
        return self.world > 1

    def barrier(self) -> None:
        if self.active:
            tdist.barrier()

    def all_true(self, flag: bool) -> bool:
        """True when ``flag`` holds on every rank (every rank must call it)."""
        if not self.active:
            return flag
        t = torch.tensor([1 if flag else 0], dtype=torch.int32)
        tdist.all_reduce(t, op=tdist.ReduceOp.MIN)
        return bool(t.item())

    def mean(self, value: float) -> float:
        """The mean of ``value`` over the ranks."""
        if not self.active:
            return value
        t = torch.tensor([value], dtype=torch.float64)
        tdist.all_reduce(t)
        return float(t.item()) / self.world

    def gather(self, obj) -> list:
        """Every rank's ``obj``, in rank order, on every rank."""
        if not self.active:
            return [obj]
        out = [None] * self.world
        tdist.all_gather_object(out, obj)
        return out


def init_from_env(device_type: str) -> Dist:
    """The process group torchrun set up the environment for (one process: ``Dist()``)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist()
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if not tdist.is_initialized():
        tdist.init_process_group("nccl" if device_type == "cuda" else "gloo")
    return Dist(rank, world, local)


def shutdown(dist: Dist) -> None:
    if dist.active and tdist.is_initialized():
        tdist.destroy_process_group()
