"""The ground-plane multi-view detector (``model.kind: bev``), after MVDet's idea: every camera's
evidence about one spot of the road meets in one grid cell.

    model = build_model(load_config(..., ["model.kind=bev"]), num_classes=2)
    out = predict_item(model, item, "cpu")          # BevOutputs: heatmaps and boxes on the item's grid
    dets = out.world_detections(0, threshold=0.3)   # 3D boxes, scores, classes (pnyolo.decoding.world)
    views = model.decode(out, item, cfg.eval)       # those boxes in every scored view, as labels are

Encoder (shared with the other models) -> each map reduced to ``model.bev.channels`` by a 1x1
convolution -> a world grid over the scored cameras' views (``pnyolo.components.bev_grid``) ->
every cell's pillar points projected into every source view, the reduced maps indexed there and
summed over the maps -> pooled over the views that see each point (mean, max, share) -> heights
stacked as channels -> the grid network -> CenterNet heads: per-class centre heatmap, centre
offset in the cell, centre height, log size, (sin, cos) of yaw. Detections are heatmap peaks, turned
into 3D boxes and projected into every scored view like the labels (``pnyolo.decoding.world``),
so every 2D metric applies unchanged; their distance comes from the 3D box.

``model.surface_depth`` (issue 87, placement): a depth head on the reduced maps, trained on the rendered depth
(``model.loss.surface_depth``), and every pillar point's place relative to the surface each view sees at its pixel
(``components.surface_depth.surface_cue``: in front, on it, behind) pooled with its features. Flat pillars give every
point along a view's ray the same features, so the grid alone cannot tell where along the ray a road user stands;
the cue can (BEVDepth's explicit depth, gathered at the pillars instead of splatted).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pnyolo.components.backbones import make_encoder
from pnyolo.components.bev_loss import bev_loss
from pnyolo.components.bev_net import BevNet, pool_views
from pnyolo.components.encoder import sample_bilinear
from pnyolo.components.geometry import project_to_views
from pnyolo.components.losses import surface_depth_loss
from pnyolo.components.surface_depth import CUE_SCALES_M, SurfaceDepthHead, surface_cue
from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt
from pnyolo.config import Config, EvalConfig
from pnyolo.config.checks import AT_LEAST_1, MAX_GRID_CELLS, Interval
from pnyolo.components.geometry import Cameras
from pnyolo.components.bev_grid import (FOOTPRINT_FAN, GRID_MULTIPLE, BevGrid, grid_for_cameras, pillar_points,
                                        project_pillars, snapped_grid)
from pnyolo.components.bev_targets import REGRESSION
from pnyolo.data.grid import GridSpec
from pnyolo.data.item import Item
from pnyolo.decoding.detections import ViewDetections, WorldDetections
from pnyolo.decoding.world import heatmap_detections, project_into_views
from pnyolo.config.model import CentreLossConfig, ImageModelConfig, check_surface_depth
from pnyolo.models.base import Model, QueryPoints, register_model
from pnyolo.onnx.convention import BEV_DECODING, BEV_GRID, BEV_OUTPUTS, BEV_POINTS, PIXELS

BASE_STRIDE = 4  # image pixels per feature of the maps the pillars read (finer maps are pooled to it)


@dataclass
class BevConfig:
    """The ground-plane grid and network (``model.bev``)."""

    cell_m: float = 0.4  # grid cell size, metres
    range_m: float = 40.0  # the grid covers each scored camera's view out to this distance (the label limit)
    bounds: list[float] | None = None  # [x_min, y_min, x_max, y_max] world metres: one fixed grid instead
    max_cells: int = 160000  # refuse grids larger than this (a wrong range or bounds, not a slow run)
    heights: list[float] = field(default_factory=lambda: [0.25, 0.75, 1.25, 1.75, 2.25])  # pillar points above ground
    channels: int = 32  # image features per view and height (a 1x1 reduction of every encoder map)
    hidden: int = 32  # width of the grid network at full resolution (twice that at half)
    dilations: list[int] = field(default_factory=lambda: [1, 2, 4])  # residual blocks at half resolution
    min_radius: int = 2  # cells: the smallest Gaussian radius of a heatmap target
    top_k: int = 100  # heatmap peaks decoded per item


@dataclass
class BevModelConfig(ImageModelConfig):
    """bev (the ground-plane model, pnyolo.models.bev): every view's features on one grid on the ground."""

    kind: str = "bev"
    bev: BevConfig = field(default_factory=BevConfig)
    loss: CentreLossConfig = field(default_factory=CentreLossConfig)  # its heatmap and box terms' weights
    # A depth map per view (trained by model.loss.surface_depth on the rendered depth) and each pillar point's place
    # relative to the surface its views see, pooled with its features (the module docstring).
    surface_depth: bool = False
    ranges: ClassVar[dict[str, Interval]] = {
        "bev.cell_m": Interval(0.05, 5.0), "bev.range_m": Interval(0, 1000, open_low=True),
        "bev.max_cells": Interval(1, MAX_GRID_CELLS), "bev.channels": AT_LEAST_1, "bev.hidden": AT_LEAST_1,
        "bev.min_radius": Interval(0, 64), "bev.top_k": Interval(1, 10000)}
    max_heights: ClassVar[int] = 64  # pillar points per cell
    runtime_keys: ClassVar[tuple[str, ...]] = (*ImageModelConfig.runtime_keys, "bev.max_cells", "bev.top_k")

    def reads_depth_maps(self) -> bool:
        return self.surface_depth

    def check(self, cfg) -> None:
        super().check(cfg)
        check_surface_depth(self.surface_depth, self.loss.surface_depth)
        b = self.bev
        if not b.heights or len(b.heights) > self.max_heights or \
                not all(isinstance(h, (int, float)) and not isinstance(h, bool) for h in b.heights):
            raise UserError(f"config model.bev.heights: 1-{self.max_heights} metres above the ground, got "
                            f"{excerpt(b.heights)}")
        if not b.dilations or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 1 for d in b.dilations):
            raise UserError(f"config model.bev.dilations: a non-empty list of integers >= 1, got {excerpt(b.dilations)}")
        if b.bounds is not None and (len(b.bounds) != 4 or not all(isinstance(v, (int, float)) for v in b.bounds)
                                     or not (b.bounds[0] < b.bounds[2] and b.bounds[1] < b.bounds[3])):
            raise UserError(f"config model.bev.bounds: [x_min, y_min, x_max, y_max] metres or null, got {excerpt(b.bounds)}")


@dataclass
class BevOutputs:
    heatmap: Tensor  # (B, C, ny, nx) logits
    regression: Tensor  # (B, 9, ny, nx) see pnyolo.components.bev_targets.REGRESSION
    grid: BevGrid
    view_sets: Tensor  # (B, V) bool: the source views each batch entry pooled
    heights: list[float]  # pillar heights above ground_z (the query points, for coverage)
    ground_z: float
    surface_depth: Tensor | None = None  # (V, H / 4, W / 4) each view's predicted depth, metres (model.surface_depth)

    def query_points(self, iy: int, ix: int) -> Tensor:
        """(H, 3) world points the model samples the views at for cell (iy, ix)."""
        return pillar_points(self.grid, self.heights, self.ground_z)[iy, ix]

    def world_detections(self, b: int, threshold: float, top_k: int = 100, nms_m: float = 0.0):
        """Batch entry ``b``'s heatmap peaks scoring at least ``threshold`` as world boxes
        (``decoding.world.heatmap_detections``)."""
        return heatmap_detections(self.heatmap[b], self.regression[b], self.grid, threshold, top_k, nms_m)


@register_model("bev")
class BevDetector(Model):
    description = "the ground-plane model: every view's features pooled in one grid on the ground"
    world_outputs = True
    config_class = BevModelConfig
    tuned = ()  # its detections are merged in the world (eval.centre_nms_m), not by 2D NMS
    own_view_text = "each view's grid pooling only that view's features, detections projected into that view only"
    coverage_text = "the pillar points of the grid cell holding each road user's centre"
    coverage_targets = {"near_pixels": 0.9, "in_box": 0.9}
    parameter_keys = {"anchors": "model.head.anchors", "reduce": "model.bev.channels", "net": "model.bev",
                      "surface_head": "model.surface_depth"}

    def __init__(self, cfg: Config, num_classes: int):
        super().__init__(cfg, num_classes)
        b = cfg.model.bev
        self.encoder = make_encoder(cfg)
        # Every encoder map reduced to b.channels by a 1x1 convolution; maps finer than BASE_STRIDE
        # average-pooled to it first (3x3, stride 2: output j centred on input 2j, so feature
        # centres stay on pixel stride * j); maps of one stride are summed and indexed once.
        self.reduce = nn.ModuleList(nn.Conv2d(c, b.channels, 1, bias=k == 0) for k, c in enumerate(self.encoder.channels))
        self.map_strides = sorted({max(s, BASE_STRIDE) for s in self.encoder.strides})
        self.surface_head = SurfaceDepthHead(b.channels) if cfg.model.surface_depth else None
        cue = len(CUE_SCALES_M) if self.surface_head is not None else 0
        per_height = 2 * (b.channels + cue) + 1
        self.net = BevNet(per_height * len(b.heights), b.hidden, b.dilations, num_classes + len(REGRESSION))
        with torch.no_grad():
            self.net.head.bias[:num_classes] = cfg.model.head.obj_bias_init
            self.net.head.bias[num_classes + 2] = 0.8  # centre height of a road user, roughly
        # YOLO anchors: unused by this model, kept so every model answers the same attributes
        self.register_buffer("anchors", torch.tensor(cfg.model.head.anchors, dtype=torch.float32))

    # -- the interface ----------------------------------------------------------------------------
    def inputs(self, item: Item, device) -> dict:
        """Also the views whose sight the grid covers (``Item.grid_views``), and whether the item is mirrored
        (a fixed ``model.bev.bounds`` grid is mirrored with it)."""
        return {**super().inputs(item, device), "scored": item.grid_views, "mirrored": item.mirrored}

    def loss(self, out: "BevOutputs", item: Item, targets, device):
        """CenterNet's terms (``bev_loss``) and, with a depth head, the surface-depth term against the rendered depth."""
        loss, terms = bev_loss(out, item, self.config.loss, self.config.bev.min_radius, device)
        if out.surface_depth is None:
            return loss, terms
        extra = self.config.loss.surface_depth * surface_depth_loss(out.surface_depth, item.surface_depth.to(device),
                                                                    BASE_STRIDE)
        return loss + extra, {**terms, "surface_depth": float(extra.detach())}

    def world_detections(self, out: "BevOutputs", item: Item, ev: EvalConfig, threshold: float) -> list[WorldDetections]:
        return [out.world_detections(b, threshold, self.config.bev.top_k, ev.centre_nms_m)
                for b in range(out.view_sets.shape[0])]

    def decode(self, out: "BevOutputs", item: Item, ev: EvalConfig,
               conf_threshold: float | None = None) -> list[ViewDetections]:
        """Pooled over every source view and projected into every scored view, or (one batch entry
        per view, ``own_view_only``) each view's own, projected into it."""
        threshold = ev.conf_threshold if conf_threshold is None else conf_threshold
        cars = self.world_detections(out, item, ev, threshold)
        if len(cars) == 1:
            return project_into_views(cars[0], item, item.scored)
        return [project_into_views(c, item, [b])[b] for b, c in enumerate(cars)]

    def coverage_points(self, out: "BevOutputs", item: Item) -> QueryPoints:
        """The pillar of the grid cell holding each road user's centre."""
        boxes = item.boxes_3d

        def pillar(v: int, j: int, row: int) -> np.ndarray:
            iy, ix = out.grid.cell_of(boxes[row, :2])
            if not bool(out.grid.inside(iy, ix)):
                return np.zeros((0, 3))
            return out.query_points(int(iy), int(ix)).numpy().astype(np.float64)
        return pillar

    def image_maps(self, images: Tensor) -> dict[int, Tensor]:
        """images (V, 3, H, W) -> {stride: (V, channels, H / stride, W / stride)}, strides >= BASE_STRIDE."""
        maps: dict[int, Tensor] = {}
        for reduce, f, stride in zip(self.reduce, self.encoder(images), self.encoder.strides):
            while stride < BASE_STRIDE:
                f, stride = F.avg_pool2d(f, 3, 2, 1, count_include_pad=False), stride * 2
            f = reduce(f)
            maps[stride] = maps[stride] + f if stride in maps else f
        return maps

    def grid_for(self, K: Tensor, camera_to_world: Tensor, width: int, height: int, scored: list[int],
                 mirrored: bool = False) -> BevGrid:
        """The grid over the ``scored`` views' sight, or the fixed ``model.bev.bounds`` (mirrored in x = 0
        with a mirrored item, whose cameras see the mirrored world: ``data.hflip``)."""
        b, views = self.config.bev, Cameras(K, camera_to_world, width, height)
        if b.bounds is None or not mirrored:
            return grid_for_cameras(views, scored, b.cell_m, b.range_m, b.bounds, b.max_cells)
        x_min, y_min, x_max, y_max = b.bounds  # the mirrored cameras must see the mirrored bounds
        grid_for_cameras(views, scored, b.cell_m, b.range_m, [-x_max, y_min, -x_min, y_max])
        return snapped_grid(b.bounds, b.cell_m, b.max_cells).mirrored()

    def check_data(self, ds) -> None:
        """Before any work: the grid's one-line error (bounds over no camera, too many cells) for the
        first ``data.num_views`` cameras of each of ``ds``'s scenarios (a MultiViewDataset)."""
        for s in ds.scenarios:
            g = ds.grid(s)
            cams = ds.ds.scenario(s).cameras[: self.data_cfg.num_views]
            K = torch.stack([torch.tensor(c.resized(g.width, g.height).K, dtype=torch.float32) for c in cams])
            c2w = torch.stack([torch.tensor(c.camera_to_world, dtype=torch.float32) for c in cams])
            self.grid_for(K, c2w, g.width, g.height, list(range(len(cams))))

    def forward(self, images: Tensor, K: Tensor, camera_to_world: Tensor, grid: GridSpec, **options) -> BevOutputs:
        """images (V, 3, H, W), K (V, 3, 3), camera_to_world (V, 4, 4) -> BevOutputs with one batch entry pooling
        every view, or with ``own_view_only`` one per view, each alone; ``options``: ``BevOptions``."""
        opts = BevOptions(**options)
        V = images.shape[0]
        b = self.config.bev
        g = opts.bev_grid or self.grid_for(K, camera_to_world, grid.width, grid.height,
                                           list(range(V)) if opts.scored is None else list(opts.scored), opts.mirrored)
        points = pillar_points(g, b.heights, self.data_cfg.ground_z, device=images.device)
        eye = torch.eye(V, dtype=torch.bool, device=images.device)
        view_sets = eye if opts.own_view_only else torch.ones(1, V, dtype=torch.bool, device=images.device)
        heatmap, regression, depth = self.heads(images, K, camera_to_world, points, view_sets, grid.width, grid.height,
                                                opts.projection)
        return BevOutputs(heatmap, regression, g, view_sets, list(b.heights), self.data_cfg.ground_z, depth)

    def rig_constants(self, item: Item) -> dict:
        """The grid over the item's scored cameras and its pillars' pixels in every view."""
        g = self.grid_for(item.K, item.camera_to_world, item.grid.width, item.grid.height, item.grid_views,
                          item.mirrored)
        points = pillar_points(g, self.config.bev.heights, self.data_cfg.ground_z)
        return {"bev_grid": g, "projection": project_pillars(item.K, item.camera_to_world, points, item.grid.width,
                                                             item.grid.height)}

    def graph_inputs(self, item: Item) -> dict[str, Tensor]:
        """The views and the pillar points of the grid over the item's scored cameras (chosen here)."""
        g = self.grid_for(item.K, item.camera_to_world, item.grid.width, item.grid.height, item.grid_views,
                          item.mirrored)
        points = pillar_points(g, self.config.bev.heights, self.data_cfg.ground_z)
        return {**super().graph_inputs(item), "points": points}

    def export_graph(self, item: Item, ev: EvalConfig) -> tuple[nn.Module, dict[str, dict[int, str]]]:
        return _BevGraph(self, item.grid.width, item.grid.height), {"points": {0: "ny", 1: "nx"}}

    def graph_convention(self, ev: EvalConfig) -> dict:
        b = self.config.bev
        return {"outputs": BEV_OUTPUTS, "decoding": BEV_DECODING, "inputs": {"points": BEV_POINTS},
                "cell_m": b.cell_m, "heights": list(b.heights), "ground_z": self.data_cfg.ground_z,
                "conf_threshold": ev.conf_threshold, "top_k": b.top_k, "centre_nms_m": ev.centre_nms_m,
                "grid": {"rule": BEV_GRID, "range_m": b.range_m, "fan": FOOTPRINT_FAN, "multiple": GRID_MULTIPLE,
                         "bounds": None if b.bounds is None else list(b.bounds)}, "pixels": PIXELS}

    def outputs_from_graph(self, arrays: dict[str, Tensor], item: Item) -> BevOutputs:
        b = self.config.bev
        g = self.grid_for(item.K, item.camera_to_world, item.grid.width, item.grid.height, item.grid_views,
                          item.mirrored)
        return BevOutputs(arrays["heatmap"], arrays["regression"], g, torch.ones(1, len(item.images), dtype=torch.bool),
                          list(b.heights), self.data_cfg.ground_z)

    def heads(self, images: Tensor, K: Tensor, camera_to_world: Tensor, points: Tensor, view_sets: Tensor,
              width: int, height: int, projection: tuple | None = None) -> tuple[Tensor, Tensor, Tensor | None]:
        """The heatmap (B, C, ny, nx), regression (B, 9, ny, nx) and, with a depth head, each view's depth map from
        the views and the grid's pillar points (ny, nx, H, 3): all of forward but choosing the grid (the part an
        ONNX graph holds); ``projection``: the points' (uv, valid) in the views, when known."""
        V = images.shape[0]
        ny, nx, H = points.shape[:3]
        maps = self.image_maps(images)
        uv, valid = projection or project_pillars(K, camera_to_world, points, width, height)  # (V, ny, nx, H, ...)
        N = ny * nx * H
        f, depth = self.point_features(maps, K, camera_to_world, points.reshape(N, 3), uv.reshape(V, N, 2))
        pooled = pool_views(f, valid.reshape(V, N), view_sets)  # (B, 2C + 1, N)
        B = pooled.shape[0]
        x = pooled.reshape(B, -1, ny, nx, H).permute(0, 1, 4, 2, 3).reshape(B, -1, ny, nx)
        out = self.net(x)
        C = self.num_classes
        return out[:, :C], out[:, C:], depth

    def point_features(self, maps: dict[int, Tensor], K: Tensor, camera_to_world: Tensor, points: Tensor, uv: Tensor
                       ) -> tuple[Tensor, Tensor | None]:
        """Each view's features at world points (N, 3) seen at pixels uv (V, N, 2): (V, channels, N), with a depth head
        the points' surface cue appended (V, channels + cue, N), and the depth maps (V, h, w) or None."""
        f = sum(sample_maps(m, uv, s) for s, m in maps.items())
        if self.surface_head is None:
            return f, None
        depth = self.surface_head([self.joined_map(maps)])  # (V, h, w) at BASE_STRIDE
        z = project_to_views(K, camera_to_world, points, 1, 1)[2]  # planar depth (the image size does not enter)
        seen = sample_maps(depth.detach()[:, None], uv, BASE_STRIDE)[:, 0]  # the surface each view sees there
        return torch.cat([f, surface_cue(z, seen).permute(0, 2, 1)], dim=1), depth

    @staticmethod
    def joined_map(maps: dict[int, Tensor]) -> Tensor:
        """The reduced maps of every stride read at the finest map's feature centres (BASE_STRIDE; feature j of a
        map of stride s centred on pixel s * j) and summed: (V, channels, h, w)."""
        fine = min(maps)
        V, C, h, w = maps[fine].shape
        on = maps[fine]
        y, x = torch.meshgrid(torch.arange(h, device=on.device, dtype=on.dtype),
                              torch.arange(w, device=on.device, dtype=on.dtype), indexing="ij")
        pixels = (torch.stack([x, y], dim=-1).reshape(1, h * w, 2) * fine).expand(V, h * w, 2)
        return sum(m if s == fine else sample_maps(m, pixels, s).reshape(V, C, h, w) for s, m in maps.items())


@dataclass(frozen=True)
class BevOptions:
    """What one forward of the ground-plane model does (``forward``'s keywords): ``scored``, the views whose sight
    the grid covers (default all); ``bev_grid``, a given grid; ``mirrored``, the views show the mirrored world (a
    fixed grid is mirrored too); ``projection``, the pillars' pixels in each view for this grid (``rig_constants``);
    ``return_samples`` changes nothing: the query points are the grid's pillars (``BevOutputs``)."""

    own_view_only: bool = False
    scored: list[int] | None = None
    bev_grid: BevGrid | None = None
    return_samples: bool = False
    mirrored: bool = False
    projection: tuple | None = None


def sample_maps(fmap: Tensor, uv: Tensor, stride: int) -> Tensor:
    """Bilinear features of a map (V, C, h, w) of ``stride`` at pixels uv (V, N, 2) -> (V, C, N)
    (feature j centred on pixel stride * j, as ``encoder.index_features``; border-padded)."""
    return sample_bilinear(fmap, uv / stride)



class _BevGraph(nn.Module):
    """The ground-plane model's heads for one image size, every view pooled: (images, K,
    camera_to_world, points) -> heatmap and regression; the grid's size follows ``points``."""

    def __init__(self, model: BevDetector, width: int, height: int):
        super().__init__()
        self.model, self.width, self.height = model, width, height

    def forward(self, images: Tensor, K: Tensor, camera_to_world: Tensor, points: Tensor) -> dict[str, Tensor]:
        view_sets = torch.ones(1, images.shape[0], dtype=torch.bool, device=images.device)
        heatmap, regression, _ = self.model.heads(images, K, camera_to_world, points, view_sets, self.width, self.height)
        return {"heatmap": heatmap, "regression": regression}
