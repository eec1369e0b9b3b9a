"""Shared fixtures. Datasets are made once per test session in a temporary folder."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def synthetic_dataset(tmp_path_factory):
    """A valid 3-scenario dataset ray-cast in numpy (no Blender): exact depth and ids, 64x48."""
    from dataset_spec.synthetic import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("synthetic") / "ds", n_scenarios=3)


BLENDER_TOY_ARGS = ["--scene", "toy", "--hdr", "noon,dusk", "--resolution", "96x64", "--samples", "4"]


@pytest.fixture(scope="session")
def blender_toy_dataset(tmp_path_factory):
    """The procedural ``toy`` scene rendered once per session by ``blender-gen`` (96x64, 4 spp,
    HDR variants noon and dusk). Skips when bpy is not installed. Treat as read-only; copy it
    before modifying."""
    pytest.importorskip("bpy")
    import os

    from blender_tools.cli import main

    os.environ.setdefault("BLENDER_TOOLS_CACHE", str(tmp_path_factory.mktemp("blender_cache")))
    root = tmp_path_factory.mktemp("blender_toy") / "ds"
    assert main(["render", *BLENDER_TOY_ARGS, "--out", str(root), "--no-progress"]) == 0
    return root


@pytest.fixture(scope="session")
def example_kind_package(tmp_path_factory):
    """``tests/example_kind`` (the ground-mean kind of docs/guide/detector.md) installed with pip into a
    folder of its own, as a user installs a package of theirs: the folder to put on the path."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    src = shutil.copytree(Path(__file__).parent / "example_kind", tmp_path_factory.mktemp("example_src") / "pkg")
    target = tmp_path_factory.mktemp("example_site")
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--no-index", "--quiet",
                    "--disable-pip-version-check", "--target", str(target), str(src)], check=True)
    return target
