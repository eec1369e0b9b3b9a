"""seg-viewer: colourised segmentation PNGs, contact sheets and hover HTML pages for a dataset."""
from __future__ import annotations

import sys

from dataset_spec import Dataset
from dataset_spec.atomic import atomic_write_text
from dataset_spec.cli_support import OneLineArgumentParser, UserError, check_output_dir, cli_main
from dataset_spec.names import below

EPILOG = """examples:
  seg-viewer out/dataset
      every view: RGB | instance ids | legend (+ label boxes if labelled), one contact sheet per
      scenario and one hover page per view, under out/dataset/viewer/
  seg-viewer out/dataset --scenario toy_01 --camera cam_0 --mode overlay --scale 4
  seg-viewer out/dataset --semantic --no-html --out /tmp/seg
  seg-viewer out/dataset --sheet-only --variant dusk

Open the .html files in a browser: moving the mouse over the image shows id, name and class.
"""


def build_parser() -> OneLineArgumentParser:
    p = OneLineArgumentParser(prog="seg-viewer", description=__doc__, epilog=EPILOG)
    p.add_argument("dataset", help="dataset folder (dataset_spec layout)")
    p.add_argument("--scenario", action="append", default=None, metavar="NAME", help="repeatable; default: all")
    p.add_argument("--camera", action="append", default=None, metavar="NAME", help="repeatable; default: all")
    p.add_argument("--variant", default=None, metavar="NAME", help="lighting variant for RGB (default: the first)")
    p.add_argument("--mode", choices=("side", "overlay", "seg"), default="side",
                   help="side: RGB | ids; overlay: ids over RGB; seg: ids only (default side)")
    p.add_argument("--semantic", action="store_true", help="colour classes instead of instances")
    p.add_argument("--no-labels", action="store_true", help="do not draw stored 2D label boxes")
    p.add_argument("--scale", type=int, default=None, help="integer enlargement (default: to >= 480 px wide)")
    p.add_argument("--out", default=None, metavar="DIR", help="output folder (default: DATASET/viewer)")
    p.add_argument("--no-html", action="store_true", help="skip the hover HTML pages")
    p.add_argument("--sheet-only", action="store_true", help="only the per-scenario contact sheets")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


@cli_main
def main(argv: list[str] | None = None) -> int:
    from tools.viewer import contact_sheet, hover_page, view_image, write_png

    args = build_parser().parse_args(argv)
    if args.scale is not None and not 1 <= args.scale <= 16:
        raise UserError("--scale must be within 1..16")
    ds = Dataset.open(args.dataset)
    names = ds.select_scenarios(args.scenario)
    out = check_output_dir(args.out if args.out else ds.root / "viewer")
    chosen = {}
    for name in names:  # every option checked before anything is written
        scn = ds.scenario(name)
        if args.variant is not None and args.variant not in [v.name for v in scn.lighting]:
            raise UserError(f"--variant {args.variant!r}: scenario {name} has {[v.name for v in scn.lighting]}")
        chosen[name] = [c for c in scn.cameras if not args.camera or c.name in args.camera]
        if args.camera and not chosen[name]:
            raise UserError(f"--camera: scenario {name} has cameras {[c.name for c in scn.cameras]}")
    ds.check_segmentation_sizes(names)
    from tqdm import tqdm

    written = 0
    bar = tqdm(total=sum(1 if args.sheet_only else 1 + len(c) for c in chosen.values()), unit="picture",
               desc="seg-viewer", disable=args.quiet, file=sys.stderr)
    for name, cams in chosen.items():
        scn = ds.scenario(name)
        scale = args.scale or max(1, -(-480 // scn.cameras[0].width))
        write_png(below(out, name, "contact_sheet.png"), contact_sheet(ds, name, args.variant, scale=scale))
        written += 1
        bar.update(1)
        if args.sheet_only:
            continue
        for cam in cams:
            kind = "semantic" if args.semantic else "instance"
            img = view_image(ds, name, cam.name, args.variant, mode=args.mode, semantic=args.semantic,
                             labels=not args.no_labels, scale=scale)
            write_png(below(out, name, f"{cam.name}_{kind}_{args.mode}.png"), img)
            written += 1
            if not args.no_html:
                atomic_write_text(below(out, name, f"{cam.name}.html"), hover_page(ds, name, cam.name, args.variant))
                written += 1
            bar.update(1)
    bar.close()
    print(f"{written} files written under {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
