"""The dataset contract: on-disk format, readers, writers and validator (no bpy, no torch).

See ``dataset_spec/SPEC.md`` for the format; ``Dataset`` is the entry point.
"""
from .dataset import Dataset
from .splits import make_splits
from .errors import SpecError
from .layout import Layout
from .labels2d import Label2D, LabelThresholds, ViewLabels
from .schema import (DEFAULT_CLASSES, SPEC_VERSION, Actor, Box3D, CameraInfo, ClassInfo, DatasetInfo, LightingVariant,
                     Scenario)

__all__ = ["Dataset", "make_splits", "SpecError", "Layout", "DEFAULT_CLASSES", "SPEC_VERSION", "Actor", "Box3D",
           "CameraInfo", "ClassInfo", "DatasetInfo", "Label2D", "LabelThresholds", "LightingVariant", "Scenario",
           "ViewLabels"]
