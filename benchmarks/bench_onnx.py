"""Inference latency per frame of V views: torch eager against ONNX Runtime, for every checkpoint given.

    python benchmarks/bench_onnx.py out/bench_cpu/runs/*/best.pt --size 320x180 --threads 1,2

For each checkpoint and thread count: the median and the spread (10th-90th percentile) over --repeat
frames after --warmup, of the model's outputs by torch and by ONNX Runtime (the same exported file the
backend uses), and the torch time split into the encoder, the rest of the forward (rays / grid
sampling and heads) and decoding (NMS, peaks, projection; the same Python code after either backend).
Frames are random images from a fixed rig of V cameras; the thread count is stated on every line.
Writes one JSON line per measurement to stdout and a Markdown table to --out (if given).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from dataset_spec.atomic import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def timed(fn, warmup: int, repeat: int) -> tuple[float, float, float]:
    """Median, 10th and 90th percentile of ``fn``'s wall time in milliseconds."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000)
    return float(np.median(times)), float(np.percentile(times, 10)), float(np.percentile(times, 90))


def int8_file(model, cfg, class_names, fp32: Path, dataset: str, width: int, height: int, views: int) -> Path:
    """``fp32`` quantised to INT8, calibrated on 16 frames of ``dataset``'s val split (as pnyolo-export --int8)."""
    from pnyolo.onnx.int8 import calibration_items, quantize_int8

    items = calibration_items(cfg, class_names, dataset, "val", width, height, views, 16)
    return quantize_int8(model, fp32, fp32.with_name("int8.onnx"), items)


def accuracy(model, cfg, runner, dataset: str, views: int) -> dict:
    """F1@0.2 (strict), AP50 and the recall of road users hidden in the target view but seen in another,
    on ``dataset``'s test split, from ``runner``'s outputs."""
    from pnyolo.data.dataset import MultiViewDataset
    from pnyolo.engine.predict import predict
    from pnyolo.evaluation.evaluate import score
    from pnyolo.evaluation.metrics import HIDDEN_SEEN_ELSEWHERE

    ds = MultiViewDataset(dataset, "test", cfg, training=False, views=list(range(views)))
    s = score(predict(model, ds, cfg.eval, runner=runner), cfg.eval).summary()
    hidden = s["recall_by_visibility"]["0.2"].get(HIDDEN_SEEN_ELSEWHERE, {"recall": float("nan")})["recall"]
    return {"f1": s["strict"]["0.2"]["f1"], "ap50": s["ap50"], "hidden_recall": hidden}


def measure(path: str, width: int, height: int, views: int, threads: int, warmup: int, repeat: int,
            int8: str | None = None, with_accuracy: bool = False) -> dict:
    from pnyolo.engine.checkpoint import load_detector, read_checkpoint
    from pnyolo.models import predict_item
    from pnyolo.onnx.backend import OnnxRunner, example_item, export_onnx

    torch.set_num_threads(threads)
    ckpt = read_checkpoint(path)
    model, cfg = load_detector(ckpt, path, list(ckpt["class_names"]), "cpu")
    model.eval()
    from pnyolo.components.backbones import backbone_computed

    with tempfile.TemporaryDirectory() as tmp, backbone_computed(model):
        onnx = export_onnx(model, Path(tmp) / "m.onnx", width, height, views, cfg.eval)
        runner = OnnxRunner(onnx, model, threads)
        item = example_item(model, width, height, views)
        torch.manual_seed(0)
        item.images = torch.rand_like(item.images)
        with torch.no_grad():
            out = predict_item(model, item, "cpu", cfg.eval)
            eager = timed(lambda: predict_item(model, item, "cpu", cfg.eval), warmup, repeat)
            encoder = timed(lambda: model.encoder(item.images), warmup, repeat)
            decode = timed(lambda: model.decode(out, item, cfg.eval), warmup, repeat)
            ort = timed(lambda: runner(item), warmup, repeat)
        row = {"checkpoint": path, "kind": model.kind, "size": f"{width}x{height}", "views": views, "threads": threads,
               "torch_ms": eager, "onnxruntime_ms": ort, "encoder_ms": encoder[0],
               "rest_of_forward_ms": eager[0] - encoder[0], "decode_ms": decode[0], "speedup": eager[0] / ort[0]}
        if int8:
            quantised = OnnxRunner(int8_file(model, cfg, list(ckpt["class_names"]), onnx, int8, width, height, views),
                                   model, threads)
            row["int8_ms"] = timed(lambda: quantised(item), warmup, repeat)
            if with_accuracy:
                row["accuracy"] = {"fp32": accuracy(model, cfg, runner, int8, views),
                                   "int8": accuracy(model, cfg, quantised, int8, views)}
    return row


def int8_table(rows: list[dict]) -> str:
    """INT8 beside FP32 (ONNX Runtime, ms; accuracy where measured)."""
    lines = ["| model | threads | FP32 ms | INT8 ms | x faster | F1@0.2 FP32 / INT8 | AP50 FP32 / INT8 | hidden-but-seen "
             "recall FP32 / INT8 |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "int8_ms" not in r:
            continue
        acc = r.get("accuracy")
        pair = (lambda k: f"{acc['fp32'][k]:.3f} / {acc['int8'][k]:.3f}") if acc else (lambda k: "-")
        lines.append(f"| {r['kind']} | {r['threads']} | {r['onnxruntime_ms'][0]:.1f} | {r['int8_ms'][0]:.1f} | "
                     f"{r['onnxruntime_ms'][0] / r['int8_ms'][0]:.2f} | {pair('f1')} | {pair('ap50')} | "
                     f"{pair('hidden_recall')} |")
    return "\n".join(lines) + "\n" if len(lines) > 2 else ""


def table(rows: list[dict]) -> str:
    lines = ["| model | size | threads | torch eager ms (p10-p90) | ONNX Runtime ms (p10-p90) | x faster | encoder / "
             "rest of forward / decode ms (torch) | ORT + decode vs single view (same threads) |",
             "|---|---|---|---|---|---|---|---|"]
    single = {(r["size"], r["threads"]): r for r in rows if r["kind"] == "single-view"}
    for r in rows:
        base = single.get((r["size"], r["threads"]))
        ratio = (f"{(r['onnxruntime_ms'][0] + r['decode_ms']) / (base['onnxruntime_ms'][0] + base['decode_ms']):.2f}x"
                 if base else "-")
        lines.append(f"| {r['kind']} | {r['size']} | {r['threads']} | {r['torch_ms'][0]:.1f} ({r['torch_ms'][1]:.1f}-"
                     f"{r['torch_ms'][2]:.1f}) | {r['onnxruntime_ms'][0]:.1f} ({r['onnxruntime_ms'][1]:.1f}-"
                     f"{r['onnxruntime_ms'][2]:.1f}) | {r['speedup']:.2f} | {r['encoder_ms']:.1f} / "
                     f"{r['rest_of_forward_ms']:.1f} / {r['decode_ms']:.1f} | {ratio} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="+")
    p.add_argument("--size", default="320x180", help="camera images WxH, comma-separated for several")
    p.add_argument("--views", type=int, default=3)
    p.add_argument("--threads", default="1,2", help="torch and ONNX Runtime intra-op threads, comma-separated")
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--repeat", type=int, default=30)
    p.add_argument("--int8", metavar="DATASET", help="also INT8 (QDQ) calibrated on DATASET's val split")
    p.add_argument("--accuracy", action="store_true", help="with --int8: F1@0.2, AP50, hidden-but-seen recall of "
                   "FP32 and INT8 on DATASET's test split (at the first thread count)")
    p.add_argument("--out", help="write the Markdown table here")
    a = p.parse_args()
    rows = []
    for size in a.size.split(","):
        w, h = (int(v) for v in size.split("x"))
        for n, threads in enumerate(int(t) for t in a.threads.split(",")):
            for path in a.checkpoints:
                rows.append(measure(path, w, h, a.views, threads, a.warmup, a.repeat, a.int8, a.accuracy and n == 0))
                print(json.dumps(rows[-1]), flush=True)
    text = table(rows) + "\n" + int8_table(rows)
    print(text)
    if a.out:
        atomic_write_text(a.out, text)


if __name__ == "__main__":
    main()
