"""``pnyolo-export``: a checkpoint as an ONNX file for ONNX Runtime and deployment toolchains."""
from __future__ import annotations

import re
import sys

from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_file, cli_main

EXAMPLES = """examples:
  pnyolo-export runs/bev/best.pt --onnx runs/bev/model.onnx --size 320x180
  pnyolo-export runs/mv/best.pt --onnx mv.onnx --size 1920x1080 --views 3    the paper's renders
  pnyolo-predict runs/bev/best.pt out/dataset --backend onnxruntime --onnx runs/bev/model.onnx

The file holds the model from images and cameras (intrinsics, camera-to-world of each view) to its raw
outputs, for --views cameras whose images are --size (resized by the checkpoint's data.image_scale before
the graph, as in training); decoding (NMS, heatmap peaks, projection into views) stays in Python, shared
with the torch backend. The ground-plane model's grid (its pillar points) is an input of any size.
"""


@cli_main
def main(argv=None) -> int:
    p = OneLineArgumentParser(prog="pnyolo-export", description=__doc__, epilog=EXAMPLES)
    p.add_argument("checkpoint")
    p.add_argument("--onnx", required=True, metavar="OUT.onnx", help="the ONNX file to write")
    p.add_argument("--size", required=True, metavar="WxH", help="the camera images' size, e.g. 320x180")
    p.add_argument("--views", type=int, help="cameras per frame (default: the checkpoint's data.num_views)")
    args = p.parse_args(argv)
    size = re.fullmatch(r"(\d+)x(\d+)", args.size)
    if not size or min(int(size[1]), int(size[2])) < 8:
        raise UserError(f"--size {args.size!r}: expected WIDTH x HEIGHT in pixels, e.g. 320x180")
    if args.views is not None and args.views < 1:
        raise UserError(f"--views must be >= 1, got {args.views}")
    out = check_output_file(args.onnx, "--onnx")

    from pnyolo.engine.checkpoint import load_detector, read_checkpoint
    from pnyolo.onnx_backend import export_onnx

    ckpt = read_checkpoint(args.checkpoint)
    model, cfg = load_detector(ckpt, args.checkpoint, list(ckpt["class_names"]), "cpu")
    views = args.views or cfg.data.num_views
    export_onnx(model, out, int(size[1]), int(size[2]), views, cfg.eval)
    print(f"{out}: {model.kind} for {views} views of {size[1]}x{size[2]} ({out.stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
