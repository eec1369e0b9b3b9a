"""What a preset, a file that may come from someone else, may ask for, checked on what it resolves to: the blender-gen
options that say what the data is (never where or how rendering runs, nor a path), and the places a model runs and
reads or writes (the command line's, never a preset's)::

    check_render_options(["--quality", "preview"], "preset x: render")   # one-line UserError otherwise
    check_places(preset, preset.models, "preset x")
"""
from __future__ import annotations

import re
from pathlib import Path

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt

REPO = Path(__file__).resolve().parents[2]

# What a preset (a file that may come from someone else) may ask of blender-gen: options that say what the data is,
# each with the values it takes. Where and how rendering runs (--ray, --workers, --device, --out, --timings, ...) is
# the user's command line only (pnyolo-bench --ray, --render-workers, --render-gpu).
RENDER_DATA_OPTIONS = {"--quality": ("default", "final", "preview"), "--resolution": r"[0-9]{1,5}x[0-9]{1,5}",
                       "--samples": r"[0-9]{1,5}", "--denoise": ("on", "off"), "--frames": r"[0-9]{1,5}",
                       "--fps": r"[0-9]{1,3}(\.[0-9]{1,3})?", "--moving-cameras": r"[0-9]{1,3}", "--hdr": "lighting"}
# train keys that say where a model runs (with every path its kind names, ``ModelConfig.path_keys``: what it reads or
# writes outside its run): the user's --set on the command line sets them, never a preset
TRAIN_PLACES = ("device", "threads", "workers")
LIGHTING_NAME = r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}"  # a lighting variant by name: no suffix, no separator, never a path


def check_render_options(options: list[str], where: str) -> None:
    """One line for a blender-gen option a preset may not give (``RENDER_DATA_OPTIONS``), or a value it does not
    take: a preset never chooses where or how rendering runs, nor a path."""
    words = [part for o in options for part in (o.split("=", 1) if o.startswith("--") and "=" in o else [o])]
    if len(words) % 2:
        raise UserError(f"{where}: options and their values in pairs, got {excerpt(options)}")
    for option, value in zip(words[::2], words[1::2]):
        allowed = RENDER_DATA_OPTIONS.get(option)
        if allowed is None:
            raise UserError(f"{where}: {excerpt(option)} is not a data option a preset may give (allowed: "
                            f"{', '.join(RENDER_DATA_OPTIONS)}; where rendering runs is the command line's)")
        if allowed == "lighting":
            names = value.split(":", 1)[1] if value.startswith("random:") else value
            ok = value in ("all", "random") or all(re.fullmatch(LIGHTING_NAME, n) for n in names.split(","))
        elif isinstance(allowed, tuple):
            ok = value in allowed
        else:
            ok = re.fullmatch(allowed, value) is not None
        if not ok:
            raise UserError(f"{where}: {option} {excerpt(value)} is not a value it takes here (lighting variants "
                            "by name, no paths)" if allowed == "lighting" else f"{where}: {option} {excerpt(value)}")


def places(cfg) -> dict[str, object]:
    """Where a config's model runs and what it reads or writes outside its run: the train keys ``TRAIN_PLACES`` and
    every path its kind names (``ModelConfig.path_keys``), by dotted key."""
    out = {f"train.{k}": getattr(cfg.train, k) for k in TRAIN_PLACES}
    for key in cfg.model.path_keys:
        *sections, name = key.split(".")
        obj = cfg.model
        for section in sections:
            obj = getattr(obj, section)
        out[f"model.{key}"] = getattr(obj, name)
    return out


def check_places(preset, models, where: str) -> None:
    """A preset (a file that may come from someone else) checked on what it resolves to: the config each of
    ``models`` trains with by the preset alone (its config file, its overrides as lines or as mappings, its base)
    names the same places (``places``) as the project's config file it starts from, or the defaults; the user's
    --set on the command line comes later and may set them."""
    from pnyolo.config import load_config

    trusted = preset.config_path if preset.config_path.resolve().is_relative_to(REPO / "configs") else None
    for kind in models:
        got = places(load_config(preset.config_path, [*preset.overrides_for(kind), f"model.kind={kind}"]))
        want = places(load_config(trusted, [f"model.kind={kind}"]))
        for key, value in got.items():
            if value != want[key]:
                raise UserError(f"{where}: it resolves {key} to {excerpt(value)} for {kind} (through its overrides, "
                                f"config file or base); where a model runs and the paths it reads or writes are the "
                                f"command line's (--set {key}=...), never a preset's")
