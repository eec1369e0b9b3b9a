"""Files from others, round three (issue 75): what a received checkpoint's pickle or config may ask a reader to build
or compute is bounded before anything is built. Each test names the rule it holds, not only the payload."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset

from dataset_spec.cli_support import UserError
from pnyolo.cli import eval_main, train_main
from pnyolo.config import load_config, to_dict
from pnyolo.config.checks import RANGES
from pnyolo.registry import kinds

torch.set_num_threads(2)

try:
    from numpy._core.multiarray import _reconstruct
except ImportError:  # numpy 1
    from numpy.core.multiarray import _reconstruct


class _Array:
    """Unpickles as numpy's ``_reconstruct(ndarray, shape, dtype)``: an array the file's bytes never held."""

    def __init__(self, shape, code):
        self.shape, self.code = shape, code

    def __reduce__(self):
        return (_reconstruct, (np.ndarray, self.shape, self.code))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bounds")
    ds = make_dataset(tmp / "ds", n_scenarios=1)
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=1", "train.epochs=1"]), [])
    assert train_main([str(ds), "--out", str(tmp / "run"), "--quiet", *sets]) == 0
    return tmp


def _run_capped(module: str, args: list[str], gib: int = 3) -> subprocess.CompletedProcess:
    """``python -m MODULE ARGS`` in a process whose address space is capped: what it builds beyond that fails
    instead of taking the machine."""
    code = (f"import resource, runpy, sys; resource.setrlimit(resource.RLIMIT_AS, ({gib} << 30, {gib} << 30)); "
            f"sys.argv[0] = {module!r}; runpy.run_module({module!r}, run_name='__main__')")
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("shape, code, words", [((1 << 31,), "O", "only numbers are read"),
                                                ((1 << 34,), "b", "more than the file's")])
def test_only_the_upgrade_reads_the_old_format_and_builds_no_object_or_oversized_array(world, tmp_path, shape, code,
                                                                                       words):
    """Rule: a reader other than ``pnyolo-checkpoint upgrade`` never builds the old format's objects (it reads the
    pickle's opcodes); the upgrade builds numeric arrays no larger than the file."""
    ckpt = torch.load(world / "run" / "latest.pt", weights_only=True)
    ckpt["format"] = "pnyolo-checkpoint-1"
    ckpt["rng"] = {"numpy": ("MT19937", _Array(shape, code), 0, 0, 0.0)}
    evil = tmp_path / "old.pt"
    torch.save(ckpt, evil)
    assert evil.stat().st_size < 10 << 20
    read = _run_capped("pnyolo.cli.eval", [str(evil), str(world / "ds"), "--out", str(tmp_path / "e")])
    assert read.returncode == 2 and "pnyolo-checkpoint upgrade" in read.stderr, read.stderr
    assert "Traceback" not in read.stderr and "MemoryError" not in read.stderr
    up = _run_capped("pnyolo.cli.checkpoint", ["upgrade", str(evil), "--out", str(tmp_path / "new.pt")])
    assert up.returncode == 2 and words in up.stderr and len(up.stderr.strip().splitlines()) == 1, up.stderr
    assert not (tmp_path / "new.pt").exists()


def _dotted(mapping: dict, prefix: str = ""):
    for key, value in mapping.items():
        if isinstance(value, dict):
            yield from _dotted(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def test_every_numeric_config_key_of_every_kind_has_a_range():
    """Rule: every number a config holds is range-checked where a config (or a checkpoint's) is loaded."""
    for kind in kinds():
        cfg = load_config(None, [f"model.kind={kind}"])
        own = {f"model.{k}" for k in cfg.model.ranges}
        loose = [k for k, v in _dotted(to_dict(cfg)) if isinstance(v, (int, float)) and not isinstance(v, bool)
                 and k not in RANGES and k not in own]
        assert not loose, f"{kind}: numeric keys without a range: {loose}"


@pytest.mark.parametrize("sets, words", [
    (["data.image_scale=120"], "data.image_scale must be in (0, 8]"),
    (["data.cell_px=0.01"], "data.cell_px must be in [1, 1024]"),
    (["model.sampler.num_samples=2000000"], "model.sampler.num_samples must be in [1, 1024]"),
    (["model.kind=bev", "model.bev.max_cells=1000000000000"], "model.bev.max_cells must be in [1, 1048576]"),
])
def test_keys_no_tensor_shape_depends_on_are_bounded_for_a_checkpoints_config(world, tmp_path, capsys, sets, words):
    """Rule: a key that sizes work but no weight (so the loader's shape check cannot see it) has an upper bound,
    and a checkpoint carrying more is refused in one line before anything is allocated."""
    with pytest.raises(UserError, match=words.replace("(", r"\(").replace("[", r"\[")):
        load_config(None, sets)
    if any(s.startswith("model.kind") for s in sets):
        return  # the run below is pixelnerf-yolo's
    ckpt = torch.load(world / "run" / "latest.pt", weights_only=True)
    for s in sets:
        key, value = s.split("=")
        *path, name = key.split(".")
        node = ckpt["config"]
        for part in path:
            node = node[part]
        node[name] = type(node[name])(float(value))
    bad = tmp_path / "bad.pt"
    torch.save(ckpt, bad)
    assert eval_main([str(bad), str(world / "ds"), "--out", str(tmp_path / "e")]) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err


def test_sizes_derived_from_several_keys_are_checked_against_a_budget(world, tmp_path, capsys):
    """Rule: the image, the grid and the rays x samples a view asks for are derived and checked before an item is
    built, whatever each key alone allows."""
    ckpt = torch.load(world / "run" / "latest.pt", weights_only=True)
    ckpt["config"]["data"].update(image_scale=8.0, cell_px=1.0)
    ckpt["config"]["model"]["sampler"].update(num_samples=1024, fine_samples=1024, cell_rays=8)
    bad = tmp_path / "work.pt"
    torch.save(ckpt, bad)
    assert eval_main([str(bad), str(world / "ds"), "--out", str(tmp_path / "e"), "--split", "train"]) == 2
    err = capsys.readouterr().err
    assert "3D points a view, above" in err and len(err.strip().splitlines()) == 1, err
    from pnyolo.data.grid import grid_for

    with pytest.raises(UserError, match="above 8192 a side"):
        grid_for(1920, 1080, 8.0, 16)
    with pytest.raises(UserError, match="cells"):
        grid_for(8000, 8000, 1.0, 1)
