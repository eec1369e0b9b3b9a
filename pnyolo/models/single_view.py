"""The single-view baseline: the same encoder and YOLO head, targets and loss, no 3D.

    model = build_model(load_config(..., ["model.kind=single-view"]), num_classes=2)
    out = model(images, K, camera_to_world, grid)     # ViewOutputs (V, S_h, S_w, A, ...), depth NaN

Each view's encoder features are indexed at its grid cell centres and a small conv head predicts
the anchors' YOLO values, so every metric and picture is shared with the multi-view model.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from pnyolo.components.backbones import make_encoder
from pnyolo.components.encoder import index_features
from pnyolo.components.geometry import grid_cell_centres
from pnyolo.components.renderer import RayOutputs
from pnyolo.config import Config
from pnyolo.config.model import ImageModelConfig
from pnyolo.data.grid import GridSpec
from pnyolo.models.base import register_model
from pnyolo.models.yolo_grid import ViewOutputs, YoloGridModel


@dataclass
class SingleViewConfig(ImageModelConfig):
    """single-view (the baseline): each view's features at its grid cells, a conv head."""

    kind: str = "single-view"


@register_model("single-view")
class SingleViewYolo(YoloGridModel):
    """Baseline: the same encoder, features indexed at each cell centre, a conv head per view.

    Outputs the same ``ViewOutputs`` (confidence = sigmoid(obj); depth is NaN: no distance
    estimate) so targets, loss, decoding and metrics are shared with the multi-view model.
    """

    description = "the baseline: each view's features at its grid cells, a conv head, no other view"
    reads_other_views = False  # each view's outputs come from its own image
    estimates_depth = False
    config_class = SingleViewConfig

    def __init__(self, cfg: Config, num_classes: int, hidden: int = 256):
        super().__init__(cfg, num_classes)
        self.encoder = make_encoder(cfg)
        self.register_buffer("anchors", torch.tensor(cfg.model.head.anchors, dtype=torch.float32))
        A = len(cfg.model.head.anchors)
        self.head = nn.Sequential(nn.Conv2d(self.encoder.latent_size, hidden, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(hidden, hidden, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(hidden, A * (5 + num_classes), 1))
        with torch.no_grad():
            last = self.head[-1]
            nn.init.normal_(last.weight, std=1e-3)
            last.bias.view(A, 5 + num_classes).zero_()
            last.bias.view(A, 5 + num_classes)[:, 0] = cfg.model.head.obj_bias_init

    def forward(self, images: Tensor, K: Tensor, camera_to_world: Tensor, grid: GridSpec,
                own_view_only: bool = False) -> ViewOutputs:
        """images (V, 3, H, W), K (V, 3, 3), camera_to_world (V, 4, 4) -> ViewOutputs (V, S_h, S_w, A, ...).
        ``own_view_only`` changes nothing: each view's outputs come from its own features anyway."""
        V = images.shape[0]
        feats = self.encoder(images)
        uv = grid_cell_centres(grid.grid_h, grid.grid_w, grid.width, grid.height, device=images.device)
        f = index_features(feats, uv.reshape(1, -1, 2).expand(V, -1, 2), self.encoder.strides)
        f = f.transpose(1, 2).reshape(V, -1, grid.grid_h, grid.grid_w)
        raw = self.head(f).permute(0, 2, 3, 1).reshape(V, grid.grid_h, grid.grid_w, len(self.anchors), -1)
        conf = torch.sigmoid(raw[..., 0])
        return RayOutputs(conf, raw[..., 1:5], raw[..., 5:], torch.full_like(conf, float("nan")))

