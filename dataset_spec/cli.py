"""``dataset-spec``: check and inspect dataset folders."""
from __future__ import annotations

import sys

from .cli_support import OneLineArgumentParser, cli_main

EPILOG = """examples:
  dataset-spec validate out/dataset            check structure, shapes, dtypes, ids, matrices
  dataset-spec validate out/dataset --quick    JSON and matrices only, no image reads
  dataset-spec info out/dataset                scenarios, cameras, variants and splits
  dataset-spec info out/dataset --plots out/stats    + label histograms per class and the road users
                                               hidden in one camera but seen by another, per scenario
                                               (statistics.json and PNG pictures; needs labels.json)
"""


@cli_main
def main(argv: list[str] | None = None) -> int:
    parser = OneLineArgumentParser(prog="dataset-spec", description=__doc__, epilog=EPILOG)
    sub = parser.add_subparsers(dest="command", required=True)
    p_val = sub.add_parser("validate", help="check a dataset folder against the spec")
    p_val.add_argument("root", help="dataset folder")
    p_val.add_argument("--quick", action="store_true", help="skip reading image files")
    p_val.add_argument("--strict", action="store_true", help="treat warnings as errors")
    p_info = sub.add_parser("info", help="summarise a dataset folder", epilog=EPILOG,
                            formatter_class=parser.formatter_class)
    p_info.add_argument("root")
    p_info.add_argument("--plots", metavar="OUT", help="also write label statistics (JSON and pictures) to OUT")
    args = parser.parse_args(argv)
    if args.command == "validate":
        from .validate import validate

        problems = validate(args.root, check_images=not args.quick)
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
    if args.plots:
        check_output_dir(args.plots, "--plots")
    print(f"dataset {ds.info.name!r} (spec {ds.info.spec_version}) at {ds.root}")
    print("classes: " + ", ".join(f"{c.id}={c.name}{'' if c.detectable else ' (not detected)'}" for c in ds.info.classes))
    for split, names in ds.info.splits.items():
        print(f"split {split}: {len(names)} scenarios")
    for name in ds.scenario_names():
        s = ds.scenario(name)
        print(f"  {name}: {len(s.actors)} actors, {len(s.cameras)} cameras, lighting: {[v.name for v in s.lighting]}")
    if args.plots:
        from .statistics import label_statistics, write_statistics

        stats = label_statistics(ds)
        t = stats["totals"]
        print(f"labels: {t['labels']} (road user, camera) pairs, {t['ground_truth']} ground truth, "
              f"{t['fully_hidden']} fully hidden, {t['hidden_but_seen']} of them seen by another camera")
        for path in write_statistics(stats, args.plots):
            print(f"written: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
