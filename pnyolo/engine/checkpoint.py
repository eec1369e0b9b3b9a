"""Checkpoints: model + optimizer + scheduler + RNG states + config, written atomically, holding data only.

A checkpoint is a ``torch.save`` of tensors, numbers, strings, lists and plain dicts (the config as
``to_dict`` gives it, random states as tensors and lists), read with ``weights_only=True`` and checked
whole (``checkpoint_schema``) before any of it is used: loading never runs code from the file, so a
crafted checkpoint is refused before any of its objects is built. A loaded config is range-checked as
a config file is, and the paths it names (``ModelConfig.path_keys``: weights to read, a feature cache
to write) are dropped: a checkpoint from someone else never chooses what we read or where we write.
Checkpoints of format 1 (numpy random states pickled as objects) are refused with the command that
converts them (``pnyolo-checkpoint upgrade``), which reads them as data too (``legacy_globals``).
"""
from __future__ import annotations

import pickle
import random
from pathlib import Path

import numpy as np
import torch

from dataset_spec.atomic import atomic_path
from dataset_spec.cli_support import UserError
from pnyolo.config import Config, checkpoint_defaults, from_dict, model_signature, to_dict, upgrade_legacy
from pnyolo.config.checks import validate
from pnyolo.engine.checkpoint_schema import (FORMAT, LEGACY_FORMATS, MAX_RECORDS, check_checkpoint,
                                             legacy_globals, mentions_legacy_format)
from pnyolo.engine.runtime import apply_threads
from pnyolo.models import build_model


def numpy_state_as_data(state) -> dict:
    """numpy's legacy random state (a tuple holding an array) as tensors and numbers."""
    _, keys, pos, has_gauss, cached = state
    return {"keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos), "has_gauss": int(has_gauss),
            "cached_gaussian": float(cached)}


def rng_state() -> dict:
    version, internal, gauss = random.getstate()
    state = {"python": [version, list(internal), gauss], "numpy": numpy_state_as_data(np.random.get_state()),
             "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    n = state["numpy"]
    np.random.set_state(("MT19937", n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: str | Path, **payload) -> None:
    payload = {"format": FORMAT, **payload}
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def checkpoint_file(path: str | Path) -> Path:
    """``path`` as a checkpoint file: one line for a folder or a missing file."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"checkpoint {path}: is a folder; expected a checkpoint file (e.g. {path / 'best.pt'})")
    if not path.is_file():
        raise UserError(f"checkpoint {path} does not exist")
    return path


def _check_archive(path: Path) -> None:
    """A torch file's zip records checked on what they declare before anything is read or decompressed: torch.save
    stores every record uncompressed, so a compressed record (a DEFLATE record of zeros expands a thousandfold) or
    records declaring more bytes than the file holds are refused in one line."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
    except (OSError, zipfile.BadZipFile, EOFError, ValueError):
        return  # not a zip: torch.load names it as not a readable torch file
    size = path.stat().st_size
    packed = next((i for i in infos if i.compress_type != zipfile.ZIP_STORED), None)
    if packed is not None:
        raise UserError(f"checkpoint {path}: record {packed.filename[:80]!r} is compressed; torch.save stores every "
                        "record as it is (nothing of it was decompressed)")
    if len(infos) > MAX_RECORDS or sum(i.file_size for i in infos) > size:
        raise UserError(f"checkpoint {path}: its {len(infos)} records declare {sum(i.file_size for i in infos)} bytes, "
                        f"more than the file's {size} (or more than {MAX_RECORDS} records)")


def _load(path: Path, legacy: bool = False):
    """``torch.load`` as data only (``legacy``: also the numpy globals of a format-1 random state); a file that
    is not a torch file, or holds objects that would have to run, is a one-line error (nothing of it run)."""
    _check_archive(path)
    try:
        if legacy:
            with torch.serialization.safe_globals(legacy_globals(path.stat().st_size)):
                return torch.load(path, map_location="cpu", weights_only=True)
        return torch.load(path, map_location="cpu", weights_only=True)
    except UserError as exc:  # a legacy global refused what it was asked to build
        raise UserError(f"{path}: {exc}") from None
    except pickle.UnpicklingError as exc:
        if "Unsupported global" in str(exc) or "Can only build" in str(exc):
            raise UserError(f"checkpoint {path}: holds Python objects that loading would have to run (a crafted file "
                            "or not a pnyolo checkpoint); nothing of it was run") from None
        raise UserError(f"checkpoint {path}: not a readable torch file (UnpicklingError)") from None
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's input problem
        raise UserError(f"checkpoint {path}: not a readable torch file ({exc.__class__.__name__})") from None


def read_checkpoint(path: str | Path) -> dict:
    """A checkpoint read as data and checked whole (``check_checkpoint``); a format-1 file is refused with the
    command that converts it."""
    path = checkpoint_file(path)
    try:
        ckpt = _load(path)
    except UserError:
        if _is_legacy(path):
            raise UserError(f"checkpoint {path}: written before format 2 (numpy random states); convert it, which "
                            f"reads it as data: pnyolo-checkpoint upgrade {path} --out NEW.pt") from None
        raise
    check_checkpoint(ckpt, path)
    checkpoint_config(ckpt, path)  # ranges and relations, as a config file's
    return ckpt


def _is_legacy(path: Path) -> bool:
    """Whether ``path`` is a torch file whose pickle names the old format; its objects are never built here."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            entry = next((i for i in archive.infolist() if i.filename.endswith("/data.pkl")), None)
            if entry is None or entry.file_size > path.stat().st_size * 64 + (1 << 20):
                return False
            return mentions_legacy_format(archive.read(entry))
    except (OSError, zipfile.BadZipFile, EOFError, ValueError):
        return False


def _rng_as_data(state: dict) -> dict:
    """A format-1 random state (tuples, a numpy state tuple) as format 2 stores it."""
    version, internal, gauss = state["python"]
    out = {**state, "python": [version, list(internal), gauss], "torch": state["torch"]}
    if not isinstance(state["numpy"], dict):
        out["numpy"] = numpy_state_as_data(state["numpy"])
    return out


def upgrade_checkpoint(src: str | Path, dst: str | Path) -> dict:
    """Convert a format-1 checkpoint to format 2, reading it as data (``legacy_globals``: no code in it runs), its
    config in today's form (``upgrade_legacy``: the loss weights in ``model.loss``). The result is checked whole
    before anything is written, then read back from ``dst``; returns it."""
    src = checkpoint_file(src)
    old = _load(src, legacy=True)
    if not isinstance(old, dict) or old.get("format") not in (*LEGACY_FORMATS, FORMAT):
        raise UserError(f"checkpoint {src}: not a pnyolo checkpoint")
    new = {**old, "format": FORMAT}
    try:
        if "rng" in old:
            new["rng"] = _rng_as_data(old["rng"])
        if "rng_ranks" in old:
            new["rng_ranks"] = [_rng_as_data(r) for r in old["rng_ranks"]]
    except (TypeError, ValueError, KeyError, IndexError, AttributeError):
        raise UserError(f"checkpoint {src}: its random state is not numpy's, python's and torch's as pnyolo "
                        "wrote them") from None
    check_checkpoint(new, src)
    new["config"] = to_dict(checkpoint_config(new, src, keep_paths=True))  # its config in today's form
    save_checkpoint(dst, **{k: v for k, v in new.items() if k != "format"})
    return read_checkpoint(dst)


def checkpoint_config(ckpt: dict, path=None, keep_paths: bool = False) -> Config:
    """The config a checkpoint was trained with, in today's form (``upgrade_legacy``), range-checked as a config
    file is, without the paths it names (``path_keys``: a caller that trusts a path passes it to ``load_detector``;
    ``keep_paths``: kept, for rewriting the file)."""
    try:
        cfg = from_dict(checkpoint_defaults(upgrade_legacy(ckpt["config"])))
        cfg = cfg if keep_paths else drop_paths(cfg)
        validate(cfg)
    except UserError as exc:
        raise UserError(f"checkpoint {path}: {exc}" if path is not None else str(exc)) from None
    return cfg


def drop_paths(cfg: Config) -> Config:
    """``cfg`` (changed in place) with every path its kind names (``ModelConfig.path_keys``) set to None."""
    for key in cfg.model.path_keys:
        *sections, name = key.split(".")
        node = cfg.model
        for part in sections:
            node = getattr(node, part, None)
        if node is not None and hasattr(node, name):
            setattr(node, name, None)
    return cfg


def check_compatible(ckpt: dict, cfg: Config, class_names: list[str], path) -> None:
    """A checkpoint from another model config or class list is a one-line user error."""
    theirs = model_signature(checkpoint_config(ckpt))
    ours = model_signature(cfg)
    if theirs != ours:
        diff = sorted(f"model.{k}" for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k))
        raise UserError(f"checkpoint {path} was made with another model config (differs in: {', '.join(diff)})")
    if list(ckpt["class_names"]) != list(class_names):
        raise UserError(f"checkpoint {path} predicts classes {ckpt['class_names']}, the dataset has {class_names}")


def make_payload(model, optimizer, scheduler, cfg: Config, class_names, **state) -> dict:
    return {"model": model.state_dict(), "optimizer": optimizer.state_dict() if optimizer else None,
            "scheduler": scheduler.state_dict() if scheduler else None, "config": to_dict(cfg),
            "class_names": list(class_names), "rng": rng_state(), **state}


def load_weights(model, state: dict, path, check_only: bool = False) -> None:
    """``model.load_state_dict(state)``, a mismatch named in one line: which tensor, its shapes, and
    which config key builds it (``model.config_key``: a checkpoint whose weights do not fit its stored config);
    ``check_only``: the names and shapes only (a model built on the ``meta`` device)."""
    own = model.state_dict()
    for name, tensor in state.items():
        if name in own and tuple(own[name].shape) != tuple(tensor.shape):
            key = model.config_key(name)
            raise UserError(f"checkpoint {path}: tensor {name} has shape {tuple(tensor.shape)}, the config builds "
                            f"{tuple(own[name].shape)} (see config {key})")
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    if missing or unexpected:
        name = (missing or unexpected)[0]
        key = model.config_key(name)
        what = "lacks" if missing else "has a tensor the config does not build:"
        raise UserError(f"checkpoint {path} {what} {name} ({len(missing)} missing, {len(unexpected)} unexpected; "
                        f"see config {key})")
    if not check_only:
        model.load_state_dict(state)


def load_detector(ckpt: dict, path, class_names: list[str], device, data_cfg=None, paths: dict | None = None):
    """(model, cfg) from a read checkpoint, checked against the dataset's classes (and a data config, if given),
    with torch's CPU threads set from its ``train.threads`` (``runtime.apply_threads``: the bench and every command
    that runs the model run it on the same count, so they give the same figures).
    ``paths``: config keys below ``model.`` the caller trusts (its own feature cache), set after loading. The
    checkpoint's tensor shapes are compared with what its config builds on the ``meta`` device first, so a
    crafted config allocates no more memory than the file's own tensors take."""
    cfg = checkpoint_config(ckpt, path)
    for key, value in (paths or {}).items():
        section, name = key.rsplit(".", 1)
        setattr(getattr(cfg.model, section), name, value)
    check_compatible(ckpt, cfg, class_names, path)
    if data_cfg is not None:
        for key in ("image_scale", "cell_px"):
            if getattr(cfg.data, key) != getattr(data_cfg, key):
                raise UserError(f"{path}: data.{key} = {getattr(cfg.data, key)} differs from the other checkpoint's "
                                f"{getattr(data_cfg, key)}; fused detectors must share the image scale and grid")
    with torch.device("meta"):
        load_weights(build_model(cfg, len(class_names)), ckpt["model"], path, check_only=True)
    model = build_model(cfg, len(class_names))
    load_weights(model, ckpt["model"], path)
    apply_threads(cfg.train.threads)
    return model.to(device), cfg
