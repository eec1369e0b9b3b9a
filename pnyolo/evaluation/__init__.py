"""Scoring what the models predicted (``pnyolo.engine.predict``): ``evaluate`` (a model's predictions, or a
comparison of models and what is made of them, scored item by item), ``matching`` and ``metrics`` (strict and
paper counting, AP, recall by visibility), ``metrics_3d``, ``metrics_bins``, ``nuscenes_metrics`` and
``devkit_eval`` (the 3D figures, the nuScenes devkit's own), ``ground_moda`` (the field's ground-plane MODA),
``coverage`` (where the samples lie), ``fusion`` (two detectors' union), ``predictions`` and
``nuscenes_results`` (other detectors' result files), ``bootstrap`` (standard errors), and the pictures and
reports (``pictures``, ``top_down``, ``report``)."""
