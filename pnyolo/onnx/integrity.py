"""What an exported graph's integrity checks protect against, and what they do not::

    seal(proto, model)                         # at export: pnyolo.graph_digest and pnyolo.binding in its metadata
    views, size = checked_metadata(meta, path)  # the fields the runtime trusts, range-checked (one-line errors)
    check_digest(proto, meta, path)             # on opening: an accident
    check_binding(proto, meta, model, path)     # with the checkpoint: a changed graph
    check_detached(path, "model.onnx.sha256")  # a digest the user kept apart from the file (or its hex)

* ``pnyolo.graph_digest``: an unkeyed sha256 of the graph (nodes, weights) and of the metadata the runtime
  trusts (``SIGNED``). It catches accidents (a truncated or edited file, metadata that no longer matches)
  but not an attacker: whoever changes the graph can recompute it, since it is kept in the file.
* ``pnyolo.binding``: an HMAC-SHA256 of the same message keyed by a digest of the checkpoint's exact tensors
  (every parameter and buffer, bit for bit; batch-norm statistics and step counters that the graph does not
  hold among them). It is checked whenever the checkpoint is given with the file (``--backend onnxruntime``
  always gives it): a graph changed by someone who does not hold that checkpoint cannot match it. Someone who
  holds the checkpoint can make a matching file.
* The detached ``<file>.sha256`` that ``pnyolo-export`` writes beside the file (``sha256sum`` format): kept
  by the user apart from the file (or compared with a copy they trust), ``--onnx-sha256`` refuses any other
  file, whoever made it.
"""
from __future__ import annotations

import hashlib
import hmac
import json
import re
from pathlib import Path

import torch

from dataset_spec.atomic import atomic_write_text
from dataset_spec.cli_support import UserError
from dataset_spec.images import MAX_PIXELS
from dataset_spec.names import excerpt

# the metadata the runtime and the documented client trust: covered by the digest and the binding
SIGNED = ("pnyolo.kind", "pnyolo.config", "pnyolo.weights", "pnyolo.views", "pnyolo.size", "pnyolo.convention",
          "pnyolo.precision")
MAX_VIEWS = 64


def _message(proto, meta: dict) -> bytes:
    trusted = {k: meta[k] for k in SIGNED if k in meta}
    return proto.graph.SerializeToString() + json.dumps(trusted, sort_keys=True).encode()


def binding_key(model) -> bytes:
    """A digest of every tensor of ``model``'s state (names, dtypes, shapes, values bit for bit)."""
    h = hashlib.sha256(b"pnyolo-onnx-binding-1")
    for name, t in model.state_dict().items():
        t = t.detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())  # the bits, whatever the dtype
    return h.digest()


def seal(proto, meta: dict, model) -> dict:
    """``meta`` with ``pnyolo.graph_digest`` and ``pnyolo.binding`` of ``proto`` (set as its metadata)."""
    message = _message(proto, meta)
    sealed = {**meta, "pnyolo.graph_digest": hashlib.sha256(message).hexdigest(),
              "pnyolo.binding": hmac.new(binding_key(model), message, hashlib.sha256).hexdigest()}
    del proto.metadata_props[:]
    for k, v in sealed.items():
        proto.metadata_props.add(key=k, value=v)
    return sealed


def checked_metadata(meta: dict, path) -> tuple[int, tuple[int, int]]:
    """(views, (width, height)) from the metadata, refused in one line unless they are numbers in range."""
    views, size = meta.get("pnyolo.views", ""), meta.get("pnyolo.size", "")
    if not re.fullmatch(r"\d{1,3}", views) or not 1 <= int(views) <= MAX_VIEWS:
        raise UserError(f"{path}: pnyolo.views {excerpt(views)} is not a number of views 1..{MAX_VIEWS}")
    wh = re.fullmatch(r"(\d{1,5})x(\d{1,5})", size)
    if not wh or min(int(wh[1]), int(wh[2])) < 8 or int(wh[1]) * int(wh[2]) > MAX_PIXELS:
        raise UserError(f"{path}: pnyolo.size {excerpt(size)} is not WIDTHxHEIGHT of at least 8 pixels and at most "
                        f"{MAX_PIXELS} in all")
    return int(views), (int(wh[1]), int(wh[2]))


def check_digest(proto, meta: dict, path) -> None:
    """The digest the file carries (accidents: a truncated or edited file), one line."""
    if meta.get("pnyolo.graph_digest") != hashlib.sha256(_message(proto, meta)).hexdigest():
        raise UserError(f"{path}: its graph or metadata changed after export (the digest it carries does not "
                        f"match): export again with pnyolo-export CHECKPOINT --onnx {path}")


def check_binding(proto, meta: dict, model, path) -> None:
    """The binding to ``model``'s checkpoint (a graph changed by someone without it), one line."""
    binding = hmac.new(binding_key(model), _message(proto, meta), hashlib.sha256).hexdigest()
    if not hmac.compare_digest(meta.get("pnyolo.binding", ""), binding):
        raise UserError(f"{path}: not bound to this checkpoint (its graph or metadata was changed after export): "
                        f"export this one with pnyolo-export CHECKPOINT --onnx {path}")


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_detached(path: str | Path) -> Path:
    """``<path>.sha256`` beside ``path`` in ``sha256sum``'s format (``sha256sum -c`` checks it too)."""
    path = Path(path)
    out = path.with_name(path.name + ".sha256")
    atomic_write_text(out, f"{file_sha256(path)}  {path.name}\n")
    return out


def check_detached(path: str | Path, expected: str) -> None:
    """``expected``: a sha256 in hex, or a ``sha256sum`` file holding one; one line when ``path``'s differs."""
    text = expected
    if not re.fullmatch(r"[0-9a-fA-F]{64}", expected):
        try:
            text = Path(expected).read_text(encoding="utf-8", errors="replace")[:4096]
        except OSError:
            raise UserError(f"--onnx-sha256 {excerpt(expected)}: neither a sha256 in hex nor a readable file") from None
    found = re.match(r"\s*([0-9a-fA-F]{64})\b", text)
    if found is None:
        raise UserError(f"--onnx-sha256 {excerpt(expected)}: holds no sha256 (64 hex digits)")
    if found[1].lower() != file_sha256(path):
        raise UserError(f"{path}: its sha256 is not the one you kept ({found[1][:12]}...): not the file you exported")
