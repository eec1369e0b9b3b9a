"""What every exporter shares: which views and images to export, under which split, with which labels.

Usage::

    for view in export_views(ds, scenarios=None, thresholds=None, variant=None):
        view.image_path, view.stem, view.split, view.labels   # labels: kept Label2D list
        view.ignored     # the labels the thresholds left out: road users to mark as ignore regions

A label the thresholds reject (too truncated, too far, too small, or more hidden than
``min_visible``) is a real road user, not background: formats that have ignore regions get it as
one (KITTI ``DontCare``, COCO ``iscrowd: 1``); YOLO and the pixelNeRF layout have none and leave it out.
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from dataset_spec import CameraInfo, Dataset, Label2D, LabelThresholds
from dataset_spec.schema import SPLIT_NAMES
from dataset_spec.atomic import atomic_path
from dataset_spec.cli_support import UserError
from dataset_spec.names import JoinedNames

UNSPLIT = "unsplit"  # scenarios that are in no split of dataset.json


@dataclass
class ExportView:
    """One exported image: a camera of a scenario at one frame under one lighting variant."""

    scenario: str
    camera: CameraInfo
    camera_index: int  # position of the camera in the scenario
    variant: str
    split: str  # train / val / test, or UNSPLIT
    stem: str  # unique file stem: <scenario>__<camera>[__<variant>]
    image_path: Path  # the dataset's RGB PNG
    labels: list[Label2D]  # labels kept by the thresholds
    ignored: list[Label2D]  # labels of detectable classes the thresholds left out (ignore regions)
    frame: int = 0  # the frame of a sequence (its camera is where it is at this frame)


def scenario_splits(ds: Dataset) -> dict[str, str]:
    """Each scenario in a split -> that split, read once through ``Dataset.split`` (broken splits are refused); a
    scenario in none is UNSPLIT (``.get(name, UNSPLIT)``)."""
    return {name: split for split in SPLIT_NAMES for name in ds.split(split)}


def export_variants(ds: Dataset, scenario: str, variant: str | None) -> list[str]:
    """Lighting variants to export: the first (None), all ('all'), or the named one."""
    names = [v.name for v in ds.scenario(scenario).lighting]
    if not names:
        raise UserError(f"scenario {scenario} has no lighting variants, so no RGB images to export")
    if variant is None:
        return names[:1]
    if variant == "all":
        return names
    if variant not in names:
        raise UserError(f"scenario {scenario} has no lighting variant {variant!r} (has: {', '.join(names)})")
    return [variant]


def export_views(ds: Dataset, scenarios: list[str] | None = None, thresholds: LabelThresholds | None = None,
                 variant: str | None = None):
    """Yield an ``ExportView`` per (scenario, frame, camera, variant), labels read from labels.json.

    ``thresholds`` None keeps the labels the stored thresholds accept. A sequence's stems end in the
    frame (``__f0003``); a scenario of one frame keeps the stems it always had.
    """
    names = scenarios if scenarios is not None else ds.scenario_names()
    stems = export_stems(ds, names, variant)  # every file name checked before the first is written
    detectable, split_of = set(ds.info.detectable_classes), scenario_splits(ds)
    for scenario in names:
        split = split_of.get(scenario, UNSPLIT)
        variants = export_variants(ds, scenario, variant)
        for frame in ds.frames(scenario):
            scn = ds.scenario_at(scenario, frame)
            for index, cam in enumerate(scn.cameras):
                labels = ds.read_labels(scenario, cam.name, frame)
                kept = labels.kept(thresholds)
                ignored = [o for o in labels.left_out(thresholds) if o.cls in detectable]
                for var in variants:
                    yield ExportView(scenario, cam, index, var, split, stems[scenario, cam.name, frame, var],
                                     ds.layout.rgb(scenario, cam.name, var, frame), kept, ignored, frame)


def export_stems(ds: Dataset, scenarios: list[str], variant: str | None) -> dict[tuple, str]:
    """The file stem of every (scenario, camera, frame, variant) an export writes: ``SCENARIO__CAMERA``, then
    ``__fFRAME`` for a sequence and ``__VARIANT`` when every variant is exported; checked together for collisions
    and length (``JoinedNames``) before anything is written."""
    joined, stems = JoinedNames("export file name", suffix=".json"), {}
    for scenario in scenarios:
        sequence = ds.scenario(scenario).frames > 1
        for frame in ds.frames(scenario):
            for cam in ds.scenario_at(scenario, frame).cameras:
                for var in export_variants(ds, scenario, variant):
                    parts = (scenario, cam.name, *([f"f{frame:04d}"] if sequence else []),
                             *([var] if variant == "all" else []))
                    stems[scenario, cam.name, frame, var] = joined(*parts)
    return stems


def sequence_names(ds: Dataset, scenarios: list[str], variant: str | None) -> dict[tuple[str, str, str], str]:
    """The name of every (scenario, camera, variant) sequence an export writes (MOTChallenge folders, CocoVID videos):
    ``SCENARIO__CAMERA`` and ``__VARIANT`` when every variant is exported, made from those parts and checked
    together (``JoinedNames``) after that last step, never cut out of a file stem."""
    joined, out = JoinedNames("sequence name"), {}
    for scenario in scenarios:
        for cam in ds.scenario(scenario).cameras:
            for var in export_variants(ds, scenario, variant):
                out[scenario, cam.name, var] = joined(scenario, cam.name, *([var] if variant == "all" else []))
    return out


def class_index(ds: Dataset) -> dict[str, int]:
    """Detector class index of each detectable class name (position in ``detectable_classes``)."""
    return {name: i for i, name in enumerate(ds.info.detectable_classes)}


def check_images(ds: Dataset, scenarios: list[str] | None = None, variant: str | None = None) -> int:
    """Decode every RGB image an export would copy (SpecError naming the first that is missing,
    corrupt or of the wrong size), so no export holds an image that does not read back; returns
    how many were checked."""
    views = [(scenario, cam.name, var, frame) for scenario in (scenarios if scenarios is not None else ds.scenario_names())
             for var in export_variants(ds, scenario, variant) for frame in ds.frames(scenario)
             for cam in ds.scenario(scenario).cameras]
    for view in views:
        ds.read_rgb(*view)
    return len(views)


def copy_file(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst`` atomically (the destination folder is created)."""
    if not src.is_file():
        raise UserError(f"{src}: image is missing (render the view before exporting)")
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)
