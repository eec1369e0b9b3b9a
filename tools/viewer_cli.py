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
  seg-viewer out/seq --scenario intersection_07 --frame 12     a sequence at frame 12
  seg-viewer out/seq --frame all --no-html                      every frame; and per camera of a sequence
      <camera>_strip.png (every frame, labelled, with its time) and <camera>_strip.gif (the frames animated)
  seg-viewer out/seq --frame all --sheet-only --max-gb 8        a long sequence: more than the default 2 GB of pixels

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
    p.add_argument("--frame", default="0", metavar="N|all",
                   help="the frame of a sequence to show, or 'all' (default 0; names end in _fNNNN for sequences)")
    p.add_argument("--max-gb", type=float, default=2.0, metavar="GB",
                   help="refuse before writing when the pictures would hold more than this many GB of pixels "
                        "(PNG stores them in about a quarter of that; default 2)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _frames(args, ds: Dataset, names: list[str]) -> dict[str, list[int]]:
    """The frames ``--frame`` asks for, per scenario (a one-line error for a frame a scenario lacks)."""
    if args.frame == "all":
        return {n: ds.frames(n) for n in names}
    if not (args.frame.isascii() and args.frame.isdigit()):  # '²' is a digit to str.isdigit, not to int()
        raise UserError(f"--frame must be a frame index or 'all', got {args.frame!r}")
    frame = int(args.frame)
    for n in names:
        if frame >= ds.scenario(n).frames:
            raise UserError(f"--frame {frame}: scenario {n} has frames 0..{ds.scenario(n).frames - 1}")
    return {n: [frame] for n in names}


def _check_size(args, ds: Dataset, chosen: dict, frames: dict) -> None:
    """One line, before anything is written, when the pictures asked for would hold more than ``--max-gb``."""
    from tools.viewer import picture_pixels

    if not args.max_gb > 0:
        raise UserError(f"--max-gb must be > 0, got {args.max_gb}")
    total = 0
    for name, cams in chosen.items():
        scale = args.scale or max(1, -(-480 // ds.scenario(name).cameras[0].width))
        per_frame = picture_pixels(ds, name, [], scale, args.mode, sheet=True)
        if not args.sheet_only:  # each camera's pictures from its own size (a rig may mix sizes)
            per_frame += picture_pixels(ds, name, cams, scale, args.mode, sheet=False)
        total += 3 * per_frame * len(frames[name])
    if total > args.max_gb * 1e9:
        raise UserError(f"these pictures would hold {total / 1e9:.1f} GB of pixels (about {total / 4e9:.1f} GB of PNG), "
                        f"above --max-gb {args.max_gb:g}: choose fewer frames, scenarios or cameras, or raise --max-gb")


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
    frames = _frames(args, ds, names)
    _check_size(args, ds, chosen, frames)
    ds.check_segmentation_sizes(names)
    from tqdm import tqdm

    written = 0
    bar = tqdm(total=sum(len(frames[n]) * (1 if args.sheet_only else 1 + len(c)) for n, c in chosen.items()),
               unit="picture", desc="seg-viewer", disable=args.quiet, file=sys.stderr)
    for name, cams in chosen.items():
        scale = args.scale or max(1, -(-480 // ds.scenario(name).cameras[0].width))
        for frame in frames[name]:
            tag = f"_f{frame:04d}" if ds.scenario(name).frames > 1 else ""
            write_png(below(out, name, f"contact_sheet{tag}.png"), contact_sheet(ds, name, args.variant, scale, frame))
            written += 1
            bar.update(1)
            if args.sheet_only:
                continue
            for cam in cams:
                kind = "semantic" if args.semantic else "instance"
                img = view_image(ds, name, cam.name, args.variant, mode=args.mode, semantic=args.semantic,
                                 labels=not args.no_labels, scale=scale, frame=frame)
                write_png(below(out, name, f"{cam.name}_{kind}_{args.mode}{tag}.png"), img)
                written += 1
                if not args.no_html:
                    atomic_write_text(below(out, name, f"{cam.name}{tag}.html"),
                                      hover_page(ds, name, cam.name, args.variant, frame=frame))
                    written += 1
                bar.update(1)
        written += _strips(ds, name, cams, args.variant, out) if ds.scenario(name).frames > 1 else 0
    bar.close()
    print(f"{written} files written under {out}")
    return 0


def _strips(ds: Dataset, name: str, cams, variant: str | None, out) -> int:
    """Each camera of a sequence over time: ``<camera>_strip.png`` (a contact sheet of the frames) and
    ``<camera>_strip.gif`` (the frames animated at the sequence's rate); returns the files written."""
    from tools.viewer import time_strip, write_gif, write_png

    scn = ds.scenario(name)
    for cam in cams:
        sheet, frames = time_strip(ds, name, cam.name, variant)
        write_png(below(out, name, f"{cam.name}_strip.png"), sheet)
        # a strip of fewer frames than the sequence plays them at the pace of the whole
        write_gif(below(out, name, f"{cam.name}_strip.gif"), frames, (scn.fps or 1) * len(frames) / scn.frames)
    return 2 * len(cams)


if __name__ == "__main__":
    sys.exit(main())
