"""Shared fixtures. Datasets are made once per test session in a temporary folder."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def synthetic_dataset(tmp_path_factory):
    """A valid 3-scenario dataset ray-cast in numpy (no Blender): exact depth and ids, 64x48."""
    from dataset_spec.synthetic import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("synthetic") / "ds", n_scenarios=3)
