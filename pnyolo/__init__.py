"""pnyolo: the pixelNeRF-YOLO multi-view detector (no bpy; reads datasets through dataset_spec).

Components (one job each): ``geometry`` (torch camera math, rays, samplers, projection),
``encoder`` (ResNet-18/34, torchvision names), ``mlp`` (per-view blocks, swappable combine),
``renderer`` (max confidence, confidence-weighted values and depth), ``targets``/``loss`` (YOLO),
``boxes_torch``/``nms``/``postprocess`` (decoding), ``metrics`` (strict and paper counting, AP,
recall by visibility). Composition: ``model`` (registry: ``pixelnerf-yolo``, ``single-view``),
``data``, ``train``, ``evaluate``, ``inference``, ``cli`` (``pnyolo-train``, ``pnyolo-eval``).
"""
