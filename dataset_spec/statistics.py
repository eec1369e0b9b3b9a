"""Dataset statistics from the 2D labels, as numbers (JSON) and pictures (``dataset-spec info DIR --plots OUT``).

    stats = label_statistics(Dataset.open("out/dataset"))
    stats["classes"]["pedestrian"]["visible_fraction"]     # {"edges": [...], "counts": [...]}
    stats["scenarios"]["intersection_07"]["hidden_but_seen"]
    write_statistics(stats, "out/stats")                  # statistics.json, label_histograms.png, hidden_but_seen.png

Every labelled road user (every actor of a detectable class in a camera's frustum, the ground truth
and the ones the thresholds leave out) counts in the histograms of visible fraction, in-frame
fraction and distance, per class. *Hidden but seen* is what this dataset exists for: a road user of
the ground truth fully hidden in one camera (visible fraction 0) that another camera of the same
scenario sees; counted per (road user, camera) pair and scenario.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .atomic import atomic_savefig, atomic_write_json
from .dataset import Dataset
from .errors import SpecError

MEASURES = {"visible_fraction": np.linspace(0, 1, 11), "in_frame_fraction": np.linspace(0, 1, 11),
            "distance": np.arange(0, 85, 5.0)}


def label_statistics(ds: Dataset, scenarios: list[str] | None = None) -> dict:
    """Histograms per class and hidden-but-seen counts per scenario (see the module docstring)."""
    names = ds.select_scenarios(scenarios)
    values = {c: {m: [] for m in MEASURES} for c in ds.info.detectable_classes}
    per_scenario = {}
    for name in names:
        counts = {"cameras": len(ds.scenario(name).cameras), "frames": ds.scenario(name).frames, "labels": 0,
                  "ground_truth": 0, "fully_hidden": 0, "hidden_but_seen": 0}
        for frame in ds.frames(name):
            _count_frame(ds, name, frame, values, counts)
        per_scenario[name] = counts
    classes = {}
    for cls, by_measure in values.items():
        classes[cls] = {"n": len(by_measure["distance"])}
        for m, edges in MEASURES.items():
            v = np.clip(np.asarray(by_measure[m], dtype=np.float64), edges[0], edges[-1])
            classes[cls][m] = {"edges": edges.tolist(), "counts": np.histogram(v, bins=edges)[0].tolist()}
    totals = {k: sum(s[k] for s in per_scenario.values()) for k in ("labels", "ground_truth", "fully_hidden",
                                                                       "hidden_but_seen")}
    return {"dataset": ds.info.name, "scenarios": per_scenario, "classes": classes, "totals": totals}


def _count_frame(ds: Dataset, name: str, frame: int, values: dict, counts: dict) -> None:
    """Add one frame of a scenario (every camera's labels) to the histograms' ``values`` and its ``counts``."""
    views = {}
    for cam in ds.scenario(name).cameras:
        path = ds.layout.labels(name, cam.name, frame)
        if not path.is_file():
            raise SpecError(path, f"no 2D labels for this view (make them: project-labels {ds.root})")
        views[cam.name] = ds.read_labels(name, cam.name, frame)
    seen_by = {}
    for cam_name, vl in views.items():
        for o in vl.objects:
            if o.visible_pixels is None or o.visible_pixels > 0:  # unknown (camera data): in frame, seen
                seen_by.setdefault(o.instance_id, set()).add(cam_name)
    for cam_name, vl in views.items():
        kept = {id(o) for o in vl.kept()}
        for o in vl.objects:
            if o.cls not in values:
                continue
            for m in MEASURES:
                if getattr(o, m) is not None:  # not measured: in no histogram
                    values[o.cls][m].append(getattr(o, m))
            counts["labels"] += 1
            if id(o) in kept:
                counts["ground_truth"] += 1
                if o.visible_fraction is not None and o.visible_fraction <= 0:
                    counts["fully_hidden"] += 1
                    counts["hidden_but_seen"] += bool(seen_by.get(o.instance_id, set()) - {cam_name})


def write_statistics(stats: dict, out_dir: str | Path) -> list[Path]:
    """``statistics.json`` and two pictures in ``out_dir``; returns the paths written."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    paths = [out / "statistics.json", out / "label_histograms.png", out / "hidden_but_seen.png"]
    atomic_write_json(paths[0], stats)
    classes = [c for c, s in stats["classes"].items() if s["n"]]
    fig, axes = plt.subplots(len(MEASURES), 1, figsize=(7, 2.4 * len(MEASURES)), squeeze=False)
    titles = {"visible_fraction": "visible fraction in the camera (0: fully hidden)",
              "in_frame_fraction": "in-frame fraction (share of the 3D box in view)", "distance": "distance (m)"}
    for ax, m in zip(axes[:, 0], MEASURES):
        for k, cls in enumerate(classes):
            h = stats["classes"][cls][m]
            edges = np.asarray(h["edges"])
            width = (edges[1] - edges[0]) / (len(classes) + 1)
            ax.bar(edges[:-1] + (k + 0.5) * width, h["counts"], width, label=f"{cls} (n = {stats['classes'][cls]['n']})")
        ax.set_title(titles[m], fontsize=9)
        ax.set_ylabel("labels")
        ax.grid(axis="y", alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    _save(fig, paths[1])
    names = list(stats["scenarios"])
    fig, ax = plt.subplots(figsize=(max(5, 0.35 * len(names) + 2), 3.2))
    x = np.arange(len(names))
    ax.bar(x - 0.2, [stats["scenarios"][n]["fully_hidden"] for n in names], 0.4, label="fully hidden in a camera")
    ax.bar(x + 0.2, [stats["scenarios"][n]["hidden_but_seen"] for n in names], 0.4,
           label="... and seen by another camera")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("(road user, camera) pairs")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    _save(fig, paths[2])
    plt.close("all")
    return paths


def _save(fig, path: Path) -> None:
    atomic_savefig(fig, path, dpi=110)
