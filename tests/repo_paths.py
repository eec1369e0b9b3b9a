"""Where the repository and the tests' shared files are, for a test in any folder of tests/."""
from __future__ import annotations

from pathlib import Path

TESTS = Path(__file__).resolve().parent  # conftest.py, the shared helpers, example_kind/
REPO = TESTS.parent
