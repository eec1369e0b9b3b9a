"""pnyolo: the pixelNeRF-YOLO multi-view detector and the single-view baseline (no bpy; reads datasets
through dataset_spec).

The folders follow the pipeline: ``data`` (items, augmentation, YOLO grid and targets) ->
``components`` (geometry, ray samplers, encoder, MLP, renderer, losses) -> ``models`` (the registry:
``pixelnerf-yolo``, ``single-view``) -> ``engine`` (training, checkpoints) -> ``evaluation``
(decoding, metrics, fusion, reports) -> ``bench`` (the occlusion benchmark). ``config`` holds every
knob, ``cli`` the ``pnyolo-train`` / ``pnyolo-eval`` commands, ``inference`` a small Python API.
"""
