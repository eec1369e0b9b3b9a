"""How far a benchmark run's data travels through pnyolo: the smoke bench run under a profiler that records, in
the order they first happen, the distinct calls from a function of one pnyolo module into a function of another
(the nearest pnyolo frame is the caller: a call through torch's ``Module.__call__`` counts as the model's), then
counts them, the modules they pass through, and the returns: new calls that start from a module other than
the one the last new call went into (the walk went back to a module it had left).

    .venv/bin/python benchmarks/data_walk.py                      # this tree
    .venv/bin/python benchmarks/data_walk.py --base 211dbc5~1     # and a git revision beside it (a worktree)

Import-time code is left out (``<module>``). The same counts are also made afresh from the test stage's start
(``select_and_test``) on: what choosing on validation, scoring and reporting walk, training aside. Each side runs in
a fresh process; on 2 cores about 3 minutes each.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
from pathlib import Path

from dataset_spec.atomic import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def walking(root: Path):
    """Within: the distinct cross-module calls of ``root``'s pnyolo recorded in the yielded dicts, (caller module,
    callee module, callee) -> the order it first happened; ``stage`` holds the same from the first call of
    ``select_and_test`` on."""
    package = str(root / "pnyolo") + os.sep
    walk = {"seen": {}, "stage": {}}
    seen, stage = walk["seen"], walk["stage"]

    def module(filename: str) -> str:
        return Path(filename).relative_to(root).with_suffix("").as_posix().replace("/", ".")

    def profile(frame, event, arg):
        code = frame.f_code
        if event != "call" or not code.co_filename.startswith(package) or code.co_name == "<module>":
            return
        caller = frame.f_back
        while caller is not None and not caller.f_code.co_filename.startswith(package):
            caller = caller.f_back
        if caller is None or caller.f_code.co_name == "<module>" or caller.f_code.co_filename == code.co_filename:
            return
        key = (module(caller.f_code.co_filename), module(code.co_filename), code.co_name)
        seen.setdefault(key, len(seen))
        if stage or code.co_name == "select_and_test":
            stage.setdefault(key, len(stage))

    sys.setprofile(profile)
    try:
        yield walk
    finally:
        sys.setprofile(None)


def walk_here(root: Path, out: Path) -> dict:
    """The smoke bench in ``root``'s pnyolo, traced; its cross-module calls counted."""
    from pnyolo.bench.cli import main

    with walking(root) as walk:
        rc = main(["smoke", "--out", str(out), "--quiet"])
    return {"rc": rc, **counted(walk["seen"]), "test_stage": counted(walk["stage"])}


def counted(seen: dict[tuple, int]) -> dict:
    """Calls, modules and returns of a walk (its calls in the order they first happened)."""
    calls = sorted(seen, key=seen.get)
    modules = {m for caller, callee, _ in calls for m in (caller, callee)}
    # a return: the next new call starts from a module other than the one the last call went into
    returns = sum(1 for before, after in zip(calls, calls[1:]) if after[0] != before[1])
    return {"calls": len(calls), "modules": len(modules), "returns": returns, "module_list": sorted(modules),
            "call_list": [list(c) for c in calls]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--base", help="a git revision to measure beside this tree")
    p.add_argument("--save", metavar="FILE.json", help="also write each side's counts and call lists to FILE.json")
    p.add_argument("--here", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.here:
        print(json.dumps(walk_here(Path(args.here), Path(args.out))))
        return 0
    from pnyolo.devtools.sides import run_here, sides  # this tree's: only the orchestrating side needs it

    saved = {}
    try:
        with tempfile.TemporaryDirectory() as tmp, sides(ROOT, args.base, Path(tmp)) as checkouts:
            for name, root in checkouts.items():
                r = saved[name] = run_here(__file__, root, Path(tmp) / f"out_{len(name)}_{abs(hash(name))}")
                t = r["test_stage"]
                print(f"{name}: {r['calls']} cross-module calls through {r['modules']} modules, "
                      f"{r['returns']} returns to a module already left; from the test stage on (select_and_test): "
                      f"{t['calls']} calls, {t['modules']} modules, {t['returns']} returns")
    finally:
        if args.save:
            atomic_write_text(args.save, json.dumps(saved))
    return 0


if __name__ == "__main__":
    sys.exit(main())
