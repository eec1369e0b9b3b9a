"""INT8 ONNX files: an exported graph quantised statically in the QDQ format by ONNX Runtime's
quantisation tools, calibrated on frames of a dataset (the checkpoint's own classes and image size)::

    items = calibration_items(cfg, class_names, "out/dataset", "val", 320, 180, views=3, count=32)
    quantize_int8(model, "m.onnx", "m_int8.onnx", items)     # OnnxRunner opens it as it opens m.onnx

Convolutions and matrix products with learned weights on image features are quantised (``QUANTIZED_OPS``):
weights INT8 per output channel, activations INT8 with ranges from the calibration frames (MinMax);
everything else stays FP32: the products of two activations (a projection by the input cameras, a ray's
fine samples) and every product computed from the cameras and points alone (``geometry_nodes``). A pixel
coordinate of a 320-pixel image in 256 levels is off by pixels, which on trained checkpoints wiped out
bev's detections.
QDQ is the format ONNX Runtime runs fast on the CPU (dynamic quantisation is often slower than FP32 there).
The file keeps the FP32 export's metadata (kind, config, weights, views, size) with ``pnyolo.precision``
``int8`` and a digest of the quantised graph.
"""
from __future__ import annotations

import contextlib
import logging
import tempfile
from pathlib import Path

from dataset_spec.atomic import atomic_path
from dataset_spec.cli_support import UserError
from pnyolo.onnx.backend import INSTALL
from pnyolo.onnx.integrity import seal, write_detached

# the operators quantised: the convolutions and matrix products that hold the time; the ray rendering
# (cumulative sums, exponentials) and the decoding arithmetic stay FP32, where INT8 loses depth precision
QUANTIZED_OPS = ["Conv", "MatMul", "Gemm"]
# the graph inputs that carry pixels; every other input is geometry (K, camera_to_world, points)
IMAGE_INPUTS = {"images"}


def geometry_nodes(graph) -> set[str]:
    """Names of the nodes of an ONNX graph that compute from the geometry inputs (and constants) alone,
    not from the images: the camera projections and ray positions, which must stay FP32."""
    constants = {i.name for i in graph.initializer}
    from_images = {i.name for i in graph.input if i.name in IMAGE_INPUTS}
    geometry = {i.name for i in graph.input if i.name not in IMAGE_INPUTS and i.name not in constants}
    names = set()
    for node in graph.node:  # ONNX nodes are stored in topological order
        if any(i in from_images for i in node.input):
            from_images.update(node.output)
        elif any(i in geometry for i in node.input):
            geometry.update(node.output)
            names.add(node.name)
    return names


def calibration_items(cfg, class_names: list[str], root, split: str, width: int, height: int, views: int,
                      count: int) -> list:
    """Up to ``count`` items of ``split`` of the dataset at ``root`` (``views`` cameras each, spread over its
    scenarios and frames), checked against the checkpoint: the same classes, images of ``width`` x ``height``
    (one-line errors otherwise)."""
    from pnyolo.data.dataset import MultiViewDataset, open_dataset
    from pnyolo.evaluation.evaluate import spread_over_scenarios

    ds = open_dataset(root)
    if list(ds.info.detectable_classes) != list(class_names):
        raise UserError(f"--calibrate {root}: its classes {ds.info.detectable_classes} are not the checkpoint's "
                        f"{list(class_names)}")
    names = ds.split(split) if split in ds.info.splits else []
    if not names:
        raise UserError(f"--calibrate {root}: split {split!r} has no scenarios (choose another with --split)")
    sizes = {(c.width, c.height) for s in names for c in ds.scenario(s).cameras}
    if sizes != {(width, height)}:
        raise UserError(f"--calibrate {root}: its {split} images are {sorted(sizes)[0][0]}x{sorted(sizes)[0][1]}, the "
                        f"export is for {width}x{height} (--size)")
    data = MultiViewDataset(root, split, cfg, training=False, views=list(range(views)))
    return [data[k] for k in spread_over_scenarios(data.items)[:count]]


@contextlib.contextmanager
def _quiet_logging():
    """ONNX Runtime's quantiser advises on the root logger (pre-processing, bias initialisers): not the user's news."""
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)
    try:
        yield
    finally:
        root.setLevel(level)


def quantize_int8(model, fp32_path: str | Path, out_path: str | Path, items: list) -> Path:
    """``fp32_path`` (an ``export_onnx`` file of ``model``) quantised to INT8 QDQ at ``out_path``, calibrated
    on ``items`` (of the file's views and size)."""
    try:
        import onnx
        from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    except ImportError:
        raise UserError(f"INT8 export needs onnxruntime and onnx: {INSTALL}") from None
    fp32 = onnx.load(str(fp32_path))
    meta = {p.key: p.value for p in fp32.metadata_props}
    names = {i.name for i in fp32.graph.input}
    if not items:
        raise UserError("INT8 calibration needs at least one frame")
    g = items[0].grid  # the encoded size of the calibration frames
    if f"{g.width}x{g.height}" != meta.get("pnyolo.size"):
        raise UserError(f"the calibration frames encode to {g.width}x{g.height}, the file is for "
                        f"{meta.get('pnyolo.size')}")
    keep_fp32 = geometry_nodes(fp32.graph)
    weights = {i.name for i in fp32.graph.initializer}
    quantised = [n.name for n in fp32.graph.node if n.op_type in QUANTIZED_OPS and n.name not in keep_fp32
                 and any(i in weights for i in n.input[1:])]
    feeds = [{k: v.detach().cpu().numpy() for k, v in model.graph_inputs(it).items() if k in names} for it in items]

    class Frames(CalibrationDataReader):
        def __init__(self):
            self.rest = iter(feeds)

        def get_next(self):
            return next(self.rest, None)

    with tempfile.TemporaryDirectory(prefix="pnyolo_int8_") as tmp, _quiet_logging():
        quantized = Path(tmp) / "int8.onnx"
        quantize_static(str(fp32_path), str(quantized), Frames(), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QInt8, weight_type=QuantType.QInt8, per_channel=True,
                        op_types_to_quantize=QUANTIZED_OPS, nodes_to_quantize=quantised)
        proto = onnx.load(str(quantized))
    kept = {k: v for k, v in meta.items() if k not in ("pnyolo.graph_digest", "pnyolo.binding")}
    seal(proto, {**kept, "pnyolo.precision": "int8"}, model)
    with atomic_path(out_path) as tmp:
        onnx.save(proto, str(tmp))
    write_detached(out_path)
    return Path(out_path)
