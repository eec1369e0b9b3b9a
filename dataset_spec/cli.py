"""``dataset-spec``: check and inspect dataset folders."""
from __future__ import annotations

import math
import sys
from pathlib import Path

from .cli_support import OneLineArgumentParser, UserError, cli_main
from .schema import SPLIT_NAMES

EPILOG = """examples:
  dataset-spec validate out/dataset            check structure, shapes, dtypes, ids, matrices
  dataset-spec validate out/dataset --quick    JSON and matrices only, no image reads
  dataset-spec validate out/dataset --strict --quiet    warnings count as errors; no progress bar
  dataset-spec info out/dataset                scenarios, cameras, variants and splits
  dataset-spec split out/dataset --train intersection_01,intersection_02 --val intersection_03 \\
      --test intersection_07                   set the splits by hand (each scenario in at most one)
  dataset-spec split out/dataset --auto --seed 3       a seeded split by layout (redraws NAME-sK stay
                                               with their layout; 70/15/15 of the layouts)
  dataset-spec info out/dataset --plots out/stats    + label histograms per class, each scenario from above
                                               (buildings, cameras and view cones, trajectories) and the road users
                                               hidden in one camera but seen by another, per scenario
                                               (statistics.json and PNG pictures; needs labels.json)
  dataset-spec import wildtrack ~/data/Wildtrack --out out/wildtrack
                                               a Wildtrack-format folder as a dataset (cameras, people
                                               as pedestrians, boxes; first 90 % of frames train)
  dataset-spec import multiviewx out/mvx/intersection_07 --out out/back --grid 1000,640
                                               a MultiviewX-format folder (--grid: its cells, 2.5 cm)
"""


@cli_main
def main(argv: list[str] | None = None) -> int:
    parser = OneLineArgumentParser(prog="dataset-spec", description=__doc__, epilog=EPILOG)
    sub = parser.add_subparsers(dest="command", required=True)
    p_val = sub.add_parser("validate", help="check a dataset folder against the spec", epilog=EPILOG,
                           formatter_class=parser.formatter_class)
    p_val.add_argument("root", help="dataset folder")
    p_val.add_argument("--quick", action="store_true", help="skip reading image files")
    p_val.add_argument("--strict", action="store_true", help="treat warnings as errors")
    p_val.add_argument("--quiet", action="store_true", help="no progress bar")
    p_split = sub.add_parser("split", help="set the train/val/test splits of a dataset", epilog=EPILOG,
                             formatter_class=parser.formatter_class)
    p_split.add_argument("root", help="dataset folder")
    for name in SPLIT_NAMES:
        p_split.add_argument(f"--{name}", metavar="A,B,...", help=f"the scenarios of the {name} split")
    p_split.add_argument("--auto", action="store_true", help="a seeded split by layout instead of naming scenarios")
    p_split.add_argument("--seed", type=int, default=0, help="with --auto: the shuffle's seed (default 0)")
    p_info = sub.add_parser("info", help="summarise a dataset folder", epilog=EPILOG,
                            formatter_class=parser.formatter_class)
    p_info.add_argument("root")
    p_info.add_argument("--plots", metavar="OUT", help="also write label statistics (JSON and pictures) to OUT")
    p_imp = sub.add_parser("import", help="a Wildtrack- or MultiviewX-format folder as a new dataset", epilog=EPILOG,
                           formatter_class=parser.formatter_class)
    p_imp.add_argument("format", choices=["wildtrack", "multiviewx"], help="the folder's layout and units")
    p_imp.add_argument("src", help="the folder (Image_subsets, annotations_positions, calibrations)")
    p_imp.add_argument("--out", required=True, help="the new dataset's folder (absent or empty)")
    p_imp.add_argument("--grid", metavar="NX,NY[,CELL_M[,X0,Y0]]",
                       help="the ground grid of the positionIDs (default: the format's; an export of this "
                            "project states its own)")
    p_imp.add_argument("--val", type=float, default=0.0, metavar="SHARE",
                       help="this share of the frames, from the end of the training 90 %%, as validation (default 0)")
    p_imp.add_argument("--distortion", choices=["ignore", "undistort"], default="ignore",
                       help="the calibration's lens distortion (the real MultiviewX has a little): ignore it as MVDet "
                            "does (default; the import says how far it moves the image corners), or undistort the "
                            "images with OpenCV and write the undistorted images' K (boxes moved with them)")
    p_imp.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if args.command == "import":
        return _import(args)
    if args.command == "validate":
        from .validate import validate

        problems = validate(args.root, check_images=not args.quick, progress=not args.quiet)
        for p in problems:
            print(p)
        errors = [p for p in problems if p.severity == "error" or args.strict]
        warnings = len(problems) - len([p for p in problems if p.severity == "error"])
        print(f"{args.root}: {'INVALID' if errors else 'valid'} "
              f"({len([p for p in problems if p.severity == 'error'])} errors, {warnings} warnings)")
        return 1 if errors else 0
    from .cli_support import check_output_dir
    from .dataset import Dataset

    ds = Dataset.open(args.root)
    if args.command == "split":
        return _split(ds, args)
    return _info(ds, args)


def _info(ds, args) -> int:
    """``dataset-spec info``: splits, scenarios (frames and tracks of a sequence); with --plots the label
    statistics and each scenario from above."""
    from .cli_support import check_output_dir

    if args.plots:
        check_output_dir(args.plots, "--plots")
    print(f"dataset {ds.info.name!r} (spec {ds.info.spec_version}) at {ds.root}")
    print("classes: " + ", ".join(f"{c.id}={c.name}{'' if c.detectable else ' (not detected)'}" for c in ds.info.classes))
    for split in SPLIT_NAMES:
        names = ds.info.splits.get(split, [])
        print(f"split {split}: {len(names)} scenarios" + (f": {', '.join(names)}" if names else ""))
    unsplit = sorted(set(ds.scenario_names()) - set(ds.info.all_split_scenarios))
    if unsplit:
        print(f"in no split: {', '.join(unsplit)}")
    for name in ds.scenario_names():
        s = ds.scenario(name)
        timing = ""
        if s.frames > 1:
            seq = ds.sequence(name)
            timing = f", {s.frames} frames at {s.fps:g} fps ({seq.seconds:.1f} s), {len(seq.tracks)} tracks"
        print(f"  {name}: {len(s.actors)} actors, {len(s.cameras)} cameras, lighting: {[v.name for v in s.lighting]}"
              + timing)
    if args.plots:
        from .statistics import label_statistics, write_statistics

        stats = label_statistics(ds)
        t = stats["totals"]
        print(f"labels: {t['labels']} (road user, camera) pairs, {t['ground_truth']} ground truth, "
              f"{t['fully_hidden']} fully hidden, {t['hidden_but_seen']} of them seen by another camera")
        from .trajectories import plot_trajectories

        paths = write_statistics(stats, args.plots)
        paths += [plot_trajectories(ds, name, Path(args.plots) / f"trajectories_{name}.png")
                  for name in ds.scenario_names()]
        for path in paths:
            print(f"written: {path}")
    return 0


def _import(args) -> int:
    """``dataset-spec import``: every source file checked before the dataset is written."""
    from .cli_support import check_output_dir
    from .ground_grid import GroundGrid
    from .rig_formats import FORMATS
    from .rig_import import import_rig

    grid = None
    if args.grid:
        try:
            nums = [float(v) for v in args.grid.split(",")]
        except ValueError:
            nums = []
        if len(nums) not in (2, 3, 5) or not all(math.isfinite(v) for v in nums) or nums[0] < 1 or nums[1] < 1 \
                or nums[0] % 1 or nums[1] % 1 or (len(nums) > 2 and nums[2] <= 0):
            raise UserError(f"--grid {args.grid}: expected NX,NY[,CELL_M[,X0,Y0]] (finite numbers: whole cell counts, "
                            "a positive cell)")
        cell = nums[2] if len(nums) > 2 else FORMATS[args.format].grid.cell_m
        origin = tuple(nums[3:5]) if len(nums) == 5 else FORMATS[args.format].grid.origin_m
        grid = GroundGrid(int(nums[0]), int(nums[1]), cell, origin)
    check_output_dir(args.out)
    s = import_rig(args.format, args.src, args.out, grid=grid, val=args.val, progress=not args.quiet,
                   distortion=args.distortion)
    print(f"{args.out}: {s['frames']} frames of {s['cameras']} cameras, {s['people']} people, {s['boxes']} boxes "
          f"(splits: {', '.join(f'{k} {v}' for k, v in s['splits'].items())}); calibration check: the standing "
          f"cylinders project {s['box_error_px']:.1f} px from the annotated boxes (median)"
          + ("; the world's z pointed down and was turned up" if s["z_turned"] else ""))
    lens = s["distortion"]
    if lens["max_corner_shift_px"] and lens["mode"] == "ignore":
        print(f"note: lens distortion ignored (as MVDet does): it moves the image corners by up to "
              f"{lens['max_corner_shift_px']:.1f} px ({lens['camera']}); --distortion undistort corrects the images")
    elif lens["max_corner_shift_px"]:
        print(f"images undistorted (corners moved by up to {lens['max_corner_shift_px']:.1f} px, {lens['camera']}); "
              "each camera's K is the undistorted images'")
    return 0


def _split(ds, args) -> int:
    """``dataset-spec split``: the named scenarios (each existing, each in one split) or a seeded split
    by layout; checked whole before dataset.json is written."""
    from .splits import layout_of, make_splits

    named = {s: getattr(args, s) for s in SPLIT_NAMES if getattr(args, s) is not None}
    have = ds.scenario_names()
    if args.auto == bool(named):
        raise UserError("give either --auto or the scenarios of --train/--val/--test")
    if args.auto:
        splits = make_splits(have, seed=args.seed)
    else:
        splits, seen = {s: [] for s in SPLIT_NAMES}, {}
        for split, text in named.items():
            listed = [n.strip() for n in text.split(",") if n.strip()]
            if not listed:
                raise UserError(f"--{split} {text!r}: names no scenario (leave --{split} out to keep that split empty)")
            for name in listed:
                if name not in have:
                    raise UserError(f"--{split} {name}: no such scenario in {ds.root} (have: {', '.join(have)})")
                if name in seen:
                    raise UserError(f"--{split} {name}: already in --{seen[name]}; a scenario is in one split")
                seen[name] = split
                splits[split].append(name)
    ds.set_splits(splits)
    for split in SPLIT_NAMES:
        print(f"split {split}: {', '.join(ds.info.splits[split]) or '-'}")
    where = {}
    for split, names in ds.info.splits.items():
        for name in names:
            where.setdefault(layout_of(name), set()).add(split)
    shared = sorted(lay for lay, s in where.items() if len(s) > 1)
    if shared:
        print(f"note: redraws of {', '.join(shared)} are in more than one split (the layouts leak between them)")
    unsplit = sorted(set(have) - set(ds.info.all_split_scenarios))
    if unsplit:
        print(f"in no split: {', '.join(unsplit)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
