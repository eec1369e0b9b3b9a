"""project-labels: write 2D labels (boxes, in-frame and visible fractions) for a dataset, and export them."""
from __future__ import annotations

import sys

from dataset_spec import Dataset, LabelThresholds
from dataset_spec.atomic import staged_folder
from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_dir, cli_main

EPILOG = """examples:
  project-labels out/dataset
      label every view (labels.json per camera; all actors in the frustum, thresholds stored)
  project-labels out/dataset --min-in-frame 0.5 --min-visible 0.1 --max-distance 60
  project-labels out/dataset --class-option pedestrian:max_distance=40 --class-option car:min_visible=0.05
  project-labels out/dataset --export yolo,coco --out out/exports
      also write an Ultralytics YOLO tree and COCO JSON (one per split) under out/exports/<format>
  project-labels out/dataset --export pixelnerf,kitti --variant all
      every lighting variant becomes its own image (default: each scenario's first variant)
  project-labels out/seq --export mot,multiviewx
      a sequence: MOTChallenge ground truth per camera (gt/gt.txt, seqinfo.ini) and MultiviewX folders
      with the real frames (one per lighting variant; its GMVD config.json beside)
  project-labels out/seq --no-labelling --export nuscenes --variant all
      nuScenes tables (v1.0-occluded), camera images and pseudo-LiDAR sweeps: the devkit opens them
  project-labels out/seq --no-labelling --export nuscenes --nuscenes-channels cam_0,cam_1,cam_2,cam_3,cam_4,cam_5
      those cameras as CAM_FRONT, CAM_FRONT_RIGHT, CAM_FRONT_LEFT, CAM_BACK, CAM_BACK_LEFT, CAM_BACK_RIGHT
      (mmdetection3d's converter: docs/guide/labels.md)
  project-labels out/procedural --no-labelling --export multiviewx --multiviewx-cameras all
      every camera of each rig (default: the first six, the Camera1..6 MVDet's and GMVD's loaders read)

Thresholds only select which stored labels count as ground truth: they are written into every
labels.json and can be re-applied later (ViewLabels.kept(other_thresholds)) without relabelling.
Labels they leave out are real road users: KITTI gets them as DontCare, COCO as iscrowd (ignored).
Fully hidden road users are exported as ordinary boxes (the default --min-visible 0 is what
multi-view training wants); raise --min-visible for a detector that should learn only what its
image shows. Formats: yolo, coco (amodal masks, visible masks beside them; video fields for sequences),
kitti, pixelnerf, multiviewx, mot (a sequence's every frame: one image per frame, or per camera a sequence),
nuscenes (a scene per scenario and lighting variant, a sample per frame).
Default --out: DATASET/exports.
"""

THRESHOLD_KEYS = ("min_in_frame", "min_visible", "max_distance", "min_box_pixels")


def parse_class_options(options: list[str], known_classes: list[str]) -> dict[str, dict[str, float]]:
    """``["pedestrian:max_distance=40,min_visible=0.1", ...]`` -> ``{"pedestrian": {...}}``."""
    per_class: dict[str, dict[str, float]] = {}
    for text in options:
        cls, sep, rest = text.partition(":")
        if not sep or not rest:
            raise UserError(f"--class-option {text!r}: expected CLASS:KEY=VALUE[,KEY=VALUE...]")
        if cls not in known_classes:
            raise UserError(f"--class-option {text!r}: unknown class {cls!r} (classes: {', '.join(known_classes)})")
        for item in rest.split(","):
            key, eq, value = item.partition("=")
            key = key.strip().replace("-", "_")
            if not eq or key not in THRESHOLD_KEYS:
                raise UserError(f"--class-option {text!r}: option must be one of {', '.join(THRESHOLD_KEYS)} "
                                f"as KEY=VALUE")
            try:
                number = float(value)
            except ValueError:
                raise UserError(f"--class-option {text!r}: {value!r} is not a number") from None
            per_class.setdefault(cls, {})[key] = number
    return per_class


def _number_in(low: float, high: float, what: str):
    """An argparse type: a float within [low, high], else a one-line error saying ``what`` it must be."""
    import argparse

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{text} {what}")
        return value

    return parse


_fraction = _number_in(0.0, 1.0, "is not within [0, 1]")
_positive = _number_in(0.0, float("inf"), "must not be negative")


def build_parser() -> OneLineArgumentParser:
    p = OneLineArgumentParser(prog="project-labels", description=__doc__, epilog=EPILOG)
    p.add_argument("dataset", help="dataset folder (dataset_spec layout)")
    p.add_argument("--min-in-frame", type=_fraction, default=0.25,
                   help="least share of the amodal silhouette inside the image (default 0.25)")
    p.add_argument("--min-visible", type=_fraction, default=0.0,
                   help="least visible fraction (default 0: multi-view training keeps fully hidden objects)")
    p.add_argument("--max-distance", type=_positive, default=None, help="largest distance in metres (default: none)")
    p.add_argument("--min-box-pixels", type=_positive, default=2.0,
                   help="least width and height of the clipped 2D box in pixels (default 2)")
    p.add_argument("--class-option", action="append", default=[], metavar="CLASS:KEY=VALUE",
                   help="per-class threshold, repeatable, e.g. pedestrian:max_distance=40")
    p.add_argument("--scenario", action="append", default=None, metavar="NAME",
                   help="label only this scenario (repeatable; default: all)")
    p.add_argument("--export", default="", metavar="FORMATS",
                   help="comma-separated: yolo,coco,kitti,pixelnerf,multiviewx,mot,nuscenes")
    p.add_argument("--out", default=None, metavar="DIR", help="export folder (default: DATASET/exports)")
    p.add_argument("--variant", default=None, metavar="NAME|all",
                   help="lighting variant whose images are exported (default: each scenario's first; 'all')")
    p.add_argument("--nuscenes-channels", default=None, metavar="CAMERA,...",
                   help="nuscenes export: only these cameras (1 to 6 names), as nuScenes' CAM_FRONT, CAM_FRONT_RIGHT, "
                        "CAM_FRONT_LEFT, CAM_BACK, CAM_BACK_LEFT, CAM_BACK_RIGHT in that order (default: every camera, "
                        "CAM_ and its own name)")
    p.add_argument("--multiviewx-cameras", default=None, metavar="K|all",
                   help="multiviewx export: the first K cameras of each rig, or all (default 6: MVDet's and GMVD's "
                        "loaders read Camera1..6; a procedural layout has 3-8)")
    p.add_argument("--no-labelling", action="store_true",
                   help="export the labels already in the dataset, with the thresholds given here")
    p.add_argument("--quiet", action="store_true", help="no progress bar or statistics")
    return p


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from tools.exporters import EXPORTERS

    formats = [f.strip() for f in args.export.split(",") if f.strip()]
    unknown = [f for f in formats if f not in EXPORTERS]
    if unknown:
        raise UserError(f"--export: unknown format(s) {', '.join(unknown)} (known: {', '.join(EXPORTERS)})")
    if (args.out or args.variant) and not formats:
        raise UserError("--out and --variant only apply to exports: add --export FORMATS")
    channels = None if args.nuscenes_channels is None else [c.strip() for c in args.nuscenes_channels.split(",")]
    if channels is not None and "nuscenes" not in formats:
        raise UserError("--nuscenes-channels goes with --export nuscenes")
    mvx_cameras = _multiviewx_cameras(args.multiviewx_cameras, formats)

    ds = Dataset.open(args.dataset)
    thresholds = LabelThresholds(args.min_in_frame, args.min_visible, args.max_distance, args.min_box_pixels,
                                 parse_class_options(args.class_option, [c.name for c in ds.info.classes]))
    names = ds.select_scenarios(args.scenario)
    if args.variant not in (None, "all"):
        for s in names:
            if args.variant not in [v.name for v in ds.scenario(s).lighting]:
                raise UserError(f"--variant {args.variant!r}: scenario {s} has lighting variants "
                                f"{[v.name for v in ds.scenario(s).lighting]}")

    out_root = check_output_dir(args.out if args.out else ds.root / "exports") if formats else None
    if formats:  # an image that does not decode is named before anything is labelled or written
        from tools.exporters.common import check_images

        check_images(ds, names, args.variant)
        if "nuscenes" in formats:
            from tools.exporters.nuscenes import channel_names

            channel_names(ds, names, channels)  # the cameras named exist in every scenario
        if "multiviewx" in formats:
            from tools.exporters.multiviewx import check_rigs

            check_rigs(ds, names)
    if not args.no_labelling:
        if not ds.info.has("instance"):
            raise UserError(f"{ds.root} has no instance maps to label from (camera data: its labels came with it); "
                            "add --no-labelling to export them")
        check_output_dir(ds.root, "dataset")  # labels.json goes into every view folder
        ds.check_segmentation_sizes(names)
        from tools.occlusion import format_statistics, label_and_measure, occlusion_statistics

        from tqdm import tqdm

        all_labels = []
        for name in tqdm(names, desc="labelling", unit="scenario", disable=args.quiet):
            all_labels += label_and_measure(ds, name, thresholds)
        if not args.quiet:
            kept = sum(len(v.kept()) for v in all_labels)
            total = sum(len(v.objects) for v in all_labels)
            print(f"{len(all_labels)} views labelled: {total} actor-camera pairs in the frustum, {kept} kept as "
                  f"ground truth by the thresholds")
            print(format_statistics(occlusion_statistics(all_labels)))

    if formats:  # written whole into a temporary folder, then moved into --out: a failure leaves it as it was
        with staged_folder(out_root) as staged:
            for fmt in formats:
                extra = {"nuscenes": {"channels": channels}, "multiviewx": {"max_cameras": mvx_cameras}}.get(fmt, {})
                EXPORTERS[fmt](ds, staged / fmt, scenarios=names, thresholds=thresholds, variant=args.variant, **extra)
        if not args.quiet:
            for fmt in formats:
                print(f"{fmt}: written to {out_root / fmt}")
    return 0


def _multiviewx_cameras(text: str | None, formats: list[str]) -> int | None:
    """``--multiviewx-cameras``: K (1 or more) or all (None); the default, six."""
    from tools.exporters.multiviewx import MVDET_CAMERAS

    if text is None:
        return MVDET_CAMERAS
    if "multiviewx" not in formats:
        raise UserError("--multiviewx-cameras goes with --export multiviewx")
    if text == "all":
        return None
    if not text.isdigit() or int(text) < 1 or len(text) > 4:
        raise UserError(f"--multiviewx-cameras {text[:20]!r}: a number of cameras >= 1, or all")
    return int(text)


if __name__ == "__main__":
    sys.exit(main())
