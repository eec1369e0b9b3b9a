"""Evaluation: ``postprocess`` (decode, threshold, NMS via ``nms``), ``metrics`` (strict and paper
counting, AP, recall by visibility), ``fusion`` (union of two detectors), ``evaluate`` (running models
over a split), ``report`` (markdown, JSON, plots), ``pictures`` (example detections as PNG)."""
