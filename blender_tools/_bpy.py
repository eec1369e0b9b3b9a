"""The one guarded import of ``bpy`` (Blender as a Python module).

Modules that drive Blender call ``require_bpy()``; modules that do not (scene model, assets,
scenarios, HDR skies, CLI parsing) never import it, so they work and are tested without Blender.
"""
from __future__ import annotations

BPY_MISSING = ("Blender's Python module 'bpy' is not installed: install it with "
               "`pip install 'occluded-road-users[blender]'` (bpy==5.0.1, Python 3.11), "
               "or run inside Blender: blender -b -P blender_tools/blender_entry.py -- ARGS")


class BlenderMissing(RuntimeError):
    pass


def require_bpy():
    """Return the ``bpy`` module or raise ``BlenderMissing`` with install instructions."""
    try:
        import bpy  # noqa: F401
    except ImportError as exc:
        raise BlenderMissing(f"{BPY_MISSING} ({exc})") from None
    return bpy
