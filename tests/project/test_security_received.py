"""Files from others, round four (issue 84): a received file is checked on what it resolves to, not on how it is
written (a preset by the config it makes, names after their last transformation, a report by the values it hands
on, a run's files on every append, a checkpoint on its records). Each test names the rule it holds."""
from __future__ import annotations

import json

import pytest
import torch
from test_pnyolo_common import TINY, make_dataset
from test_security_bounds import world  # noqa: F401 - the trained toy those tests use, shared (a pytest fixture)

from dataset_spec.cli_support import UserError
from pnyolo.cli import eval_main, train_main

torch.set_num_threads(2)


def test_a_preset_s_own_config_file_names_no_place_and_the_command_line_still_may(tmp_path):
    """Rule (issue 84 item 1): a preset is checked on the config it resolves to, whatever file sets a place: a config
    file in the preset's folder setting train.threads is refused like an override; the user's --set on the command
    line sets the same key freely."""
    import yaml

    from pnyolo.bench.cli import _parser, _preset
    from pnyolo.bench.presets import load_preset
    from pnyolo.bench.stages import model_config

    (tmp_path / "mine.yaml").write_text(yaml.safe_dump({"train": {"threads": 8, "lr": 0.001}}))
    (tmp_path / "p.yaml").write_text(yaml.safe_dump({"base": "smoke", "config": "mine.yaml"}))
    with pytest.raises(UserError, match="it resolves train.threads to 8"):
        load_preset(tmp_path / "p.yaml")
    (tmp_path / "mine.yaml").write_text(yaml.safe_dump({"train": {"lr": 0.001}}))
    assert load_preset(tmp_path / "p.yaml").config.endswith("mine.yaml")
    args = _parser().parse_args([str(tmp_path / "p.yaml"), "--set", "train.threads=1"])
    preset = _preset(args)  # the command line's place passes, and every model runs on it
    assert {model_config(preset, k, 0).train.threads for k in preset.models} == {1}


def test_sequence_names_are_checked_after_the_last_step_that_makes_them(tmp_path):
    """Rule (issue 84 item 4): a name an export makes is made from its parts and checked after its last
    transformation: cameras cam_0 and cam_0__f0000 of a sequence are two MOTChallenge sequences and two CocoVID
    videos (a stem with its frame cut out once made both one, an image overwritten)."""
    import json

    from dataset_spec.synthetic import write_synthetic_dataset
    from tools.projection import label_dataset
    from tools.projection_cli import main as labels_main

    root = write_synthetic_dataset(tmp_path / "ds", n_scenarios=1, frames=2)
    scn = root / "scenarios" / "toy_01"
    for name in ("scenario.json", "frames.json"):
        (scn / name).write_text((scn / name).read_text().replace('"cam_1"', '"cam_0__f0000"'))
    (scn / "views" / "cam_1").rename(scn / "views" / "cam_0__f0000")
    label_dataset(root, progress=False)
    out = tmp_path / "x"
    assert labels_main([str(root), "--no-labelling", "--export", "mot,coco", "--out", str(out), "--quiet"]) == 0
    folders = sorted(p.parent.name for p in (out / "mot").rglob("seqinfo.ini"))
    assert folders == ["toy_01__cam_0", "toy_01__cam_0__f0000", "toy_01__cam_2"]
    assert all(len(list(p.glob("img1/*.png"))) == 2 for p in (out / "mot").rglob("toy_01__*") if p.is_dir()
               and (p / "img1").is_dir())  # each camera its own two frames
    videos = [v["name"] for f in (out / "coco").rglob("*.json") for v in json.loads(f.read_text()).get("videos", [])]
    assert sorted(videos) == folders


def test_every_json_from_others_is_read_by_one_reader_whose_errors_are_one_line(tmp_path, capsys):
    """Rule (issue 84 item 6): one JSON reader (dataset_spec.dataset.read_json) for files from others: a number Python
    will not read (an integer of 5000 digits) is one line naming the file, in a results file, a scenario.json and a
    COCO file alike; a scenario name with such a number is one line too."""
    from dataset_spec.dataset import read_json
    from dataset_spec.errors import SpecError
    from dataset_spec.synthetic import write_synthetic_dataset
    from blender_tools.cli import main as blender_gen
    from pnyolo.cli import eval_main
    from tools.exporters.coco import read_coco

    huge = "9" * 5000
    bad = tmp_path / "huge.json"
    bad.write_text('{"meta": {}, "results": {"x": [' + huge + "]}}")
    for read in (lambda p: read_json(p, "x"), read_coco):
        with pytest.raises(SpecError, match="invalid JSON .*4300 digits"):
            read(bad)
    root = write_synthetic_dataset(tmp_path / "ds")
    assert eval_main(["--results", str(bad), str(root), "--quiet"]) == 2
    scn = root / "scenarios" / "toy_01" / "scenario.json"
    scn.write_text(scn.read_text().replace('"seed": 0', '"seed": ' + huge, 1))
    assert eval_main(["--results", str(bad), str(root), "--quiet"]) == 2
    assert blender_gen(["render", "--scene", f"procedural-1-s{huge}", "--out", str(tmp_path / "r")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 3 and "4300 digits" in lines[1], [line[:200] for line in lines]
    assert all("Traceback" not in line and len(line) < 2000 for line in lines)


@pytest.fixture(scope="module")
def bev_run(tmp_path_factory):
    """A ground-plane model (3D detections: late fusion) trained a step on the toy."""
    from test_pnyolo_common import tiny

    tmp = tmp_path_factory.mktemp("bev_bounds")
    ds = make_dataset(tmp / "ds", n_scenarios=2)
    sets = sum((["--set", s] for s in tiny("model.kind=bev", "train.max_steps=1", "train.epochs=1")), [])
    assert train_main([str(ds), "--out", str(tmp / "run"), "--quiet", *sets]) == 0
    return tmp


GOOD_LATE = {"rule": "agreement", "send": 0.3, "keep": 0.6, "calibration": None}
GOOD_CHOICE = {"threshold": 0.45, "eval_stats": "running", "depth_peaks": 1, "nms_iou": 0.45, "depth_gap": None,
               "checkpoint": "latest.pt"}


@pytest.mark.parametrize("models, words", [
    ([], "chose no late-fusion rule"),  # a list where a mapping goes
    ({"bev": [], "bev, late fusion": []}, "chose no late-fusion rule"),
    ({"bev": {"selection": GOOD_CHOICE},
      "bev, late fusion": {"late_fusion_selection": {**GOOD_LATE, "send": "high"}}}, "eval.late_send"),
    ({"bev": {"selection": GOOD_CHOICE},
      "bev, late fusion": {"late_fusion_selection": {**GOOD_LATE, "send": 5.0}}}, "eval.late_send"),
    ({"bev": {"selection": {**GOOD_CHOICE, "threshold": 7}},
      "bev, late fusion": {"late_fusion_selection": GOOD_LATE}}, "eval.conf_threshold must be in [0, 1]"),
    ({"bev": {"selection": GOOD_CHOICE}, "bev, late fusion": {"late_fusion_selection": {
        **GOOD_LATE, "rule": "calibrated agreement", "calibration": "abc"}}}, "eval.late_calibration"),
    ({"bev": {"selection": {**GOOD_CHOICE, "depth_peaks": 0}},
      "bev, late fusion": {"late_fusion_selection": GOOD_LATE}}, "eval.depth_peaks must be in [1, 8]"),
    ({"bev": {"selection": {**GOOD_CHOICE, "eval_stats": "mine"}},
      "bev, late fusion": {"late_fusion_selection": GOOD_LATE}}, "names eval_stats 'mine'"),
])
def test_a_bench_report_read_by_from_is_checked_like_the_command_line(bev_run, tmp_path, capsys, models, words):
    """Rule (issue 84 item 7): every value a bench report hands on through --late-rule from: passes the checks the
    command line's and a config's pass, before any prediction: one line, nothing written."""
    import json

    report = tmp_path / "report.json"
    report.write_text(json.dumps({"models": models}, allow_nan=True))
    out = tmp_path / "e"
    assert eval_main([str(bev_run / "run" / "latest.pt"), str(bev_run / "ds"), "--every-camera", "--late-fusion",
                      "--late-rule", f"from:{report}", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and "Traceback" not in err[0] and not out.exists(), err


def test_a_run_log_is_checked_on_every_append_not_only_when_the_run_starts(tmp_path):
    """Rule (issue 84 item 8): a file a run keeps appending to (log.jsonl) is checked on every append: a hard link
    planted while the run goes on, or another file put in its place, gets none of the run's records."""
    import os

    from dataset_spec.errors import SpecError
    from pnyolo.engine.logs import JsonlLog

    log = JsonlLog(tmp_path / "log.jsonl")
    log.write({"step": 1})
    os.link(tmp_path / "log.jsonl", tmp_path / "theirs.jsonl")  # planted mid-run
    with pytest.raises(SpecError, match="2 names"):
        log.write({"step": 2})
    (tmp_path / "theirs.jsonl").unlink()
    (tmp_path / "other.jsonl").write_text("")
    os.replace(tmp_path / "other.jsonl", tmp_path / "log.jsonl")  # another file in its place
    with pytest.raises(SpecError, match="another file than the one this run wrote"):
        log.write({"step": 3})
    assert (tmp_path / "log.jsonl").read_text() == ""


def test_a_checkpoint_is_checked_on_its_records_and_keys_before_anything_is_decompressed(world, tmp_path, capsys):
    """Rule (issue 84 item 2): a checkpoint's zip records are checked on what they declare before torch reads them
    (torch.save stores every record as it is: a compressed one, a DEFLATE bomb's way in, is refused), and a
    checkpoint holds only the keys pnyolo writes."""
    import zipfile

    src = world / "run" / "latest.pt"
    packed = tmp_path / "packed.pt"
    with zipfile.ZipFile(src) as a, zipfile.ZipFile(packed, "w", compression=zipfile.ZIP_DEFLATED) as b:
        for info in a.infolist():
            b.writestr(info.filename, a.read(info))
    extra = tmp_path / "extra.pt"
    ckpt = torch.load(src, weights_only=True)
    ckpt["payload"] = torch.zeros(4)
    torch.save(ckpt, extra)
    for bad, words in ((packed, "is compressed; torch.save stores every record as it is"),
                       (extra, "unknown top-level key(s) ['payload']")):
        assert eval_main([str(bad), str(world / "ds"), "--out", str(tmp_path / "e")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0] and not (tmp_path / "e").exists(), err


def test_the_upgrade_route_builds_arrays_only_through_the_checked_constructor(tmp_path, capsys):
    """Rule (issue 84 item 2): converting a format-1 checkpoint builds numpy arrays only through the checked
    _reconstruct: a pickle calling numpy.ndarray itself is refused, and arrays each under the file's size are refused
    once together they pass it (a pickle may fill many arrays from one memoised buffer)."""
    import numpy as np

    from pnyolo.cli.checkpoint import main as checkpoint_main
    from pnyolo.engine.checkpoint_schema import NdarrayName, legacy_globals

    class Direct:
        def __reduce__(self):
            return np.ndarray, ((10 ** 9,), "f8")  # 8 GB, no _reconstruct

    path = tmp_path / "direct.pt"
    torch.save({"format": "pnyolo-checkpoint-1", "rng": {"numpy": Direct()}}, path)
    assert checkpoint_main(["upgrade", str(path), "--out", str(tmp_path / "new.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "calls numpy.ndarray itself" in err[0], err
    reconstruct = legacy_globals(10_000)[0][0]
    reconstruct(NdarrayName, (1000,), b"f")  # 8000 bytes of float64 ('f' is float32: 4000): under the file's 10000
    with pytest.raises(UserError, match="more than the file's 10000 bytes"):
        for _ in range(3):
            reconstruct(NdarrayName, (1000,), b"d")


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
    assert "3D points a view, above the memory budget" in err and len(err.strip().splitlines()) == 1, err
    # issue 84 item 2: the budget is what fits in memory, not a count: 2^26 - 1 points (under the old count) refused
    from types import SimpleNamespace

    from pnyolo.config.checks import MAX_SAMPLE_BYTES, check_work, sample_bytes
    from pnyolo.config import load_config

    cfg = load_config(None, TINY + ["model.sampler.num_samples=1023", "model.sampler.fine_samples=0"])
    grid = SimpleNamespace(grid_w=65537, grid_h=1)  # 65537 x 1023 = 2^26 - 1 points
    with pytest.raises(UserError, match="memory budget"):
        check_work(cfg, grid)
    assert sample_bytes(65537 * 1023, cfg.data.num_views) > MAX_SAMPLE_BYTES >= sample_bytes(10 ** 6, 8)
    from pnyolo.data.grid import grid_for

    with pytest.raises(UserError, match="above 8192 a side"):
        grid_for(1920, 1080, 8.0, 16)
    with pytest.raises(UserError, match="cells"):
        grid_for(8000, 8000, 1.0, 1)


def test_what_one_command_writes_is_bounded_before_it_writes(tmp_path, capsys):
    """Rule: a command whose output grows with what the data declares (frames, cameras, sizes) says the size and
    asks for a flag before writing, instead of filling the disk."""
    from dataset_spec.synthetic import write_synthetic_dataset
    from tools.viewer_cli import main as viewer_main

    root = write_synthetic_dataset(tmp_path / "seq", frames=12, width=64, height=48)
    out = tmp_path / "viewer"
    assert viewer_main([str(root), "--frame", "all", "--sheet-only", "--out", str(out), "--quiet",
                        "--scale", "16", "--max-gb", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "GB of pixels" in err and "--max-gb" in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()
    assert viewer_main([str(root), "--frame", "all", "--sheet-only", "--out", str(out), "--quiet", "--no-html"]) == 0
    # issue 84 item 5: each camera's pictures estimated from its own size, not the first camera's
    big = write_synthetic_dataset(tmp_path / "big")
    scn = big / "scenarios" / "toy_01" / "scenario.json"
    doc = json.loads(scn.read_text())
    doc["cameras"][1]["width"] = doc["cameras"][1]["height"] = 4096
    scn.write_text(json.dumps(doc))
    assert viewer_main([str(big), "--out", str(tmp_path / "v2"), "--quiet", "--no-html"]) == 2
    err = capsys.readouterr().err
    assert "GB of pixels" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "v2").exists(), err


def test_a_killed_upgrade_s_leftover_is_removed_and_a_live_writer_s_kept(world, tmp_path):
    """Issue 83 item 7: pnyolo-checkpoint upgrade removes the temporary file a killed conversion left beside its
    output (its writer no longer runs), never one whose writer still runs."""
    import os

    from pnyolo.cli.checkpoint import main as checkpoint_main
    from test_security import _format_one

    old = _format_one(world)
    left = tmp_path / f".new.tmp-{2 ** 22 + 17}-abc.pt"  # above Linux's largest pid_max: no such process
    live = tmp_path / f".new.tmp-{os.getpid()}-abc.pt"
    left.write_bytes(b"half"), live.write_bytes(b"busy")
    assert checkpoint_main(["upgrade", str(old), "--out", str(tmp_path / "new.pt")]) == 0
    assert not left.exists() and live.exists() and (tmp_path / "new.pt").is_file()
