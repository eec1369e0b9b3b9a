"""Sampling coverage and step time of the multi-view model's sampling options, without training.

    .venv/bin/python benchmarks/bench_coverage.py out/data_cpu --split test
    .venv/bin/python benchmarks/bench_coverage.py out/data_cpu --checkpoint out/bench_cpu/runs/pixelnerf-yolo/best.pt

For each option (a set of ``--set`` overrides on the cpu preset's multi-view config) it prints, as
JSON lines and a markdown table: the coverage of the split's road users (pnyolo.evaluation.coverage:
a query point inside the 3D box, on the visible pixels in a view that sees it, within one feature
cell of them; per class, for the hidden-but-seen ones and all), the seconds of one training step
on the split's items and the median milliseconds of one item's forward pass and decoding
(``engine.predict.time_per_item``: the split's first items, the same for every option; with ``--scenario``, the
items of those scenarios for both). Untrained, hierarchical fine samples follow a flat coarse confidence (the
uniform share of their density); with ``--checkpoint`` they follow the trained model's.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pnyolo.bench.presets import load_preset  # noqa: E402

MULTI = "pixelnerf-yolo"  # the kind whose sampling this measures
from pnyolo.config import load_config  # noqa: E402
from pnyolo.data.dataset import MultiViewDataset  # noqa: E402
from pnyolo.engine.checkpoint import checkpoint_config, load_detector, read_checkpoint  # noqa: E402
from pnyolo.engine.predict import time_per_item  # noqa: E402
from pnyolo.evaluation.coverage import CoverageAccumulator  # noqa: E402
from pnyolo.models import build_model, predict_item  # noqa: E402

OPTIONS = {
    "one ray, 16 samples (cpu preset)": [],
    "one ray, 32 samples": ["model.sampler.num_samples=32"],
    "one ray, 16 + 16 fine": ["model.sampler.fine_samples=16"],
    "2x2 rays, 16 samples": ["model.sampler.cell_rays=2"],
    "2x2 rays, 8 + 8 fine": ["model.sampler.cell_rays=2", "model.sampler.num_samples=8", "model.sampler.fine_samples=8"],
    "3x3 rays, 16 samples": ["model.sampler.cell_rays=3"],
    "frustum segments, 16 + 8 fine": ["model.sampler.footprint=frustum"],
    "frustum segments, 16 + 8 fine per anchor": ["model.sampler.footprint=frustum", "model.sampler.fine_weights=per_anchor"],
    "points and segment footprints (run 59)": ["model.sampler.footprint=both"],
    "where along the segment the views agree": ["model.sampler.footprint=evidence"],
}


def coverage_of(model, dataset, items: int) -> dict:
    acc = CoverageAccumulator(dataset.class_names, stride=model.coverage_stride())
    model.eval()
    with torch.no_grad():
        for k in range(min(items, len(dataset))):
            item = dataset[k]
            out = predict_item(model, item, "cpu", return_samples=True)
            acc.add_points(item, model.coverage_points(out, item), dataset.instance_maps(item))
    return acc.summary()


def step_seconds(cfg, root: str, split: str, steps: int = 6, warmup: int = 2) -> float:
    data = MultiViewDataset(root, split, cfg, training=True)
    model = build_model(cfg, len(data.class_names)).train()
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    times = []
    for k in range(warmup + steps):
        item = data[k % len(data)]
        t0 = time.perf_counter()
        options, targets = model.training_options(item, model.targets(item), cfg.train)
        out = predict_item(model, item, "cpu", **options)
        loss, _ = model.loss(out, item, targets, "cpu")
        opt.zero_grad()
        loss.backward()
        opt.step()
        times.append(time.perf_counter() - t0)
    return sum(times[warmup:]) / steps


def pooled(summary: dict, group: str | None) -> dict:
    """Coverage shares over every class of one group (None: every group)."""
    recs = [r for groups in summary.values() for g, r in groups.items() if group in (None, g) and r["n"]]
    n = sum(r["n"] for r in recs)
    return {"n": n, **{m: (sum((r[m] or 0) * r["n"] for r in recs) / n if n else None)
                       for m in ("in_box", "on_pixels", "near_pixels", "segment_in_box")}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", help="a labelled dataset folder with splits")
    p.add_argument("--split", default="test")
    p.add_argument("--items", type=int, default=12, help="items of the split to measure (default 12)")
    p.add_argument("--checkpoint", help="a trained multi-view checkpoint (coverage of its own sampling only)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--scenario", action="append", help="only these scenarios of the split (repeatable)")
    p.add_argument("--options", help="semicolon-separated option names (default: every one)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    preset = load_preset("cpu")
    rows = []
    if args.checkpoint:
        ckpt = read_checkpoint(args.checkpoint)
        options = {Path(args.checkpoint).name: None}
    else:
        wanted = [o.strip() for o in args.options.split(";")] if args.options else list(OPTIONS)
        options = {name: OPTIONS[name] for name in wanted}
    for name, sets in options.items():
        if sets is None:
            cfg = checkpoint_config(ckpt)
            data = MultiViewDataset(args.dataset, args.split, cfg, training=False, every_camera=True,
                                    scenarios=args.scenario)
            model, cfg = load_detector(ckpt, args.checkpoint, data.class_names, "cpu")
            seconds = None
        else:
            cfg = load_config(preset.config_path, [*preset.overrides_for(MULTI), *sets])
            data = MultiViewDataset(args.dataset, args.split, cfg, training=False, every_camera=True,
                                    scenarios=args.scenario)
            model = build_model(cfg, len(data.class_names))
            seconds = step_seconds(cfg, args.dataset, "train" if data.ds.split("train") else args.split)
        summary = coverage_of(model, data, args.items)  # the same items time_per_item times
        row = {"bench": "coverage", "option": name, "sets": sets, "step_s": seconds,
               "inference_ms": time_per_item(model, data, cfg.eval, args.items), "coverage": summary}
        print(json.dumps(row), flush=True)
        rows.append(row)
    print("\n| option | step (s) | inference per item (ms) | hidden-but-seen: point in box / on pixels / near / fine in box / segment in box / "
          "footprint on pixels (peds; cars) | all: point in box |")
    print("|---|---|---|---|---|")
    fmt = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    for r in rows:
        per = [r["coverage"].get(c, {}).get("hidden-but-seen") for c in ("pedestrian", "car")]
        hs = "; ".join(" / ".join(fmt(x[m]) for m in ("in_box", "on_pixels", "near_pixels", "fine_in_box",
                                                      "segment_in_box", "footprint_on_pixels")) if x and x["n"] else "n/a"
                       for x in per)
        print(f"| {r['option']} | {fmt(r['step_s'])} | {r['inference_ms']:.0f} | {hs} | {fmt(pooled(r['coverage'], None)['in_box'])} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
