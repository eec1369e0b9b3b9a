"""Run blender-gen inside a Blender executable (no pip-installed ``bpy`` needed).

Usage::

    blender -b -P blender_tools/blender_entry.py -- list
    blender -b -P blender_tools/blender_entry.py -- render --scene intersection_07 --hdr all --out out/dataset
    blender -b -P blender_tools/blender_entry.py -- render --blend my_street.blend --hdr noon

Everything after ``--`` is a normal ``blender-gen`` command line. Inside Blender, rendering runs
in the Blender process itself (``--in-process``; ``--workers`` is ignored). Blender 5.0 bundles
Python 3.11 and numpy; the project's other dependencies (OpenEXR, opencv-python-headless<4.12,
tqdm) must be importable: this script appends the repository's ``.venv`` site-packages (if
present) and ``$BLENDER_TOOLS_SITE`` to ``sys.path``, or install them into Blender's Python
(``<blender>/5.0/python/bin/python3.11 -m pip install OpenEXR "opencv-python-headless<4.12" tqdm``).
"""
from __future__ import annotations

import glob
import os
import sys


def _setup_path() -> None:
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if repo not in sys.path:
        sys.path.insert(0, repo)
    extra = [os.environ.get("BLENDER_TOOLS_SITE", "")]
    ver = f"python{sys.version_info.major}.{sys.version_info.minor}"
    extra += glob.glob(os.path.join(repo, ".venv", "lib", ver, "site-packages"))
    for p in extra:
        if p and os.path.isdir(p) and p not in sys.path:
            sys.path.append(p)  # after Blender's own modules (bpy, numpy)


def main() -> int:
    _setup_path()
    from blender_tools.cli import main as cli_main

    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    if argv and argv[0] == "render" and "--in-process" not in argv:
        argv.append("--in-process")
    return cli_main(argv) or 0


if __name__ == "__main__":
    code = main()
    if code:
        sys.exit(code)
