"""MOTChallenge ground truth, one sequence per camera, in the layout TrackEval's MOTChallenge reader expects
by default (benchmark ``OCC``, one split folder per dataset split), for trackers and the tools that score
them (``motmetrics``, TrackEval)::

    OUT/seqmaps/OCC-<split>.txt                                        'name', then the split's sequences
    OUT/OCC-<split>/<scenario>__<camera>[__<variant>]/seqinfo.ini      name, imDir, frameRate, seqLength, ...
    OUT/OCC-<split>/<scenario>__<camera>[__<variant>]/img1/000001.png  the frames, numbered from 1
    OUT/OCC-<split>/<scenario>__<camera>[__<variant>]/gt/gt.txt        frame, id, bb_left, bb_top, bb_width,
                                                                       bb_height, conf, class, visibility

One row per labelled road user per frame (MOT17's columns). ``id`` is the actor id, the track id of the
sequence; boxes are the amodal label boxes in MOT's 1-based pixels (the image's first pixel covers
[1, 2), so MOT = COCO + 1: ``bb_left`` 1 for a box at the left edge); ``conf`` 1 for ground truth and 0 for
a road user the label thresholds left out (MOT's "ignore"); ``class`` MOT17's numbers: 1 pedestrian, 3 car
(another class its dataset id plus 100); ``visibility`` the visible fraction (-1 where it was not
measured). A scenario of one frame is a sequence of one frame.

    folder = export_mot(ds, "out/exports/mot")
    rows = read_mot_gt(folder / "OCC-train/toy__cam_a/gt/gt.txt")     # (N, 9) float
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dataset_spec import Dataset, LabelThresholds
from dataset_spec.atomic import atomic_write_text
from dataset_spec.names import below

from .coco import coco_bbox
from .common import copy_file, export_views, sequence_names

MOT_CLASSES = {"pedestrian": 1, "car": 3}
BENCHMARK = "OCC"  # TrackEval's --BENCHMARK: the split folders are OCC-<split>, the seqmaps OCC-<split>.txt


def mot_class(ds: Dataset, cls: str) -> int:
    return MOT_CLASSES.get(cls, 100 + ds.info.class_id(cls))


def _row(ds: Dataset, frame: int, label, conf: int) -> str:
    left, top, width, height = coco_bbox(label.box)  # pixel (0, 0) covers [0, 1): MOT's covers [1, 2)
    vis = -1.0 if label.visible_fraction is None else label.visible_fraction
    return (f"{frame + 1},{label.instance_id},{left + 1:.2f},{top + 1:.2f},{width:.2f},{height:.2f},{conf},"
            f"{mot_class(ds, label.cls)},{vis:.4f}\n")


def export_mot(ds: Dataset, out_dir: str | Path, scenarios: list[str] | None = None,
               thresholds: LabelThresholds | None = None, variant: str | None = None) -> Path:
    """Write one MOTChallenge sequence per (scenario, camera[, variant]) under ``out_dir``; returns ``out_dir``."""
    out = Path(out_dir)
    sequences: dict[tuple[str, str], dict] = {}
    names = sequence_names(ds, scenarios if scenarios is not None else ds.scenario_names(), variant)
    for view in export_views(ds, scenarios, thresholds, variant):
        name = names[view.scenario, view.camera.name, view.variant]
        seq = sequences.setdefault((view.split, name), {"rows": [], "frames": 0, "view": view})
        folder = below(out, f"{BENCHMARK}-{view.split}", name)
        copy_file(view.image_path, folder / "img1" / f"{view.frame + 1:06d}.png")
        seq["rows"] += [_row(ds, view.frame, o, 1) for o in view.labels]
        seq["rows"] += [_row(ds, view.frame, o, 0) for o in view.ignored]
        seq["frames"] = max(seq["frames"], view.frame + 1)
    for (split, name), seq in sequences.items():
        folder = below(out, f"{BENCHMARK}-{split}", name)
        view = seq["view"]
        fps = ds.scenario(view.scenario).fps or 1
        atomic_write_text(folder / "gt" / "gt.txt", "".join(sorted(seq["rows"], key=_order)))
        atomic_write_text(folder / "seqinfo.ini", (
            f"[Sequence]\nname={name}\nimDir=img1\nframeRate={fps:g}\nseqLength={seq['frames']}\n"
            f"imWidth={view.camera.width}\nimHeight={view.camera.height}\nimExt=.png\n"))
    for split in sorted({split for split, _ in sequences}):
        names = sorted(name for s, name in sequences if s == split)
        atomic_write_text(below(out, "seqmaps", f"{BENCHMARK}-{split}.txt"), "name\n" + "".join(f"{n}\n" for n in names))
    return out


def _order(row: str) -> tuple[int, int]:
    frame, track = row.split(",", 2)[:2]
    return int(frame), int(track)


def read_mot_gt(path: str | Path) -> np.ndarray:
    """(N, 9) rows of a MOTChallenge ``gt.txt`` (frame, id, left, top, width, height, conf, class, visibility)."""
    text = Path(path).read_text(encoding="utf-8").strip()
    return np.array([[float(v) for v in line.split(",")] for line in text.splitlines()]).reshape(-1, 9)
