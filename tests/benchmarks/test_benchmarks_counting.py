"""The counting scripts count right (issue 86, item 5): benchmarks/forward_count.py's counter and
benchmarks/data_walk.py's walk, each run on something whose answer is known beforehand, so a figure they give about
the bench (forwards per caller, calls / modules / returns) is a count and not an artefact of the counting."""
from __future__ import annotations

import importlib.util
import sys
import textwrap

import pytest
import torch
from repo_paths import REPO
from test_pnyolo_common import TINY, for_kind, make_dataset

from pnyolo.config import load_config
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.models import build_model


def _script(name: str):
    """benchmarks/NAME.py as a module (it is a script, not a package member)."""
    spec = importlib.util.spec_from_file_location(f"bench_script_{name}", REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_forward_count_counts_each_forward_once_by_caller_kind_scenario_and_condition(tmp_path):
    """pnyolo-track's predictions, once of every view alone (--late-fusion) and once of the items, make one forward
    per item of a two-scenario split each: the counter gives exactly those, under their caller in pnyolo (the
    plan's runner passed through), and puts the models' function back after."""
    from types import SimpleNamespace

    import pnyolo.engine.predict as engine
    from pnyolo.cli.track import _predicted

    root = make_dataset(tmp_path / "ds", n_scenarios=4)  # two of them in the training split
    cfg = load_config(None, for_kind(TINY, ["model.kind=bev"]))
    torch.manual_seed(0)
    model = build_model(cfg, 2).eval()
    ds = MultiViewDataset(root, "train", cfg)
    per_scenario = {}
    for key in ds.items:
        per_scenario[key[0]] = per_scenario.get(key[0], 0) + 1
    real = engine.predict_item
    with _script("forward_count").counting(REPO) as seen:
        for late in (True, False):
            _predicted(SimpleNamespace(checkpoint="bev.pt", late_fusion=late, quiet=True), model, cfg, ds, None)
    assert engine.predict_item is real
    expected = {("pnyolo/cli/track:_predicted", "bev", s, c): n
                for s, n in per_scenario.items() for c in ("clean", "own view")}
    assert len(per_scenario) == 2 and dict(seen) == expected


def test_data_walk_counts_calls_modules_and_returns_of_a_known_walk(tmp_path, monkeypatch):
    """A package written here whose calls are known: a.start -> b.step (-> b.inner, same module: not counted)
    -> c.leaf, then back in a: a.start -> d.other, and b.step again (seen before: one call). Three distinct
    cross-module calls, four modules, one return (d.other starts from a, the last call went into c)."""
    pkg = tmp_path / "pnyolo"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text(textwrap.dedent("""
        from pnyolo import b, d
        def start():
            b.step()
            d.other()
            b.step()
    """))
    (pkg / "b.py").write_text(textwrap.dedent("""
        from pnyolo import c
        def inner():
            return c.leaf()
        def step():
            return inner()
    """))
    (pkg / "c.py").write_text("def leaf():\n    return 1\n")
    (pkg / "d.py").write_text("def other():\n    return 2\n")
    walk_script = _script("data_walk")
    for name in [m for m in sys.modules if m == "pnyolo" or m.startswith("pnyolo.")]:
        monkeypatch.delitem(sys.modules, name)  # the package written here, not the real one, for this test
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        from pnyolo import a

        with walk_script.walking(tmp_path) as walk:
            a.start()
    finally:  # the written package's modules leave with it (monkeypatch puts the real pnyolo back)
        for name in ("pnyolo.a", "pnyolo.b", "pnyolo.c", "pnyolo.d"):
            sys.modules.pop(name, None)
    figures = walk_script.counted(walk["seen"])
    assert figures["call_list"] == [["pnyolo.a", "pnyolo.b", "step"], ["pnyolo.b", "pnyolo.c", "leaf"],
                                    ["pnyolo.a", "pnyolo.d", "other"]]
    assert (figures["calls"], figures["modules"], figures["returns"]) == (3, 4, 1)
    assert walk["stage"] == {}  # no select_and_test: the test stage's walk is empty
    assert sys.getprofile() is None


@pytest.mark.parametrize("calls, expected", [
    ([], (0, 0, 0)),
    ([("x", "y", "f"), ("y", "z", "g"), ("z", "y", "h")], (3, 3, 0)),  # each call starts where the last went
    ([("x", "y", "f"), ("x", "z", "g"), ("x", "y", "h")], (3, 3, 2)),  # twice back to x
])
def test_counted_on_call_lists(calls, expected):
    figures = _script("data_walk").counted({c: k for k, c in enumerate(calls)})
    assert (figures["calls"], figures["modules"], figures["returns"]) == expected
