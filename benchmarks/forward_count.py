"""How many times the smoke bench runs a model, and where from (issue 77): every call of ``predict_item`` (the
one function through which a pnyolo model is run on an item) counted by its caller (the nearest pnyolo frame
outside the models, ``engine/predict.py`` and the plan's runner ``bench/plan.py``), the model's kind, the split of the item's scenario and the
condition (clean, own view, samples kept, delayed source views), training's forwards apart.

    .venv/bin/python benchmarks/forward_count.py                     # this tree
    .venv/bin/python benchmarks/forward_count.py --base 8212677      # and a git revision beside it (a worktree)

Each side runs in a fresh process; on 2 cores about 3 minutes each (Blender renders the smoke data).
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def counting(root: Path):
    """Within: every ``predict_item`` of ``root``'s pnyolo counted into the yielded Counter by (caller, kind,
    scenario, condition); the caller is the nearest frame of ``root/pnyolo`` outside the models, ``engine/predict.py``
    and the prediction plan's runner (``bench/plan.py``: the one through which every caller predicts) ("?" when
    none is)."""
    import pnyolo.models.base as base

    package, real = str(root / "pnyolo") + os.sep, base.predict_item
    skip = (str(root / "pnyolo" / "models") + os.sep, str(root / "pnyolo" / "engine" / "predict.py"),
            str(root / "pnyolo" / "bench" / "plan.py"))
    seen: collections.Counter = collections.Counter()

    def counted(model, item, *args, **options):
        frame = sys._getframe(1)
        while frame is not None and (not frame.f_code.co_filename.startswith(package)
                                     or frame.f_code.co_filename.startswith(skip)):
            frame = frame.f_back
        where = "?" if frame is None else (f"{Path(frame.f_code.co_filename).relative_to(root).with_suffix('')}"
                                           f":{frame.f_code.co_name}")
        condition = ("own view" if options.get("own_view_only") else "samples kept" if options.get("return_samples")
                     else "delayed" if item.view_frames and set(item.view_frames) != {item.frame} else "clean")
        seen[(where, model.kind, item.scenario, condition)] += 1
        return real(model, item, *args, **options)

    # every module that imported it by name, and those to come (the models' module itself)
    patched = [m for name, m in list(sys.modules.items())
               if name.startswith("pnyolo") and getattr(m, "predict_item", None) is real]
    for module in patched:
        module.predict_item = counted
    try:
        yield seen
    finally:
        for module in patched:
            module.predict_item = real


def count_here(root: Path, out: Path) -> dict:
    """The smoke bench in ``root``'s pnyolo with every ``predict_item`` counted, by split instead of scenario."""
    from pnyolo.bench.cli import main

    with counting(root) as seen:
        rc = main(["smoke", "--out", str(out), "--quiet"])
    from dataset_spec import Dataset

    ds = Dataset.open(out / "dataset")
    split = {s: name for name in ("train", "val", "test") for s in ds.split(name)}
    rows = collections.Counter()
    for (where, kind, scenario, condition), n in seen.items():
        rows[(where, kind, split.get(scenario, "?"), condition)] += n
    return {"rc": rc, "rows": [[*k, n] for k, n in sorted(rows.items())]}


def print_side(name: str, rows: list) -> None:
    train = sum(r[-1] for r in rows if r[0].startswith("pnyolo/training/train"))
    rest = [r for r in rows if not r[0].startswith("pnyolo/training/train")]
    print(f"{name}: {sum(r[-1] for r in rows)} forwards: {train} in training and validation, "
          f"{sum(r[-1] for r in rest)} elsewhere")
    by_caller = collections.Counter()
    for where, kind, split, condition, n in rows:
        by_caller[where] += n
    for where, n in by_caller.most_common():
        print(f"  {n:5d}  {where}")
    print("  by (kind, split, condition), outside training:")
    by_key = collections.Counter()
    for where, kind, split, condition, n in rest:
        by_key[(kind, split, condition)] += n
    for (kind, split, condition), n in sorted(by_key.items()):
        print(f"  {n:5d}  {kind:15s} {split:5s} {condition}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--base", help="a git revision to count beside this tree")
    p.add_argument("--here", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.here:
        print(json.dumps(count_here(Path(args.here), Path(args.out))))
        return 0
    from pnyolo.devtools.sides import run_here, sides  # this tree's: only the orchestrating side needs it

    with tempfile.TemporaryDirectory() as tmp, sides(ROOT, args.base, Path(tmp)) as checkouts:
        for k, (name, root) in enumerate(checkouts.items()):
            print_side(name, run_here(__file__, root, Path(tmp) / f"out_{k}")["rows"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
