"""ground-mean: an example model kind in a package of its own (docs/guide/detector.md, "Write your own
model"). Each cell of a grid on the ground reads every camera's features at a point 1 m above it,
averages them over the cameras that see it, and a 1x1 convolution predicts CenterNet heatmaps and boxes:
a multi-view kind with 3D outputs (so it late-fuses), without an image encoder, exported to ONNX."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import torch
from torch import nn

from pnyolo.components.bev_grid import BevGrid, grid_for_cameras, pillar_points, project_pillars
from pnyolo.components.geometry import Cameras
from pnyolo.components.bev_loss import bev_loss
from pnyolo.components.bev_net import pool_views
from pnyolo.components.bev_targets import REGRESSION
from pnyolo.components.encoder import sample_bilinear
from pnyolo.decoding.world import heatmap_detections, project_into_views
from pnyolo.config.checks import Interval
from pnyolo.config.model import CentreLossConfig, ModelConfig
from pnyolo.models.base import Model, register_model
from pnyolo.onnx.convention import BEV_DECODING, BEV_OUTPUTS, BEV_POINTS

STRIDE = 4  # image pixels per feature


@dataclass
class GroundMeanConfig(ModelConfig):
    """ground-mean (an example kind): its grid and the width of its features."""

    kind: str = "ground-mean"
    cell_m: float = 0.8  # grid cell size, metres
    range_m: float = 40.0  # the grid covers the scored cameras' views out to this distance
    channels: int = 8  # features per pixel: a strided convolution of the image
    loss: CentreLossConfig = field(default_factory=CentreLossConfig)  # its heatmap and box terms' weights
    # every number a config holds is range-checked where it is loaded (keys relative to ``model.``)
    ranges: ClassVar[dict[str, Interval]] = {
        "cell_m": Interval(0.05, 5.0), "range_m": Interval(0, 1000, open_low=True), "channels": Interval(1, 1024)}


@dataclass
class GroundOutputs:
    heatmap: torch.Tensor  # (B, C, ny, nx) logits: B = 1 (every view pooled) or one per view (own view only)
    regression: torch.Tensor  # (B, 9, ny, nx): pnyolo.components.bev_targets.REGRESSION
    grid: BevGrid


@register_model("ground-mean")
class GroundMean(Model):
    description = "an example kind: every camera's features averaged on a ground grid, CenterNet heads"
    config_class = GroundMeanConfig
    world_outputs = True
    tuned = ()  # its detections are merged in the world, not by 2D NMS
    own_view_text = "each ground cell reading only that view's features"

    def __init__(self, cfg, num_classes: int):
        super().__init__(cfg, num_classes)
        c = self.config.channels
        self.features = nn.Sequential(nn.Conv2d(3, c, 2 * STRIDE - 1, STRIDE, STRIDE - 1), nn.ReLU())
        self.head = nn.Conv2d(2 * c + 1, num_classes + len(REGRESSION), 1)

    def inputs(self, item, device) -> dict:
        return {**super().inputs(item, device), "scored": item.scored}

    def grid_for(self, K, camera_to_world, width: int, height: int, scored) -> BevGrid:
        return grid_for_cameras(Cameras(K, camera_to_world, width, height), list(scored), self.config.cell_m,
                                self.config.range_m)

    def points(self, g: BevGrid) -> torch.Tensor:
        return pillar_points(g, [1.0], self.data_cfg.ground_z)

    def rig_constants(self, item) -> dict:  # what depends on the cameras only: computed once for a parked rig
        return {"ground": self.grid_for(item.K, item.camera_to_world, item.grid.width, item.grid.height, item.scored)}

    def forward(self, images, K, camera_to_world, grid, scored=None, own_view_only: bool = False, ground=None):
        V = images.shape[0]
        g = ground or self.grid_for(K, camera_to_world, grid.width, grid.height, range(V) if scored is None else scored)
        on = images.device  # every tensor made here goes where the inputs are (a CPU one fails on the GPU)
        sets = torch.eye(V, dtype=torch.bool, device=on) if own_view_only else torch.ones(1, V, dtype=torch.bool, device=on)
        heatmap, regression = self.heads(images, K, camera_to_world, self.points(g).to(on), sets, grid.width,
                                         grid.height)
        return GroundOutputs(heatmap, regression, g)

    def heads(self, images, K, camera_to_world, points, view_sets, width: int, height: int):
        V, (ny, nx) = images.shape[0], points.shape[:2]
        uv, valid = project_pillars(K, camera_to_world, points, width, height)  # (V, ny, nx, 1, ...)
        f = sample_bilinear(self.features(images), uv.reshape(V, -1, 2) / STRIDE)  # (V, C, ny * nx)
        out = self.head(pool_views(f, valid.reshape(V, -1), view_sets).reshape(len(view_sets), -1, ny, nx))
        return out[:, :self.num_classes], out[:, self.num_classes:]

    def loss(self, out, item, targets, device):
        return bev_loss(out, item, self.config.loss, 1, device)

    def world_detections(self, out, item, ev, threshold: float):
        return [heatmap_detections(out.heatmap[b], out.regression[b], out.grid, threshold, nms_m=ev.centre_nms_m)
                for b in range(out.heatmap.shape[0])]

    def decode(self, out, item, ev, conf_threshold=None):
        cars = self.world_detections(out, item, ev, ev.conf_threshold if conf_threshold is None else conf_threshold)
        if len(cars) == 1:
            return project_into_views(cars[0], item, item.scored)
        return [project_into_views(c, item, [v])[v] for v, c in enumerate(cars)]

    # ONNX: the graph takes the grid's points (the grid is chosen in Python, from the cameras)
    def graph_inputs(self, item) -> dict:
        g = self.grid_for(item.K, item.camera_to_world, item.grid.width, item.grid.height, item.scored)
        return {**super().graph_inputs(item), "points": self.points(g)}

    def export_graph(self, item, ev):
        return _Graph(self, item.grid.width, item.grid.height), {"points": {0: "ny", 1: "nx"}}

    def outputs_from_graph(self, arrays, item) -> GroundOutputs:
        g = self.grid_for(item.K, item.camera_to_world, item.grid.width, item.grid.height, item.scored)
        return GroundOutputs(arrays["heatmap"], arrays["regression"], g)

    def graph_convention(self, ev) -> dict:  # the file's metadata: how a caller decodes the outputs
        return {"outputs": BEV_OUTPUTS, "decoding": BEV_DECODING, "inputs": {"points": BEV_POINTS},
                "cell_m": self.config.cell_m, "heights": [1.0], "ground_z": self.data_cfg.ground_z,
                "conf_threshold": ev.conf_threshold, "top_k": 100, "centre_nms_m": ev.centre_nms_m}


class _Graph(nn.Module):
    def __init__(self, model: GroundMean, width: int, height: int):
        super().__init__()
        self.model, self.width, self.height = model, width, height

    def forward(self, images, K, camera_to_world, points):
        sets = torch.ones(1, images.shape[0], dtype=torch.bool, device=images.device)
        heatmap, regression = self.model.heads(images, K, camera_to_world, points, sets, self.width, self.height)
        return {"heatmap": heatmap, "regression": regression}
