"""Figures do not depend on how busy the machine is (issue 83): a run's torch threads come from its config and the
machine's cores, never from the cores idle at the moment, so the same command trains the same weights and scores
the same figures beside a busy process."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch
from test_pnyolo_common import TINY, make_dataset

from pnyolo.cli import eval_main, train_main
from pnyolo.engine.runtime import usable_cores

SPIN = "import time\nend = time.time() + 600\nwhile time.time() < end:\n    pass\n"


def _train_and_score(ds, out) -> tuple[dict, dict, dict]:
    """(weights, the run's summary line, the test split's figures) of one training and evaluation of the toy."""
    sets = sum((["--set", s] for s in TINY + ["train.threads=0", "train.max_steps=3", "train.epochs=1"]), [])
    assert train_main([str(ds), "--out", str(out / "run"), "--quiet", *sets]) == 0
    assert eval_main([str(out / "run" / "latest.pt"), str(ds), "--split", "test", "--conf", "0.01",
                      "--out", str(out / "eval"), "--quiet"]) == 0
    weights = torch.load(out / "run" / "latest.pt", map_location="cpu", weights_only=False)["model"]
    metrics = json.loads((out / "eval" / "metrics.json").read_text())
    log = [json.loads(line) for line in (out / "run" / "log.jsonl").read_text().splitlines()]
    return weights, next(r for r in log if "threads" in r), metrics


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_the_same_command_gives_the_same_weights_and_figures_beside_busy_processes(tmp_path):
    ds = make_dataset(tmp_path / "ds", n_scenarios=3)
    idle = _train_and_score(ds, tmp_path / "idle")
    spinners = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(usable_cores())]  # every core busy
    try:
        busy = _train_and_score(ds, tmp_path / "busy")
    finally:
        for p in spinners:
            p.kill()
            p.wait()
    assert idle[1]["threads"] == busy[1]["threads"] == usable_cores()  # recorded in the run, the same both times
    assert idle[0].keys() == busy[0].keys()
    assert all(torch.equal(idle[0][k], busy[0][k]) for k in idle[0])
    assert idle[2]["strict"] == busy[2]["strict"] and idle[2]["ap50"] == busy[2]["ap50"]
    assert idle[2]["strict"]["0.2"]["tp"] + idle[2]["strict"]["0.2"]["fn"] > 0  # something was scored
