"""Detector models: the registry (``build_model``) and the registered kinds.

``pixelnerf-yolo`` (the paper, ``pixelnerf_yolo``), ``single-view`` (the baseline,
``single_view``) and ``bev`` (the ground-plane model, ``bev``). Importing this package registers them.
"""
from pnyolo.models import bev, pixelnerf_yolo, single_view  # noqa: F401  (registers the kinds)
from pnyolo.models.registry import (MODEL_REGISTRY, ViewOutputs, build_model, make_encoder, predict_item,
                                    register_model, use_eval_stats)

__all__ = ["MODEL_REGISTRY", "ViewOutputs", "build_model", "make_encoder", "predict_item", "register_model",
           "use_eval_stats"]
