"""The command-line entry points, one module each: ``train`` (pnyolo-train, and the ``python -m pnyolo.cli
train|eval|predict`` dispatcher torchrun starts on every rank), ``eval``, ``predict``, ``export``, ``checkpoint``,
``track``; ``options`` holds what they share (views, thresholds, the device)."""
from pnyolo.cli.eval import eval_main
from pnyolo.cli.train import main, train_main

__all__ = ["eval_main", "main", "train_main"]
