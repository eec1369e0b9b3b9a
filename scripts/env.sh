#!/usr/bin/env bash
# Create or update the project's virtual environment in .venv (idempotent).
# Sourced by scripts/demo and scripts/test; re-installs only when pyproject.toml changed.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
PY="${PYTHON:-python3.11}"
if ! command -v "$PY" >/dev/null 2>&1; then
  echo "error: $PY not found; this project needs Python 3.11 (bpy 5.0.1 is cp311-only). Set PYTHON=/path/to/python3.11" >&2
  exit 1
fi
if [ ! -x "$VENV/bin/python" ]; then
  echo "[env] creating $VENV" >&2
  "$PY" -m venv "$VENV"
fi
STAMP="$VENV/.installed-$(sha256sum "$ROOT/pyproject.toml" | cut -c1-16)"
if [ ! -f "$STAMP" ]; then
  echo "[env] installing the project and its dependencies into .venv (first run: a few minutes)" >&2
  "$VENV/bin/python" -m pip install --disable-pip-version-check -q -e "$ROOT[all,test]"
  rm -f "$VENV"/.installed-*
  touch "$STAMP"
fi
export PATH="$VENV/bin:$PATH"
