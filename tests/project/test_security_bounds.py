"""Files from others, round three (issue 75): what a received checkpoint's pickle or config may ask a reader to build
or compute is bounded before anything is built. Each test names the rule it holds, not only the payload."""
from __future__ import annotations

import json
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


@pytest.mark.parametrize("field, value, words", [
    ("render", ["--ray", "127.0.0.1:47123"], "'--ray' is not a data option"),
    ("render", ["--ray=127.0.0.1:47123"], "'--ray' is not a data option"),
    ("render", ["--quality", "preview", "--workers", "16"], "'--workers' is not a data option"),
    ("render", ["--device", "gpu"], "'--device' is not a data option"),
    ("render", ["--out", "/tmp/elsewhere"], "'--out' is not a data option"),
    ("render", ["--hdr-dir", "/home"], "'--hdr-dir' is not a data option"),
    ("render", ["--hdr", "/etc/sky.hdr"], "no paths"),
    ("render", ["--resolution", "320x180; rm"], "--resolution"),
    ("split_render", {"train": ["--frames", "5", "--ray", "auto"]}, "'--ray' is not a data option"),
    ("overrides", ["train.device=cuda"], "it resolves train.device to 'cuda'"),
    ("overrides", ["train.workers=64"], "it resolves train.workers to 64"),
    ("model_overrides", {"bev": ["model.encoder.backbone=efficientnet_lite0", "model.encoder.freeze=true",
                                 "model.encoder.context_channels=0",
                                 "model.encoder.feature_cache=/tmp/cache"]},
     "it resolves model.encoder.feature_cache to '/tmp/cache' for bev"),
    # issue 84 item 1: what the preset resolves to, however it is written (a mapping, a whole section)
    ("overrides", ["model.encoder={backbone: efficientnet_lite0, feature_cache: /tmp/out, freeze: true}"],
     "model.encoder.feature_cache to '/tmp/out'"),
    ("overrides", ["train={device: auto, threads: 1024, workers: 64}"], "it resolves train.threads to 1024"),
    ("hdr", "/etc/sky.exr", "no paths"),
    ("hdr", "sky.exr", "no paths"),  # a legal-looking name that blender-gen would open as a path
    ("render", ["--hdr", "noon,sky.exr"], "no paths"),
    ("base", "../../outside.yaml", "neither a built-in preset nor a file in the preset's folder"),
    ("config", "/etc/passwd", "outside the preset's folder"),
    ("splits", {"train": {"layouts": ["intersection_01"], "redraws": 200000000}, "val": ["intersection_02"],
                "test": ["intersection_03"]}, "redraws: a whole number in 0..1000"),  # issue 84 item 2: bounded counts
    ("splits", {"train": {"layouts": [f"procedural-{k}" for k in range(20)], "redraws": 999},
                "val": ["intersection_02"], "test": ["intersection_03"]}, "more than 10000 scenarios"),
    ("workers", 8, "unknown key"),
])
def test_a_received_preset_says_what_the_data_is_never_where_or_how_to_run(tmp_path, field, value, words):
    """Rule: a preset's render and train options come from an allow-list of data options; where to run (Ray,
    addresses, workers, devices) and paths outside its folder are the user's command line only."""
    import yaml

    from pnyolo.bench.presets import load_preset

    preset = {"base": "smoke", field: value}
    (tmp_path / "deep" / "er").mkdir(parents=True)
    (tmp_path / "outside.yaml").write_text(yaml.safe_dump({"base": "smoke"}))  # a file outside the preset's folder
    path = tmp_path / "deep" / "er" / "received.yaml"  # a base three folders up leaves the preset's folder
    path.write_text(yaml.safe_dump(preset))
    with pytest.raises(UserError, match=words.replace("(", r"\(")):
        load_preset(path)
    path.write_text(yaml.safe_dump({"base": "smoke", "render": ["--resolution", "96x54", "--hdr", "random:noon,dusk"],
                                    "overrides": ["train.val_every=5"]}))
    assert load_preset(path).render == ["--resolution", "96x54", "--hdr", "random:noon,dusk"]


def test_where_the_bench_renders_comes_from_its_command_line(tmp_path, monkeypatch):
    """Rule: blender-gen's placement options (workers, Ray, device) are the command line's: the bench passes exactly
    those, and a preset sized for a GPU is refused on a machine without one unless the CPU is asked for."""
    from pnyolo.bench import cli

    seen = []
    monkeypatch.setattr(cli, "run_benchmark", lambda run, *a, **k: seen.append(run.render_place) or {})
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    assert cli.main(["smoke", "--out", str(tmp_path / "a"), "--render-workers", "2"]) == 0
    assert seen[-1] == ("--workers", "2")
    assert cli.main(["smoke", "--out", str(tmp_path / "d"), "--render-gpu"]) == 0 and seen[-1][-2:] == ("--device", "gpu")
    assert cli.main(["gpu_quick", "--out", str(tmp_path / "b")]) == 2
    assert cli.main(["gpu_quick", "--out", str(tmp_path / "b"), "--device", "cpu"]) == 0
    assert cli.main(["smoke", "--out", str(tmp_path / "c"), "--ray", "auto", "--render-workers", "2"]) == 2


def test_every_part_of_an_exr_is_checked_before_decoding(tmp_path):
    """Rule: the size check covers what the decoder reads: a multi-part EXR (or one of many channels) is refused
    from its header, before anything is decoded."""
    import OpenEXR

    from dataset_spec import Dataset
    from dataset_spec.images import read_depth
    from dataset_spec.validate import validate

    root = make_dataset(tmp_path / "ds", labels=False)
    ds = Dataset.open(root)
    scn = ds.scenario(ds.scenario_names()[0])
    depth_path = next((root / "scenarios" / scn.name).rglob("depth.exr"))
    h, w = read_depth(depth_path).shape
    head = {"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION, "displayWindow": ((0, 0), (w - 1, h - 1))}
    big = {**head, "dataWindow": ((0, 0), (3999, 3999))}
    parts = [OpenEXR.Part(head, {"Z": np.ones((h, w), np.float32)}, name="depth"),
             OpenEXR.Part(big, {"Z": np.zeros((4000, 4000), np.float32)}, name="more")]
    with OpenEXR.File(parts) as exr:
        exr.write(str(depth_path))
    assert depth_path.stat().st_size < 1 << 20  # 64 MB of pixels in a small file
    problems = [p for p in validate(root) if p.path == depth_path or str(depth_path) in str(p)]
    assert any("EXR of 2 parts" in str(p) for p in problems), problems
    many = {f"C{i}": np.ones((h, w), np.float32) for i in range(9)}
    with OpenEXR.File(head, many) as exr:
        exr.write(str(depth_path))
    with pytest.raises(Exception, match="EXR of 9 channels"):
        read_depth(depth_path)
    # issue 84 item 2: channels x pixels against a budget of decoded bytes, from the header (here a budget of 1 kB)
    import dataset_spec.images as images

    with OpenEXR.File(head, {f"C{i}": np.ones((h, w), np.float32) for i in range(2)}) as exr:
        exr.write(str(depth_path))
    old, images.MAX_EXR_BYTES = images.MAX_EXR_BYTES, 1000
    try:
        with pytest.raises(Exception, match=f"EXR of 2 channels of {w}x{h}: decoding it takes more than"):
            images.exr_size(depth_path)
    finally:
        images.MAX_EXR_BYTES = old
    assert images.exr_size(depth_path) == (h, w) and 8 * 4096 * 4096 * 4 > images.MAX_EXR_BYTES


def test_names_joined_from_two_names_never_collide_or_outgrow_a_file_name(tmp_path, capsys):
    """Rule: every name an export builds from several names is checked for collisions and length before anything is
    written (nuScenes scenes, YOLO/COCO/KITTI stems, MultiviewX folders, pixelNeRF scenes, --results' samples)."""
    from dataset_spec.synthetic import write_synthetic_dataset
    from tools.projection_cli import main as labels_main

    from tools.projection import label_dataset

    root = write_synthetic_dataset(tmp_path / "ds", names={"toy_01": ["a__b", "noon"], "toy_01__a": ["b"]})
    label_dataset(root, progress=False)
    for fmt in ("nuscenes", "pixelnerf"):  # SCENARIO__VARIANT
        out = tmp_path / f"x_{fmt}"
        assert labels_main([str(root), "--no-labelling", "--export", fmt, "--variant", "all", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "would be made by both" in err and "toy_01__a__b" in err and len(err.strip().splitlines()) == 1, err
        assert not out.exists() or not any(p.is_file() for p in out.rglob("*")), fmt
    out = tmp_path / "x_yolo"  # SCENARIO__CAMERA__VARIANT: distinct here, every view its own file
    assert labels_main([str(root), "--no-labelling", "--export", "yolo", "--variant", "all", "--out", str(out)]) == 0
    from dataset_spec import Dataset

    ds = Dataset.open(root)
    views = sum(len(ds.scenario(n).cameras) * len(ds.scenario(n).lighting) for n in ds.scenario_names())
    assert len({p.name for p in out.rglob("*.png")}) == views == len(list(out.rglob("*.png")))
    long = label_dataset(write_synthetic_dataset(tmp_path / "long", names={"s" * 128: ["v" * 128]}), progress=False)
    assert labels_main([str(tmp_path / "long"), "--no-labelling", "--export", "nuscenes", "--variant", "all", "--out", str(tmp_path / "xl")]) == 2
    err = capsys.readouterr().err
    assert "above 255" in err and "File name too long" not in err, err


def _run_copy(world: Path, tmp_path: Path) -> Path:
    import shutil

    run = tmp_path / "run"
    shutil.copytree(world / "run", run)
    return run


@pytest.mark.parametrize("plant", ["tensorboard link", "log hard link", "log not json"])
def test_resume_writes_only_into_the_runs_own_files(world, tmp_path, capsys, plant):
    """Rule: every file and folder a run writes into on --resume is its own: a symbolic or hard link there is
    refused in one line before anything is written, and a log that is not the run's is named, never a traceback."""
    import os

    run, target = _run_copy(world, tmp_path), tmp_path / "elsewhere"
    target.mkdir()
    if plant == "tensorboard link":
        import shutil

        shutil.rmtree(run / "tensorboard", ignore_errors=True)
        os.symlink(target, run / "tensorboard")
    elif plant == "log hard link":
        (target / "mine.jsonl").write_text((run / "log.jsonl").read_text())
        (run / "log.jsonl").unlink()
        os.link(target / "mine.jsonl", run / "log.jsonl")
    else:
        (run / "log.jsonl").write_text("not json\n")
    before = {p: p.read_bytes() for p in target.rglob("*") if p.is_file()}
    sets = sum((["--set", s] for s in TINY + ["train.max_steps=2", "train.epochs=2"]), [])
    assert train_main([str(world / "ds"), "--out", str(run), "--resume", "--quiet", *sets]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert {p: p.read_bytes() for p in target.rglob("*") if p.is_file()} == before


def test_a_file_output_is_never_written_through_a_linked_folder(world, tmp_path, capsys):
    """Rule: the folder a file output (--onnx, --out of upgrade, --timings) is written into is declared an output
    folder as given: a link there is refused, nothing lands in its target."""
    import os

    from pnyolo.cli.export import main as export_main

    target = tmp_path / "target"
    target.mkdir()
    (tmp_path / "x").mkdir()
    os.symlink(target, tmp_path / "x" / "sub")
    assert export_main([str(world / "run" / "latest.pt"), "--onnx", str(tmp_path / "x" / "sub" / "m.onnx"),
                        "--size", "64x48"]) == 2
    assert "is a link" in capsys.readouterr().err and not list(target.iterdir())


def test_received_results_are_bounded_in_depth_and_boxes(world, tmp_path, capsys):
    """Rule: a results file is read by one JSON reader that names nesting it cannot follow in one line, and holds
    at most so many detections an image (COCO keeps 100, the devkit refuses over 500): scoring stays linear."""
    from dataset_spec import Dataset
    from pnyolo.evaluation.predictions import MAX_RESULTS_PER_VIEW
    from tools.exporters.coco import coco_image_ids

    nested = tmp_path / "nested.json"
    nested.write_text("[" * 200_000 + "]" * 200_000)
    crowded = tmp_path / "crowded.json"
    first = next(iter(coco_image_ids(Dataset.open(world / "ds")).values()))
    crowded.write_text(json.dumps([{"image_id": first.id, "category_id": 1, "bbox": [1, 1, 5, 5], "score": 0.5}]
                                  * (MAX_RESULTS_PER_VIEW + 1)))
    for path, words in ((nested, "nested deeper than"), (crowded, "more than 1000")):
        assert eval_main(["--results", str(path), str(world / "ds"), "--split", "train", "--out",
                          str(tmp_path / "e")]) == 2
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    nested.write_text('{"meta": {}, "results": {"x": ' + "[" * 200_000 + "]" * 200_000 + "}}")
    assert eval_main(["--results", str(nested), str(world / "ds"), "--split", "train", "--out", str(tmp_path / "e")]) == 2
    assert "nested deeper than" in capsys.readouterr().err


def test_a_report_set_beside_is_checked_whole_before_any_work(tmp_path):
    """Rule: another run's report.json is data from others: every figure a number (or none) and every row name
    free of markup, checked when the run starts, not when its report is written after training."""
    from pnyolo.bench.presets import load_preset
    from pnyolo.bench.robustness import FIGURES, read_sweep

    preset = load_preset("smoke")
    row = {k: 0.5 for k in FIGURES}
    sweep = {"0": row, **{f"{s:g}": row for s in preset.pose_noise_sweep}}

    def report(name, rows):
        path = tmp_path / "report.json"
        path.write_text(json.dumps({"models": {name: {"pose_noise_sweep": rows}}, "preset": {"test": preset.test}}))
        return path

    assert read_sweep(report("bev", sweep), preset, "other")
    for name, rows, words in (("bev", {**sweep, "0": {**row, "f1": "0.5"}}, "as numbers"),
                              ("<img src=x onerror=alert(1)>", sweep, "is not a model row's name"),
                              ("bev|x", sweep, "is not a model row's name")):
        with pytest.raises(UserError, match=words):
            read_sweep(report(name, rows), preset, "other")
    with pytest.raises(UserError, match="label"):
        read_sweep(report("bev", sweep), preset, "<b>x</b>")


def test_a_name_given_for_a_report_row_is_a_name():
    """Rule: a name that goes into report.md as it is follows the name rule (no markup)."""
    from types import SimpleNamespace

    from pnyolo.bench.cli import _external

    with pytest.raises(UserError, match="--external"):
        _external(SimpleNamespace(external=["<img src=x onerror=alert(1)>=results.json"]))
