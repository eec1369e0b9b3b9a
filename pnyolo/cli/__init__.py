"""The command-line entry points, one module each: ``train`` (pnyolo-train, and the ``python -m pnyolo.cli
train|eval|predict`` dispatcher torchrun starts on every rank), ``eval``, ``predict``, ``export``, ``checkpoint``,
``track``; ``options`` holds what they share (views, thresholds, the device).

The package imports none of them until asked (``from pnyolo.cli import eval_main``), so ``python -m pnyolo.cli.eval``
runs its module once, without runpy's warning about a module imported before it runs."""
from __future__ import annotations

_WHERE = {"eval_main": "pnyolo.cli.eval", "main": "pnyolo.cli.train", "train_main": "pnyolo.cli.train"}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module 'pnyolo.cli' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(_WHERE[name]), name)
