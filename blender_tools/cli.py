"""``blender-gen``: render procedural intersections (or your own .blend) into a dataset.

Each view (scenario, camera) gets depth + instance segmentation once and one RGB image per HDR
lighting variant. Runs are resumable: complete files are skipped (``--force`` redoes them), and a
kill loses at most the render in flight. Rendering happens in worker processes (``--workers N``,
one fresh bpy process per scenario and worker, so memory stays flat), or as Ray tasks on a
cluster (``--ray``, one per scenario; see blender_tools.ray_farm).

Inside a Blender executable (no pip-installed bpy needed)::

    blender -b -P blender_tools/blender_entry.py -- render --scene toy --quality preview --out out/ds
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_dir, check_output_file, cli_main
from dataset_spec.names import check_name, excerpt

from .run_support import (Progress, occlusion, plan_splits, print_summary, remove_leftovers, run_in_process,
                          run_workers, update_splits)

EPILOG = """examples:
  blender-gen list
  blender-gen render --scene intersection_07 --hdr all                  default preset, every HDR variant
  blender-gen render --scene intersection_07 --hdr noon,sunset --quality preview
  blender-gen render --scene all --quality final --workers 2 --out out/full
  blender-gen render --scene intersection_01,intersection_02 --resolution 960x540 --samples 32
  blender-gen render --scene intersection_01-s1,intersection_01-s2       the same layout redrawn (seeds 1, 2)
  blender-gen render --scene procedural-0,procedural-1,procedural-2-s1   layouts drawn from a distribution (and a redraw)
  blender-gen render --scene intersection_07 --frames 20 --fps 5 --hdr noon   a 4-second sequence, cameras parked
  blender-gen render --scene intersection_07 --frames 50 --moving-cameras 2   two of the camera cars drive
  blender-gen render --scene intersection_03 --hdr all --hdr-dir my_hdris/   built-ins + your .hdr/.exr files
  blender-gen render --scene intersection_01-s1,intersection_01-s2 --hdr random   each scene under one drawn lighting
  blender-gen render --blend my_street.blend --hdr noon                     your scene (docs/guide/data.md: Cars/Pedestrians)
  blender -b -P blender_tools/blender_entry.py -- render --scene toy         inside a Blender executable
  blender-gen render --scene all --hdr all --ray local                  one Ray task per scenario on this machine
  blender-gen render --scene all --hdr all --ray auto --ray-cpus 4      on the running cluster (`ray start --head`)
  blender-gen render --scene all --ray HEAD:6379 --shared-out --out /nfs/ds   nodes write to shared storage

quality presets: preview 320x180 8 spp | default 480x270 16 spp + OIDN | final 1920x1080 128 spp + OIDN denoising

splits: rendering into a dataset keeps its train/val/test assignment; a new scenario joins its layout's split
(NAME-sK with NAME), a new layout the empty split (test, then val) or the one furthest below 70/15/15; the run
says where each went. `dataset-spec split` sets them by hand or by a seeded split of the layouts.
"""

LIST_EPILOG = """examples:
  blender-gen list                          built-in scenarios (each also as NAME-sK: the layout redrawn) and
                                            HDR variants, with what each holds
  blender-gen list | grep intersection      just the intersections
"""


def _parser() -> OneLineArgumentParser:
    from .render import PRESETS

    p = OneLineArgumentParser(prog="blender-gen", description=__doc__.split("\n\n")[0], epilog=EPILOG)
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list the built-in scenarios and HDR variants", epilog=LIST_EPILOG,
                   formatter_class=p.formatter_class)
    r = sub.add_parser("render", help="render scenarios into a dataset", epilog=EPILOG,
                       formatter_class=p.formatter_class)
    r.add_argument("--scene", default=None, help="scenario name, comma list, or 'all' (see `blender-gen list`)")
    r.add_argument("--blend", default=None, help="render a user .blend file (collections Cars, Pedestrians)")
    r.add_argument("--hdr", default="all",
                   help="'all', or comma list of variants / .hdr/.exr paths (default all); 'random' (or "
                        "'random:A,B,...'): each scene under one of them, drawn by its name and --seed")
    r.add_argument("--hdr-dir", default=None, help="folder of your own .hdr/.exr files (added to the variants)")
    r.add_argument("--quality", default="default", choices=sorted(PRESETS), help="preset (default: default)")
    r.add_argument("--resolution", default=None, help="WxH, overrides the preset, e.g. 960x540")
    r.add_argument("--samples", type=int, default=None, help="Cycles samples per pixel, overrides the preset")
    r.add_argument("--denoise", choices=("on", "off"), default=None, help="OIDN denoising, overrides the preset")
    r.add_argument("--device", choices=("cpu", "gpu"), default="cpu", help="Cycles device (default cpu)")
    r.add_argument("--out", default="out/dataset", help="dataset folder (default out/dataset)")
    r.add_argument("--seed", type=int, default=0, help="procedural seed (default 0)")
    r.add_argument("--split", choices=("train", "val", "test"), default=None,
                   help="put this call's scenarios in that split (default: new layouts by a seeded split, the others "
                        "keep theirs)")
    r.add_argument("--frames", type=int, default=1,
                   help="render a sequence of N frames: road users move (docs/guide/data.md); default 1, one instant")
    r.add_argument("--fps", type=float, default=10.0, help="frames per second of a sequence (default 10)")
    r.add_argument("--moving-cameras", type=int, default=0, metavar="K",
                   help="with --frames: K of the camera cars drive, their cameras with them (default 0: parked)")
    r.add_argument("--workers", type=int, default=1, help="parallel bpy processes over cameras (default 1)")
    r.add_argument("--force", action="store_true", help="re-render files that already exist")
    r.add_argument("--in-process", action="store_true", help="render in this process (used inside Blender)")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.add_argument("--timings", default=None, help="write per-render timings (JSON) here (for benchmarks)")
    r.add_argument("--ray", default=None, metavar="auto|local|ADDRESS",
                   help="render on a Ray cluster, one task per scenario: 'local' starts one on this machine, 'auto' "
                        "joins the running one, HOST:PORT a given head (pip install -e '.[cluster]')")
    r.add_argument("--shared-out", action="store_true",
                   help="with --ray: every node sees --out, tasks write there directly (default: files come back "
                        "through Ray and this process writes them)")
    r.add_argument("--ray-cpus", type=int, default=1, metavar="N",
                   help="with --ray: CPUs each task declares and Cycles uses (default 1)")
    return p


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "list":
        return cmd_list()
    return cmd_render(args)


def cmd_list() -> int:
    from .hdri import BUILTIN
    from .scenarios import list_scenarios

    print("scenarios:")
    for name, desc in list_scenarios():
        print(f"  {name:<17} {desc}")
    print("  (each also as NAME-sK, K >= 1: the same layout with road users, cameras and buildings redrawn "
          "with seed --seed + K)")
    print("HDR variants (built-in, procedural): " + ", ".join(BUILTIN))
    return 0


# ----------------------------------------------------------------------------- render
def _parse_resolution(text: str | None):
    if text is None:
        return None, None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UserError(f"--resolution {text!r}: expected WxH, e.g. 960x540") from None
    if not (8 <= w <= 16384 and 8 <= h <= 16384):
        raise UserError(f"--resolution {text!r}: width and height must be within 8..16384")
    return w, h


def _check_out_dir(out: Path) -> None:
    """A writable dataset folder or one that can be made (made only by the first file written)."""
    check_output_dir(out)
    if (out / "dataset.json").is_file():
        from dataset_spec import Dataset

        Dataset.open(out)  # SpecError (one line) if it is not a readable dataset


def _scene_names(args) -> list[str]:
    from .scenarios import catalog, split_variant

    if args.blend:
        path = Path(args.blend)
        if not path.is_file():
            raise UserError(f"--blend {path}: no such file")
        if path.suffix.lower() != ".blend":
            raise UserError(f"--blend {path}: not a .blend file")
        with open(path, "rb") as fh:
            head = fh.read(7)
        if head not in (b"BLENDER",) and not head.startswith((b"\x1f\x8b", b"\x28\xb5")):  # plain, gzip, zstd
            raise UserError(f"--blend {path}: not a readable .blend file (bad header)")
        name = args.scene or path.stem
        if (why := check_name(name)) is not None:
            source = (f"--scene {excerpt(name)}" if args.scene else f"scenario name {excerpt(name)} (from the file name "
                      f"{path.name}; pass --scene NAME)")
            raise UserError(f"{source}: {why}")
        return [name]
    if not args.scene:
        raise UserError("give --scene NAME (or 'all'), or --blend FILE (see `blender-gen list`)")
    cat = catalog()
    names = []
    for item in (s.strip() for s in args.scene.split(",")):
        if item == "all":
            names += [n for n in cat if n != "toy"]
        elif item:
            try:
                split_variant(item)
            except KeyError:
                raise UserError(f"unknown scenario {excerpt(item)} (known: {', '.join(cat)}, or 'all'; procedural-K for "
                                f"K >= 0 draws a layout; NAME-sK for K >= 1 redraws a layout with seed --seed + K)") \
                    from None
            names.append(item)
    return list(dict.fromkeys(names))


def _check_sequence(args, names: list[str]) -> None:
    """--frames, --fps and --moving-cameras against each other, the scenes and what --out already holds."""
    from dataset_spec.layout import MAX_FRAMES

    if not 0 <= args.seed < 2 ** 63:  # numpy's generators take non-negative seeds: checked before any worker starts
        raise UserError(f"--seed must be an integer in 0..{2 ** 63 - 1}, got {args.seed}")
    if not 1 <= args.frames <= MAX_FRAMES:
        raise UserError(f"--frames must be 1..{MAX_FRAMES}, got {args.frames}")
    if not (args.fps > 0 and args.fps < float("inf")):
        raise UserError(f"--fps must be a number > 0, got {args.fps}")
    if args.moving_cameras < 0:
        raise UserError("--moving-cameras must be >= 0")
    if args.frames == 1 and args.moving_cameras:
        raise UserError("--moving-cameras goes with --frames N > 1 (one frame has no motion)")
    if args.blend and args.frames > 1:
        raise UserError("--frames N > 1 needs a built-in scene: a .blend has no motion rules (render it one frame)")
    if args.moving_cameras:
        from .scenarios import build_model

        for name in names:
            rigs = len(build_model(name, args.seed).cameras)
            if args.moving_cameras > rigs:
                raise UserError(f"--moving-cameras {args.moving_cameras}: {name} has {rigs} camera cars")
    out = Path(args.out)
    if args.force or not (out / "dataset.json").is_file():
        return
    from dataset_spec import Dataset
    from dataset_spec.errors import SpecError

    for name in names:
        try:
            old = Dataset.open(out).scenario(name)
        except (SpecError, KeyError, OSError):
            continue
        fps = args.fps if args.frames > 1 else None
        if (old.frames, old.fps) != (args.frames, fps):
            held = f"{old.frames} frames at {old.fps:g} fps" if old.frames > 1 else "one frame"
            raise UserError(f"{out}: {name} holds {held}, not the {args.frames} asked for "
                            f"(--force renders it again, or choose another --out)")


def cmd_render(args) -> int:
    from .hdri import HdrError, random_spec, resolve_variants
    from .pipeline import Job
    from .render import RenderSettings

    names = _scene_names(args)
    try:
        draw, spec = random_spec(args.hdr)
        variants = resolve_variants(spec, args.hdr_dir)
    except HdrError as exc:
        raise UserError(str(exc)) from None
    w, h = _parse_resolution(args.resolution)
    _check_sequence(args, names)
    if args.samples is not None and args.samples < 1:
        raise UserError("--samples must be >= 1")
    if args.workers < 1:
        raise UserError("--workers must be >= 1")
    if args.ray is None and (args.shared_out or args.ray_cpus != 1):
        raise UserError("--shared-out and --ray-cpus go with --ray")
    if args.ray is not None:
        if args.ray_cpus < 1:
            raise UserError("--ray-cpus must be >= 1")
        if args.workers != 1 or args.in_process:
            raise UserError("--ray replaces --workers and --in-process (one Ray task per scenario)")
        from .ray_farm import check_address, require_ray

        require_ray()
        check_address(args.ray)
    out = Path(args.out)
    _check_out_dir(out)
    if args.timings:
        check_output_file(args.timings, "--timings")
    from dataset_spec.atomic import remove_stale_temporaries

    from .pipeline import remove_stale_temp_dirs

    remove_stale_temp_dirs()  # what killed render workers of earlier runs left in $TMPDIR
    if out.is_dir():
        remove_stale_temporaries(out)  # and half-written files a killed driver or worker left in the dataset
    splits = plan_splits(out, names, args.seed, args.split)
    workers = 1 if args.in_process else args.workers
    cores = os.cpu_count() or 1
    settings = RenderSettings.from_preset(args.quality, width=w, height=h, samples=args.samples,
                                          denoise=None if args.denoise is None else args.denoise == "on",
                                          device=args.device, threads=max(1, cores // workers) if workers > 1 else 0)
    var_dicts = [{"name": lm.name, "hdr": lm.hdr, "path": str(p.resolve()), "strength": lm.strength,
                  "rotation_deg": lm.rotation_deg} for lm, p in variants]
    lighting = {name: _drawn(var_dicts, name, args.seed) if draw else var_dicts for name in names}
    progress = Progress(disable=args.no_progress)
    summary = []
    if args.ray is not None:
        return _render_on_ray(args, names, out, lighting, settings, progress, splits)
    try:
        for name in names:
            t0 = time.perf_counter()
            remove_leftovers(out, name)
            jobs = [Job(str(out), name, args.seed, args.blend, lighting[name], settings.to_dict(), args.force, i, workers,
                        frames=args.frames, fps=args.fps, moving_cameras=args.moving_cameras) for i in range(workers)]
            stats = run_in_process(jobs[0], progress) if args.in_process else run_workers(jobs, progress)
            occ = occlusion(out, name, progress)
            update_splits(out, splits)
            wall = time.perf_counter() - t0
            summary.append((name, wall, stats, occ))
    finally:
        progress.close()
    if args.timings:
        from dataset_spec.atomic import atomic_write_json

        atomic_write_json(args.timings, [{"scenario": n, "wall_s": w, **st} for n, w, st, _ in summary])
    print_summary(out, summary)
    return 0


def _drawn(var_dicts: list[dict], scenario: str, seed: int) -> list[dict]:
    """``--hdr random``: the one variant of ``var_dicts`` that ``scenario`` is rendered under."""
    from .hdri import drawn_variant

    name = drawn_variant([v["name"] for v in var_dicts], scenario, seed)
    return [v for v in var_dicts if v["name"] == name]


def _render_on_ray(args, names: list[str], out: Path, lighting: dict[str, list[dict]], settings, progress,
                   splits) -> int:
    """One Ray task per scenario (blender_tools.ray_farm); labels and splits on this driver as they come in."""
    from .pipeline import Job
    from .ray_farm import render_on_ray

    settings.threads = args.ray_cpus
    for name in names:
        remove_leftovers(out, name)
    jobs = [Job(str(out), name, args.seed, args.blend, lighting[name], settings.to_dict(), args.force, frames=args.frames,
                fps=args.fps, moving_cameras=args.moving_cameras) for name in names]
    summary = []

    def after_scenario(name: str, result: dict) -> None:
        occ = occlusion(out, name, progress)
        update_splits(out, splits)
        summary.append((name, result["task_s"], {"files": result["rendered"], "render_s": result["render_s"]}, occ))

    try:
        stats = render_on_ray(jobs, args.ray, args.shared_out, args.ray_cpus, args.device == "gpu", progress,
                              after_scenario)
    finally:
        progress.close()
    if args.timings:
        from dataset_spec.atomic import atomic_write_json

        atomic_write_json(args.timings, {"ray": stats, "scenarios": [
            {"scenario": n, "task_s": w, **st} for n, w, st, _ in summary]})
    print_summary(out, sorted(summary))
    print(f"ray: {stats['units']} units, {stats['retries']} retries, {stats['files']} files in "
          f"{stats['wall_s']:.1f} s wall (Cycles {stats['render_s']:.1f} s) -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
