"""pnyolo benchmarks: MLP throughput vs FLOP rate, peak memory of a step, slab savings, ray share, data-parallel steps.

    .venv/bin/python benchmarks/bench_pnyolo.py                 # all three, paper-sized MLP
    .venv/bin/python benchmarks/bench_pnyolo.py --only memory --samples 128   # the full paper step (slow on CPU)

Figures (printed as JSON lines):
* ``mlp``: sample-points/s (forward + backward, V source views per point) of the paper-sized MLP
  and the ratio of its achieved FLOP rate to a plain fp32 matmul measured in the same run.
* ``memory``: peak memory of one training step (3 views, 1920x1080 input, image_scale 1.0,
  encoder + checkpointed ray chunks + backward + Adam step). CPU: peak RSS growth of a fresh
  process; CUDA: ``torch.cuda.max_memory_allocated``.
* ``slab``: share of plain near/far samples outside the ground..height-cap slab (wasted), i.e.
  the samples slab clipping saves at equal sample spacing.
* ``rays``: seconds per training step of the cpu preset's multi-view model at several
  ``train.background_rays`` shares, and the share of rays each renders, on ``--data DIR``'s
  training split (a rendered dataset) or, without it, a synthetic 320x180 dataset.
  Measured on 2 cores, cpu dataset: 0.24 s per step at 1.0, 0.16 s at 0.25 (44 % of the rays
  rendered); synthetic: 0.22 s and 0.13 s (36 %). Steps of the cpu benchmark's run 11: 0.18 s.
* ``grid``: seconds per training step of each model of a preset (``--preset``, default cpu_pretrained)
  at its own cell size and finer ones (image cells for pixelNeRF-YOLO and the single view, ground
  cells for bev), 2 threads, a frozen backbone's cache warm (12 steps after the first epoch), on a
  synthetic dataset of ``--size`` (default 320x180): what each model's finest grid costs.
* ``ddp``: seconds per step and items per second of that model trained by ``pnyolo-train`` with
  one process, one process accumulating 2 items, and ``--nproc 2`` (the same global batch of 2).

    .venv/bin/python benchmarks/bench_pnyolo.py --only rays --data out/data_cpu
    .venv/bin/python benchmarks/bench_pnyolo.py --only grid --size 480x270
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pnyolo.components.mlp import YoloMLP  # noqa: E402
from pnyolo.components.mlp import MLPConfig  # noqa: E402
from pnyolo.config import Config, load_config  # noqa: E402

MULTI = "pixelnerf-yolo"  # the kind whose rays these modes measure


def matmul_gflops(device, n=4096, k=512, m=512, reps=20) -> float:
    a, b = torch.randn(n, k, device=device), torch.randn(k, m, device=device)
    for _ in range(3):
        a @ b
    sync(device)
    t = time.perf_counter()
    for _ in range(reps):
        a @ b
    sync(device)
    return 2 * n * k * m * reps / (time.perf_counter() - t) / 1e9


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def mlp_flops_per_point(cfg: MLPConfig, d_in: int, d_latent: int, V: int, A: int, C: int) -> float:
    H = cfg.hidden
    per_view = d_in * H + cfg.combine_layer * (d_latent * H + 2 * H * H)
    shared = (cfg.num_blocks - cfg.combine_layer) * 2 * H * H + H * A * (5 + C)
    return 2.0 * 3.0 * (V * per_view + shared)  # 2 FLOPs per MAC; backward ~ 2x forward


def bench_mlp(device, points: int, V: int = 3, reps: int = 5) -> dict:
    cfg = Config()
    mlp = YoloMLP(512, 3, 2, cfg.model.mlp).to(device)
    x = torch.randn(V, points, 3, device=device)
    d = torch.nn.functional.normalize(torch.randn(V, points, 3, device=device), dim=-1)
    valid = torch.ones(V, points, dtype=torch.bool, device=device)
    f = torch.randn(V, points, 512, device=device)
    for _ in range(2):
        mlp(x, d, valid, f).sum().backward()
    sync(device)
    t = time.perf_counter()
    for _ in range(reps):
        mlp.zero_grad()
        mlp(x, d, valid, f).sum().backward()
    sync(device)
    pps = points * reps / (time.perf_counter() - t)
    flops = mlp_flops_per_point(cfg.model.mlp, mlp.lin_in.in_features, 512, V, 3, 2)
    peak = matmul_gflops(device)
    return {"bench": "mlp", "device": str(device), "views": V, "points": points, "points_per_s": round(pps),
            "achieved_gflops": round(pps * flops / 1e9, 1), "matmul_gflops": round(peak, 1),
            "ratio": round(pps * flops / 1e9 / peak, 3), "target_ratio": 0.5}


def memory_step(samples: int, chunk_mb: float, device_name: str, sets: list[str] = ()) -> dict:
    """One training step at 1920x1080 (run in a fresh process for a clean peak RSS); ``sets``: more
    config overrides (the sampling options: model.sampler.fine_samples, cell_rays, model.loss.occupancy)."""
    from dataset_spec.synthetic import toy_scenario
    from pnyolo.data.dataset import road_user_boxes
    from pnyolo.data.grid import grid_for
    from pnyolo.data.targets import OBJECT, TARGET_CHANNELS
    from pnyolo.engine.memory import limit_heap_retention
    from pnyolo.models import build_model

    device = torch.device(device_name)
    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "paper.yaml",
                      ["data.image_scale=1.0", "data.cell_px=60", f"model.sampler.num_samples={samples}",
                       f"model.chunk_memory_mb={chunk_mb}", *sets])
    W, H = 1920, 1080
    scn = toy_scenario(width=W, height=H)
    g = grid_for(W, H, 1.0, 60)
    K = torch.tensor(np.stack([c.K for c in scn.cameras]), dtype=torch.float32, device=device)
    T = torch.tensor(np.stack([c.camera_to_world for c in scn.cameras]), dtype=torch.float32, device=device)
    model = build_model(cfg, 2).to(device).train()
    chunked = limit_heap_retention(model, 3, 3 * g.grid_h * g.grid_w)  # as training sets it
    opt = torch.optim.Adam(model.parameters(), 1e-4)
    images = torch.rand(3, 3, H, W, device=device)
    targets = torch.zeros(3, g.grid_h, g.grid_w, 3, TARGET_CHANNELS, device=device)
    targets[:, 5, 10, 1, :7] = torch.tensor([1, 0.5, 0.5, 0.04, 0.07, 1.0, 1.0], device=device)
    targets[:, 5, 10, 1, OBJECT] = 1  # the first road user of the toy scene (its 3D box: the per-sample targets)
    item = {"boxes_3d": road_user_boxes(scn, ["car", "pedestrian"], False)[0].to(device)}
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    t = time.perf_counter()
    out = model(images, K, T, g, return_samples=getattr(getattr(cfg.model, "loss", None), "occupancy", 0) > 0)
    loss, _ = model.loss(out, item, targets, device)
    loss.backward()
    opt.step()
    sync(device)
    res = {"bench": "memory", "device": str(device), "input": f"3 x {W}x{H}", "grid": f"{g.grid_w}x{g.grid_h}",
           "samples": samples, "sets": list(sets), "cells_per_chunk": model.rays_per_chunk(3),
           "fixed_mmap_threshold": chunked,
           "seconds": round(time.perf_counter() - t, 1)}
    if device.type == "cuda":
        res["peak_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
        res["peak_rss_gib"] = round(peak, 2)
        res["growth_over_startup_gib"] = round(peak - base, 2)
    res["target_gib"] = 8
    return res


def bench_slab(num_samples=128, near=1.0, far=13.0, cap=3.0) -> dict:
    from dataset_spec.synthetic import toy_scenario
    from pnyolo.components.geometry import grid_cell_centres, pixel_rays
    from pnyolo.components.ray_samplers import sample_along_rays

    scn = toy_scenario(width=960, height=540)
    wasted = total = 0
    for cam in scn.cameras:
        uv = grid_cell_centres(18, 32, 960, 540, dtype=torch.float64).reshape(-1, 2)
        o, d = pixel_rays(torch.tensor(cam.K), torch.tensor(cam.camera_to_world), uv)
        t, _ = sample_along_rays(o, d, num_samples, near, far)
        z = (o[:, None] + t[..., None] * d[:, None])[..., 2]
        wasted += int(((z < 0) | (z > cap)).sum())
        total += z.numel()
    return {"bench": "slab", "cameras": "toy scene, 1.4 m high, 32x18 grid", "near": near, "far": far,
            "height_cap": cap, "plain_samples": total, "outside_slab": wasted,
            "saved_fraction": round(wasted / total, 3)}


def labelled_synthetic(root: Path, n_scenarios: int, width: int, height: int) -> str:
    """A synthetic dataset of toy box scenes at ``root``, its 2D labels written: the benchmarks' stand-in data."""
    from dataset_spec.synthetic import write_synthetic_dataset
    from tools.projection import label_dataset

    data = str(write_synthetic_dataset(root, n_scenarios=n_scenarios, width=width, height=height))
    label_dataset(data, progress=False)
    return data


def train_steps(data: str, config: Path, out: Path, sets: list[str], *args: str, env: dict | None = None) -> list[dict]:
    """Train with ``pnyolo-train`` in a child process (this checkout first on its path) and return the
    step events of its log; a failed run stops the benchmark with its error."""
    cmd = [sys.executable, "-m", "pnyolo.cli", "train", data, "--config", str(config), "--out", str(out), "--quiet",
           *sum((["--set", s] for s in sets), []), *args]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), **(env or {})}
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(done.stderr.strip()[-2000:])
    return [e for e in map(json.loads, (out / "log.jsonl").read_text().splitlines()) if e.get("event") == "step"]


def bench_rays(data: str | None, device, shares=(1.0, 0.5, 0.25), steps: int = 20, warmup: int = 4) -> dict:
    import tempfile

    from pnyolo.bench.presets import load_preset
    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.models import build_model, predict_item

    if data is None:
        with tempfile.TemporaryDirectory() as tmp:
            root = labelled_synthetic(Path(tmp) / "ds", 2, 320, 180)
            return {**bench_rays(root, device, shares, steps, warmup), "data": "synthetic 320x180"}
    preset = load_preset("cpu")
    result = {"bench": "rays", "data": str(data), "device": str(device), "steps": steps}
    for share in shares:
        cfg = load_config(preset.config_path, [*preset.overrides_for(MULTI), f"train.background_rays={share}"])
        torch.manual_seed(0)
        split = MultiViewDataset(data, "train", cfg, training=True)
        model = build_model(cfg, len(split.class_names)).to(device).train()
        opt = torch.optim.Adam(model.parameters(), 1e-3)
        times, rendered = [], []
        for k in range(warmup + steps):
            item = split[k % len(split)]
            sync(device)
            t = time.perf_counter()
            opt.zero_grad()
            options, targets = model.training_options(item, model.targets(item), cfg.train)
            mask = options.get("ray_mask")
            out = predict_item(model, item, device, **options)
            loss, _ = model.loss(out, item, targets, device)
            loss.backward()
            opt.step()
            sync(device)
            if k >= warmup:
                times.append(time.perf_counter() - t)
                rendered.append(1.0 if mask is None else float(mask.float().mean()))
        result[f"share_{share}"] = {"seconds_per_step": round(float(np.mean(times)), 4),
                                    "rays_rendered": round(float(np.mean(rendered)), 3)}
    return result


# the cell sizes the grid benchmark tries per model kind: the config key and its values, coarse to fine
GRID_CELLS = {"pixelnerf-yolo": ("data.cell_px", (16, 8)), "single-view": ("data.cell_px", (16, 8, 4)),
              "bev": ("model.bev.cell_m", (0.4, 0.2))}


def bench_grid(preset_name: str, size: str) -> dict:
    """Seconds per training step (median over the steps after the first epoch: a frozen backbone's
    features come from its cache, as in a long run) of each model of the preset at each cell size."""
    import tempfile
    from dataclasses import replace

    from pnyolo.bench.presets import load_preset
    from pnyolo.bench.stages import model_config

    preset = replace(load_preset(preset_name), anchors=0)
    width, height = map(int, size.split("x"))
    result = {"bench": "grid", "preset": preset.name, "data": f"synthetic {size}, 4 scenes"}
    with tempfile.TemporaryDirectory() as tmp:
        data = labelled_synthetic(Path(tmp) / "ds", 4, width, height)
        for kind in preset.models:
            key, values = GRID_CELLS[kind]
            frozen = model_config(preset, kind, seed=0).model.encoder.freeze
            for value in values:
                out = Path(tmp) / f"{kind}_{value}"
                sets = [*preset.overrides_for(kind), f"model.kind={kind}", f"{key}={value}", "train.val_every=0",
                        "train.tensorboard=false", "train.save_every_epochs=1000", "train.threads=2",
                        "train.epochs=4", "train.max_steps=0", "train.vis_every=0"]
                if frozen:
                    sets.append(f"model.encoder.feature_cache={tmp}/cache_{kind}")
                # four epochs: the first fills the cache, the other three are timed
                step = float(np.median([e["seconds"] for e in train_steps(data, preset.config_path, out, sets)
                                        if e["epoch"] >= 1]))
                result[f"{kind} {key}={value}"] = {"seconds_per_step": round(step, 3),
                                                  "minutes_for_preset_steps": round(step * preset.steps / 60, 1)}
    return result


def bench_ddp(data: str | None, steps: int = 12, warmup: int = 3) -> dict:
    """Seconds per optimizer step and items per second of the cpu preset's multi-view model trained
    by pnyolo-train with 1 process (2 threads), 1 process accumulating 2 items, and 2 processes
    (``--nproc 2``, 1 thread each: the same global batch of 2)."""
    import tempfile

    from pnyolo.bench.presets import load_preset

    with tempfile.TemporaryDirectory() as tmp:
        if data is None:
            data = labelled_synthetic(Path(tmp) / "ds", 4, 320, 180)
        preset = load_preset("cpu")
        base = [*preset.overrides_for(MULTI), f"train.max_steps={warmup + steps}", "train.val_every=0",
                "train.tensorboard=false", "train.save_every_epochs=1000"]
        result = {"bench": "ddp", "data": data, "steps": steps, "cores": os.cpu_count()}
        for name, nproc, sets in (("1 process", 1, ["train.threads=2"]),
                                  ("1 process, 2 items per step", 1, ["train.threads=2", "train.items_per_step=2"]),
                                  ("2 processes", 2, ["train.threads=1"])):
            out = Path(tmp) / name.replace(" ", "_").replace(",", "")
            t0 = time.perf_counter()
            logged = train_steps(data, preset.config_path, out, base + sets, "--nproc", str(nproc),
                                 env={"OMP_NUM_THREADS": "1"})
            wall = time.perf_counter() - t0
            secs = [e["seconds"] for e in logged][warmup:]
            items = nproc * (2 if "train.items_per_step=2" in sets else 1)
            step = float(np.median(secs))
            result[name] = {"seconds_per_step": round(step, 3), "items_per_step": items,
                            "items_per_second": round(items / step, 2), "process_wall_s": round(wall, 1)}
    return result


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", choices=["mlp", "memory", "slab", "rays", "ddp", "grid"])
    p.add_argument("--preset", default="cpu_pretrained", help="grid: the bench preset whose models are timed")
    p.add_argument("--size", default="320x180", help="grid: the synthetic images' size, WxH")
    p.add_argument("--data", help="rays, ddp: a labelled dataset folder with a train split (default: synthetic)")
    p.add_argument("--points", type=int, default=4096)
    p.add_argument("--samples", type=int, default=16, help="samples per ray in the memory step (paper: 128)")
    p.add_argument("--chunk-mb", type=float, default=1024)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: the usable cores)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="memory: a config override of the step (e.g. model.sampler.fine_samples=32), repeatable")
    p.add_argument("--_memory-child", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args()
    if not re.fullmatch(r"[1-9]\d*x[1-9]\d*", a.size):
        p.error(f"--size: WxH in pixels, e.g. 480x270, got {a.size!r}")
    from pnyolo.engine.runtime import apply_threads

    a.threads, line = apply_threads(a.threads)  # stated beside every figure below
    if not a._memory_child:
        print(line, file=sys.stderr)
    stamp = lambda row: json.dumps({**row, "threads": a.threads})  # noqa: E731
    if a._memory_child:
        print(stamp(memory_step(a.samples, a.chunk_mb, a.device, a.set)))
        return
    device = torch.device(a.device)
    if a.only in (None, "mlp"):
        print(stamp(bench_mlp(device, a.points)), flush=True)
    if a.only in (None, "slab"):
        print(stamp(bench_slab()), flush=True)
    if a.only in (None, "rays"):
        print(stamp(bench_rays(a.data, device)), flush=True)
    if a.only in (None, "ddp"):
        print(stamp(bench_ddp(a.data)), flush=True)
    if a.only in (None, "grid"):
        print(stamp(bench_grid(a.preset, a.size)), flush=True)
    if a.only in (None, "memory"):
        cmd = [sys.executable, __file__, "--_memory-child", "--samples", str(a.samples), "--chunk-mb", str(a.chunk_mb),
               "--device", a.device, *sum((["--set", s] for s in a.set), [])] + \
            ["--threads", str(a.threads)]
        out = subprocess.run(cmd, capture_output=True, text=True, env=os.environ)
        print(out.stdout.strip() or out.stderr.strip()[-2000:], flush=True)


if __name__ == "__main__":
    main()
