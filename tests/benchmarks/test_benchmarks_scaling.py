"""The scaling curve (issue 85, item 6): each point's figures on both test sets, the paired differences between
points with their standard errors over layouts, and a finished bench run adopted as a point only when it trained bev
on that point's scenes with the cpu preset's settings, checked before any work. Built on synthetic bench reports
whose per-scenario counts are known, so every figure can be recomputed here."""
from __future__ import annotations

import importlib.util
import json
import sys

import pytest
from repo_paths import REPO
from report_text import bare_differences

from pnyolo.bench.analyses.two_test_sets import sets_json
from pnyolo.bench.presets import load_preset

BUILT = ["intersection_07", "intersection_11", "intersection_07-s1", "intersection_11-s1"]
NEW = ["procedural-20000", "procedural-20001", "procedural-20002"]


def _script(name: str):
    """benchmarks/NAME.py as a module (a script, not a package member)."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    spec = importlib.util.spec_from_file_location(f"bench_script_{name}", REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _summary(counts: dict[str, tuple]) -> dict:
    """A bev summary whose per-scenario strict counts (TP, FP, FN) and hidden-but-seen (found, n) are ``counts``."""
    per = {s: {"counts": {"0.2": list(c[:3])}, "hidden_seen": {"0.2": list(c[3:])}} for s, c in counts.items()}
    tp, fp, fn, found, n = (sum(c[i] for c in counts.values()) for i in range(5))
    return {"per_scenario": per, "strict": {"0.2": {"f1": 2 * tp / (2 * tp + fp + fn)}}, "ap50": 0.3,
            "standard_errors": {}, "recall_by_visibility": {"0.2": {"hidden here, seen in another view":
                                                                    {"recall": found / n, "n": n}}},
            "selection": {"best_val_f1": 0.5, "val_f1_se": 0.01}}


def _run(root, name: str, counts: dict[str, tuple], preset: dict, seed: int = 0):
    """A finished bench run's files under ``root/name``: report.json and bev's training timing."""
    bev = _summary(counts)
    report = {"preset": preset, "seed": seed, "command": f"pnyolo-bench {name}", "models": {"bev": bev},
              "analyses": {"test_sets": sets_json({"bev": bev}, preset["test"], "0.2")}}
    (root / name / "report").mkdir(parents=True)
    (root / name / "runs" / "bev").mkdir(parents=True)
    (root / name / "report" / "report.json").write_text(json.dumps(report))
    (root / name / "runs" / "bev" / "bench_timing.json").write_text(json.dumps({"seconds": 100.0, "threads": 2}))
    return root / name


def _cpu_preset(scaling, curve, point: str) -> dict:
    """What a bench run of the cpu preset's settings, trained on ``point``'s scenes, writes as its preset."""
    cpu = load_preset("cpu")
    doc = {k: json.loads(json.dumps(getattr(cpu, k))) for k in (*scaling.SHARED, "model_overrides")}
    return {**doc, "train": curve.training_scenes(*curve.POINTS[point]), "models": ["bev"]}


def _f1(counts: dict[str, tuple], scenarios: list[str]) -> float:
    tp, fp, fn = (sum(counts[s][i] for s in scenarios) for i in range(3))
    return 2 * tp / (2 * tp + fp + fn)


COUNTS_A = {s: (10 + k, 5, 6 - k % 3, 3, 6) for k, s in enumerate(BUILT + NEW)}
COUNTS_B = {s: (8 + 2 * (k % 2), 7, 8, 2 + k % 2, 6) for k, s in enumerate(BUILT + NEW)}


def test_the_curve_states_each_pair_s_difference_on_both_test_sets_with_its_layout_standard_error(tmp_path):
    curve = _script("scaling_curve")
    out = tmp_path / "out"
    _run(out, "procedural-84", COUNTS_A, {"test": BUILT + NEW, "train": []})
    _run(out, "redraws-84", COUNTS_B, {"test": BUILT + NEW, "train": []})
    _run(out, "redraws-168", COUNTS_B, {"test": BUILT + NEW, "train": []})
    assert curve.main(["--out", str(out)]) == 0
    doc = json.loads((out / "report" / "points.json").read_text())
    rows = {r["point"]: r for r in doc["points"]}
    assert rows["procedural-84"]["sets"]["new layouts"]["f1"] == pytest.approx(_f1(COUNTS_A, NEW))
    assert rows["redraws-84"]["sets"]["built-in"]["f1"] == pytest.approx(_f1(COUNTS_B, BUILT))
    diffs = {(d["a"], d["b"], d["set"]): d for d in doc["differences"]}
    # procedural against redraws at 84, and the redraws' doubling: each on both sets
    assert set(diffs) == {(a, b, s) for a, b in (("procedural-84", "redraws-84"), ("redraws-168", "redraws-84"))
                          for s in ("built-in", "new layouts")}
    for test_set, names in (("built-in", BUILT), ("new layouts", NEW)):
        d = diffs[("procedural-84", "redraws-84", test_set)]
        assert d["f1"] == pytest.approx(_f1(COUNTS_A, names) - _f1(COUNTS_B, names))
        assert d["layouts"] == len({s.split("-s")[0] for s in names}) and d["f1_se"] > 0
        same = diffs[("redraws-168", "redraws-84", test_set)]   # the same counts: no difference, no spread
        assert same["f1"] == 0 and same["f1_se"] == pytest.approx(0, abs=1e-12)
    text = (out / "report" / "scaling.md").read_text()
    assert "| procedural-84 - redraws-84 | new layouts |" in text and (out / "report" / "scaling.png").stat().st_size
    assert not bare_differences(text)


def test_a_run_is_adopted_as_a_point_only_when_it_trained_bev_on_the_point_s_scenes_with_the_cpu_preset(
        tmp_path, capsys):
    scaling, curve = _script("scaling"), _script("scaling_curve")
    out, runs = tmp_path / "out", tmp_path / "runs"
    preset = _cpu_preset(scaling, curve, "redraws-84")
    counts = {s: (10, 5, 6, 3, 6) for s in preset["test"]}
    good = _run(runs, "cpu", counts, preset)
    other_steps = _run(runs, "short", counts, {**preset, "steps": 100})
    for args, words in ((["--adopt", f"procedural-84={good}"], "training split is not the point's 84 scenes"),
                        (["--adopt", f"redraws-84={other_steps}"], "its steps differs"),
                        (["--adopt", f"redraws-84={good}", "--seed", "3"], "not 3"),
                        (["--adopt", f"redraws-84={tmp_path}"], "not a finished bench run"),
                        (["--adopt", "redraws-84"], "expected POINT=DIR")):
        assert scaling.main(["--out", str(out), "--report-only", *args]) == 2, args
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and words in err, (args, err)
        assert not out.exists()   # refused before any work
    assert scaling.main(["--out", str(out), "--report-only", "--adopt", f"redraws-84={good}"]) == 0
    assert (out / "redraws-84").resolve() == good.resolve()
    rows = json.loads((out / "report" / "points.json").read_text())["points"]
    assert [r["point"] for r in rows] == ["redraws-84"]
    assert rows[0]["sets"]["new layouts"]["layouts"] == sum(s.startswith("procedural-2") for s in preset["test"])


def test_points_of_an_earlier_report_join_the_curve_paired_where_they_kept_their_sums_else_unpaired(tmp_path, capsys):
    curve = _script("scaling_curve")
    test = {"test": BUILT + NEW, "train": []}
    together, earlier, later = tmp_path / "together", tmp_path / "earlier", tmp_path / "later"
    for out in (together, earlier):
        _run(out, "procedural-84", COUNTS_A, test)
    for out in (together, later):
        _run(out, "procedural-168", COUNTS_B, test)
    _run(earlier, "redraws-84", COUNTS_B, test)
    assert curve.main(["--out", str(together)]) == 0 and curve.main(["--out", str(earlier)]) == 0
    kept = earlier / "report" / "points.json"
    assert curve.main(["--out", str(later), "--keep", str(kept)]) == 0
    one_session = json.loads((together / "report" / "points.json").read_text())["differences"]
    joined = json.loads((later / "report" / "points.json").read_text())
    assert [r["point"] for r in joined["points"]] == ["redraws-84", "procedural-84", "procedural-168"]
    assert joined["points"][1]["kept_from"] == str(kept) and "kept_from" not in joined["points"][2]
    new_pair = [d for d in joined["differences"] if d["a"] == "procedural-168"]
    assert new_pair == [{**d, "paired": True} for d in one_session]   # as if run in one session
    # a kept row without per-scenario sums (an older report): the unpaired error, the two errors' root sum of squares
    doc = json.loads(kept.read_text())
    published = doc["differences"]
    for row in doc["points"]:
        del row["per_scenario"]
    kept.write_text(json.dumps(doc))
    assert curve.main(["--out", str(later), "--keep", str(kept)]) == 0
    rejoined = json.loads((later / "report" / "points.json").read_text())
    rows, diffs = {r["point"]: r for r in rejoined["points"]}, rejoined["differences"]
    assert [d for d in diffs if d["a"] == "procedural-84"] == published   # two kept points: as published (paired)
    for d in [d for d in diffs if d["a"] == "procedural-168"]:
        a, b = (rows[x]["sets"][d["set"]] for x in ("procedural-168", "procedural-84"))
        assert d["paired"] is False and d["f1"] == pytest.approx(a["f1"] - b["f1"])
        assert d["f1_se"] == pytest.approx((a["f1_se"] ** 2 + b["f1_se"] ** 2) ** 0.5)
    text = (later / "report" / "scaling.md").read_text()
    assert "| unpaired: a kept point without per-scenario sums" in text and not bare_differences(text)
    capsys.readouterr()
    kept.write_text(json.dumps({"points": [{"point": "redraws-5", "f1": 0.5}]}))
    for bad, words in ((kept, "not this curve's points: ['redraws-5']"), (tmp_path / "none.json", "not a scaling")):
        assert curve.main(["--out", str(later), "--keep", str(bad)]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and words in err, err
