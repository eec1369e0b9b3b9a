"""From model outputs to detections, below the models that call it: the result types
(``detections``), NMS (``nms``), a YOLO grid's decoding (``yolo``) and 3D boxes in and out of camera
views (``world``)."""
