"""What a checkpoint file must hold, checked whole before any of it is used: one schema of keys and types
shared by every reader (eval, predict, export, track, ``--fuse``, ``--resume``, ``Detector.load``, the
bench) and by ``pnyolo-checkpoint upgrade`` before it writes, each problem a one-line error::

    check_checkpoint(ckpt, "runs/mv/best.pt")      # UserError naming the key and what it holds instead
    torch.load(path, weights_only=True, ...) under legacy_globals(size): a format-1 file read as data

A format-1 checkpoint pickled numpy's random state (a tuple holding a uint32 array); reading it needs
exactly the numpy globals of ``legacy_globals`` (an array rebuilt from its bytes and its dtype), each checked
before it builds (numbers only, no larger than the file), which ``torch.load(weights_only=True)`` allows in
``pnyolo-checkpoint upgrade`` and nowhere else, so converting one runs no code and allocates what the file holds.
Every other reader only recognises the old format by reading its pickle's opcodes (``mentions_legacy_format``).
"""
from __future__ import annotations

import numpy as np
import torch

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt

FORMAT = "pnyolo-checkpoint-2"
LEGACY_FORMATS = ("pnyolo-checkpoint-1",)  # pickled numpy random states: converted by upgrade_checkpoint
MAX_CLASSES = 1000
MAX_RECORDS = 100000  # zip records of a torch file (one per tensor storage, a few more)
# every top-level key a checkpoint may hold (``make_payload``, the trainer's state); any other is refused
KNOWN_KEYS = frozenset({"format", "model", "optimizer", "scheduler", "config", "class_names", "rng", "train_state",
                        "rng_ranks", "train_model"})


def legacy_globals(max_bytes: int) -> list:
    """The numpy globals a format-1 random state needs (named as numpy 1 and numpy 2 pickle them), each checked
    before it builds anything: no object dtype, no array larger than ``max_bytes`` (the file's size: what its bytes
    could hold), no subclass of ndarray."""
    try:
        from numpy._core.multiarray import _reconstruct as rebuild  # numpy 2 (and 1.26's forward alias)
    except ImportError:
        from numpy.core.multiarray import _reconstruct as rebuild

    def plain(dt: np.dtype) -> np.dtype:
        if dt.hasobject or dt.kind not in "biufc":
            raise UserError(f"checkpoint: holds an array of {excerpt(str(dt))} (only numbers are read)")
        return dt

    def dtype(obj, align=False, copy=False):  # numpy.dtype as a pickle calls it
        return plain(np.dtype(obj, align, copy))

    built = [0]  # bytes of every array built so far: together bounded by the file's size too

    def reconstruct(subtype, shape, code):  # an empty array that BUILD then fills from the file's bytes
        if subtype is not NdarrayName or not isinstance(shape, tuple) or len(shape) > 8 or \
                not all(isinstance(n, int) and 0 <= n for n in shape):
            raise UserError("checkpoint: holds an array of another kind than numpy's plain ndarray")
        item = plain(np.dtype(code)).itemsize
        built[0] += int(np.prod(shape, dtype=object)) * item
        if built[0] > max_bytes:
            raise UserError(f"checkpoint: holds arrays (the last of shape {excerpt(shape)}) that together take more "
                            f"than the file's {max_bytes} bytes could hold")
        return rebuild(np.ndarray, shape, code)

    # what the pickle names numpy.ndarray is only ever _reconstruct's argument: called itself (an array of any size
    # or dtype, past every check above) it refuses
    return [(reconstruct, "numpy.core.multiarray._reconstruct"), (reconstruct, "numpy._core.multiarray._reconstruct"),
            (NdarrayName, "numpy.ndarray"), (np.ndarray, "pnyolo.built.ndarray"),  # BUILD fills a built ndarray;
            (dtype, "numpy.dtype"), np.dtypes.UInt32DType]                           # no pickle names that one


class NdarrayName:
    """Stands for ``numpy.ndarray`` where a format-1 pickle names it: ``_reconstruct``'s argument, never a
    constructor (the checked ``reconstruct`` alone builds arrays)."""

    def __new__(cls, *args, **kwargs):
        raise UserError("checkpoint: calls numpy.ndarray itself (arrays are built only through the checked "
                        "_reconstruct)")


def mentions_legacy_format(data_pkl: bytes) -> bool:
    """Whether a torch file's pickle names a format-1 checkpoint (a string it holds), read opcode by opcode:
    nothing in it is built, so only ``pnyolo-checkpoint upgrade`` ever reads the old format."""
    import pickletools

    try:
        return any(isinstance(arg, str) and arg in LEGACY_FORMATS for _, arg, _ in pickletools.genops(data_pkl))
    except Exception:  # noqa: BLE001 - a pickle that does not parse names nothing
        return False


def _fail(path, key: str, what: str, value) -> None:
    raise UserError(f"checkpoint {path}: {key} must be {what}, got {excerpt(value)}")


def _tensors(value, path, key: str) -> None:
    if not isinstance(value, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                              for k, v in value.items()):
        _fail(path, key, "a mapping of parameter names to tensors", type(value).__name__ if isinstance(value, dict)
              else value)


def _rng(state, path, key: str) -> None:
    """A random state as format 2 stores it: python [version, 625 ints, gauss], numpy (624 keys, pos, ...), torch bytes."""
    if not isinstance(state, dict) or not {"python", "numpy", "torch"} <= set(state):
        _fail(path, key, "a mapping with python, numpy and torch states", state)
    py = state["python"]
    if not (isinstance(py, (list, tuple)) and len(py) == 3 and isinstance(py[0], int)
            and isinstance(py[1], (list, tuple)) and len(py[1]) == 625 and all(isinstance(v, int) for v in py[1])
            and (py[2] is None or isinstance(py[2], float))):
        _fail(path, f"{key}.python", "[version, 625 integers, gauss]", py)
    n = state["numpy"]
    if not (isinstance(n, dict) and isinstance(n.get("keys"), torch.Tensor) and tuple(n["keys"].shape) == (624,)
            and all(isinstance(n.get(k), int) for k in ("pos", "has_gauss"))
            and isinstance(n.get("cached_gaussian"), float)):
        _fail(path, f"{key}.numpy", "numpy's MT19937 state (624 keys, pos, has_gauss, cached_gaussian)", n)
    if not (isinstance(state["torch"], torch.Tensor) and state["torch"].dtype == torch.uint8):
        _fail(path, f"{key}.torch", "torch's random state (a uint8 tensor)", state["torch"])


def check_checkpoint(ckpt, path) -> None:
    """Every key a reader may use, with its type, before any of it is used (one line for the first problem)."""
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise UserError(f"checkpoint {path}: not a pnyolo checkpoint")
    unknown = sorted(str(k)[:40] for k in ckpt if k not in KNOWN_KEYS)
    if unknown:
        raise UserError(f"checkpoint {path}: unknown top-level key(s) {unknown[:5]} (a checkpoint holds "
                        f"{', '.join(sorted(KNOWN_KEYS))})")
    for key in ("config", "model", "class_names"):
        if key not in ckpt:
            raise UserError(f"checkpoint {path}: has no {key}")
    config = ckpt["config"]
    if not isinstance(config, dict) or not isinstance(config.get("model"), dict):
        _fail(path, "config", "a mapping with a model section", config)
    _tensors(ckpt["model"], path, "model")
    if "train_model" in ckpt:
        _tensors(ckpt["train_model"], path, "train_model")
    names = ckpt["class_names"]
    if not (isinstance(names, list) and 0 < len(names) <= MAX_CLASSES and all(isinstance(n, str) and 0 < len(n) <= 128
                                                                                for n in names)):
        _fail(path, "class_names", f"a list of 1..{MAX_CLASSES} class names", names)
    for key in ("optimizer", "scheduler"):
        if ckpt.get(key) is not None and not isinstance(ckpt[key], dict):
            _fail(path, key, "a state mapping or null", ckpt[key])
    state = ckpt.get("train_state")
    if state is not None and not (isinstance(state, dict) and isinstance(state.get("step"), int) and state["step"] >= 0):
        _fail(path, "train_state", "a mapping with a step >= 0", state)
    if "rng" in ckpt:
        _rng(ckpt["rng"], path, "rng")
    if "rng_ranks" in ckpt:
        ranks = ckpt["rng_ranks"]
        if not isinstance(ranks, list) or not ranks:
            _fail(path, "rng_ranks", "a list of random states", ranks)
        for i, r in enumerate(ranks):
            _rng(r, path, f"rng_ranks[{i}]")
