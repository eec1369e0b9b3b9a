"""The bench report's own picture: recall by visibility group for every row (the sweeps draw theirs beside them)."""
from __future__ import annotations

import textwrap
from pathlib import Path

from dataset_spec.atomic import atomic_savefig
from pnyolo.bench.record import Result
from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE as HIDDEN_SEEN


def recall_plot(results: dict[str, Result], path: Path, iou: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    figures = {name: r.figures for name, r in results.items()}
    groups = [g for g in next(iter(figures.values())).recall_by_group.get(iou, {})
              if not g.startswith(HIDDEN_SEEN + ",")]  # the split by the other view's pixels: in the table
    fig, ax = plt.subplots(figsize=(7, 3.6))
    width = 0.8 / max(1, len(figures))
    for k, (name, f) in enumerate(figures.items()):
        vals = [(f.recall(iou, g).recall or 0.0) for g in groups]
        ax.bar(np.arange(len(groups)) + k * width, vals, width, label=name)
    ax.set_xticks(np.arange(len(groups)) + width * (len(figures) - 1) / 2)
    ax.set_xticklabels([textwrap.fill(g, 12) for g in groups], fontsize=7)
    ax.set_ylabel(f"recall @ IoU {iou}")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
