"""The placement probe's short runs (issue 87, item 1): the ground-plane model (bev) as a preset trains it, once a
variant, for a few steps on the preset's rendered dataset, each scored on the validation split by the devkit's
DetectionEval over car and pedestrian (mAP, AP within 0.5 / 1 m, ATE) and by ``placement_errors.py`` (the error
along the line of sight and across it). Validation decides what a full run then uses.

    .venv/bin/python benchmarks/placement_probe.py out/bench_cpu_seq/dataset --preset cpu_seq --steps 1500 \\
        --variant base= --variant depth=model.surface_depth=true,model.loss.surface_depth=0.5 --out out/probe

Each variant: OUT/NAME/run (pnyolo-train; resumed if stopped), OUT/NAME/predict (pnyolo-predict on validation, every
lighting), OUT/NAME/devkit.json, OUT/NAME/placement (the decomposition); OUT/probe.md the table. Runs one at a time.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="placement_probe.py", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog="example:\n" + __doc__.split("\n\n")[1])
    p.add_argument("dataset", help="the preset's rendered and labelled dataset (pnyolo-bench's OUT/dataset)")
    p.add_argument("--preset", default="cpu_seq", help="the bench preset whose bev config is trained (default cpu_seq)")
    p.add_argument("--steps", type=int, default=1500, help="training steps a variant (default 1500)")
    p.add_argument("--variant", action="append", required=True, metavar="NAME=KEY=VALUE,...",
                   help="a variant: its name and config overrides, comma-separated (empty: the preset's own)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out/placement_probe", help="output folder (default out/placement_probe)")
    return p.parse_args()


def _variants(specs: list[str]) -> dict[str, list[str]]:
    out = {}
    for spec in specs:
        name, _, sets = spec.partition("=")
        if not name or not name.replace("-", "").replace("_", "").isalnum() or name in out:
            sys.exit(f"placement_probe.py: --variant {spec!r}: NAME=KEY=VALUE,... with a distinct name of letters and digits")
        out[name] = [s for s in sets.split(",") if s]
    return out


def _tool(name: str) -> str:
    return str(Path(sys.executable).parent / name)


def _config(preset_name: str, seed: int, path: Path) -> Path:
    """The preset's bev config as the bench trains it, written to ``path``."""
    import yaml

    from dataset_spec.atomic import atomic_write_text
    from pnyolo.bench.presets import load_preset
    from pnyolo.bench.stages import model_config
    from pnyolo.config import to_dict

    cfg = model_config(load_preset(preset_name), "bev", seed)
    atomic_write_text(path, yaml.safe_dump(to_dict(cfg), sort_keys=False))
    return path


def _run(cmd: list[str]) -> None:
    print("[probe] " + " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def _variant(args, name: str, sets: list[str], config: Path) -> dict:
    from pnyolo.evaluation.devkit_eval import devkit_detection

    out = Path(args.out) / name
    run, pred = out / "run", out / "predict"
    t0 = time.time()
    resume = ["--resume"] if (run / "latest.pt").is_file() else []
    _run([_tool("pnyolo-train"), args.dataset, "--config", str(config), "--out", str(run), "--quiet", *resume,
          *(f"--set={s}" for s in [*sets, f"train.max_steps={args.steps}", f"train.seed={args.seed}",
                                   "train.val_every=0"])])  # its latest.pt is scored on validation after
    seconds = time.time() - t0
    _run([_tool("pnyolo-predict"), str(run / "latest.pt"), args.dataset, "--split", "val", "--variant", "all",
          "--conf", "0.05", "--out", str(pred), "--quiet"])
    doc = json.loads((pred / "results_nusc_val.json").read_text())
    kit = json.loads(json.dumps(devkit_detection(args.dataset, "val", doc, out, "all")["car_pedestrian"]))  # str keys
    (out / "devkit.json").write_text(json.dumps(kit, indent=1))
    _run([sys.executable, str(ROOT / "benchmarks" / "placement_errors.py"), args.dataset, "--split", "val",
          "--results", f"{name}={out / 'results_nusc_val.json'}", "--out", str(out / "placement")])
    placement = json.loads((out / "placement" / "placement.json").read_text())[name]
    return {"sets": sets, "train_seconds": seconds, "devkit": kit, "placement": {
        c: {k: v for k, v in f.items() if k != "points"} for c, f in placement.items()}}


def _table(figures: dict) -> str:
    lines = ["| variant | mAP | car AP 0.5 m / 1 m | pedestrian AP 0.5 m / 1 m | mATE m | car radial share | training s |",
             "|---|---|---|---|---|---|---|"]
    for name, f in figures.items():
        kit, ap = f["devkit"], f["devkit"]["ap"]
        share = next(r for r in f["placement"]["car"]["rows"] if r["bin"] == "all")["radial_share"]
        lines.append(f"| {name} | {kit['map']:.3f} | {ap['car']['0.5']:.3f} / {ap['car']['1.0']:.3f} | "
                     f"{ap['pedestrian']['0.5']:.3f} / {ap['pedestrian']['1.0']:.3f} | {kit['errors']['trans_err']:.3f} | "
                     f"{share if share is None else round(share, 2)} | {f['train_seconds']:.0f} |")
    return "\n".join(lines)


def main() -> int:
    args = _parse()
    sys.path.insert(0, str(ROOT))
    variants = _variants(args.variant)
    if not (Path(args.dataset) / "dataset.json").is_file():
        sys.exit(f"placement_probe.py: {args.dataset} holds no dataset.json")
    if args.steps < 1:
        sys.exit("placement_probe.py: --steps must be at least 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    config = _config(args.preset, args.seed, out / "bev.yaml")
    figures = {name: _variant(args, name, sets, config) for name, sets in variants.items()}
    from dataset_spec.atomic import atomic_write_json, atomic_write_text

    atomic_write_json(out / "probe.json", figures)
    atomic_write_text(out / "probe.md", _table(figures) + "\n")
    print(_table(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
