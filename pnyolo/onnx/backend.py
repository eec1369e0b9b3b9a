"""ONNX export of every model kind and an ONNX Runtime backend; decoding stays the torch path's::

    export_onnx(model, "model.onnx", 320, 180, num_views=3, ev=cfg.eval)   # model, cfg from load_detector
    runner = OnnxRunner("model.onnx", model)       # refuses a file of another checkpoint or config
    out = runner(item)                             # what predict_item(model, item) returns, by ONNX Runtime
    dets = model.decode(out, item, cfg.eval)

Each kind says what its graph holds (``Model.export_graph``, ``graph_inputs``, ``outputs_from_graph``):
the YOLO-grid kinds the whole forward for one grid; the ground-plane model everything but choosing
the grid, whose pillar points are an input with a free size. The number of views and the image size
are fixed in the file (opset 17, the TorchScript exporter) and stated in its metadata with the
checkpoint's config signature, a digest of the checkpoint's weights, a digest of the graph and the
trusted metadata and a binding of both to the checkpoint's exact tensors (``pnyolo.onnx.integrity``:
what each protects against), so a file whose weights, nodes or metadata were changed after export is
refused on opening; a call with other views or sizes is refused in one line.
"""
from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from dataset_spec.atomic import atomic_path
from dataset_spec.cli_support import UserError
from dataset_spec.schema import CameraInfo
from pnyolo.components.backbones import backbone_computed
from pnyolo.data.frame import frame_item
from pnyolo.onnx.convention import calling_convention
from pnyolo.onnx.integrity import check_binding, check_digest, checked_metadata, seal, write_detached

OPSET = 17
INSTALL = "pip install -e '.[onnx]' (the README's set-up installs it)"


def weights_digest(model: nn.Module) -> str:
    """A digest of the model's parameters and buffers (which checkpoint an ONNX file was made from)."""
    h = hashlib.sha1()
    for k, v in model.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:20]


def model_metadata(model) -> dict[str, str]:
    return {"pnyolo.kind": model.kind, "pnyolo.weights": weights_digest(model),
            "pnyolo.config": json.dumps(model.config.signature(), sort_keys=True, default=str)}


def example_item(model, width: int, height: int, num_views: int):
    """An item of ``num_views`` black ``width`` x ``height`` images from cameras on a line, 1.5 m up,
    looking along +x (the export's example; the graph does not depend on the values)."""
    K = np.array([[width, 0, (width - 1) / 2], [0, width, (height - 1) / 2], [0, 0, 1.0]])
    axes = np.array([[0, 0, 1.0], [-1, 0, 0], [0, -1, 0]])  # camera x, y, z in world: -y, -z, +x
    cams = []
    for v in range(num_views):
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = axes, [0.0, 2.0 * v, 1.5]
        cams.append(CameraInfo(f"cam{v}", width, height, K, c2w))
    images = [np.zeros((height, width, 3), np.uint8)] * num_views
    return frame_item(images, cams, model.data_cfg, [f"class{c}" for c in range(model.num_classes)])[0]


class _Ordered(nn.Module):
    """A graph returning a dict, as a tuple in ``names``' order (what the exporter takes)."""

    def __init__(self, graph: nn.Module, names: list[str]):
        super().__init__()
        self.graph, self.names = graph, names

    def forward(self, *inputs):
        out = self.graph(*inputs)
        return tuple(out[n] for n in self.names)


def _shapes(values) -> dict[str, list]:
    """An ONNX graph's inputs or outputs -> {name: shape}, a symbolic axis by its name."""
    return {v.name: [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim] for v in values}


def export_onnx(model, path: str | Path, width: int, height: int, num_views: int, ev,
                class_names: list[str] | None = None) -> Path:
    """Write ``model`` (eval mode) for ``num_views`` camera images of ``width`` x ``height`` (resized by
    ``data.image_scale`` before the graph, as always) with the evaluation settings ``ev`` its outputs
    depend on (``Model.eval_options``) as an ONNX file, its calling convention in its metadata
    (``pnyolo.convention``; ``class_names`` name the classes there)."""
    try:
        import onnx
    except ImportError:
        raise UserError(f"ONNX export needs the onnx package: {INSTALL}") from None
    model.eval()
    item = example_item(model, width, height, num_views)
    graph, dynamic = model.export_graph(item, ev)
    inputs = model.graph_inputs(item)
    with torch.no_grad(), backbone_computed(model), warnings.catch_warnings():
        # the graph computes the features a cache would hold; sizes are fixed in the file on purpose,
        # so the tracer's notes that shapes become constants (and the exporter's deprecation) are not news
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.simplefilter("ignore", DeprecationWarning)
        names = list(graph(*inputs.values()))
        wrapped = _Ordered(graph, names).eval()
        with atomic_path(path) as tmp:
            torch.onnx.export(wrapped, tuple(inputs.values()), str(tmp), input_names=list(inputs), output_names=names,
                              dynamic_axes=dynamic or None, opset_version=OPSET, dynamo=False)
            proto = onnx.load(str(tmp))
            names = class_names or [f"class{c}" for c in range(model.num_classes)]
            convention = calling_convention(model, _shapes(proto.graph.input), _shapes(proto.graph.output), names, ev)
            seal(proto, {**model_metadata(model), "pnyolo.views": str(num_views),
                         "pnyolo.size": f"{item.grid.width}x{item.grid.height}",  # the encoded images
                         "pnyolo.convention": json.dumps(convention)}, model)
            onnx.save(proto, str(tmp))
    write_detached(path)
    return Path(path)


def _load_proto(path: Path):
    """The ONNX model at ``path`` with its weights (external data only from beside it, as onnx allows)."""
    try:
        import onnx
    except ImportError:
        raise UserError(f"--backend onnxruntime needs the onnx package: {INSTALL}") from None
    return onnx.load(str(path))


class OnnxRunner:
    """``model``'s outputs for items by ONNX Runtime on the CPU, from a file ``export_onnx`` wrote for
    that model (kind, config and weights checked on opening; views and size on every call)."""

    def __init__(self, path: str | Path, model, threads: int | None = None):
        try:
            import onnxruntime as ort
        except ImportError:
            raise UserError(f"--backend onnxruntime needs onnxruntime: {INSTALL}") from None
        path = Path(path)
        if not path.is_file():
            raise UserError(f"{path}: no such ONNX file (write one with pnyolo-export CHECKPOINT --onnx {path})")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads or torch.get_num_threads()
        opts.inter_op_num_threads = 1
        try:
            proto = _load_proto(path)
        except UserError:
            raise
        except Exception as exc:  # onnx raises its own classes for unreadable files
            raise UserError(f"{path}: not a readable ONNX file ({exc.__class__.__name__})") from None
        # integrity before work: digest and binding from the file's bytes and metadata, before a session exists
        # (creating one already runs the graph's constant folding, whatever the file asks of it)
        meta = {p.key: p.value for p in proto.metadata_props}
        views, (width, height) = checked_metadata(meta, path)
        check_digest(proto, meta, path)
        want = model_metadata(model)
        for key, what in (("pnyolo.kind", "model kind"), ("pnyolo.config", "configuration"), ("pnyolo.weights", "weights")):
            if meta.get(key) != want[key]:
                raise UserError(f"{path} was exported from another checkpoint ({what} differs): export this one with "
                                f"pnyolo-export CHECKPOINT --onnx {path}")
        check_binding(proto, meta, model, path)
        try:
            self.session = ort.InferenceSession(proto.SerializeToString(), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own classes for graphs it cannot run
            raise UserError(f"{path}: not a runnable ONNX file ({exc.__class__.__name__})") from None
        self.model, self.path = model, path
        self.views, self.size = views, f"{width}x{height}"
        self.outputs = [o.name for o in self.session.get_outputs()]
        self.inputs = [i.name for i in self.session.get_inputs()]  # the exporter drops inputs a graph ignores

    def __call__(self, item):
        if len(item.images) != self.views or f"{item.grid.width}x{item.grid.height}" != self.size:
            raise UserError(f"{self.path} was exported for {self.views} views of {self.size} (the encoded images); "
                            f"this item has {len(item.images)} of {item.grid.width}x{item.grid.height}: export again "
                            "with --views / --size")
        feeds = {k: v.detach().cpu().numpy() for k, v in self.model.graph_inputs(item).items() if k in self.inputs}
        arrays = self.session.run(self.outputs, feeds)
        return self.model.outputs_from_graph({n: torch.from_numpy(a) for n, a in zip(self.outputs, arrays)}, item)
