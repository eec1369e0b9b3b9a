"""What an older config or checkpoint resolves to today: the loss weights that moved into each kind's ``model.loss``,
keys that moved between sections or went away, and, for a checkpoint, the keys its kind added since it was written
(``ModelConfig.trained_without``)::

    obj = upgrade_legacy(yaml_mapping)                 # today's form of a config file's or checkpoint's mapping
    obj = checkpoint_defaults(upgrade_legacy(ckpt["config"]))   # and the model that checkpoint holds
"""
from __future__ import annotations

import copy
import sys
from typing import Any

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt
from pnyolo.config.model import DEFAULT_KIND, ModelConfig, field_names, keys_for_kind
from pnyolo.registry import config_class, kinds


def model_config_class(model: Any) -> type[ModelConfig]:
    """The config class of the kind a ``model`` mapping names (the default kind's without one)."""
    kind = model.get("kind", DEFAULT_KIND) if isinstance(model, dict) else DEFAULT_KIND
    if not isinstance(kind, str):
        raise UserError(f"config model.kind: expected a kind's name, got {excerpt(kind)} ({' | '.join(sorted(kinds()))})")
    return config_class(kind)


# The top-level ``loss`` section of older versions: its keys are each kind's ``model.loss`` now (renamed where given).
OLD_LOSS_KEYS = ("box", "obj", "noobj", "cls", "obj_target", "obj_loss", "hidden_weight", "unseen_weight", "depth",
                  "iou", "surface_depth", "occupancy", "bev_heatmap", "bev_box")
_RENAMED_LOSS_KEYS = {"bev_heatmap": "heatmap", "bev_box": "regression"}


def move_loss(obj: dict, say: bool = False) -> dict:
    """``obj`` with an older version's top-level ``loss`` section moved into the kind's ``model.loss``: each key
    that kind's loss takes (``bev_heatmap`` as ``heatmap``, ``bev_box`` as ``regression``; a value already under
    ``model.loss`` wins), those only other kinds took left out; ``say``: one line on stderr naming where they went."""
    old = obj.get("loss")
    if old is None:
        return obj
    if not isinstance(old, dict):
        raise UserError(f"config loss: expected a mapping, got {type(old).__name__} (the weights are model.loss's now)")
    unknown = sorted(set(old) - set(OLD_LOSS_KEYS))
    if unknown:
        raise UserError(f"config loss: unknown key(s) {excerpt(unknown)} (the loss weights are each kind's model.loss)")
    model = obj.get("model") if isinstance(obj.get("model"), dict) else {}
    takes = field_names(getattr(model_config_class(model)(), "loss", None))
    names = {k: _RENAMED_LOSS_KEYS.get(k, k) for k in old if _RENAMED_LOSS_KEYS.get(k, k) in takes}  # old -> new
    obj = {k: v for k, v in obj.items() if k != "loss"}
    if names:
        section = model.get("loss") if isinstance(model.get("loss"), dict) else {}
        obj["model"] = {**model, "loss": {**{new: old[k] for k, new in names.items()}, **section}}
    if say:
        where = ", ".join(f"loss.{k} -> model.loss.{new}" for k, new in names.items())
        print(f"pnyolo: config: the loss weights moved into the kind's section ({where or 'none for this kind'}); "
              "read from the old place this time", file=sys.stderr)
    return obj


def moved_loss_overrides(obj: dict, overrides: list[str]) -> list[str]:
    """``overrides`` with an older version's ``loss.KEY=V`` written as the kind's ``model.loss.NEW=V`` (one line on
    stderr saying so): a command-line value wins over the file's ``model.loss`` as any ``--set`` does, and is
    checked as one; a key only other kinds' losses take is theirs (left out); an unknown one is refused."""
    model = obj.get("model") if isinstance(obj.get("model"), dict) else {}
    takes = field_names(getattr(model_config_class(model)(), "loss", None))
    out, moved = [], []
    for item in overrides:
        key, sep, raw = item.partition("=")
        parts = key.strip().split(".")
        if parts[0] != "loss":
            out.append(item)
            continue
        if len(parts) != 2 or parts[1] not in OLD_LOSS_KEYS or not sep:
            raise UserError(f"--set {excerpt(item)}: the loss weights are each kind's model.loss.KEY (known old keys: "
                            f"{', '.join(OLD_LOSS_KEYS)})")
        new = _RENAMED_LOSS_KEYS.get(parts[1], parts[1])
        if new in takes:
            out.append(f"model.loss.{new}={raw}")
        moved.append(f"loss.{parts[1]} -> " + (f"model.loss.{new}" if new in takes else "not this kind's"))
    if moved:
        print(f"pnyolo: config: the loss weights moved into the kind's section ({', '.join(moved)})", file=sys.stderr)
    return out


def upgrade_legacy(obj: dict, say: bool = False) -> dict:
    """A config mapping in today's form: ``model.sampler.ground_z`` (older versions) is ``data.ground_z``,
    ``eval.centre_match_m`` is gone (the devkit's thresholds), ``loss`` is the kind's ``model.loss`` (``move_loss``;
    ``say``: one line saying so), and model keys of kinds other than ``model.kind`` are left out (a checkpoint's
    unused ones: every kind had every section; a shared file's, for the other kinds)."""
    model = obj.get("model")
    if not isinstance(model, dict):
        return move_loss(obj, say)
    sampler = model.get("sampler")
    if isinstance(sampler, dict) and "ground_z" in sampler:
        sampler = dict(sampler)
        ground = sampler.pop("ground_z")
        model = {**model, "sampler": sampler}
        obj = {**obj, "data": {"ground_z": ground, **(obj.get("data") or {})}}
    ev = obj.get("eval")
    if isinstance(ev, dict) and "centre_match_m" in ev:  # 3D AP thresholds are now the nuScenes devkit's own
        obj = {**obj, "eval": {k: v for k, v in ev.items() if k != "centre_match_m"}}
    kind = model.get("kind", DEFAULT_KIND)
    obj = move_loss({**obj, "model": model}, say)
    if isinstance(kind, str) and kind in kinds():
        obj["model"] = keys_for_kind(obj["model"], kind)
    return obj


def checkpoint_defaults(obj: dict) -> dict:
    """A checkpoint's config mapping (in today's form) with each key its kind added since (``trained_without``) and
    the mapping lacks set to the value it was trained with: what the absent key resolves to for that checkpoint is
    the model it holds, not today's default."""
    if not isinstance(obj.get("model"), dict):
        return obj
    model = copy.deepcopy(obj["model"])
    for key, value in model_config_class(model).trained_without.items():
        *sections, name = key.split(".")
        node = model
        for part in sections:
            node = node.setdefault(part, {}) if isinstance(node, dict) else None
        if isinstance(node, dict) and name not in node:
            node[name] = value
    return {**obj, "model": model}
