"""``pnyolo-bench``: the occlusion benchmark, the preset's model kinds against each other and its baseline.

One command renders (or reuses) a dataset of built-in scenarios with a scenario-level split,
projects 2D labels, trains every model with the same budget and configuration (only ``model.kind``
and each kind's own overrides differ), evaluates them, their fusion and what each kind's abilities
allow (own-view ablation, late fusion, coverage) on the held-out scenarios, and writes a report
folder (markdown + JSON + pictures). Every stage reuses what exists, so a re-run after an
interruption continues where it stopped.

    pnyolo-bench demo                      # the README's main job: about 20 minutes on 2 CPU cores
    pnyolo-bench cpu --out out/cpu         # the CPU benchmark (about an hour on 2 cores, dataset cached)
    pnyolo-bench gpu                       # the paper's scale (needs a GPU and hours)
    pnyolo-bench smoke                     # tiny end-to-end run for CI (minutes)
    pnyolo-bench my_bench.yaml             # a preset file of your own (see configs/bench/)
"""
from __future__ import annotations

import importlib.util
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_dir, cli_main
from dataset_spec.names import check_name, excerpt
from pnyolo.bench.preset_checks import check_places
from pnyolo.bench.presets import BenchPreset, builtin_presets, load_preset
from pnyolo.bench.record import BenchRun
from pnyolo.bench.robustness import read_sweep
from pnyolo.bench.stages import (configure, dataset_statistics, fit_anchors, label, log, model_config, render_dataset,
                                 set_splits, train_model)
from pnyolo.cli.options import add_run_options
from pnyolo.registry import kinds


def run_benchmark(run: BenchRun, quiet: bool = False, external: dict[str, Path] | None = None) -> dict:
    """Every stage of ``run``'s preset into its folder (``BenchRun``: the dataset folder, the seed, the device
    validation and test run on, where blender-gen renders, other runs whose pose-noise rows the report shows too),
    each filling in the run record; ``external``: other detectors' results scored beside the models. Returns the
    report's JSON. Stages reuse what exists."""
    from pnyolo.bench.report import write_report  # torch and matplotlib only once there is work
    from pnyolo.bench.testing import select_and_test

    preset = run.preset
    t_all = time.time()
    render_dataset(run)
    set_splits(run)
    label(run)
    fit_anchors(run)
    configure(run)
    for kind in preset.models:
        train_model(run, kind, quiet)
    t0 = time.time()
    select_and_test(run, external)
    run.timings["evaluate (every model, fusion, ablations)"] = time.time() - t0
    run.timings["total"] = time.time() - t_all
    dataset_statistics(run)
    result = write_report(run)
    log(f"report: {run.report / 'report.md'}")
    for name, ok in result["targets"].items():
        log(f"{'PASS' if ok else ('n/a' if ok is None else 'FAIL')}: {name}: {result['target_figures'][name]}")
    return result


DESCRIPTION = ("The occlusion benchmark: the preset's model kinds (multi-view, ground-plane, late fusion) "
               "against each other and a one-camera baseline.")


def _epilog() -> str:
    """The built-in presets (read from their files) and examples, for ``--help``."""
    lines = [f"  {name:6s} {load_preset(name).description}" for name in builtin_presets()]
    return "presets (configs/bench/NAME.yaml; or give a preset file of your own):\n" + "\n".join(lines) + EXAMPLES


EXAMPLES = """

examples:
  pnyolo-bench demo                          render, label, train, evaluate, report (re-runs reuse what exists)
  pnyolo-bench cpu --out out/bench_cpu --seed 1
  pnyolo-bench smoke --out /tmp/smoke
  pnyolo-bench cpu --data out/dataset        reuse (and complete) an existing dataset folder
  pnyolo-bench cpu --out out/bench_bce --set model.loss.obj_loss=bce    an ablation: every YOLO model, same budget
  pnyolo-bench cpu --out out/bench_hw3 --set-model KIND:model.loss.hidden_weight=3    an ablation of one model kind
  pnyolo-bench cpu --out out/bench_s1 --set-model KIND:train.seed=1    a seed check of one model
  pnyolo-bench configs/bench/cpu.yaml --out out/mine      the same preset given as a file (copy it to make your own)
  pnyolo-bench cpu --external yolov8n=yolo_test.json      another detector's COCO results scored beside the models
  pnyolo-bench gpu --ray auto                render the dataset on the running Ray cluster
  pnyolo-bench cpu --models KIND             train and score one kind (others' runs kept; any registered kind)
  pnyolo-bench cpu --models KIND --set-model KIND:train.pose_noise=[0.2,0.2] --out out/cpu_noise \
      --sweep-beside "no noise=out/bench_cpu/report/report.json"    a noise-trained model beside the noise-free runs

KIND: a registered model kind (pnyolo-train --help lists them; a package of yours registers its own).
"""


def _parser() -> OneLineArgumentParser:
    p = OneLineArgumentParser(prog="pnyolo-bench", description=DESCRIPTION, epilog=_epilog())
    p.add_argument("preset", help=f"a built-in preset ({' | '.join(builtin_presets())}) or a preset YAML file")
    p.add_argument("--out", help="output folder (default out/bench_PRESET)")
    p.add_argument("--data", help="dataset folder to render into / reuse (default OUT/dataset)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed for scene generation and training (default 0; --set-model KIND:train.seed=N trains "
                        "that model with another)")
    p.add_argument("--steps", type=int, help="override the preset's training steps per model")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every model that has the key, after the preset's "
                        "(e.g. model.loss.obj_loss=bce)")
    p.add_argument("--set-model", action="append", default=[], metavar="KIND:KEY=VALUE",
                   help=f"config override for one model kind ({', '.join(kinds())}) only, after --set; repeatable")
    p.add_argument("--models", metavar="KIND,KIND",
                   help=f"train and score only these kinds ({', '.join(kinds())}; the preset's or any other "
                        "registered kind); the others' runs are left alone, cached runs reused")
    p.add_argument("--external", action="append", default=[], metavar="NAME=PREDICTIONS.json",
                   help="another detector's COCO results on the test split (every lighting variant: ids as in "
                        "project-labels --export coco --variant all), scored beside the models; repeatable")
    p.add_argument("--sweep-beside", action="append", default=[], metavar="LABEL=REPORT.json",
                   help="another bench run's report.json on the same test split: its pose-noise sweep rows, named "
                        "'NAME (LABEL)', go into this report's robustness table and plot; repeatable")
    p.add_argument("--ray", metavar="auto|local|ADDRESS",
                   help="render the dataset on a Ray cluster (blender-gen render --ray; pip install -e '.[cluster]')")
    p.add_argument("--render-workers", type=int, default=1, metavar="N",
                   help="local blender-gen processes rendering the dataset (default 1; not with --ray)")
    p.add_argument("--render-gpu", action="store_true",
                   help="blender-gen renders with Cycles on the GPU (blender-gen --device gpu; default the CPU)")
    add_run_options(p, quiet="no training progress bars")
    return p


def _preset(args) -> BenchPreset:
    """The preset with the command line's steps, overrides and models, every model's config checked."""
    preset = load_preset(args.preset)
    if args.steps is not None and args.steps < 1:
        raise UserError("--steps must be >= 1")
    known = kinds()
    own = {kind: list(preset.model_overrides.get(kind, [])) for kind in known}
    for item in args.set_model:
        kind, sep, setting = item.partition(":")
        if not sep or kind not in known or "=" not in setting:
            raise UserError(f"--set-model {item!r}: expected KIND:KEY=VALUE with KIND one of {', '.join(known)}")
        own[kind].append(setting)
    models = preset.models
    if args.models is not None:
        models = [m.strip() for m in args.models.split(",") if m.strip()]
        bad = [m for m in models if m not in known]
        if not models or bad or len(set(models)) != len(models):
            raise UserError(f"--models {args.models!r}: distinct registered kinds ({', '.join(known)})")
    check_places(preset, models, f"benchmark preset {preset.name}")  # the kinds --models picks, before --set joins
    preset = replace(preset, steps=preset.steps if args.steps is None else args.steps,
                     overrides=[*preset.overrides, *args.set], model_overrides={k: v for k, v in own.items() if v},
                     models=models)
    for kind in preset.models:  # a bad key or value (for that model kind) fails now, not after rendering
        ious = model_config(preset, kind, args.seed).eval.match_ious
        if preset.select_iou not in ious:
            raise UserError(f"preset {preset.name}: select_iou {preset.iou} is not among {kind}'s eval.match_ious {ious}")
    return preset


def _external(args) -> dict[str, Path]:
    external = {}
    for text in args.external:
        name, sep, path = text.partition("=")
        if not sep or not name or not path:
            raise UserError(f"--external {text!r}: expected NAME=PREDICTIONS.json")
        if check_name(name) is not None:  # the name goes into the report as it is: no markup
            raise UserError(f"--external: the name {excerpt(name)} {check_name(name)}")
        if name in (*kinds(), "fusion") or name in external:
            raise UserError(f"--external {text!r}: the name {name!r} is taken")
        if not Path(path).is_file():
            raise UserError(f"--external {text!r}: {path} does not exist")
        external[name] = Path(path)
    return external


def _beside(args, preset: BenchPreset) -> tuple[dict[str, Path], dict]:
    """The runs set beside this one (label -> report.json) and their pose-noise rows, read now: a wrong file fails
    before any work, and the report reads the rows from the record."""
    beside, rows = {}, {}
    for text in args.sweep_beside:
        label, sep, path = text.partition("=")
        if not sep or not label or not path or label in beside:
            raise UserError(f"--sweep-beside {text!r}: expected LABEL=REPORT.json with a label of its own")
        if not preset.pose_noise_sweep:
            raise UserError(f"--sweep-beside: preset {preset.name} has no pose_noise_sweep to set rows beside")
        rows |= read_sweep(Path(path), preset, label)
        beside[label] = Path(path)
    return beside, rows


def _render_place(args) -> tuple[str, ...]:
    """blender-gen's options for where it renders, from the command line (a preset never gives them)."""
    if args.render_workers < 1:
        raise UserError("--render-workers must be >= 1")
    if args.ray is not None and args.render_workers != 1:
        raise UserError("--render-workers is for local rendering; with --ray the cluster's tasks render")
    place = ["--ray", args.ray] if args.ray is not None else ["--workers", str(args.render_workers)]
    return (*place, *(["--device", "gpu"] if args.render_gpu else []))


@cli_main
def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    preset = _preset(args)
    out = check_output_dir(args.out or f"out/bench_{preset.name}")
    command = "pnyolo-bench " + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    external, (beside, beside_rows) = _external(args), _beside(args, preset)
    if args.ray is not None and importlib.util.find_spec("ray") is None:
        raise UserError("--ray needs Ray: pip install -e '.[cluster]'")
    from pnyolo.engine.runtime import pick_device

    device = pick_device(args.device)
    if preset.needs_gpu and device.type == "cpu" and args.device != "cpu":
        raise UserError(f"preset {preset.name} is sized for a GPU and this machine has none (CUDA); "
                        "--device cpu runs it on the CPU anyway")
    run = BenchRun(preset, out, args.seed, args.data, command, beside=beside, beside_rows=beside_rows,
                   device=device, render_place=_render_place(args))
    run_benchmark(run, args.quiet, external)
    return 0


if __name__ == "__main__":
    sys.exit(main())
