"""The one list of model kinds. A kind registers itself, in its own module, with ``@register_model``;
the built-in kinds are the modules of ``pnyolo.models``, and a kind in another installed package
registers through the entry-point group ``pnyolo.models`` (nerfstudio's way), so it appears in
``--model``, configs, checkpoints and the bench without an edit of pnyolo::

    # another package's pyproject.toml
    [project.entry-points."pnyolo.models"]
    ground-mean = "my_package.ground_mean:GroundMean"

    kinds()                      # {"bev": BevDetector, "pixelnerf-yolo": ..., "ground-mean": GroundMean, ...}
    model_class("bev")           # the class: its capabilities, read without building it
    config_class("bev")          # its ``model`` section: the class's ``config_class``, never a second list

This module sits in the lowest layer (configs need it); it reaches the kinds by importing them by
name, as plugins are loaded, so no layer imports upward. With ``PNYOLO_PLUGINS=0`` in the environment only the
built-in kinds load (the generated references describe pnyolo itself, whatever else is installed).
"""
from __future__ import annotations

import importlib
import os
from importlib.metadata import entry_points

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt

ENTRY_POINT_GROUP = "pnyolo.models"
BUILT_IN = "pnyolo.models"  # the package whose modules are the built-in kinds
_KINDS: dict[str, type] = {}
_loading = False
_loaded = False


def register_model(name: str):
    """Class decorator: ``name`` becomes a ``model.kind``; its ``model`` section is ``cls.config_class``."""
    def deco(cls: type) -> type:
        if cls.renders_rays != cls.config_class.casts_rays:
            raise TypeError(f"{cls.__name__}.renders_rays and {cls.config_class.__name__}.casts_rays must agree")
        known = _KINDS.get(name)
        if known is not None and known is not cls and known.__qualname__ != cls.__qualname__:
            raise TypeError(f"model kind {name!r} is registered twice ({known.__module__}.{known.__qualname__} and "
                            f"{cls.__module__}.{cls.__qualname__})")
        cls.kind = name
        _KINDS[name] = cls
        return cls
    return deco


def unregister_model(name: str) -> None:
    """Remove a kind (tests that register one for their own run)."""
    _KINDS.pop(name, None)


def load_kinds() -> None:
    """Register the built-in kinds and every installed package's (once per process)."""
    global _loading, _loaded
    if _loaded or _loading:
        return
    _loading = True
    try:
        importlib.import_module(BUILT_IN)
        plugins = os.environ.get("PNYOLO_PLUGINS", "1") != "0"
        for ep in entry_points(group=ENTRY_POINT_GROUP) if plugins else ():
            try:
                obj = ep.load()
            except Exception as exc:  # noqa: BLE001 - another package's import error, said in one line
                raise UserError(f"model kind {ep.name!r} (entry point {ep.value} of group {ENTRY_POINT_GROUP}): "
                                f"cannot be loaded ({exc.__class__.__name__}: {excerpt(str(exc))})") from None
            if isinstance(obj, type) and ep.name not in _KINDS:
                register_model(ep.name)(obj)
        _loaded = True
    finally:
        _loading = False


def kinds() -> dict[str, type]:
    """Every registered kind's class, by name."""
    load_kinds()
    return dict(_KINDS)


def model_class(kind: str) -> type:
    """The registered class of ``kind``, or a one-line error listing the kinds."""
    load_kinds()
    if kind not in _KINDS:
        raise UserError(f"config model.kind: {excerpt(kind)} ({' | '.join(sorted(_KINDS))})")
    return _KINDS[kind]


def config_class(kind: str) -> type:
    """The ``model`` section of ``kind``: its class's ``config_class``."""
    return model_class(kind).config_class
