"""Checkpoints: model + optimizer + scheduler + RNG states + config, written atomically."""
from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import torch

from dataset_spec.atomic import atomic_path
from dataset_spec.cli_support import UserError
from pnyolo.config import Config, from_dict, model_signature, to_dict
from pnyolo.models import build_model

FORMAT = "pnyolo-checkpoint-1"


def rng_state() -> dict:
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: str | Path, **payload) -> None:
    payload = {"format": FORMAT, **payload}
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def read_checkpoint(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's input problem
        raise UserError(f"checkpoint {path}: not a readable torch file ({exc.__class__.__name__})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise UserError(f"checkpoint {path}: not a pnyolo checkpoint")
    return ckpt


def checkpoint_config(ckpt: dict) -> Config:
    return from_dict(ckpt["config"])


def check_compatible(ckpt: dict, cfg: Config, class_names: list[str], path) -> None:
    """A checkpoint from another model config or class list is a one-line user error."""
    theirs = model_signature(checkpoint_config(ckpt))
    ours = model_signature(cfg)
    if theirs != ours:
        diff = sorted(k for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k))
        raise UserError(f"checkpoint {path} was made with another model config (differs in: {', '.join(diff)})")
    if list(ckpt["class_names"]) != list(class_names):
        raise UserError(f"checkpoint {path} predicts classes {ckpt['class_names']}, the dataset has {class_names}")


def make_payload(model, optimizer, scheduler, cfg: Config, class_names, **state) -> dict:
    return {"model": model.state_dict(), "optimizer": optimizer.state_dict() if optimizer else None,
            "scheduler": scheduler.state_dict() if scheduler else None, "config": to_dict(cfg),
            "class_names": list(class_names), "rng": rng_state(), **state}


def load_detector(ckpt: dict, path, class_names: list[str], device, data_cfg=None):
    """(model, cfg) from a read checkpoint, checked against the dataset's classes (and a data config, if given)."""
    cfg = checkpoint_config(ckpt)
    check_compatible(ckpt, cfg, class_names, path)
    if data_cfg is not None:
        for key in ("image_scale", "cell_px"):
            if getattr(cfg.data, key) != getattr(data_cfg, key):
                raise UserError(f"{path}: data.{key} = {getattr(cfg.data, key)} differs from the other checkpoint's "
                                f"{getattr(data_cfg, key)}; fused detectors must share the image scale and grid")
    model = build_model(cfg, len(class_names))
    model.load_state_dict(ckpt["model"])
    return model.to(device), cfg
