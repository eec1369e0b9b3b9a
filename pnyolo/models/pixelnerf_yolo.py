"""pixelNeRF-YOLO (the paper): encoder -> rays through each grid cell of each encoded view -> samples ->
projection into all source views -> feature indexing -> MLP -> renderer.

    model = build_model(cfg, num_classes=2)                     # cfg.model.kind == "pixelnerf-yolo"
    out = model(images, K, camera_to_world, grid)               # images (V, 3, H, W), K (V, 3, 3), c2w (V, 4, 4)
    out.ray_confidence.shape                                    # (V, S_h, S_w, A)

Beyond the paper, each off by default (``configs/paper.yaml`` keeps the paper's model):

* ``model.sampler.cell_rays``: k x k rays through each cell, aggregated together as one thick ray;
* ``model.sampler.fine_samples``: hierarchical sampling, fine samples where the coarse confidence is
  (the MLP is told each sample's bin half-width: a coarse sample stands for its bin);
* ``model.sampler.footprint``: what a coarse sample reads, its point, its frustum segment's footprint
  (``pnyolo.components.footprints``) or where along its segment the views agree
  (``pnyolo.components.segment_evidence``);
* ``model.loss.state`` (on): each anchor's 3D state, so a detection is a world box
  (``pnyolo.components.view_state``) and the kind has 3D detections like bev (``world_detections``: late
  fusion's messages, the tracker, DetectionEval on the results and the ground plane read them);
* ``eval.depth_peaks``: up to k candidates per ray and anchor at confidence peaks along the ray;
* ``model.surface_depth``: a depth head on the encoder's last maps, and where each (sample, view)
  lies relative to the surface that view sees (``pnyolo.components.surface_depth``);
* with ``return_samples`` the outputs keep every rendered sample (``RayOutputs.samples``) for the
  per-sample 3D loss (``pnyolo.components.occupancy``) and the sampling coverage.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import numpy as np
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from pnyolo.components.backbones import make_encoder
from pnyolo.components.encoder import index_features
from pnyolo.components.geometry import Cameras, invert_rigid
from pnyolo.components.losses import surface_depth_loss
from pnyolo.components.mlp import YoloMLP
from pnyolo.components.occupancy import OccupancyLoss
from pnyolo.components.ray_bundles import CoarseSamples, RayBundle, ViewBundle
from pnyolo.components.ray_attention import RayTransformer
from pnyolo.components.footprints import Segments, index_footprints, segment_footprints
from pnyolo.components.segment_evidence import read_segments
from pnyolo.components.frustums import Frustums
from pnyolo.components.ray_samplers import (bin_samples, cell_ray_pixels, cell_spread, fine_weights, ray_interval,
                                            sample_from_weights)
from pnyolo.components.renderer import RayOutputs, SampleOutputs, YoloRayRenderer
from pnyolo.components.surface_depth import CUE_SCALES_M, SurfaceDepthHead, surface_cue
from pnyolo.components.view_state import STATE, view_state_loss
from pnyolo.config import Config, EvalConfig, TrainConfig
from pnyolo.data.grid import GridSpec
from pnyolo.data.item import Item
from pnyolo.data.targets import target_cell, unseen_elsewhere_cells
from pnyolo.components.ray_selection import ignore_unrendered, own_view_dropout_mask, training_ray_mask
from pnyolo.models.base import QueryPoints, register_model
from pnyolo.models.pixelnerf_yolo_config import PixelNeRFYoloConfig
from pnyolo.models.yolo_grid import ViewOutputs, YoloGridModel

HALF_WIDTH_SCALE_M = 4.0  # the MLP's bin half-width input is metres / this
AGREEMENT_SCALE = 4.0  # the MLP's segment-agreement input is segment_evidence's agreement / this


@register_model("pixelnerf-yolo")
class PixelNeRFYolo(YoloGridModel):
    """The multi-view detector: (V source views) -> ViewOutputs on each view's YOLO grid."""

    description = "the paper's model: rays through each view's grid cells, samples read every source view"
    renders_rays = True  # training may render a subset of the grid rays (pnyolo.components.ray_selection)
    world_outputs = True  # its detections are world boxes (a built model without the 3D state says False)
    config_class = PixelNeRFYoloConfig
    tuned = ("nms_iou", "depth_gap", "depth_peaks")
    own_view_text = ("each view's rays sampling only that view's image features (the views are still encoded "
                     "together)")
    coverage_text = "the query points of the cell each road user's target is assigned to"
    coverage_targets = {"on_pixels": 0.5, "near_pixels": 0.9, "in_box": 0.9, "segment_in_box": 0.9}
    parameter_keys = {**YoloGridModel.parameter_keys, "surface_head": "model.surface_depth",
                      "renderer": "model.aggregator"}

    def __init__(self, cfg: Config, num_classes: int):
        super().__init__(cfg, num_classes)
        self.encoder = make_encoder(cfg)
        self.register_buffer("anchors", torch.tensor(cfg.model.head.anchors, dtype=torch.float32))
        self.surface_head = None
        # The head reads the encoder's last layer and its context maps (one resolution).
        self.surface_maps = slice(self.encoder.num_layers - 1, None)
        self.surface_stride = self.encoder.strides[-1]  # the depth map has the last maps' resolution
        if cfg.model.surface_depth:
            self.surface_head = SurfaceDepthHead(sum(self.encoder.channels[self.surface_maps]))
        self.cue_size = len(CUE_SCALES_M) if self.surface_head is not None else 0
        self.hierarchical = cfg.model.sampler.fine_samples > 0
        self.sub_rays = cfg.model.sampler.cell_rays ** 2  # rays per cell, rendered as one thick ray
        self.reads = 2 if cfg.model.sampler.footprint == "both" else 1  # feature sets a sample reads per view
        self.evidence = cfg.model.sampler.footprint == "evidence"  # where along its segment the views agree
        self.state = len(STATE) if cfg.model.loss.state > 0 else 0  # each anchor's 3D state (raw's last channels)
        self.world_outputs = self.state > 0  # type: ignore[misc] - a model trained without the state places no box
        A = len(cfg.model.head.anchors)
        self.mlp = YoloMLP((self.encoder.latent_size + self.cue_size) * self.reads, A, num_classes, cfg.model.mlp,
                           cfg.model.head.obj_bias_init, d_point=int(self.hierarchical) + 2 * self.evidence,
                           state=self.state)
        agg = cfg.model.aggregator
        self.renderer = YoloRayRenderer(attention=None if agg.kind == "weighted_mean" else RayTransformer(
            A, A * (5 + num_classes + self.state), agg.width, agg.layers, agg.heads), state=self.state)

    # -- the interface's kind-specific parts ------------------------------------------------------
    def render_chunks(self, num_views: int, cells: int) -> int:
        return -(-cells // self.rays_per_chunk(num_views))

    def eval_options(self, ev: EvalConfig) -> dict:
        """Evaluation renders up to ``eval.depth_peaks`` confidence peaks per ray, ``eval.peak_gap`` apart."""
        return {"depth_peaks": ev.depth_peaks, "peak_gap": ev.peak_gap}

    def training_options(self, item: Item, targets: Tensor, train: TrainConfig) -> tuple[dict, Tensor]:
        """With ``train.background_rays`` < 1 a step renders the target cells, their neighbours and that
        share of the background, the other cells ignored by the loss; with ``train.own_view_dropout`` >
        0 that share of the rendered rays goes without its own view's features
        (pnyolo.components.ray_selection); with ``model.loss.occupancy`` the samples are kept for its terms."""
        mask = None
        if train.background_rays < 1:
            mask = training_ray_mask(targets, train.background_rays)
            targets = ignore_unrendered(targets, mask)
        drop = None
        if train.own_view_dropout > 0:
            unseen = torch.stack([unseen_elsewhere_cells(gt, item.grid) for gt in item.gt])
            drop = own_view_dropout_mask(unseen, train.own_view_dropout, mask)
        options = {"ray_mask": mask, "drop_own_view": drop, "return_samples": self.config.loss.occupancy > 0}
        return options, targets

    def loss(self, out: ViewOutputs, item: Item, targets: Tensor, device) -> tuple[Tensor, dict[str, float]]:
        """The YOLO loss; with ``model.loss.state`` the 3D state's terms (pnyolo.components.view_state); with
        ``model.loss.occupancy`` the per-sample 3D terms of the rendered samples (``out.samples``,
        pnyolo.components.occupancy); with a depth head (``out.surface_depth``) the surface-depth term against
        ``item.surface_depth``."""
        loss, terms = super().loss(out, item, targets, device)
        weights = self.config.loss
        if self.state:
            extra, more = view_state_loss(out.state, targets.to(device), item.boxes_3d,
                                          item.camera_to_world[:, :3, 3].to(device))
            loss, terms = loss + weights.state * extra, {**terms, **{k: weights.state * v for k, v in more.items()}}
        if out.samples is not None and weights.occupancy > 0:
            extra, more = OccupancyLoss(weights.occupancy)(out.samples, targets, item.boxes_3d, self.anchors)
            loss, terms = loss + extra, {**terms, **more}
        if out.surface_depth is not None:  # (config validation: model.surface_depth needs model.loss.surface_depth > 0)
            extra = weights.surface_depth * surface_depth_loss(out.surface_depth, item.surface_depth.to(device),
                                                               self.surface_stride)
            loss, terms = loss + extra, {**terms, "surface_depth": float(extra.detach())}
        return loss, terms

    def coverage_points(self, out: ViewOutputs, item: Item) -> QueryPoints | None:
        """Every sample of the rays of the cell whose target slot holds the road user (its centre's
        cell if it lost its slot): the points that cell queried (``out`` from ``return_samples``)."""
        if out.samples is None:
            return None
        g, targets, smp = item.grid, self.targets(item), out.samples
        valid = smp.valid.detach().cpu().numpy()
        ray_cell = smp.cell.detach().cpu().numpy()
        numpy = lambda x: x.detach().cpu().numpy().astype("float64")  # noqa: E731
        fr = smp.frustums
        origins, dirs, t, half = numpy(fr.origins), numpy(fr.dirs), numpy(fr.t), numpy(fr.half)
        lateral = None if fr.lateral is None else numpy(fr.lateral)

        def cell_rays(v: int, j: int, row: int) -> Segments:
            cell = target_cell(targets[v], row, item.gt[v].boxes[j], g)
            rays = ray_cell == v * g.grid_h * g.grid_w + cell
            keep = valid[rays]  # (rays of the cell, S): each a bin (a fine sample: a point) or a frustum segment
            each = lambda a: a[rays][keep]  # noqa: E731
            count = keep.sum(axis=1)
            return Segments(np.repeat(origins[rays], count, 0), np.repeat(dirs[rays], count, 0), each(t), each(half),
                            None if lateral is None else each(lateral))
        return cell_rays

    # -- memory budget ---------------------------------------------------------------------------
    def rays_per_chunk(self, num_views: int) -> int:
        """Rays whose activations fit ``chunk_memory_mb`` (rough, float32, forward + grads)."""
        m, s = self.config.mlp, self.config.sampler
        per_sample_view = ((self.encoder.latent_size + self.cue_size) * 2 * self.reads + self.mlp.pe.d_out + 8
                           + m.hidden * (1 + 4 * m.combine_layer)
                           + (self.encoder.latent_size * 2 * s.evidence_points if self.evidence else 0))
        per_sample = num_views * per_sample_view + m.hidden * 4 * (m.num_blocks - m.combine_layer) + 64
        per_ray = (s.num_samples + s.fine_samples) * per_sample * 4 * 2 * self.sub_rays
        return max(1, int(self.config.chunk_memory_mb * 2**20 // per_ray))  # cells (thick rays) per chunk

    # -- components ------------------------------------------------------------------------------
    def generate_rays(self, K: Tensor, camera_to_world: Tensor, grid: GridSpec) -> tuple[Tensor, Tensor]:
        """The rays of every view's cells -> origins, dirs (V * S_h * S_w * k, 3), each cell's k rays
        (``cell_rays`` squared, through a sub-grid of the cell; one: its centre) consecutive."""
        uv = cell_ray_pixels(grid.grid_h, grid.grid_w, grid.width, grid.height, self.config.sampler.cell_rays,
                             device=K.device)
        o, d = Cameras(K, camera_to_world, grid.width, grid.height).pixel_rays(uv)
        return o.reshape(-1, 3), d.reshape(-1, 3)

    def sample(self, origins: Tensor, dirs: Tensor) -> CoarseSamples:
        """Rays (R, 3) -> coarse samples: distances t (R, S), valid (R, S) bool, and each ray's interval
        t_near, t_far (R,) (``model.sampler``): S equal bins, one sample in each (jittered in training)."""
        s, slab = self.config.sampler, (self.data_cfg.ground_z, self.config.sampler.height_cap)
        t_near, t_far, ok = ray_interval(origins, dirs, s.near, s.far, slab if s.slab_clip else None)
        t = bin_samples(t_near, t_far, s.num_samples, stratified=s.stratified and self.training)
        return CoarseSamples(t, ok[:, None].expand_as(t), t_near, t_far)

    def query(self, frustums: Frustums, rays: RayBundle, views: ViewBundle,
              sub: int = 1) -> tuple[Tensor, Tensor | None]:
        """The MLP at the samples ``frustums`` (n, S) of ``rays`` (n) reading ``views`` -> raw (n, S, A, 5 + C + state)
        and, with ``model.sampler.footprint`` evidence, where in each segment the views agree (n, S, ``sub``; else
        None). Each sample's half-length along its ray is an MLP input with hierarchical sampling; with a lateral
        extent the sample reads each map's maximum over its frustum segment's footprint (footprint frustum; with
        ``both`` beside the features at its centre; no extent: the features at its centre); with evidence, each view's
        features where the views agree among ``sub`` sub-points of its segment, the place and agreement as inputs."""
        points, half_width, lateral = frustums.points(), frustums.half, frustums.lateral
        n, S = points.shape[:2]
        K, camera_to_world, surface = views.K, views.camera_to_world, views.surface
        cams = Cameras(K, camera_to_world, views.width, views.height)
        uv, x_view, _, valid = cams.project(points)
        V = K.shape[0]
        w2c_rot = invert_rigid(camera_to_world)[:, :3, :3]  # (V, 3, 3)
        d_view = torch.einsum("vij,nj->vni", w2c_rot, rays.dirs)[:, :, None].expand(V, n, S, 3)
        # The depth map is indexed like one more feature map; detached, it is a measurement for the
        # MLP: detection losses do not reshape the depth head through it.
        maps = list(views.feats) if surface is None else [*views.feats, surface.detach()[:, None]]
        strides = self.encoder.strides if surface is None else [*self.encoder.strides, self.surface_stride]
        extra, where = [], None
        own = torch.arange(V, device=rays.view.device)[:, None] == rays.view[None, :]  # (V, n) each ray's target view
        if self.evidence:  # the agreement of the source views other than the ray's own
            ev, valid = read_segments(frustums, cams, maps, strides, sub, own)
            f, where = ev.features, ev.weights.reshape(n, S, sub)
            extra = [ev.offset[:, None], ev.agreement[:, None] / AGREEMENT_SCALE]
        elif lateral is None:
            f = index_features(maps, uv.reshape(V, n * S, 2), strides)
        else:  # every point of the segment's sphere projects inside its footprint, where it reads
            half, front = segment_footprints(x_view.reshape(V, n * S, 3), frustums.radius().reshape(-1), K[:, 0, 0],
                                             K[:, 1, 1])
            f = index_footprints(maps, uv.reshape(V, n * S, 2), half, strides, self.config.sampler.footprint_levels)
            if self.reads == 2:  # where the point is, and what its segment covers
                f = torch.cat([index_features(maps, uv.reshape(V, n * S, 2), strides), f], dim=-1)
            valid = valid & front.reshape(V, n, S)
        if surface is not None:
            f = torch.cat([f[..., :-1], surface_cue(x_view.reshape(V, n * S, 3)[..., 2], f[..., -1])], dim=-1)
        is_target = own[:, :, None]
        # A withheld view counts as not seeing the point: its features are zeroed and its valid flag
        # says so; the point's position in that view's camera (the box's frame) stays an input.
        valid = valid & ~(is_target & rays.drop_own[None, :, None])
        point = [half_width.reshape(n * S, 1) / HALF_WIDTH_SCALE_M] if self.hierarchical else []
        point = torch.cat(point + extra, dim=-1) if point + extra else None
        raw = self.mlp(x_view.reshape(V, n * S, 3), d_view.reshape(V, n * S, 3), valid.reshape(V, n * S), f,
                       is_target.expand(V, n, S).reshape(V, n * S), point)
        return raw.reshape(n, S, *raw.shape[1:]), where

    def render_chunk(self, rays: RayBundle, coarse: CoarseSamples, views: ViewBundle,
                     peaks: tuple[int, float]) -> RayOutputs:
        """Rays (n), a whole number of cells' ``cell_rays``^2 consecutive rays, with their coarse samples ->
        the cells' values, their peaks' (``peaks``: how many and how far apart, metres; more than one outside
        training) and every sample (``RayOutputs.samples``: t, half-width, valid, raw per ray)."""
        s, t, sample_valid = self.config.sampler, coarse.t, coarse.valid
        half = ((coarse.t_far - coarse.t_near) / (2 * s.num_samples))[:, None].expand_as(t)
        footprint = s.footprint in ("frustum", "both")
        lateral = rays.spread[:, None] * (t + half) if footprint else None  # at the bin's far end
        frustums = Frustums(rays.origins, rays.dirs, t, half, lateral)
        raw, where = self.query(frustums, rays, views, s.evidence_points)
        if self.hierarchical:
            with torch.no_grad():  # where the coarse samples say an object is: the sampling, not a gradient
                weights = fine_weights(torch.sigmoid(raw[..., 0]), s.fine_weights) * sample_valid
                if where is not None:  # each bin's weight spread over its equal parts by where the views agree
                    weights = (weights[..., None] * where).reshape(len(weights), -1)
                t_fine = sample_from_weights(coarse.t_near, coarse.t_far, weights, s.fine_samples,
                                             stratified=self.training)
            zero = torch.zeros_like(t_fine)  # fine samples are points along the ray
            fine = Frustums(rays.origins, rays.dirs, t_fine, zero, zero if lateral is not None else None)
            raw_fine, _ = self.query(replace(fine, lateral=zero if self.reads == 2 else None), rays, views)
            frustums, raw = frustums.then(fine), torch.cat([raw, raw_fine], dim=1)
            sample_valid = torch.cat([sample_valid, sample_valid[:, :1].expand_as(t_fine)], dim=1)
        t = frustums.t
        k, n, S = self.sub_rays, t.shape[0], t.shape[1]  # a cell's rays are one thick ray to the renderer
        out = self.renderer(raw.reshape(n // k, k * S, *raw.shape[2:]), t.reshape(n // k, k * S),
                            sample_valid.reshape(n // k, k * S), peaks=1 if self.training else peaks[0], gap=peaks[1])
        out.samples = SampleOutputs(frustums, sample_valid, raw[..., :raw.shape[-1] - self.state], rays.cell)
        return out

    def forward(self, images: Tensor, K: Tensor, camera_to_world: Tensor, grid: GridSpec, **options) -> ViewOutputs:
        """images (V, 3, H, W) in [0, 1], K (V, 3, 3), camera_to_world (V, 4, 4) of the encoded images,
        ``grid`` their size and YOLO grid -> ViewOutputs (V, S_h, S_w, A, ...); ``options``: ``RenderOptions``."""
        opts = RenderOptions(**options)
        feats = self.encoder(images)
        surface = None if self.surface_head is None else self.surface_head(feats[self.surface_maps])
        out = self._render_views(ViewBundle(K, camera_to_world, grid.width, grid.height, feats, surface), grid, opts)
        out.surface_depth = surface
        return out

    def _render_views(self, views: ViewBundle, grid: GridSpec, opts: RenderOptions) -> ViewOutputs:
        K, V, k = views.K, len(views), self.sub_rays
        cells = grid.grid_h * grid.grid_w
        origins, dirs = self.generate_rays(K, views.camera_to_world, grid)
        cell = torch.arange(V * cells, device=K.device).repeat_interleave(k)  # each ray's cell
        drop = torch.zeros(len(cell), dtype=torch.bool, device=K.device) if opts.drop_own_view is None else \
            opts.drop_own_view.reshape(-1).to(K.device).repeat_interleave(k)
        spread = cell_spread(K, grid, self.config.sampler.cell_rays)[cell // cells]  # each ray's cell half-width
        rays = RayBundle(origins, dirs, cell // cells, cell, drop, spread)
        if opts.own_view_only:
            if opts.ray_mask is not None or opts.drop_own_view is not None:
                raise ValueError("own_view_only renders every ray with its own view (no ray_mask, no drop_own_view)")
            n = cells * k
            out = RayOutputs.cat([self.render_rays(replace(rays[v * n:(v + 1) * n], view=rays.view.new_zeros(n)),
                                                   views.select(v), opts) for v in range(V)])
            return out.reshape(V, grid.grid_h, grid.grid_w)
        keep = None
        if opts.ray_mask is not None:
            keep = opts.ray_mask.reshape(-1).to(K.device).nonzero().squeeze(1)  # the cells to render
            rays = rays[(keep[:, None] * k + torch.arange(k, device=K.device)).reshape(-1)]
        out = self.render_rays(rays, views, opts)
        if keep is not None:
            out = out.scatter(keep, V * cells)
        return out.reshape(V, grid.grid_h, grid.grid_w)

    def render_rays(self, rays: RayBundle, views: ViewBundle, opts: RenderOptions) -> RayOutputs:
        """``rays`` (R), ``cell_rays``^2 consecutive per cell, each sampling ``views``, rendered in chunks of
        ``opts.chunk_rays`` cells (default: as many as ``model.chunk_memory_mb`` holds) -> RayOutputs with one
        entry per cell (R / cell_rays^2), their samples kept with ``opts.return_samples``."""
        coarse = self.sample(rays.origins, rays.dirs)
        R, k = len(rays), self.sub_rays
        chunk = (opts.chunk_rays or self.rays_per_chunk(len(views))) * k
        # One chunk holds everything: checkpointing would only add a second forward pass.
        use_ckpt = self.config.checkpointing and torch.is_grad_enabled() and chunk < R
        peaks, parts = (opts.depth_peaks, opts.peak_gap), []
        for a in range(0, max(R, 1), chunk):  # an empty selection still gives (empty) outputs
            args = (rays[a:a + chunk], coarse[a:a + chunk], views, peaks)
            out = checkpoint(self.render_chunk, *args, use_reentrant=False) if use_ckpt else self.render_chunk(*args)
            parts.append(out if opts.return_samples else replace(out, samples=None))
        return RayOutputs.cat(parts)


@dataclass(frozen=True)
class RenderOptions:
    """What one forward renders (``forward``'s keywords).

    ``ray_mask`` (V, S_h, S_w) bool: render only these cells' rays (the rest come back as confidence 0, see
    ``RayOutputs.scatter``); None renders all. ``own_view_only``: an ablation for evaluation; the views are
    encoded together as usual, but each view's rays sample only that view's features, as if the other source
    views were not there: what they add. ``drop_own_view`` (V, S_h, S_w) bool: these cells' rays do not see
    their own (target) view's image features, only the other source views' (``train.own_view_dropout``).
    ``return_samples``: keep every rendered sample in ``out.samples``. ``chunk_rays``: cells rendered at once
    (default: as many as ``model.chunk_memory_mb`` holds). ``depth_peaks`` (evaluation): up to that many
    confidence peaks per ray and anchor, ``peak_gap`` metres apart (``eval_options``)."""

    chunk_rays: int | None = None
    ray_mask: Tensor | None = None
    own_view_only: bool = False
    drop_own_view: Tensor | None = None
    return_samples: bool = False
    depth_peaks: int = 1
    peak_gap: float = 2.0
