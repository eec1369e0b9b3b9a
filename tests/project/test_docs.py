"""The documents stay true: docs/CLI.md matches every command's --help, docs/guide/config.md every config
key, README links resolve."""
from __future__ import annotations

import re
import subprocess
import sys

import pytest
from repo_paths import REPO

ROOT = REPO


@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_cli_reference_is_up_to_date():
    res = subprocess.run([sys.executable, str(ROOT / "scripts" / "cli_reference.py"), "--check"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr


def test_config_reference_is_up_to_date_and_every_key_has_a_meaning():
    res = subprocess.run([sys.executable, str(ROOT / "scripts" / "config_reference.py"), "--check"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr


def test_readme_is_short_and_its_links_resolve():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    links = [m for m in re.findall(r"\]\(([^)#\s]+)", text) if not m.startswith("http")]
    assert links, "the README links to its guides"
    assert [m for m in links if not (ROOT / m).exists()] == []
