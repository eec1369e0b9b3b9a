"""Every script in benchmarks/ runs as a user runs it: ``--help`` answers with usage and exit 0 (a script that no
longer imports, or lost its options, fails here rather than in the next measurement). What they share lives in
pnyolo.devtools."""
from __future__ import annotations

import subprocess
import sys

import pytest
from repo_paths import REPO

BENCHMARKS = REPO / "benchmarks"
SCRIPTS = sorted(p.name for p in BENCHMARKS.glob("*.py"))


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_benchmark_script_answers_help(script):
    res = subprocess.run([sys.executable, str(BENCHMARKS / script), "--help"], capture_output=True, text=True,
                         timeout=300, cwd=BENCHMARKS.parent)
    assert res.returncode == 0 and res.stdout.startswith(f"usage: {script}"), res.stderr[-1000:]
