"""Splits stay put: rendering more keeps the assignment, new scenarios go where a stated rule puts
them, redraws stay with their layout, and ``dataset-spec split`` sets them."""
from __future__ import annotations

import pytest

from dataset_spec import Dataset
from dataset_spec.cli import main as dataset_spec
from dataset_spec.errors import SpecError
from dataset_spec.splits import extend_splits, layout_of, make_splits
from dataset_spec.synthetic import write_synthetic_dataset


def test_layout_of_strips_the_redraw_suffix_only():
    assert layout_of("intersection_03-s2") == layout_of("intersection_03") == "intersection_03"
    assert layout_of("street-s0") == "street-s0" and layout_of("a-b") == "a-b"


def test_make_splits_keeps_redraws_with_their_layout_and_is_deterministic():
    names = [f"intersection_{i:02d}{s}" for i in range(1, 9) for s in ("", "-s1", "-s2")]
    a, b = make_splits(names, seed=3), make_splits(list(reversed(names)), seed=3)
    assert a == b and sorted(sum(a.values(), [])) == sorted(names) and all(a.values())
    for split, members in a.items():
        for name in members:
            assert all(f"{layout_of(name)}{s}" in members for s in ("", "-s1", "-s2")), (split, name)
    assert make_splits(names, seed=4) != a


def test_extend_splits_keeps_every_assignment_and_states_where_new_ones_go():
    splits = {"train": ["a", "b"], "val": [], "test": ["c"]}
    out, placed = extend_splits(splits, ["a", "b", "c"])
    assert out == splits and placed == {}
    out, placed = extend_splits(splits, ["a", "b", "c", "c-s1", "d", "a-s2"])
    assert out["test"] == ["c", "c-s1"] and "a-s2" in out["train"]  # redraws join their layout's split
    assert placed["d"][0] == "val" and "empty" in placed["d"][1]  # a new layout fills the empty split
    assert {n for n in sum(out.values(), [])} == {"a", "b", "c", "c-s1", "d", "a-s2"}
    more, placed = extend_splits(out, sum(out.values(), []) + ["e", "f", "g"])
    assert all(set(out[s]) <= set(more[s]) for s in out)  # nothing moved
    assert [placed[n][0] for n in ("e", "f", "g")] == ["train", "train", "train"]  # furthest below 70 %


def test_extend_splits_without_any_assignment_is_the_seeded_split():
    names = [f"s{i}" for i in range(7)]
    out, placed = extend_splits({"train": [], "val": [], "test": []}, names, seed=5)
    assert out == make_splits(names, seed=5) and set(placed) == set(names)


def test_rendering_more_keeps_the_split_and_rendering_nothing_writes_nothing(tmp_path, capsys):
    from blender_tools.run_support import plan_splits as _plan_splits, update_splits as _update_splits

    root = tmp_path / "ds"
    write_synthetic_dataset(root, n_scenarios=3, width=16, height=12)
    ds = Dataset.open(root)
    names = ds.scenario_names()
    ds.set_splits({"train": names[:1], "val": names[1:2], "test": names[2:]})
    before = (root / "dataset.json").stat().st_mtime_ns
    planned = _plan_splits(root, names[:2], seed=0)
    _update_splits(root, planned)
    assert (root / "dataset.json").stat().st_mtime_ns == before  # nothing new: dataset.json untouched
    assert "all 3 scenarios keep their split" in capsys.readouterr().out
    planned = _plan_splits(root, [f"{names[2]}-s1", "other"], seed=0)
    line = capsys.readouterr().out.strip()
    assert line.count("\n") == 0 and f"{names[2]}-s1 -> test" in line and "other -> train" in line
    assert planned["test"] == sorted([names[2], f"{names[2]}-s1"])
    _update_splits(root, planned)  # only scenarios that exist are written
    assert Dataset.open(root).info.splits == {"train": names[:1], "val": names[1:2], "test": names[2:]}


def test_dataset_spec_split_sets_shows_and_refuses(tmp_path, capsys):
    root = tmp_path / "ds"
    write_synthetic_dataset(root, n_scenarios=3, width=16, height=12)
    a, b, c = Dataset.open(root).scenario_names()
    assert dataset_spec(["split", str(root), "--train", f"{a},{b}", "--test", c]) == 0
    assert Dataset.open(root).info.splits == {"train": [a, b], "val": [], "test": [c]}
    capsys.readouterr()
    assert dataset_spec(["info", str(root)]) == 0
    out = capsys.readouterr().out
    assert f"split train: 2 scenarios: {a}, {b}" in out and f"split test: 1 scenarios: {c}" in out
    assert dataset_spec(["split", str(root), "--auto", "--seed", "1"]) == 0
    assert Dataset.open(root).info.splits == make_splits([a, b, c], seed=1)
    before = (root / "dataset.json").read_text()
    for argv, words in ((["--train", f"{a},nope"], "--train nope: no such scenario"),
                        (["--train", a, "--val", a], f"--val {a}: already in --train"),
                        ([], "either --auto or"), (["--auto", "--train", a], "either --auto or")):
        assert dataset_spec(["split", str(root), *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and words in err, err
    assert (root / "dataset.json").read_text() == before


@pytest.mark.parametrize("change,words", [
    (lambda s: s["test"].append(s["train"][0]), "in both 'train' and 'test' splits (leaks between splits)"),
    (lambda s: s["val"].append("nowhere_01"), "names scenario 'nowhere_01', which does not exist"),
])
def test_a_broken_split_is_refused_by_every_reader_of_splits(tmp_path, capsys, change, words):
    """Rule (issue 83 item 8): splits are read only through Dataset.split, which refuses splits that leak or name
    no scenario (the validator's errors), so an export, a training and an evaluation never work on them."""
    import json

    from tools.projection import label_dataset
    from tools.projection_cli import main as labels_main

    root = write_synthetic_dataset(tmp_path / "ds", n_scenarios=3)
    label_dataset(root, progress=False)
    doc = json.loads((root / "dataset.json").read_text())
    change(doc["splits"])
    (root / "dataset.json").write_text(json.dumps(doc))
    with pytest.raises(SpecError, match="leaks|does not exist"):
        Dataset.open(root).split("train")
    for fmt in ("nuscenes", "coco"):
        assert labels_main([str(root), "--no-labelling", "--export", fmt, "--out", str(tmp_path / fmt), "--quiet"]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0] and not (tmp_path / fmt).exists(), err


def test_render_split_puts_a_call_s_scenarios_where_it_says_and_prints_that(tmp_path, capsys):
    """Issue 85 item 5: ``blender-gen render --split S`` (what the bench passes for each of its splits) places that
    call's scenarios in S, moving one from another split, and the line it prints says so: the split printed is the
    split used."""
    from blender_tools.run_support import plan_splits

    root = write_synthetic_dataset(tmp_path / "ds", n_scenarios=3)
    ds = Dataset.open(root)
    before = {s: ds.split(s) for s in ("train", "val", "test")}
    moved = before["train"][0]
    planned = plan_splits(root, [moved, "toy_09"], seed=0, split="test")
    assert set(planned["test"]) == set(before["test"]) | {moved, "toy_09"}
    assert moved not in planned["train"] and planned["val"] == before["val"]
    line = capsys.readouterr().out.strip()
    assert line.startswith("blender-gen: splits:") and f"{moved}, toy_09 -> test (--split)" in line
