"""Model components, one job each: ``geometry`` (torch camera math, rays, projection), ``ray_samplers``
(where along a ray to query), ``encoder`` (ResNet features and their indexing), ``mlp`` (per-view
blocks and the combine step), ``renderer`` (per-ray aggregation), ``surface_depth`` (depth head and
cue), ``boxes`` (box IoUs in torch), ``losses`` (the YOLO loss and auxiliary terms)."""
