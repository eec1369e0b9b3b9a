"""Whether a change kept every output bit for bit: each kind trained briefly (augmentation, ray selection,
own-view dropout and the occupancy loss on) and evaluated (bev also by late fusion, with and without pose
noise) in this tree and in a git revision, the trained weights and the reports compared.

    .venv/bin/python benchmarks/same_outputs.py --base HEAD~3          # prints SAME or DIFF per output; exit 1 on a DIFF
    .venv/bin/python benchmarks/same_outputs.py --base HEAD~3 --bench  # and the smoke bench's report.json / report.md

The revision is checked out in a temporary worktree and run with the same interpreter; each side writes its
results under a temporary folder. On 2 cores: about 4 minutes; ``--bench`` adds the smoke bench on each side
(Blender renders its data; about 2 minutes each) and compares its report with what depends on the machine's
clock left out (timings, render seconds, inference milliseconds, the command's folder).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from dataset_spec.atomic import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("pixelnerf-yolo", "single-view", "bev")


def run_here(out: Path) -> dict:
    """This tree's (or the worktree's, by PYTHONPATH) trained weights' digests and evaluation reports."""
    import torch

    sys.path.insert(0, str(Path.cwd() / "tests"))
    from test_pnyolo_common import make_dataset, tiny

    from pnyolo.cli import eval_main, train_main

    torch.set_num_threads(1)
    ds, res = make_dataset(out / "ds", n_scenarios=3, width=96, height=72), {}
    for kind in KINDS:
        sets = tiny(f"model.kind={kind}", "train.max_steps=6", "train.epochs=3", "data.hflip=true", "data.shift_px=3",
                    "data.color_jitter=true", "train.val_every=0", "train.tensorboard=false")
        if kind == "pixelnerf-yolo":
            # loss.occupancy in its older place: both revisions read it (the newer one moves it to model.loss)
            sets += ["train.background_rays=0.5", "train.own_view_dropout=0.3", "loss.occupancy=0.5"]
        run = out / f"run_{kind}"
        assert train_main([str(ds), "--out", str(run), "--quiet", *sum((["--set", s] for s in sets), [])]) == 0
        weights = torch.load(run / "latest.pt", weights_only=False)["model"]
        res[kind] = {k: hashlib.sha1(v.cpu().numpy().tobytes()).hexdigest() for k, v in weights.items()}
        evals = {"": ["--late-fusion", "--every-camera"] if kind == "bev" else []}
        if kind == "bev":
            evals["noise"] = ["--late-fusion", "--every-camera", "--pose-noise", "0.3,1"]
        for name, extra in evals.items():
            folder = out / f"eval_{kind}{name}"
            assert eval_main([str(run / "latest.pt"), str(ds), "--split", "train", "--conf", "0.01", "--quiet",
                              "--examples", "0", "--out", str(folder), *extra]) == 0
            report = folder / ("comparison.json" if extra else "metrics.json")
            res[f"{kind} eval {name}".strip()] = report.read_text().replace(str(out), "OUT")
    return res


def bench_here(out: Path) -> dict:
    """The smoke bench's report.json and report.md, without what the machine's clock decides."""
    from pnyolo.bench.cli import main as bench_main

    assert bench_main(["smoke", "--out", str(out / "bench"), "--quiet"]) == 0
    return masked_report(out / "bench" / "report", out)


def masked_report(folder: Path, out: Path) -> dict:
    """A bench report's report.json and report.md as text, ``out`` written OUT, the clock's figures left out."""
    report = json.loads((folder / "report.json").read_text().replace(str(out), "OUT"))
    for key in ("command", "timings"):
        report.pop(key)
    for split in report["dataset"].values():
        for key in ("render_data_s", "render_rgb_s"):
            split.pop(key, None)
    for row in report["models"].values():
        row.pop("inference_ms", None)
    clocked = {k for k, v in report["target_figures"].items() if " ms " in v or v.endswith(" min")}  # judged on the clock
    for key in ("targets", "target_figures"):
        report[key] = {k: v for k, v in report[key].items() if k not in clocked}
    lines, timed = [], False
    for line in (folder / "report.md").read_text().replace(str(out), "OUT").splitlines():
        if line.startswith("## "):
            timed = line.startswith(("## Models: training", "## Timings"))
        if timed or line.startswith(("Command:", "| train |", "| val |", "| test |")) or " ms" in line:
            line = re.sub(r"\d+(\.\d+)?|PASS|FAIL", "#", line)
        lines.append(line)
    return {"bench report.json": json.dumps(report, sort_keys=False), "bench report.md": "\n".join(lines)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--base", default="HEAD", help="the git revision to compare with (default HEAD)")
    p.add_argument("--bench", action="store_true", help="also the smoke bench's report (needs Blender)")
    p.add_argument("--keep", metavar="FOLDER", help="run both sides in FOLDER and keep what they wrote")
    p.add_argument("--paths", type=int, default=40, help="a report's differing key paths to print (default 40)")
    p.add_argument("--here", metavar="OUT", help=argparse.SUPPRESS)  # one side's run, in a child process
    args = p.parse_args()
    if args.here:
        res = run_here(Path(args.here)) | (bench_here(Path(args.here)) if args.bench else {})
        atomic_write_text(Path(args.here, "result.json"), json.dumps(res, sort_keys=True))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        if args.keep:
            tmp = args.keep
            Path(tmp).mkdir(parents=True, exist_ok=True)
        base = Path(tmp) / "base"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(base), args.base], check=True)
        try:
            results = {}
            for side, tree in (("base", base), ("here", ROOT)):
                out = Path(tmp) / f"out_{side}"
                out.mkdir()
                subprocess.run([sys.executable, str(Path(__file__).resolve()), "--here", str(out),
                                *(["--bench"] if args.bench else [])], cwd=tree, check=True,
                               env={**__import__("os").environ, "PYTHONPATH": str(tree)})
                results[side] = json.loads((out / "result.json").read_text())
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(base)], check=False)
    differ = [k for k in results["base"] if results["base"][k] != results["here"].get(k)]
    for k in results["base"]:
        print(f"{'DIFF' if k in differ else 'SAME'}  {k}")
        if k in differ and k.endswith(".json") and k in results["here"]:  # where, by the report's own keys
            paths = differing(json.loads(results["base"][k]), json.loads(results["here"][k]))
            print("\n".join(f"      {p}" for p in paths[:args.paths]) + (
                f"\n      ... and {len(paths) - args.paths} more" if len(paths) > args.paths else ""))
    return 1 if differ else 0


def differing(a, b, at: str = "") -> list[str]:
    """The key paths where two JSON values differ (a number's two values beside its path)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [p for k in dict.fromkeys([*a, *b]) for p in differing(a.get(k), b.get(k), f"{at}/{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [p for k, (x, y) in enumerate(zip(a, b)) for p in differing(x, y, f"{at}[{k}]")]
    return [] if a == b else [f"{at}: {str(a)[:60]} -> {str(b)[:60]}"]


if __name__ == "__main__":
    sys.exit(main())
