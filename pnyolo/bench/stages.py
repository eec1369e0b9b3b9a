"""The benchmark's stages before evaluation: render, split, label, fit anchors, train each model.

Every stage reuses what exists, so a re-run after an interruption continues where it stopped::

    seconds = render_dataset(preset, Path("out/data"), seed=0)     # blender-gen in a subprocess
    set_splits(preset, data); label(preset, data)
    cfg = model_config(preset, MULTI, data, seed=0)                # base config + overrides + fitted anchors
    summary = train_model(preset, MULTI, data, Path("out/runs"), seed=0, quiet=True)

Rendering runs ``blender-gen`` in a subprocess (pnyolo itself never imports bpy).
"""
from __future__ import annotations

import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

from dataset_spec import Dataset
from dataset_spec.atomic import atomic_write_json
from dataset_spec.cli_support import UserError
from pnyolo.bench.presets import BenchPreset


def log(msg: str) -> None:
    print(f"[bench] {msg}", flush=True)


# --------------------------------------------------------------------------------------- stages
def render_dataset(preset: BenchPreset, data: Path, seed: int, ray: str | None = None) -> float:
    """Render (or complete) the preset's scenarios with blender-gen (local workers, or one task per
    scenario on the Ray cluster ``ray``); returns wall seconds."""
    cmd = [str(Path(sys.executable).parent / "blender-gen"), "render", "--scene", ",".join(preset.scenarios),
           "--hdr", preset.hdr, *preset.render, "--out", str(data), "--seed", str(seed),
           *(["--ray", ray] if ray else ["--workers", str(preset.workers)])]
    if not Path(cmd[0]).exists():
        cmd[0] = "blender-gen"
    log("render: " + " ".join(shlex.quote(c) for c in cmd))
    t0 = time.time()
    proc = subprocess.run(cmd)
    if proc.returncode != 0:
        raise UserError(f"rendering failed (blender-gen exited with {proc.returncode}); see the messages above")
    return time.time() - t0


def set_splits(preset: BenchPreset, data: Path) -> None:
    ds = Dataset.open(data)
    missing = [s for s in preset.scenarios if s not in ds.scenario_names()]
    if missing:
        raise UserError(f"{data}: scenarios {missing} are missing (render them first)")
    ds.set_splits({"train": preset.train, "val": preset.val, "test": preset.test})


def label_thresholds(preset: BenchPreset):
    from dataset_spec import LabelThresholds

    return LabelThresholds(max_distance=preset.max_distance)


def label(preset: BenchPreset, data: Path) -> float:
    from tools.projection import label_dataset

    t0 = time.time()
    n = label_dataset(data, thresholds=label_thresholds(preset), progress=False)
    log(f"labels: {n} views labelled")
    return time.time() - t0


def fitted_anchor_override(preset: BenchPreset, data: Path) -> list[str]:
    """``model.head.anchors=...`` fitted to the training split's labels (same for both models)."""
    if not preset.anchors:
        return []
    from pnyolo.data.anchors import anchors_from_labels

    ds = Dataset.open(data)
    return [f"model.head.anchors={anchors_from_labels(ds, ds.split('train'), preset.anchors)}"]


def model_config(preset: BenchPreset, kind: str, data: Path | None, seed: int):
    """The config one model trains with. The bench's seed comes first, so a ``train.seed`` among
    the overrides (``--set-multi train.seed=1``: another seed for one model) wins; the model kind
    and the step budget (``--steps``) come last and cannot be overridden. ``data`` None: without
    the anchors fitted to its labels (to check the overrides before there is a dataset)."""
    from pnyolo.config import load_config

    anchors = fitted_anchor_override(preset, data) if data is not None else []
    return load_config(preset.config_path, [f"train.seed={seed}", *preset.overrides_for(kind),
                                            *anchors, f"model.kind={kind}",
                                            f"train.max_steps={preset.steps}", "train.epochs=100000"])


def train_model(preset: BenchPreset, kind: str, data: Path, runs: Path, seed: int, quiet: bool) -> dict:
    """Train one model for the preset's step budget, resuming a partial run; returns its summary."""
    from pnyolo.engine.checkpoint import checkpoint_config, read_checkpoint
    from pnyolo.config import to_dict
    from pnyolo.engine.train import train

    cfg = model_config(preset, kind, data, seed)
    out = runs / kind
    latest = out / "latest.pt"
    done = 0
    if latest.is_file():
        ckpt = read_checkpoint(latest)
        stored = to_dict(checkpoint_config(ckpt))
        wanted = to_dict(cfg)
        diff = [k for k in ("data", "model", "loss") if stored.get(k) != wanted.get(k)]
        if diff:
            raise UserError(f"{out} holds a {kind} run with another configuration ({', '.join(diff)} differ); "
                            f"delete it or use another --out")
        done = ckpt["train_state"]["step"]
    timing = out / "bench_timing.json"
    if done >= preset.steps:
        record = json.loads(timing.read_text()) if timing.is_file() else {}
        log(f"train {kind}: reusing {latest} ({done} steps)")
        return {"steps": done, "reused": True, "trained_seconds": record.get("seconds"), "threads": record.get("threads")}
    log(f"train {kind}: {preset.steps} steps" + (f" (resuming at {done})" if done else ""))
    t0 = time.time()
    # no checkpoint: start over (a run that failed before its first checkpoint left only logs)
    summary = train(data, cfg, out, resume=latest.is_file(), quiet=quiet, force=not latest.is_file())
    seconds = time.time() - t0
    atomic_write_json(timing, {"seconds": seconds, "steps": summary["steps"], "resumed_from": done,
                               "threads": summary["threads"]})
    return {**summary, "seconds": seconds, "reused": False, "resumed_from": done}


def dataset_statistics(data: Path, preset: BenchPreset) -> dict:
    ds = Dataset.open(data)
    out = {}
    for split in ("train", "val", "test"):
        views = labels = hidden = 0
        for s in ds.split(split):
            scn = ds.scenario(s)
            views += len(scn.cameras) * len(scn.lighting)
            for cam in scn.cameras:
                kept = ds.read_labels(s, cam.name).kept()
                labels += len(kept)
                hidden += sum(o.visible_fraction <= 0 for o in kept)
        out[split] = {"scenarios": ds.split(split), "images": views, "labels_per_lighting": labels,
                      "fully_hidden_labels": hidden}
    out["occlusion"] = {s: ds.scenario(s).extras.get("occlusion", {}).get("summary", ds.scenario(s).extras.get(
        "occlusion")) for s in preset.test}
    return out


