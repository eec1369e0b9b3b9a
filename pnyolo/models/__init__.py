"""Detector models: the interface and registry (``base``) and the registered kinds.

``pixelnerf-yolo`` (the paper, ``pixelnerf_yolo``), ``single-view`` (the baseline, ``single_view``),
both on each view's YOLO grid (``yolo_grid``), and ``bev`` (the ground-plane model, ``bev``).
Importing this package registers them (``pnyolo.registry`` does so on first use; kinds of other
installed packages come through the entry-point group ``pnyolo.models``).
"""
from pnyolo.models import bev, pixelnerf_yolo, single_view  # noqa: F401  (registers the kinds)
from pnyolo.models.base import (Decoding, Model, build_model, eval_stats, model_device, predict_item, rig_constants_on_device,
                                use_eval_stats)
from pnyolo.registry import kinds, model_class, register_model

__all__ = ["Decoding", "Model", "build_model", "eval_stats", "kinds", "model_class", "model_device", "predict_item", "register_model",
           "rig_constants_on_device", "use_eval_stats"]
