"""pixelNeRF-YOLO (the paper): encoder -> one ray per grid cell of each encoded view -> samples ->
projection into all source views -> feature indexing -> MLP -> renderer.

    model = build_model(cfg, num_classes=2)                     # cfg.model.kind == "pixelnerf-yolo"
    out = model(images, K, camera_to_world, grid)               # images (V, 3, H, W), K (V, 3, 3), c2w (V, 4, 4)
    out.ray_confidence.shape                                    # (V, S_h, S_w, A)

With ``model.surface_depth`` a head on the encoder's last maps also predicts each view's planar
depth, and each (sample, view) pair learns where the sample lies relative to the surface that
view sees (``pnyolo.components.surface_depth``).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from pnyolo.components.encoder import index_features
from pnyolo.components.geometry import grid_cell_centres, invert_rigid, pixel_rays, project_to_views
from pnyolo.components.mlp import YoloMLP
from pnyolo.components.ray_samplers import sample_along_rays
from pnyolo.components.renderer import RayOutputs, YoloRayRenderer
from pnyolo.components.surface_depth import CUE_SCALES_M, SurfaceDepthHead, surface_cue
from pnyolo.config import Config
from pnyolo.data.grid import GridSpec
from pnyolo.models.registry import ViewOutputs, make_encoder, register_model


class PixelNeRFYolo(nn.Module):
    """The multi-view detector: (V source views) -> ViewOutputs on each view's YOLO grid."""

    def __init__(self, cfg: Config, num_classes: int):
        super().__init__()
        self.cfg = cfg
        self.num_classes = num_classes
        self.encoder = make_encoder(cfg)
        self.register_buffer("anchors", torch.tensor(cfg.model.head.anchors, dtype=torch.float32))
        self.surface_head = None
        # The head reads the encoder's last layer and its context maps (one resolution).
        self.surface_maps = slice(self.encoder.num_layers - 1, None)
        if cfg.model.surface_depth:
            self.surface_head = SurfaceDepthHead(sum(self.encoder.channels[self.surface_maps]))
        self.cue_size = len(CUE_SCALES_M) if self.surface_head is not None else 0
        self.mlp = YoloMLP(self.encoder.latent_size + self.cue_size, len(cfg.model.head.anchors), num_classes,
                           cfg.model.mlp, cfg.model.head.obj_bias_init)
        self.renderer = YoloRayRenderer()

    # -- memory budget ---------------------------------------------------------------------------
    def rays_per_chunk(self, num_views: int) -> int:
        """Rays whose activations fit ``chunk_memory_mb`` (rough, float32, forward + grads)."""
        m, s = self.cfg.model.mlp, self.cfg.model.sampler.num_samples
        per_sample_view = ((self.encoder.latent_size + self.cue_size) * 2 + self.mlp.pe.d_out + 8
                           + m.hidden * (1 + 4 * m.combine_layer))
        per_sample = num_views * per_sample_view + m.hidden * 4 * (m.num_blocks - m.combine_layer) + 64
        per_ray = s * per_sample * 4 * 2
        return max(1, int(self.cfg.model.chunk_memory_mb * 2**20 // per_ray))

    # -- components ------------------------------------------------------------------------------
    def generate_rays(self, K: Tensor, camera_to_world: Tensor, grid: GridSpec) -> tuple[Tensor, Tensor]:
        """One ray per grid cell centre of every view -> origins, dirs (V * S_h * S_w, 3)."""
        uv = grid_cell_centres(grid.grid_h, grid.grid_w, grid.width, grid.height, device=K.device)
        o, d = zip(*(pixel_rays(K[v], camera_to_world[v], uv) for v in range(K.shape[0])))
        return torch.stack(o).reshape(-1, 3), torch.stack(d).reshape(-1, 3)

    def sample(self, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        """Rays (R, 3) -> sample distances t (R, S) and valid (R, S) bool (``model.sampler``)."""
        s = self.cfg.model.sampler
        slab = (s.ground_z, s.height_cap) if s.slab_clip else None
        return sample_along_rays(origins, dirs, s.num_samples, s.near, s.far,
                                 stratified=s.stratified and self.training, slab=slab)

    def render_chunk(self, origins: Tensor, dirs: Tensor, t: Tensor, sample_valid: Tensor, ray_view: Tensor,
                     drop_own: Tensor, K: Tensor, camera_to_world: Tensor, width: int, height: int,
                     surface: Tensor | None, *feats: Tensor) -> tuple[Tensor, ...]:
        """Rays (n, 3) with samples t (n, S), each ray's target view index (n,) and whether its target
        view's image features are withheld (n,) bool -> (conf, box, cls, depth). ``surface``: the
        views' predicted depth maps (V, H_f, W_f) with model.surface_depth, else None."""
        n, S = t.shape
        points = origins[:, None] + t[..., None] * dirs[:, None]  # (n, S, 3)
        uv, x_view, _, valid = project_to_views(K, camera_to_world, points, width, height)
        V = K.shape[0]
        w2c_rot = invert_rigid(camera_to_world)[:, :3, :3]  # (V, 3, 3)
        d_view = torch.einsum("vij,nj->vni", w2c_rot, dirs)[:, :, None].expand(V, n, S, 3)
        # The depth map is indexed like one more feature map; detached, it is a measurement for the
        # MLP: detection losses do not reshape the depth head through it.
        maps = list(feats) if surface is None else [*feats, surface.detach()[:, None]]
        f = index_features(maps, uv.reshape(V, n * S, 2), width, height)
        if surface is not None:
            f = torch.cat([f[..., :-1], surface_cue(x_view.reshape(V, n * S, 3)[..., 2], f[..., -1])], dim=-1)
        is_target = (torch.arange(V, device=ray_view.device)[:, None] == ray_view[None, :])[:, :, None]
        # A withheld view counts as not seeing the point: its features are zeroed and its valid flag
        # says so; the point's position in that view's camera (the box's frame) stays an input.
        valid = valid & ~(is_target & drop_own[None, :, None])
        raw = self.mlp(x_view.reshape(V, n * S, 3), d_view.reshape(V, n * S, 3), valid.reshape(V, n * S), f,
                       is_target.expand(V, n, S).reshape(V, n * S))
        out = self.renderer(raw.reshape(n, S, *raw.shape[1:]), t, sample_valid)
        return out.ray_confidence, out.box, out.class_logits, out.depth

    renders_rays = True  # training may render a subset of the grid rays (pnyolo.engine.ray_selection)

    def forward(self, images: Tensor, K: Tensor, camera_to_world: Tensor, grid: GridSpec,
                chunk_rays: int | None = None, ray_mask: Tensor | None = None,
                own_view_only: bool = False, drop_own_view: Tensor | None = None) -> ViewOutputs:
        """images (V, 3, H, W) in [0, 1], K (V, 3, 3), camera_to_world (V, 4, 4) of the encoded images,
        ``grid`` their size and YOLO grid -> ViewOutputs (V, S_h, S_w, A, ...).
        ``ray_mask`` (V, S_h, S_w) bool: render only these cells' rays (the rest come back as
        confidence 0, see ``RayOutputs.scatter``); None renders all. ``own_view_only``: an ablation
        for evaluation; the views are encoded together as usual, but each view's rays sample only
        that view's features, as if the other source views were not there: what they add.
        ``drop_own_view`` (V, S_h, S_w) bool: these cells' rays do not see their own (target) view's
        image features, only the other source views' (training's ``train.own_view_dropout``)."""
        feats = self.encoder(images)
        surface = None if self.surface_head is None else self.surface_head(feats[self.surface_maps])
        out = self._render_views(feats, surface, K, camera_to_world, grid, chunk_rays, ray_mask, own_view_only,
                                 drop_own_view)
        out.surface_depth = surface
        return out

    def _render_views(self, feats: list[Tensor], surface: Tensor | None, K: Tensor, camera_to_world: Tensor,
                      grid: GridSpec, chunk_rays: int | None, ray_mask: Tensor | None, own_view_only: bool,
                      drop_own_view: Tensor | None) -> ViewOutputs:
        V = K.shape[0]
        origins, dirs = self.generate_rays(K, camera_to_world, grid)
        ray_view = torch.arange(V, device=K.device).repeat_interleave(grid.grid_h * grid.grid_w)
        if own_view_only:
            if ray_mask is not None or drop_own_view is not None:
                raise ValueError("own_view_only renders every ray with its own view (no ray_mask, no drop_own_view)")
            n = grid.grid_h * grid.grid_w
            out = RayOutputs.cat([self.render_rays(origins[v * n:(v + 1) * n], dirs[v * n:(v + 1) * n],
                                                   ray_view.new_zeros(n), K[v:v + 1], camera_to_world[v:v + 1], grid,
                                                   [f[v:v + 1] for f in feats], chunk_rays,
                                                   surface=None if surface is None else surface[v:v + 1])
                                   for v in range(V)])
            return out.reshape(V, grid.grid_h, grid.grid_w)
        total = origins.shape[0]
        drop = None if drop_own_view is None else drop_own_view.reshape(-1).to(K.device)
        keep = None
        if ray_mask is not None:
            keep = ray_mask.reshape(-1).to(K.device).nonzero().squeeze(1)
            origins, dirs, ray_view = origins[keep], dirs[keep], ray_view[keep]
            drop = None if drop is None else drop[keep]
        out = self.render_rays(origins, dirs, ray_view, K, camera_to_world, grid, feats, chunk_rays, drop, surface)
        if keep is not None:
            out = out.scatter(keep, total)
        return out.reshape(V, grid.grid_h, grid.grid_w)

    def render_rays(self, origins: Tensor, dirs: Tensor, ray_view: Tensor, K: Tensor, camera_to_world: Tensor,
                    grid: GridSpec, feats: list[Tensor], chunk_rays: int | None = None,
                    drop_own: Tensor | None = None, surface: Tensor | None = None) -> RayOutputs:
        """Rays (R, 3), each with its target view's index into ``K`` / ``camera_to_world`` / ``feats``
        (the source views the rays sample), rendered in chunks -> RayOutputs with R rays. ``drop_own``
        (R,) bool: the rays whose target view's image features are withheld (None: none).
        ``surface``: the views' predicted depth maps (model.surface_depth; None without)."""
        t, sample_valid = self.sample(origins, dirs)
        R = origins.shape[0]
        if drop_own is None:
            drop_own = torch.zeros(R, dtype=torch.bool, device=origins.device)
        chunk = chunk_rays or self.rays_per_chunk(K.shape[0])
        # One chunk holds everything: checkpointing would only add a second forward pass.
        use_ckpt = self.cfg.model.checkpointing and torch.is_grad_enabled() and chunk < R
        parts = []
        for a in range(0, max(R, 1), chunk):  # an empty selection still gives (empty) outputs
            args = (origins[a:a + chunk], dirs[a:a + chunk], t[a:a + chunk], sample_valid[a:a + chunk],
                    ray_view[a:a + chunk], drop_own[a:a + chunk], K, camera_to_world, grid.width, grid.height, surface,
                    *feats)
            res = checkpoint(self.render_chunk, *args, use_reentrant=False) if use_ckpt else self.render_chunk(*args)
            parts.append(RayOutputs(*res))
        return RayOutputs.cat(parts)


@register_model("pixelnerf-yolo")
def _build_pixelnerf_yolo(cfg: Config, num_classes: int) -> nn.Module:
    return PixelNeRFYolo(cfg, num_classes)

