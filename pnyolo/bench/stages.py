"""The benchmark's stages before evaluation, each filling in the run record (``pnyolo.bench.record``):
render, split, label, fit anchors (once), configure and train each model.

Every stage reuses what exists, so a re-run after an interruption continues where it stopped::

    run = BenchRun(preset, Path("out/bench"), seed=0)
    render_dataset(run); set_splits(run); label(run); fit_anchors(run)
    configure(run)                                   # run.models[kind].config for every model
    train_model(run, kind, quiet=True)               # run.models[kind].training, run.timings

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
from pnyolo.bench.record import BenchRun, ModelRun


def log(msg: str) -> None:
    print(f"[bench] {msg}", flush=True)


# --------------------------------------------------------------------------------------- stages
def render_dataset(run: BenchRun) -> None:
    """Render (or complete) the preset's scenarios with blender-gen where the command line says
    (``run.render_place``: local workers, or one task per scenario on a Ray cluster; the Cycles device): one
    blender-gen call a split, with its options (``split_render``: sequences) and ``--split``, so the splits it
    prints are the preset's; the wall seconds go to ``run.timings``."""
    preset, data, seed = run.preset, run.data, run.seed
    # one call a split, each told its split: what blender-gen prints of the splits is the preset's (set_splits)
    t0 = time.time()
    timings = run.out / ".render_timings.json"  # this call's renders, folded into RENDER_SECONDS
    for _, names, extra in preset.render_groups():  # a split's built-in layouts, then its new ones
        cmd = [str(Path(sys.executable).parent / "blender-gen"), "render", "--scene", ",".join(names),
               "--hdr", preset.hdr, *preset.render, *extra, "--out", str(data), "--seed", str(seed),
               *run.render_place, "--timings", str(timings)]
        if not Path(cmd[0]).exists():
            cmd[0] = "blender-gen"
        log("render: " + " ".join(shlex.quote(c) for c in cmd[:-2]))
        proc = subprocess.run(cmd)
        if proc.returncode != 0:
            raise UserError(f"rendering failed (blender-gen exited with {proc.returncode}); see the messages above")
        _add_render_seconds(run.out / RENDER_SECONDS, timings)
    run.timings["render (blender-gen)"] = time.time() - t0


RENDER_SECONDS = "render_seconds.json"  # scenario -> Cycles seconds of its data passes and of its RGB renders


def _add_render_seconds(path: Path, timings: Path) -> None:
    """Add what one blender-gen call rendered (its ``--timings`` file) to ``path``'s per-scenario seconds,
    so a run that found part of the dataset cached still knows what the whole of it cost."""
    done = json.loads(path.read_text()) if path.is_file() else {}
    record = json.loads(timings.read_text()) if timings.is_file() else []
    for entry in record if isinstance(record, list) else []:  # Ray's record has no per-render seconds
        renders = entry.get("renders", [])
        if not renders:
            continue
        mine = done.setdefault(entry["scenario"], {"data_s": 0.0, "rgb_s": 0.0})
        mine["data_s"] += sum(r["render_s"] for r in renders if r["kind"] == "data")
        mine["rgb_s"] += sum(r["render_s"] for r in renders if r["kind"] != "data")
    atomic_write_json(path, done)
    timings.unlink(missing_ok=True)


def set_splits(run: BenchRun) -> None:
    preset, ds = run.preset, Dataset.open(run.data)
    missing = [s for s in preset.scenarios if s not in ds.scenario_names()]
    if missing:
        raise UserError(f"{run.data}: scenarios {missing} are missing (render them first)")
    ds.set_splits({"train": preset.train, "val": preset.val, "test": preset.test})


def label_thresholds(preset: BenchPreset):
    from dataset_spec import LabelThresholds

    return LabelThresholds(max_distance=preset.max_distance)


def label(run: BenchRun) -> None:
    from tools.projection import label_dataset

    t0 = time.time()
    n = label_dataset(run.data, thresholds=label_thresholds(run.preset), progress=False)
    log(f"labels: {n} views labelled")
    run.timings["labels (project-labels)"] = time.time() - t0


def fit_anchors(run: BenchRun) -> None:
    """``run.anchors``: the preset's number of YOLO anchors fitted to the training split's labels
    (the same for every model), or None to keep the config's."""
    if not run.preset.anchors:
        return
    from pnyolo.data.anchors import anchors_from_labels

    ds = Dataset.open(run.data)
    run.anchors = anchors_from_labels(ds, ds.split("train"), run.preset.anchors)


def model_config(preset: BenchPreset, kind: str, seed: int, anchors: list | None = None):
    """The config one model trains with. The bench's seed comes first, so a ``train.seed`` among
    the overrides (``--set-multi train.seed=1``: another seed for one model) wins; the model kind
    and the step budget (``--steps``) come last and cannot be overridden. ``anchors`` None: the
    config's (to check the overrides before there is a dataset to fit them to)."""
    from pnyolo.config import field_names, load_config
    from pnyolo.registry import config_class

    has_head = "head" in field_names(config_class(kind))  # a kind without YOLO anchors gets none
    fitted = [] if anchors is None or not has_head else [f"model.head.anchors={anchors}"]
    return load_config(preset.config_path, [f"train.seed={seed}", *preset.overrides_for(kind),
                                            *fitted, f"model.kind={kind}",
                                            f"train.max_steps={preset.steps}", "train.epochs=100000"])


def configure(run: BenchRun) -> None:
    """Every model's entry in the record with the config it trains with. A frozen EfficientNet
    backbone without a feature cache of its own gets ``OUT/feature_cache``, shared by the models
    (entries are keyed by the backbone's weights and the image's content)."""
    run.models = {}
    for kind in run.preset.models:
        cfg = model_config(run.preset, kind, run.seed, run.anchors)
        enc = getattr(cfg.model, "encoder", None)
        if enc is not None and enc.backbone == "efficientnet_lite0" and enc.freeze and not enc.feature_cache:
            enc.feature_cache = str(run.out / "feature_cache")
        run.models[kind] = ModelRun(kind, cfg)


# train keys that change how a run is carried out, not what it learns: a stored run is reused across them
OPERATIONAL_TRAIN_KEYS = frozenset({"device", "threads", "max_steps", "epochs", "checkpoint_every", "vis_every",
                                    "log_every", "tensorboard", "max_bad_steps",
                                    "keep_checkpoints", "compile", "deterministic"})


def train_model(run: BenchRun, kind: str, quiet: bool) -> None:
    """Train one model for the preset's step budget, resuming a partial run (``run.models[kind].training``)."""
    import copy

    from pnyolo.config import to_dict
    from pnyolo.engine.checkpoint import checkpoint_config, drop_paths, read_checkpoint
    from pnyolo.training.train import train

    preset, data, cfg = run.preset, run.data, run.models[kind].config
    out = run.runs / kind
    latest = out / "latest.pt"
    done = 0
    if latest.is_file():
        ckpt = read_checkpoint(latest)
        stored = to_dict(checkpoint_config(ckpt))
        wanted = to_dict(drop_paths(copy.deepcopy(cfg)))  # a stored run's config names no paths
        diff = [k for k in ("data", "model") if stored.get(k) != wanted.get(k)]
        diff += [f"train.{k}" for k, v in wanted["train"].items()
                 if k not in OPERATIONAL_TRAIN_KEYS and stored.get("train", {}).get(k, v) != v]
        if diff:
            raise UserError(f"{out} holds a {kind} run with another configuration ({', '.join(diff)} differ); "
                            f"delete it or use another --out")
        done = ckpt["train_state"]["step"]
    timing = out / "bench_timing.json"
    if done >= preset.steps:
        record = json.loads(timing.read_text()) if timing.is_file() else {}
        log(f"train {kind}: reusing {latest} ({done} steps)")
        run.models[kind].training = {"steps": done, "reused": True, "trained_seconds": record.get("seconds"),
                                     "threads": record.get("threads")}
        run.timings[f"train {kind}"] = {"reused": True, "trained_seconds": record.get("seconds")}
        return
    log(f"train {kind}: {preset.steps} steps" + (f" (resuming at {done})" if done else ""))
    t0 = time.time()
    # no checkpoint: start over (a run that failed before its first checkpoint left only logs)
    summary = train(data, cfg, out, resume=latest.is_file(), quiet=quiet, force=not latest.is_file())
    wall = time.time() - t0
    seconds = summary["seconds"] or wall  # every sitting of the training, no pause (the checkpoint counts them)
    atomic_write_json(timing, {"seconds": seconds, "steps": summary["steps"], "resumed_from": done,
                               "this_sitting_s": wall, "threads": summary["threads"]})
    run.models[kind].training = {**summary, "seconds": seconds, "reused": False, "resumed_from": done}
    run.timings[f"train {kind}"] = seconds


def _render_cost(run: BenchRun, scenarios: list[str]) -> dict:
    """What rendering ``scenarios`` cost (Cycles seconds of the data passes and of the RGB renders; None where a
    scenario was rendered outside the bench) and what it holds on disk (bytes)."""
    path = run.out / RENDER_SECONDS
    seconds = json.loads(path.read_text()) if path.is_file() else {}
    known = all(s in seconds for s in scenarios)
    size = sum(p.stat().st_size for s in scenarios for p in (run.data / "scenarios" / s).rglob("*") if p.is_file())
    return {"render_data_s": sum(seconds[s]["data_s"] for s in scenarios) if known else None,
            "render_rgb_s": sum(seconds[s]["rgb_s"] for s in scenarios) if known else None, "bytes": size}


def dataset_statistics(run: BenchRun) -> None:
    """``run.statistics``: each split's scenarios, images, labels and render cost, and the test scenes' occlusion."""
    data, preset = run.data, run.preset
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
                      "fully_hidden_labels": hidden, **_render_cost(run, ds.split(split))}
    out["occlusion"] = {s: ds.scenario(s).extras.get("occlusion", {}).get("summary", ds.scenario(s).extras.get(
        "occlusion")) for s in preset.test}
    run.statistics = out


