"""Detector models: the interface and registry (``base``) and the registered kinds.

``pixelnerf-yolo`` (the paper, ``pixelnerf_yolo``), ``single-view`` (the baseline, ``single_view``),
both on each view's YOLO grid (``yolo_grid``), and ``bev`` (the ground-plane model, ``bev``).
Importing this package registers them.
"""
from pnyolo.models import bev, pixelnerf_yolo, single_view  # noqa: F401  (registers the kinds)
from pnyolo.models.base import (MODEL_REGISTRY, Model, build_model, model_class, predict_item, register_model,
                                use_eval_stats)

__all__ = ["MODEL_REGISTRY", "Model", "build_model", "model_class", "predict_item", "register_model",
           "use_eval_stats"]
