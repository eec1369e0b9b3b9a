"""``pnyolo-predict``: a trained detector's detections on a dataset split, in formats other tools read."""
from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_dir, cli_main
from dataset_spec.names import below
from pnyolo.cli.options import add_run_options, check_threshold, parse_views

PREDICT_EXAMPLES = """examples:
  pnyolo-predict runs/mv/best.pt out/dataset --split test --out out/predict
  pnyolo-predict runs/mv/best.pt out/dataset --scenario intersection_07 --variant all --pictures 4
  pnyolo-predict runs/sv/best.pt out/dataset --views 0,1,2 --conf 0.3
  pnyolo-predict runs/bev/best.pt out/dataset --backend onnxruntime --onnx runs/bev/model.onnx

Writes OUT/results_SPLIT.json (COCO results: image_id, category_id, bbox [x, y, w, h] in COCO pixel
coordinates, score; image ids as in this dataset's COCO export with the same --variant, so
pycocotools.COCOeval scores it against project-labels --export coco), OUT/views/SCENARIO/CAMERA__VARIANT.json
(boxes [x0, y0, x1, y1] in the image's pixels, class, score, distance in metres where the model has one)
and, with --pictures N, N pictures of detections. Every camera is scored once (in items of data.num_views
cameras), or the cameras --views names. A model with world outputs (bev, pixelnerf-yolo with its 3D state) also
writes OUT/results_nusc_SPLIT.json: nuScenes' detection results (one sample per scenario, lighting and frame;
sample tokens as in project-labels --export nuscenes), which pnyolo-eval --results and the nuScenes devkit both
score.
"""


def _parser() -> OneLineArgumentParser:
    p = OneLineArgumentParser(prog="pnyolo-predict", description="Run a trained detector on a dataset split and "
                              "write its detections in formats other tools read.", epilog=PREDICT_EXAMPLES)
    p.add_argument("checkpoint")
    p.add_argument("dataset")
    p.add_argument("--split", default="test", choices=["train", "val", "test"])
    p.add_argument("--scenario", action="append", default=None, metavar="NAME", help="only this scenario (repeatable)")
    p.add_argument("--variant", default=None, metavar="NAME|all",
                   help="lighting variants to predict: each scenario's first (default), NAME, or all; as the COCO "
                        "export you compare with")
    p.add_argument("--views", help="camera indices used as source views, e.g. 0,1,2 (default: every camera once)")
    p.add_argument("--conf", type=float, help="confidence threshold (default: the checkpoint's eval.conf_threshold)")
    p.add_argument("--pictures", type=int, default=0, metavar="N", help="write N pictures of detections")
    p.add_argument("--out", default="out/predict", help="output folder (default out/predict)")
    p.add_argument("--backend", default="torch", choices=["torch", "onnxruntime"],
                   help="what runs the model: torch, or ONNX Runtime on the file --onnx (pnyolo-export wrote it "
                        "from this checkpoint); decoding is the same")
    p.add_argument("--onnx", metavar="MODEL.onnx", help="with --backend onnxruntime: the exported model")
    p.add_argument("--onnx-sha256", metavar="HEX|FILE",
                   help="with --onnx: the file's sha256 as you kept it (pnyolo-export writes MODEL.onnx.sha256): "
                        "any other file is refused, whoever made it")
    add_run_options(p)
    return p


@cli_main
def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    if (args.backend == "onnxruntime") != (args.onnx is not None):
        raise UserError("--backend onnxruntime and --onnx FILE go together")
    if args.onnx_sha256:
        if not args.onnx:
            raise UserError("--onnx-sha256 goes with --onnx")
        from pnyolo.onnx.integrity import check_detached

        if not Path(args.onnx).is_file():
            raise UserError(f"{args.onnx}: no such ONNX file")
        check_detached(args.onnx, args.onnx_sha256)  # before any work

    from dataset_spec.atomic import atomic_write_json
    from pnyolo.data.dataset import MultiViewDataset, open_dataset
    from pnyolo.engine.checkpoint import checkpoint_config, load_detector, read_checkpoint
    from pnyolo.bench.plan import Backend, predict_scoring
    from pnyolo.engine.predict import Trained
    from pnyolo.engine.runtime import pick_device
    from pnyolo.evaluation.nuscenes_results import WorldPool
    from pnyolo.models import Decoding
    from pnyolo.evaluation.pictures import panel, write_png
    from pnyolo.evaluation.predictions import coco_results, image_index, view_record
    from pnyolo.inference import RigConstants

    check_threshold(args.conf, "eval.conf_threshold", "--conf")
    if args.pictures < 0:
        raise UserError(f"--pictures must be >= 0, got {args.pictures}")
    out = check_output_dir(args.out)
    ckpt = read_checkpoint(args.checkpoint)
    cfg = checkpoint_config(ckpt)
    views = parse_views(args.views)
    data = open_dataset(args.dataset)
    index = image_index(data, args.variant)
    scenarios = data.select_scenarios(args.scenario) if args.scenario else data.split(args.split)
    if args.scenario and not set(scenarios) <= set(data.split(args.split)):
        raise UserError(f"--scenario: {sorted(set(scenarios) - set(data.split(args.split)))} not in split {args.split}")
    ds = MultiViewDataset(args.dataset, args.split, cfg, training=False, views=views, every_camera=views is None,
                          scenarios=scenarios)
    ds.items = [it for it in ds.items
                if any((it.scenario, c.name, it.variant, it.frame) in index for c in ds.ds.scenario(it.scenario).cameras)]
    if not ds.items:
        raise UserError(f"--variant {args.variant!r}: no lighting variant of these scenarios to predict")
    device = pick_device(args.device)
    model, cfg = load_detector(ckpt, args.checkpoint, ds.class_names, device)
    runner = None
    if args.onnx:
        from pnyolo.onnx.backend import OnnxRunner
        runner = OnnxRunner(args.onnx, model)
    if args.conf is not None:
        cfg = replace(cfg, eval=replace(cfg.eval, conf_threshold=args.conf))  # the command line's point: a new value
    class_ids = [data.info.class_id(n) for n in ds.class_names]
    rows, written, pooled = [], 0, WorldPool(Decoding.of(model), cfg.eval, data)
    t0 = time.perf_counter()
    backend = Backend(runner, None if runner else RigConstants(model))
    preds = predict_scoring(Trained(Path(args.checkpoint), model, cfg), ds, device=device, progress=not args.quiet,
                            backend=backend).clean
    for k, p in enumerate(preds.items):
        item, dets = p.item, preds.detections_at(k, cfg.eval)
        rows += coco_results(item, dets, index, class_ids)
        pooled.add(p.out, item)
        for v in item.scored:
            rec = view_record(item, v, dets[v], ds.class_names)
            when = f"__f{item.frame:04d}" if data.scenario(item.scenario).frames > 1 else ""
            atomic_write_json(below(out, "views", item.scenario, f"{rec['camera']}{when}__{item.variant}.json"), rec)
        if written < args.pictures:
            full = ds[k]  # with its images
            write_png(below(out, "pictures", f"{item.scenario}_{item.variant}_{k}.png"),
                      panel(full, dets, ds.class_names, model.targets(full)))
            written += 1
    atomic_write_json(out / f"results_{args.split}.json", rows)
    if pooled.active:
        atomic_write_json(out / f"results_nusc_{args.split}.json", pooled.document(ds.class_names))
    rate = len(ds) / (time.perf_counter() - t0)
    print(f"{len(rows)} detections on {len(ds)} items ({rate:.1f} items/s, reading and writing included) -> "
          f"{out / f'results_{args.split}.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
