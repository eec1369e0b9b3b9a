"""Data for the detectors: ``dataset`` (items of source views from a dataset_spec folder), ``augment``
(training augmentation that keeps the geometry exact), ``grid`` (the encoded image and its YOLO grid),
``targets`` (YOLO targets and their decoding), ``anchors`` (anchors fitted to the labels)."""
