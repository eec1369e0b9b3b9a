"""Where one frame's time goes, per model kind: the forward pass, decoding, and the share spent outside torch's
operators (Python and numpy on the host), on the CPU or a GPU.

    python benchmarks/bench_frame.py runs/*/best.pt --threads 1           # trained checkpoints
    python benchmarks/bench_frame.py --kinds bev,single-view --device cuda  # the cpu preset's models, random weights

Each frame is V random images from a fixed rig (the ONNX export's example rig), the same for every kind.
Forward and decoding are timed separately (median of --repeat frames after --warmup; on a GPU synchronised);
``host_share`` is 1 - (time inside torch operators, torch.profiler's self times summed) / wall time, over
--profile frames; the slowest Python functions by their own time (cProfile) say what is left on the host.
Random weights give untrained scores: ``--conf`` (default 0.02) keeps enough candidates for decoding to do its
real work. One JSON line per kind to stdout and a Markdown table to --out.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from dataset_spec.atomic import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def timed(fn, device, warmup: int, repeat: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        _sync(device)
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append((time.perf_counter() - t0) * 1000)
    return float(np.median(times))


def models(args):
    """(model, cfg) per checkpoint, or per kind of --kinds with the cpu preset's configuration."""
    if args.checkpoints:
        from pnyolo.engine.checkpoint import load_detector, read_checkpoint

        for path in args.checkpoints:
            ckpt = read_checkpoint(path)
            yield load_detector(ckpt, path, list(ckpt["class_names"]), args.device)
        return
    from pnyolo.bench.presets import load_preset
    from pnyolo.bench.stages import model_config
    from pnyolo.models import build_model

    preset = load_preset("cpu")
    for kind in args.kinds.split(","):
        cfg = model_config(preset, kind, 0)
        torch.manual_seed(0)
        yield build_model(cfg, 2).to(args.device), cfg


def host_share(step, frames: int) -> tuple[float, list[str]]:
    """(1 - time in torch operators / wall time, the 5 Python functions with the most own time)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        t0 = time.perf_counter()
        for _ in range(frames):
            step()
        wall = time.perf_counter() - t0
    inside = sum(e.self_cpu_time_total for e in prof.key_averages()) / 1e6
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(frames):
        step()
    profiler.disable()
    stats = pstats.Stats(profiler).sort_stats("tottime")
    top = [f"{Path(f).name}:{name} {t / frames * 1000:.2f} ms" for (f, _, name), (_, _, t, _, _) in
           sorted(stats.stats.items(), key=lambda kv: -kv[1][2]) if not f.startswith("~")][:5]
    return max(0.0, 1.0 - inside / wall), top


def measure(model, cfg, args) -> dict:
    from pnyolo.components.backbones import backbone_computed
    from pnyolo.models import predict_item
    from pnyolo.onnx.backend import example_item

    width, height = (int(v) for v in args.size.split("x"))
    model.eval()
    cfg = replace(cfg, eval=replace(cfg.eval, conf_threshold=args.conf))
    item = example_item(model, width, height, args.views)
    torch.manual_seed(0)
    item.images = torch.rand_like(item.images)
    with torch.no_grad(), backbone_computed(model):
        out = predict_item(model, item, args.device, cfg.eval)
        forward = timed(lambda: predict_item(model, item, args.device, cfg.eval), args.device, args.warmup, args.repeat)
        decode = timed(lambda: model.decode(out, item, cfg.eval), args.device, args.warmup, args.repeat)
        found = sum(len(d.scores) for d in model.decode(out, item, cfg.eval))
        share, top = host_share(lambda: model.decode(predict_item(model, item, args.device, cfg.eval), item, cfg.eval),
                                args.profile)
    return {"kind": model.kind, "device": str(args.device), "threads": torch.get_num_threads(), "size": args.size,
            "views": args.views, "forward_ms": forward, "decode_ms": decode, "frame_ms": forward + decode,
            "detections": found, "host_share": share, "host_top": top}


def table(rows: list[dict]) -> str:
    lines = ["| model | device, threads | forward ms | decode ms | frame ms | outside torch's operators | detections |",
             "|---|---|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['kind']} | {r['device']}, {r['threads']} | {r['forward_ms']:.1f} | {r['decode_ms']:.1f} | "
              f"{r['frame_ms']:.1f} | {100 * r['host_share']:.0f} % | {r['detections']} |" for r in rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="*")
    p.add_argument("--kinds", default="single-view,bev,pixelnerf-yolo", help="without checkpoints: these kinds")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--size", default="320x180")
    p.add_argument("--views", type=int, default=3)
    p.add_argument("--conf", type=float, default=0.02)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--repeat", type=int, default=15)
    p.add_argument("--profile", type=int, default=5, help="frames profiled for the host share")
    p.add_argument("--out", help="write the Markdown table here")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for model, cfg in models(args):
        rows.append(measure(model, cfg, args))
        print(json.dumps(rows[-1]), flush=True)
    if args.out:
        atomic_write_text(args.out, table(rows))
    print(table(rows))


if __name__ == "__main__":
    main()
