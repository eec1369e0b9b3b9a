"""``pnyolo-export``: a checkpoint as an ONNX file for ONNX Runtime and deployment toolchains."""
from __future__ import annotations

import re
import sys

from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_file, cli_main

EXAMPLES = """examples:
  pnyolo-export runs/bev/best.pt --onnx runs/bev/model.onnx --size 320x180
  pnyolo-export runs/mv/best.pt --onnx mv.onnx --size 1920x1080 --views 3    the paper's renders
  pnyolo-export runs/bev/best.pt --onnx bev_int8.onnx --size 320x180 --int8 --calibrate out/dataset --split val
  pnyolo-predict runs/bev/best.pt out/dataset --backend onnxruntime --onnx runs/bev/model.onnx

The file holds the model from images and cameras (intrinsics, camera-to-world of each view) to its raw
outputs, for --views cameras whose images are --size (resized by the checkpoint's data.image_scale before
the graph, as in training); decoding (NMS, heatmap peaks, projection into views) stays in Python, shared
with the torch backend. The ground-plane model's grid (its pillar points) is an input of any size.
--int8 quantises the graph statically (QDQ: INT8 weights per channel, INT8 activations with ranges from
--calibration-frames frames of --calibrate's --split), the format ONNX Runtime runs fast on the CPU.
"""


@cli_main
def main(argv=None) -> int:
    p = OneLineArgumentParser(prog="pnyolo-export", description=__doc__, epilog=EXAMPLES)
    p.add_argument("checkpoint")
    p.add_argument("--onnx", required=True, metavar="OUT.onnx", help="the ONNX file to write")
    p.add_argument("--size", required=True, metavar="WxH", help="the camera images' size, e.g. 320x180")
    p.add_argument("--views", type=int, help="cameras per frame (default: the checkpoint's data.num_views)")
    p.add_argument("--int8", action="store_true", help="quantise to INT8 (QDQ), calibrated on --calibrate")
    p.add_argument("--calibrate", metavar="DATASET", help="with --int8: the dataset whose frames set the ranges")
    p.add_argument("--split", default="val", choices=["train", "val", "test"],
                   help="with --calibrate: its split to take frames from (default val)")
    p.add_argument("--calibration-frames", type=int, default=32, help="with --calibrate: frames (default 32)")
    args = p.parse_args(argv)
    if args.int8 != bool(args.calibrate):
        raise UserError("--int8 and --calibrate DATASET go together (INT8 ranges come from the dataset's frames)")
    if args.calibration_frames < 1:
        raise UserError(f"--calibration-frames must be >= 1, got {args.calibration_frames}")
    size = re.fullmatch(r"(\d+)x(\d+)", args.size)
    if not size or min(int(size[1]), int(size[2])) < 8:
        raise UserError(f"--size {args.size!r}: expected WIDTH x HEIGHT in pixels, e.g. 320x180")
    if args.views is not None and args.views < 1:
        raise UserError(f"--views must be >= 1, got {args.views}")
    out = check_output_file(args.onnx, "--onnx")

    from pnyolo.engine.checkpoint import load_detector, read_checkpoint
    from pnyolo.onnx.backend import export_onnx

    ckpt = read_checkpoint(args.checkpoint)
    names = list(ckpt["class_names"])
    model, cfg = load_detector(ckpt, args.checkpoint, names, "cpu")
    views = args.views or cfg.data.num_views
    width, height = int(size[1]), int(size[2])
    if args.int8:  # every input checked before the export
        import tempfile

        from pnyolo.onnx.int8 import calibration_items, quantize_int8

        items = calibration_items(cfg, names, args.calibrate, args.split, width, height, views,
                                  args.calibration_frames)
        with tempfile.TemporaryDirectory(prefix="pnyolo_export_") as tmp:
            fp32 = export_onnx(model, f"{tmp}/fp32.onnx", width, height, views, cfg.eval, names)
            quantize_int8(model, fp32, out, items)
    else:
        export_onnx(model, out, width, height, views, cfg.eval, names)
    precision = f"INT8 (calibrated on {len(items)} frames)" if args.int8 else "FP32"
    print(f"{out}: {model.kind} for {views} views of {width}x{height}, {precision} ({out.stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
