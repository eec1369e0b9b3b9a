"""Files from someone else are data, never code: crafted checkpoints, datasets, ONNX files and outputs
planted with links, each refused before it can act (issue 57)."""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from test_pnyolo_common import TINY, make_dataset

from dataset_spec import Dataset, SpecError
from dataset_spec.validate import validate
from pnyolo.cli.checkpoint import main as checkpoint_main
from pnyolo.cli import eval_main, train_main
from pnyolo.config.upgrades import OLD_LOSS_KEYS
from pnyolo.cli.export import main as export_main
from pnyolo.cli.predict import main as predict_main
from tools.projection_cli import main as labels_main

torch.set_num_threads(2)


class _Payload:
    """Unpickling this creates ``marker``: what a crafted checkpoint's code could do instead."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("security")
    ds = make_dataset(tmp / "ds", n_scenarios=2)
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=2", "train.epochs=1", "model.loss.state=0"]), [])  # (a)
    assert train_main([str(ds), "--out", str(tmp / "run"), "--quiet", *sets]) == 0
    return tmp


def _crafted(world: Path, name: str) -> tuple[Path, Path]:
    """A checkpoint that looks like ours but whose unpickling would create a marker file."""
    marker = world / f"{name}.pwned"
    ckpt = torch.load(world / "run" / "latest.pt", weights_only=True)
    ckpt["extra"] = _Payload(marker)
    path = world / f"{name}.pt"
    torch.save(ckpt, path)
    return path, marker


def _bench_stored_run(evil: Path, world: Path) -> int:
    from pnyolo.bench.presets import load_preset
    from pnyolo.bench.record import BenchRun, ModelRun
    from pnyolo.bench.stages import model_config, train_model

    run = BenchRun(load_preset("smoke"), world / "bench", data=world / "ds")
    run.models = {"single-view": ModelRun("single-view", model_config(run.preset, "single-view", 0))}
    (run.runs / "single-view").mkdir(parents=True, exist_ok=True)
    shutil.copy(evil, run.runs / "single-view" / "latest.pt")
    train_model(run, "single-view", quiet=True)
    return 0


def _detector_load(evil: Path, world: Path) -> int:
    from pnyolo.inference import Detector

    Detector.load(evil)
    return 0


def _resume(evil: Path, world: Path) -> int:
    run = world / "resume_run"
    shutil.copytree(world / "run", run, dirs_exist_ok=True)
    shutil.copy(evil, run / "latest.pt")
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=3", "train.epochs=1"]), [])
    return train_main([str(world / "ds"), "--out", str(run), "--resume", "--quiet", *sets])


ENTRY_POINTS = {
    "pnyolo-eval": lambda evil, w: eval_main([str(evil), str(w / "ds"), "--out", str(w / "e_evil")]),
    "pnyolo-eval --fuse": lambda evil, w: eval_main([str(w / "run" / "latest.pt"), str(w / "ds"), "--fuse", str(evil),
                                                     "--out", str(w / "f_evil")]),
    "pnyolo-predict": lambda evil, w: predict_main([str(evil), str(w / "ds"), "--out", str(w / "p_evil")]),
    "pnyolo-export": lambda evil, w: export_main([str(evil), "--onnx", str(w / "evil.onnx"), "--size", "64x48"]),
    "pnyolo-train --resume": _resume,
    "Detector.load": _detector_load,
    "bench stored run": _bench_stored_run,
    "pnyolo-checkpoint upgrade": lambda evil, w: checkpoint_main(["upgrade", str(evil), "--out",
                                                                  str(w / "upgraded_evil.pt")]),
}


@pytest.mark.parametrize("entry", list(ENTRY_POINTS))
def test_a_crafted_checkpoint_is_refused_before_its_code_runs(world, entry, capsys, monkeypatch):
    from dataset_spec.cli_support import UserError

    monkeypatch.setattr("sys.stdin.isatty", lambda: False, raising=False)
    evil, marker = _crafted(world, entry.split()[0].replace("-", "_") + str(abs(hash(entry)) % 1000))
    try:
        rc = ENTRY_POINTS[entry](evil, world)
    except UserError as exc:
        rc, message = 2, str(exc)
    else:
        message = capsys.readouterr().err
    assert rc != 0
    assert not marker.exists(), f"{entry} ran the checkpoint's code"
    assert "Traceback" not in message


def _format_one(world: Path) -> Path:
    """The run's checkpoint as format 1 wrote it: numpy's random state a tuple with an array, (a) no 3D state."""
    ckpt = torch.load(world / "run" / "latest.pt", weights_only=True)
    ckpt["format"], loss = "pnyolo-checkpoint-1", ckpt["config"]["model"].pop("loss")
    ckpt["config"]["loss"] = {k: v for k, v in loss.items() if k in OLD_LOSS_KEYS}  # where they were, the keys then
    for state in ckpt["rng_ranks"] + [ckpt["rng"]] * ("rng" in ckpt):
        n = state["numpy"]
        state["numpy"] = ("MT19937", n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                          n["cached_gaussian"])
        state["python"] = tuple(state["python"])
    path = world / "format1.pt"
    torch.save(ckpt, path)
    return path


def test_an_old_checkpoint_is_refused_with_the_command_that_converts_it(world, tmp_path, capsys):
    from pnyolo.engine.checkpoint import read_checkpoint, set_rng_state

    old = _format_one(world)
    assert eval_main([str(old), str(world / "ds"), "--out", str(tmp_path / "e")]) == 2
    assert f"pnyolo-checkpoint upgrade {old}" in capsys.readouterr().err
    (tmp_path / "new.pt").write_bytes(b"mine")  # an existing --out is kept without --force
    assert checkpoint_main(["upgrade", str(old), "--out", str(tmp_path / "new.pt")]) == 2
    assert "exists; --force replaces it" in capsys.readouterr().err and (tmp_path / "new.pt").read_bytes() == b"mine"
    assert checkpoint_main(["upgrade", str(old), "--out", str(tmp_path / "new.pt"), "--force"]) == 0  # no --trust
    new, ours = read_checkpoint(tmp_path / "new.pt"), read_checkpoint(world / "run" / "latest.pt")
    assert all(torch.equal(new["model"][k], ours["model"][k]) for k in ours["model"])
    assert "loss" not in new["config"] and new["config"]["model"]["loss"] == ours["config"]["model"]["loss"]
    set_rng_state(new["rng_ranks"][0])
    first = (np.random.rand(), torch.rand(1).item())
    set_rng_state(ours["rng_ranks"][0])
    assert (np.random.rand(), torch.rand(1).item()) == first
    assert eval_main([str(tmp_path / "new.pt"), str(world / "ds"), "--out", str(tmp_path / "e")]) == 0


def _broken(world: Path, name: str, change, fmt: str = "pnyolo-checkpoint-2") -> Path:
    ckpt = torch.load(world / "run" / "latest.pt", weights_only=True)
    ckpt["format"] = fmt
    change(ckpt)
    path = world / f"{name}.pt"
    torch.save(ckpt, path)
    return path


BROKEN = {  # a checkpoint's keys and types, checked whole before use (issue 63: CK28-CK31; issue 62: item 7)
    "no config": (lambda c: c.pop("config"), "has no config"),
    "no model": (lambda c: c.pop("model"), "has no model"),
    "string config": (lambda c: c.update(config="pixelnerf-yolo"), "config must be a mapping"),
    "class names null": (lambda c: c.update(class_names=None), "class_names must be a list"),
    "model of strings": (lambda c: c.update(model={"w": "x"}), "model must be a mapping of parameter names"),
    "negative views": (lambda c: c["config"]["data"].update(num_views=-3), "data.num_views must be in [1, 64]"),
    "huge mlp": (lambda c: c["config"]["model"]["mlp"].update(hidden=200000), "the config builds (200000"),
    "bad rng": (lambda c: c["rng_ranks"][0].update(python=[3, [1, 2], None]), "rng_ranks[0].python"),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_a_checkpoint_with_missing_or_mistyped_keys_is_one_line_for_every_reader(world, tmp_path, capsys, case):
    change, words = BROKEN[case]
    bad = _broken(world, case.replace(" ", "_"), change)
    for run in (lambda: eval_main([str(bad), str(world / "ds"), "--out", str(tmp_path / "e")]),
                lambda: predict_main([str(bad), str(world / "ds"), "--out", str(tmp_path / "p")])):
        assert run() == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and words in err and "Traceback" not in err, err
    assert not (tmp_path / "e").exists() and not (tmp_path / "p").exists()


@pytest.mark.parametrize("case", ["no config", "string config", "bad rng"])
def test_upgrade_checks_the_converted_checkpoint_before_it_writes(world, tmp_path, capsys, case):
    change, words = BROKEN[case]
    old = _broken(world, f"old_{case.replace(' ', '_')}", change, fmt="pnyolo-checkpoint-1")
    assert checkpoint_main(["upgrade", str(old), "--out", str(tmp_path / "new.pt")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and words in err, err
    assert not (tmp_path / "new.pt").exists()


def test_random_bytes_are_not_sent_to_the_upgrade_command(world, tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(os.urandom(4096))
    assert eval_main([str(junk), str(world / "ds"), "--out", str(tmp_path / "e")]) == 2
    err = capsys.readouterr().err
    assert "not a readable torch file" in err and "upgrade" not in err
    assert checkpoint_main(["upgrade", str(tmp_path), "--out", str(tmp_path / "n.pt")]) == 2  # a folder (CK08)
    assert "is a folder; expected a checkpoint file" in capsys.readouterr().err


def test_paths_in_a_checkpoint_s_config_are_never_read_or_written(world, tmp_path):
    """model.encoder.feature_cache and .weights in a checkpoint from someone else choose nothing (issue 62, item 1)."""
    from pnyolo.engine.checkpoint import checkpoint_config, read_checkpoint

    victim = tmp_path / "victim"
    weights = tmp_path / "secret.pth"
    weights.write_bytes(b"not yours")

    def plant(c):
        c["config"]["model"]["encoder"].update(feature_cache=str(victim), weights=str(weights),
                                               backbone="resnet18")
    bad = _broken(world, "paths", plant)
    cfg = checkpoint_config(read_checkpoint(bad))
    assert cfg.model.encoder.feature_cache is None and cfg.model.encoder.weights is None
    assert eval_main([str(bad), str(world / "ds"), "--out", str(tmp_path / "e"), "--quiet"]) == 0
    assert predict_main([str(bad), str(world / "ds"), "--out", str(tmp_path / "p"), "--quiet"]) == 0
    assert not victim.exists()


# ------------------------------------------------------------------------------------ names from data
def _edit_scenario(root: Path, change) -> None:
    path = next((root / "scenarios").glob("*/scenario.json"))
    obj = json.loads(path.read_text())
    change(obj)
    path.write_text(json.dumps(obj))


@pytest.mark.parametrize("field,value", [
    ("camera", "../../../../tmp/x"), ("lighting", "x/../../victim/pwned"), ("actor", "<img src=x onerror=alert(1)>"),
    ("mesh", "../../../../etc/passwd"), ("mesh", "/etc/passwd")])
def test_a_name_that_would_leave_the_dataset_is_refused_by_the_validator_and_every_reader(world, tmp_path, field,
                                                                                         value, capsys):
    root = shutil.copytree(world / "ds", tmp_path / "ds")

    def change(obj):
        if field == "camera":
            obj["cameras"][0]["name"] = value
        elif field == "lighting":
            obj["lighting"][0]["name"] = value
        elif field == "actor":
            obj["actors"][0]["name"] = value
        else:
            obj["actors"][0]["mesh"] = value
    _edit_scenario(root, change)
    problems = [p for p in validate(root) if p.severity == "error"]
    assert problems and value[:8] in str(problems[0]), problems
    out = tmp_path / "export"
    assert labels_main([str(root), "--export", "yolo,kitti", "--variant", "all", "--out", str(out)]) == 2
    assert predict_main([str(world / "run" / "latest.pt"), str(root), "--variant", "all", "--split", "train",
                         "--out", str(tmp_path / "pred")]) == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 2 and "Traceback" not in err
    assert not out.exists() and not (tmp_path / "pred").exists()


def test_a_split_entry_outside_the_dataset_is_refused_before_any_work(world, tmp_path, capsys):
    root = shutil.copytree(world / "ds", tmp_path / "ds")
    info = json.loads((root / "dataset.json").read_text())
    info["splits"]["test"] = ["../../elsewhere/scenarios/secret"]
    (root / "dataset.json").write_text(json.dumps(info))
    assert eval_main([str(world / "run" / "latest.pt"), str(root), "--out", str(tmp_path / "e")]) == 2
    assert "scenario name" in capsys.readouterr().err
    assert not (tmp_path / "e").exists()


def test_a_link_planted_in_the_dataset_does_not_lead_out_of_it(world, tmp_path):
    from dataset_spec.names import UnsafePath, below

    root = shutil.copytree(world / "ds", tmp_path / "ds")
    ds = Dataset.open(root)
    scn = ds.scenario(ds.scenario_names()[0])
    view = ds.layout.view_dir(scn.name, scn.cameras[0].name)
    shutil.rmtree(view)
    os.symlink(tmp_path / "elsewhere", view)
    with pytest.raises(UnsafePath):
        ds.layout.rgb(scn.name, scn.cameras[0].name, scn.lighting[0].name)
    with pytest.raises(UnsafePath):
        below(tmp_path / "out", "..", "x")
    assert below(tmp_path / "out", "a", "b.png") == tmp_path / "out" / "a" / "b.png"


# ------------------------------------------------------------------------------------ outputs
def test_outputs_never_follow_a_link_planted_in_the_output_folder(world, tmp_path):
    from dataset_spec.atomic import atomic_savefig, atomic_write_text
    from pnyolo.engine.logs import JsonlLog, append_csv

    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    out = tmp_path / "out"
    out.mkdir()
    for name in ("report.md", "plot.png", "log.jsonl", "epochs.csv"):
        os.symlink(victim, out / name)
    atomic_write_text(out / "report.md", "new")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig = plt.figure()
    atomic_savefig(fig, out / "plot.png")
    plt.close(fig)
    with pytest.raises(OSError):
        JsonlLog(out / "log.jsonl").write({"step": 1})
    with pytest.raises(OSError):
        append_csv(out / "epochs.csv", {"epoch": 1})
    assert victim.read_text() == "keep"
    assert not (out / "report.md").is_symlink() and (out / "report.md").read_text() == "new"


def test_a_dangling_link_counts_as_an_earlier_run(world, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    os.symlink(tmp_path / "nowhere.pt", run / "latest.pt")
    os.symlink(tmp_path / "nowhere.jsonl", run / "log.jsonl")
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=1", "train.epochs=1"]), [])
    assert train_main([str(world / "ds"), "--out", str(run), "--quiet", *sets]) == 2
    assert "already holds a training run" in capsys.readouterr().err
    assert not (tmp_path / "nowhere.jsonl").exists()


def test_temporary_names_are_unpredictable_and_taken_exclusively(tmp_path):
    from dataset_spec.atomic import atomic_path

    names = []
    for _ in range(2):
        with atomic_path(tmp_path / "a.json") as tmp:
            assert tmp.is_file() and not tmp.is_symlink()  # created by us, before the writer
            names.append(tmp.name)
            tmp.write_text("{}")
    assert names[0] != names[1] and all(n.startswith(f".a.tmp-{os.getpid()}-") for n in names)
    assert oct((tmp_path / "a.json").stat().st_mode & 0o777) == oct(0o666 & ~_umask())


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# ------------------------------------------------------------------------------------ small files stay small
def _png_header(width: int, height: int) -> bytes:
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(ihdr)) + chunk + struct.pack(">I", zlib.crc32(chunk))


def test_an_image_bomb_is_refused_from_its_header(world, tmp_path):
    from dataset_spec import images

    root = shutil.copytree(world / "ds", tmp_path / "ds")
    ds = Dataset.open(root)
    scn = ds.scenario(ds.scenario_names()[0])
    rgb = ds.layout.rgb(scn.name, scn.cameras[0].name, scn.lighting[0].name)
    rgb.write_bytes(_png_header(32000, 32000) + b"\x00" * 1000)
    t0 = time.perf_counter()
    problems = [str(p) for p in validate(root) if p.severity == "error"]
    assert time.perf_counter() - t0 < 10
    assert any("32000" in p and "differs from camera resolution" in p for p in problems), problems
    with pytest.raises(SpecError, match="at most"):
        images.read_rgb(rgb)
    exr = tmp_path / "big.exr"  # a small file whose header declares 20000 x 20000 pixels
    images.write_depth(exr, np.zeros((2, 2), np.float32))
    data = exr.read_bytes()
    for key in (b"dataWindow\x00box2i\x00", b"displayWindow\x00box2i\x00"):
        at = data.index(key) + len(key) + 4
        data = data[:at] + np.array([0, 0, 19999, 19999], "<i4").tobytes() + data[at + 16:]
    exr.write_bytes(data)
    assert images.exr_size(exr) == (20000, 20000)
    with pytest.raises(SpecError, match="at most"):
        images.read_depth(exr)


def test_error_lines_quote_a_bounded_excerpt_of_a_yaml_bomb(tmp_path, capsys):
    bomb = "a: &a [x, x, x, x, x, x, x, x, x]\n"
    for k in range(1, 9):
        bomb += f"{chr(97 + k)}: &{chr(97 + k)} [{', '.join('*' + chr(96 + k) for _ in range(9))}]\n"
    bomb += "train:\n  epochs: *i\n"
    (tmp_path / "bomb.yaml").write_text(bomb)
    t0 = time.perf_counter()
    assert train_main(["nowhere", "--config", str(tmp_path / "bomb.yaml"), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert len(err) < 600 and time.perf_counter() - t0 < 10, err[:300]


def test_the_validator_is_linear_in_the_actors(world, tmp_path):
    root = shutil.copytree(world / "ds", tmp_path / "ds")

    def many(obj):
        actor = obj["actors"][0]
        obj["actors"] = [{**actor, "id": k + 1, "name": f"a{k}", "mesh": None} for k in range(20000)]
        for cam in obj["cameras"]:
            cam["mounted_on"] = None
    _edit_scenario(root, many)
    t0 = time.perf_counter()
    validate(root, check_images=False)
    assert time.perf_counter() - t0 < 20
