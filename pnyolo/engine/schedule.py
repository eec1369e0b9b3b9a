"""What each optimizer step gets: the items' order in an epoch and the learning rate.

    order = epoch_order(len(dataset), seed=0, epoch=3)       # the same permutation on every rank
    scheduler = make_scheduler(optimizer, cfg.train, total_steps)
"""
from __future__ import annotations

import math

import torch

from dataset_spec.cli_support import UserError


LR_SCHEDULES = ("exponential", "cosine")


def make_scheduler(optimizer, tc, total_steps: int):
    """``exponential``: lr * lr_decay ** epoch (stepped per epoch). ``cosine``: half a cosine from
    lr to ``lr_min_ratio * lr`` over ``total_steps`` optimizer steps (stepped per step)."""
    if tc.lr_schedule == "exponential":
        return torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=tc.lr_decay)
    if tc.lr_schedule == "cosine":
        span, floor = max(1, total_steps), tc.lr_min_ratio

        def factor(step: int) -> float:
            return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(step, span) / span))
        return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
    raise UserError(f"unknown train.lr_schedule {tc.lr_schedule!r}; known: {', '.join(LR_SCHEDULES)}")


def epoch_order(n: int, seed: int, epoch: int) -> list[int]:
    """The items' order in an epoch: the same permutation on every rank (seeded by the run's seed and
    the epoch, as DistributedSampler does), so the ranks split one order between them."""
    return torch.randperm(n, generator=torch.Generator().manual_seed(seed * 1_000_003 + epoch)).tolist()
