"""Exporters of labelled datasets to other tools' formats, one module per format.

Every exporter has the signature ``export_X(ds, out_dir, scenarios=None, thresholds=None,
variant=None) -> Path`` and reads the labels written by ``tools.projection`` (labels.json).
``thresholds=None`` keeps what the stored thresholds accept; ``variant`` picks the lighting
variant whose RGB images are exported (None: each scenario's first, ``"all"``: every one; the
MultiviewX layout: every one). A sequence exports every frame: one image per frame (YOLO, COCO with its
video fields, KITTI, pixelNeRF), one sequence per camera (MOTChallenge), its frames as the frames
(MultiviewX, one folder per lighting variant), a sample per frame of a scene per lighting variant (nuScenes).
"""
from __future__ import annotations

from .coco import export_coco
from .kitti import export_kitti
from .mot import export_mot
from .multiviewx import export_multiviewx
from .nuscenes import export_nuscenes
from .pixelnerf import export_pixelnerf
from .yolo import export_yolo

EXPORTERS = {"yolo": export_yolo, "coco": export_coco, "kitti": export_kitti, "pixelnerf": export_pixelnerf,
             "multiviewx": export_multiviewx, "mot": export_mot, "nuscenes": export_nuscenes}

__all__ = ["EXPORTERS", "export_coco", "export_kitti", "export_mot", "export_multiviewx", "export_nuscenes",
           "export_pixelnerf", "export_yolo"]
