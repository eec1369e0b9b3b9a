"""A GPU check anyone can run (scripts/gpu-check): on a machine with CUDA and no Blender, given a rendered dataset
folder, the suite's tests that need no Blender, then every model kind trained briefly on the GPU, evaluated,
exported, predicted and (on sequences) tracked there, and one summary: pass / fail, items per second, ms a frame.

    python benchmarks/gpu_check.py out/bench_demo/dataset --out out/gpu_check     # scripts/gpu-check does this

Each step runs as the user would run it (the console commands, as subprocesses), with a time limit of its own;
a step that fails is reported with its last line and the others still run. Needs nothing beyond the project's
Python dependencies (it runs under numpy 2 and Python 3.12 too); writes OUT/summary.md and OUT/summary.json.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from bench_frame import table  # the same table bench_frame prints (this folder is on the path)

from dataset_spec.atomic import atomic_write_json, atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("single-view", "bev", "pixelnerf-yolo")
TINY = {"single-view": [], "bev": [], "pixelnerf-yolo": ["model.sampler.num_samples=16"]}


def run(step: str, cmd: list[str], limit_s: float, env=None) -> dict:
    """One step: its command, pass or fail, seconds, and its last output line (what failed, or the result)."""
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=limit_s, env=env)
        ok, text = proc.returncode == 0, (proc.stdout + proc.stderr).strip()
    except subprocess.TimeoutExpired as exc:
        ok, text = False, f"ran past its {limit_s:.0f} s ({(exc.stdout or b'')[-200:]!r})"
    lines = [ln for ln in text.splitlines() if ln.strip()]
    return {"step": step, "ok": ok, "seconds": round(time.perf_counter() - t0, 1), "last": lines[-1][:300] if lines else "",
            "output": text[-4000:]}


ENTRIES = {"pnyolo-train": ("pnyolo.cli", "train_main"), "pnyolo-eval": ("pnyolo.cli", "eval_main"),
           "pnyolo-predict": ("pnyolo.cli.predict", "main"), "pnyolo-export": ("pnyolo.cli.export", "main"),
           "pnyolo-track": ("pnyolo.cli.track", "main")}  # pyproject.toml's console scripts


def command(name: str) -> list[str]:
    """A console command of the project by its entry point (works without the console scripts installed)."""
    module, entry = ENTRIES[name]
    return [sys.executable, "-c", f"import sys; from {module} import {entry} as m; sys.exit(m(sys.argv[1:]))"]


def steps(dataset: Path, out: Path, args) -> list[dict]:
    rows = []
    if not args.no_tests:
        xdist = subprocess.run([sys.executable, "-c", "import xdist"], capture_output=True).returncode == 0
        rows.append(run("tests without Blender", [sys.executable, "-m", "pytest", "-q", "-m", "not blender",
                                                  "-p", "no:cacheprovider", *(["-n", "8"] if xdist else []), "tests"],
                        args.tests_limit))
    for kind in KINDS:
        run_dir = out / "runs" / kind
        sets = [f"model.kind={kind}", f"train.device={args.device}", f"train.max_steps={args.steps}", "train.items_per_step=4",
                "train.workers=4", "train.val_every=0", "train.epochs=1000", "train.threads=4", *TINY[kind]]
        train = run(f"train {kind}", [*command("pnyolo-train"), str(dataset), "--config", "configs/cpu.yaml",
                                      "--out", str(run_dir), "--force", "--quiet",
                                      *sum((["--set", s] for s in sets), [])], args.step_limit)
        if train["ok"]:
            summary = json.loads(next(ln for ln in reversed(train["output"].splitlines()) if ln.startswith("{")))
            train["items_per_s"] = round(summary["steps"] * summary["items_per_step"] / train["seconds"], 1)
            train["last"] = (f"{summary['steps']} steps of {summary['items_per_step']} items on {summary['device']}, "
                             f"loss {summary['last_loss']:.3f} (the whole command's seconds: start-up included)")
        rows.append(train)
        ckpt = str(run_dir / "latest.pt")
        rows.append(run(f"evaluate {kind}", [*command("pnyolo-eval"), ckpt, str(dataset), "--every-camera", "--device",
                                             args.device, "--out", str(out / "eval" / kind), "--quiet"], args.step_limit))
        rows.append(run(f"predict {kind}", [*command("pnyolo-predict"), ckpt, str(dataset), "--device", args.device,
                                            "--out", str(out / "predict" / kind), "--quiet"], args.step_limit))
        rows.append(run(f"export {kind}", [*command("pnyolo-export"), ckpt, "--onnx", str(out / f"{kind}.onnx"),
                                           "--size", "320x180"], args.step_limit))
        if kind == "bev" and args.sequences:
            rows.append(run("track bev", [*command("pnyolo-track"), ckpt, str(dataset), "--device", args.device, "--out",
                                          str(out / "tracks"), "--quiet"], args.step_limit))
    checkpoints = [str(out / "runs" / k / "latest.pt") for k in KINDS if (out / "runs" / k / "latest.pt").is_file()]
    frame = run("ms a frame (bench_frame.py)", [sys.executable, "benchmarks/bench_frame.py", *checkpoints, "--device",
                                                args.device, "--repeat", "30", "--out", str(out / "frame.md")],
                args.step_limit)
    frame["frames"] = [json.loads(ln) for ln in frame["output"].splitlines() if ln.startswith("{")]
    rows.append(frame)
    return rows


def summary_md(rows: list[dict], device: str) -> str:
    lines = [f"# GPU check ({device})", "", "| step | result | seconds | items/s | note |", "|---|---|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {r['step']} | {'pass' if r['ok'] else 'FAIL'} | {r['seconds']} | {r.get('items_per_s', '')} | "
                     f"{r['last'].replace('|', '/')[:160]} |")
    frames = next((r.get("frames") for r in rows if r.get("frames")), [])
    text = "\n".join(lines) + "\n"
    return text + "\n" + table(frames) if frames else text


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset", help="a rendered dataset folder (e.g. the demo's: out/bench_demo/dataset)")
    p.add_argument("--out", default="out/gpu_check")
    p.add_argument("--steps", type=int, default=150, help="optimizer steps per kind (4 items each)")
    p.add_argument("--tests-limit", type=float, default=240)
    p.add_argument("--step-limit", type=float, default=120)
    p.add_argument("--no-tests", action="store_true")
    p.add_argument("--device", default="cuda", help="cuda (the check), or cpu to rehearse it without a GPU")
    args = p.parse_args()
    import torch

    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print("gpu-check: error: CUDA is not available to torch here", file=sys.stderr)
        return 2
    dataset, out = Path(args.dataset).resolve(), Path(args.out).resolve()  # the caller's folder, not the project's
    if not (dataset / "dataset.json").is_file():
        print(f"gpu-check: error: {dataset}: not a dataset folder (no dataset.json)", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    args.sequences = any(json.loads(p.read_text()).get("sequence") for p in dataset.glob("scenarios/*/scenario.json"))
    t0 = time.perf_counter()
    rows = steps(dataset, out, args)
    name = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else "CPU"
    device = f"{name}, torch {torch.__version__}, Python {sys.version.split()[0]}"
    text = summary_md(rows, device) + f"\nTotal {time.perf_counter() - t0:.0f} s.\n"
    atomic_write_text(out / "summary.md", text)  # renamed into place: a link planted there is replaced, not followed
    atomic_write_json(out / "summary.json", {"device": device, "steps": rows})
    print(text)
    failed = [r["step"] for r in rows if not r["ok"]]
    passed_tests = re.search(r"(\d+) passed", next((r["last"] for r in rows if r["step"].startswith("tests")), ""))
    print(f"gpu-check: {len(rows) - len(failed)} of {len(rows)} steps passed"
          + (f" ({passed_tests[1]} tests passed)" if passed_tests else "") + (f"; failed: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
