"""The training items of an epoch in the order the steps take them, read ahead by DataLoader workers::

    items = epoch_items(train_ds, order, (epoch, pos), dist, items_per_step, workers=2, seed=0, pin=True)
    item = next(items)          # this rank's next item: reading, decoding and augmenting done in a worker

Each optimizer step takes ``world x items_per_step`` positions of the epoch's order; this rank takes its
``items_per_step`` of them. Without workers each item is read in the training process when the step needs it,
its random choices drawn from torch's global generator (as always: runs reproduce bit for bit). With
workers each position's choices are drawn from a generator seeded by (seed, rank, epoch, position): the same
items, views and augmentation for any number of workers and after a resume, with pinned memory on a GPU.
"""
from __future__ import annotations

from typing import Iterator

import torch
from torch.utils.data import DataLoader, Dataset

from pnyolo.data.item import Item
from pnyolo.engine.distributed import Dist

PRIME = 1_000_003


def item_seed(seed: int, rank: int, epoch: int, position: int) -> int:
    """The seed of one position's random choices (distinct per seed, rank, epoch and position)."""
    return (((seed * PRIME + rank) * PRIME + epoch) * PRIME + position) % (1 << 63)


def rank_positions(length: int, pos: int, rank: int, world: int, per_rank: int) -> list[int]:
    """The positions of an epoch of ``length`` this rank takes, from ``pos`` on, whole steps only."""
    step = world * per_rank
    return [start + rank * per_rank + j for start in range(pos, length - step + 1, step) for j in range(per_rank)]


class _Positions(Dataset):
    """An epoch's positions as items, each drawn with its own seeded generator (what a worker reads)."""

    def __init__(self, data, order: list[int], positions: list[int], seed: int, rank: int, epoch: int):
        self.data, self.order, self.positions = data, order, positions
        self.seed, self.rank, self.epoch = seed, rank, epoch

    def __len__(self) -> int:
        return len(self.positions)

    def __getitem__(self, k: int) -> Item:
        pos = self.positions[k]
        generator = torch.Generator().manual_seed(item_seed(self.seed, self.rank, self.epoch, pos))
        return self.data.draw(self.order[pos], generator)


def epoch_items(data, order: list[int], at: tuple[int, int], dist: Dist, per_rank: int, workers: int, seed: int,
                pin: bool = False) -> Iterator[Item]:
    """This rank's items of the epoch ``at`` = (epoch, position) from that position on, in the order its steps
    take them (``dist``: this process's rank among ``dist.world``)."""
    (epoch, pos), rank = at, dist.rank
    positions = rank_positions(len(order), pos, rank, dist.world, per_rank)
    if workers == 0:
        return (data[order[p]] for p in positions)
    # its own generator: starting the workers draws a seed, which must not move torch's global stream (the model's)
    loader = DataLoader(_Positions(data, order, positions, seed, rank, epoch), batch_size=None, shuffle=False,
                        num_workers=workers, pin_memory=pin, prefetch_factor=2 * per_rank, worker_init_fn=_one_thread,
                        generator=torch.Generator().manual_seed(item_seed(seed, rank, epoch, pos)))
    return iter(loader)


def _one_thread(_worker: int) -> None:
    """A worker decodes with one torch thread: the training process keeps the cores it was given."""
    torch.set_num_threads(1)
