"""Papercuts found by trying the tools as a new user (issue 75 items 9-14): each test names the rule it holds."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
from test_pnyolo_common import make_dataset

from dataset_spec import SpecError
from dataset_spec.cli_support import UserError
from repo_paths import REPO



def test_an_old_loss_key_on_the_command_line_wins_and_is_checked(capsys):
    """Rule: --set is the last word: an older ``loss.KEY`` is the kind's ``model.loss.KEY`` and overrides the
    file's value, checked as any value is."""
    from pnyolo.config import load_config

    cfg = load_config(REPO / "configs" / "cpu.yaml", ["loss.obj=9"])
    assert cfg.model.loss.obj == 9.0
    assert "loss.obj -> model.loss.obj" in capsys.readouterr().err
    with pytest.raises(UserError, match="expected a number"):
        load_config(REPO / "configs" / "cpu.yaml", ["loss.obj=abc"])
    with pytest.raises(UserError, match="known old keys"):
        load_config(REPO / "configs" / "cpu.yaml", ["loss.nonsense=1"])
    bev = load_config(REPO / "configs" / "cpu.yaml", ["model.kind=bev", "loss.bev_heatmap=3"])
    assert bev.model.loss.heatmap == 3.0


@pytest.mark.parametrize("name", ["mps", "xpu", "meta", "cuda:7", "tpu"])
def test_a_device_the_machine_lacks_is_one_line(name):
    """Rule: a device is used only when its backend is available here (every device type, and a CUDA index in
    range); anything else is one line naming it."""
    import torch

    from pnyolo.engine.runtime import pick_device

    if name.startswith("cuda") and torch.cuda.device_count() > 7:
        pytest.skip("a machine with 8 GPUs")
    with pytest.raises(UserError, match=name.split(":")[0]):
        pick_device(name)


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_every_command_line_module_runs_under_python_m(tmp_path):
    """Rule: every module that holds a command's main runs it under ``python -m`` (never a silent exit 0)."""
    import tomllib

    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    modules = {target.split(":")[0] for target in scripts.values()} - {"pnyolo.cli"}
    modules |= {"pnyolo.cli.eval", "pnyolo.cli.track"}  # (pnyolo.cli.train: the dispatcher torchrun starts)
    for module in sorted(modules):
        run = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=120,
                             cwd=tmp_path)
        assert run.returncode == 0 and "usage:" in run.stdout, (module, run.stderr[-300:])


def test_a_reference_between_a_scenarios_records_is_checked_where_it_is_read(tmp_path):
    """Rule: a camera's ``mounted_on`` names an actor of its scenario, checked by the reader (every export and
    command then gets one line, not a KeyError)."""
    import json

    from dataset_spec import Dataset
    from tools.projection_cli import main as labels_main

    root = make_dataset(tmp_path / "ds")
    path = next((root / "scenarios").glob("*/scenario.json"))
    doc = json.loads(path.read_text())
    doc["cameras"][0]["mounted_on"] = 987654
    path.write_text(json.dumps(doc))
    with pytest.raises(SpecError, match="mounted_on 987654 is not an actor id"):
        Dataset.open(root).scenario(doc["name"])
    assert labels_main([str(root), "--no-labelling", "--export", "nuscenes", "--out", str(tmp_path / "x")]) == 2


def test_a_killed_staged_write_leaves_nothing_behind_and_never_a_mix(tmp_path):
    """Rule: a folder result moves into place in one rename; what a killed run left (its staging folder, the old
    folder renamed aside) is removed or put back at the next start, so --out never holds two runs' files."""
    from dataset_spec.atomic import staged_folder

    dead = 2 ** 22 + 12345  # above the kernel's pid_max default: no such process
    out = tmp_path / "exports"
    (tmp_path / f".exports.tmp-{dead}-abcd").mkdir()
    (tmp_path / f".exports.tmp-{dead}-abcd" / "half.json").write_text("{}")
    out.mkdir()
    (out / "old_table.json").write_text("old")
    (out / "mine.txt").write_text("kept")
    with staged_folder(out) as tmp:
        (tmp / "old_table.json").write_text("new")
        (tmp / "new_table.json").write_text("new")
    assert {p.name: p.read_text() for p in out.iterdir()} == {"old_table.json": "new", "new_table.json": "new",
                                                              "mine.txt": "kept"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exports"]
    os.rename(out, tmp_path / f".exports.old-{dead}")  # killed between its two renames
    with pytest.raises(RuntimeError):
        with staged_folder(out):
            raise RuntimeError("a failed export")
    assert (out / "mine.txt").read_text() == "kept" and sorted(p.name for p in tmp_path.iterdir()) == ["exports"]


def test_a_from_ms_error_names_from_ms(tmp_path):
    """Rule: an error names the option the value came from."""
    from dataset_spec.synthetic import write_synthetic_dataset
    from pnyolo.config import load_config
    from pnyolo.data.dataset import Delay, MultiViewDataset
    from tools.projection import label_dataset

    root = write_synthetic_dataset(tmp_path / "seq", n_scenarios=3, frames=4, fps=2.0)
    label_dataset(root, progress=False)
    cfg = load_config(None, ["data.image_scale=1.0", "data.cell_px=8"])
    with pytest.raises(UserError, match="--from-ms 250"):
        MultiViewDataset(root, "train", cfg, training=False, every_camera=True, delay=Delay(0.0, 250.0))


def test_a_relative_path_is_the_callers(tmp_path):
    """Rule: a path given on the command line is relative to the caller's folder, whatever folder a script runs
    its tool from (scripts/gpu-check)."""
    env = {**os.environ, "PYTHON": sys.executable}
    res = subprocess.run([str(REPO / "scripts" / "gpu-check"), "no_such_data", "--device", "cpu"], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and f"{tmp_path / 'no_such_data'}: not a dataset folder" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr


def test_an_error_message_shows_a_format_as_written(tmp_path):
    """Rule: a one-line error that quotes a format quotes it as the format is written (balanced brackets)."""
    from pnyolo.evaluation.nuscenes_results import read_results

    bad = tmp_path / "results.json"
    bad.write_text("[]")
    with pytest.raises(UserError) as err:
        read_results(bad, None, "test", ["car"])
    text = str(err.value)
    assert text.endswith('{"meta": ..., "results": {sample_token: [boxes]}}')
    assert text.count("{") == text.count("}") and text.count("[") == text.count("]")


def test_python_dash_m_runs_each_command_module_without_runpy_s_warning():
    """Rule (issue 83 item 7): ``python -m pnyolo.cli.eval`` runs its module once; the package imports no command
    module until one is asked for, so runpy finds none imported before it runs."""
    for module in ("pnyolo.cli.eval", "pnyolo.cli.track", "pnyolo.cli.predict"):
        res = subprocess.run([sys.executable, "-W", "error::RuntimeWarning", "-m", module, "--help"],
                             capture_output=True, text=True, cwd=REPO, timeout=300)
        assert res.returncode == 0 and "RuntimeWarning" not in res.stderr, (module, res.stderr[-500:])


def test_a_finished_run_resumed_prints_json_other_tools_read(tmp_path, capsys):
    """Rule (issue 83 item 7): pnyolo-train's closing line is strict JSON: a finished run resumed takes no step,
    so it has no last loss (null, not NaN)."""
    import json

    from pnyolo.cli import train_main
    from test_pnyolo_common import TINY

    ds = make_dataset(tmp_path / "ds", n_scenarios=2)
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=1", "train.epochs=1"]), [])
    assert train_main([str(ds), "--out", str(tmp_path / "run"), "--quiet", *sets]) == 0
    capsys.readouterr()
    assert train_main([str(ds), "--out", str(tmp_path / "run"), "--quiet", "--resume", *sets]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    summary = json.loads(line, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))
    assert summary["steps"] == 1 and summary["last_loss"] is None
