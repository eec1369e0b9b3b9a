"""pnyolo: the detectors of occluded road users (no bpy; reads datasets through dataset_spec): three kinds,
``pixelnerf-yolo`` (the paper's multi-view model), ``single-view`` (the one-camera baseline) and ``bev`` (every
camera's features on one ground-plane grid, also run per car with late fusion), and any kind another package
registers.

The folders follow the pipeline: ``data`` (items, augmentation, YOLO grid and targets) -> ``components``
(geometry, ray samplers, encoder, MLP, renderer, ground grid, losses) -> ``models`` (the registry of kinds) ->
``engine`` (training, checkpoints, the one place a trained model predicts) -> ``decoding`` (boxes, NMS, world
detections) -> ``evaluation`` (metrics, fusion, reports) -> ``cooperation`` (late fusion, pose noise) ->
``tracking`` -> ``bench`` (the occlusion benchmark). ``config`` holds every knob, ``cli`` the ``pnyolo-*``
commands, ``onnx`` the export, ``inference`` a small Python API.
"""
