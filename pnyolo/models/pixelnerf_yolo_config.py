"""pixelnerf-yolo's ``model`` section (``PixelNeRFYoloConfig``, its model class's ``config_class``): the ray
sampler, the MLP and the aggregation along a ray (each its component's config), the memory budget, with
their ranges and relations."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from dataset_spec.cli_support import UserError
from dataset_spec.names import excerpt
from pnyolo.components.mlp import MLPConfig
from pnyolo.components.ray_attention import AggregatorConfig
from pnyolo.components.ray_samplers import SamplerConfig
from pnyolo.config.checks import AT_LEAST_0, AT_LEAST_1, METRES, POSITIVE, Interval
from pnyolo.config.model import ImageModelConfig, YoloLossConfig, check_surface_depth


@dataclass
class RayLossConfig(YoloLossConfig):
    """The YOLO loss's weights and the terms only rays have (``model.loss`` of pixelnerf-yolo)."""

    # Weight of the surface-depth term (model.surface_depth): mean absolute log-depth error of the
    # predicted depth maps against the rendered ones (sky counts as 100 m). 0: off.
    surface_depth: float = 0.0
    # Weight of the per-sample 3D terms (pnyolo.components.occupancy), 0: off (the paper): every
    # sample's confidence, class and box trained by whether it lies inside the 3D box of the road
    # user its cell and anchor are assigned (a coarse sample: whether its bin meets that box).
    occupancy: float = 0.0
    # Weight of the 3D state terms (pnyolo.components.view_state; not in the paper): on object anchors, L1 on each
    # road user's log length, width and height and on its heading's axis relative to the line from the camera, binary
    # cross-entropy on which way along it it faces; the MLP then outputs that state and each detection is a world box.
    # 0: no state outputs (the paper).
    state: float = 1.0


@dataclass
class PixelNeRFYoloConfig(ImageModelConfig):
    """pixelnerf-yolo (the paper): rays through each view's cells, samples read every source view."""

    kind: str = "pixelnerf-yolo"
    sampler: SamplerConfig = field(default_factory=SamplerConfig)
    mlp: MLPConfig = field(default_factory=MLPConfig)
    # how a ray's samples become its values (pnyolo.components.ray_attention)
    aggregator: AggregatorConfig = field(default_factory=AggregatorConfig)
    chunk_memory_mb: float = 1024.0  # activation budget per checkpointed ray chunk
    # Surface depth (not in the paper): a small head on the encoder's last feature maps predicts
    # each view's planar depth map (trained by model.loss.surface_depth on the rendered depth), and every
    # (sample, source view) pair gets two more inputs: how far the sample lies behind (+) or in
    # front of (-) the surface that view sees at its pixel, tanh(dz / 2 m) and tanh(dz / 8 m). A
    # point on a surface one view sees, behind what its own view sees, is what a road user hidden
    # in its own view looks like (pnyolo.components.surface_depth).
    surface_depth: bool = False
    checkpointing: bool = True  # activation checkpointing over ray chunks (one backward pass)
    loss: RayLossConfig = field(default_factory=RayLossConfig)  # the YOLO loss's weights and the rays' own terms
    casts_rays: ClassVar[bool] = True
    runtime_keys: ClassVar[tuple[str, ...]] = (*ImageModelConfig.runtime_keys, "chunk_memory_mb", "checkpointing")
    trained_without: ClassVar[dict[str, object]] = {"loss.state": 0.0}  # checkpoints before the 3D state
    ranges: ClassVar[dict[str, Interval]] = {
        "sampler.num_samples": Interval(1, 1024), "sampler.fine_samples": Interval(0, 1024),
        "sampler.cell_rays": Interval(1, 8), "sampler.near": POSITIVE, "sampler.far": Interval(0, 10000, True),
        "sampler.height_cap": METRES, "mlp.hidden": AT_LEAST_1, "mlp.num_blocks": AT_LEAST_1,
        "mlp.combine_layer": AT_LEAST_0, "mlp.attention_heads": AT_LEAST_1, "mlp.pe_frequencies": Interval(0, 32),
        "mlp.pe_factor": POSITIVE, "aggregator.width": AT_LEAST_1, "aggregator.layers": AT_LEAST_1,
        "aggregator.heads": AT_LEAST_1, "chunk_memory_mb": Interval(0, 1 << 20, open_low=True),
        "sampler.footprint_levels": Interval(0, 8), "sampler.evidence_points": Interval(1, 64)}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {"sampler.footprint": ("point", "frustum", "both", "evidence"),
                                                     "sampler.fine_weights": ("max", "per_anchor")}

    def points_per_cell(self) -> int:
        """3D points one grid cell queries: its rays (cell_rays squared) times their coarse and fine samples."""
        return self.sampler.cell_rays ** 2 * (self.sampler.num_samples + self.sampler.fine_samples)

    def check(self, cfg) -> None:
        super().check(cfg)
        s, agg, m = self.sampler, self.aggregator, self.mlp
        check_surface_depth(self.surface_depth, self.loss.surface_depth)
        if not s.near < s.far:
            raise UserError(f"config model.sampler: need near < far, got {excerpt(s.near)} and {excerpt(s.far)}")
        if s.slab_clip and s.height_cap <= cfg.data.ground_z:
            raise UserError("config model.sampler.height_cap must be above data.ground_z")
        if s.footprint != "point" and self.surface_depth:
            raise UserError(f"config model.sampler.footprint {s.footprint} pools the maps over a footprint; "
                            "model.surface_depth reads a depth at a point: use one of them")
        if agg.kind not in ("weighted_mean", "transformer"):
            raise UserError(f"config model.aggregator.kind: {excerpt(agg.kind)} (weighted_mean | transformer)")
        if agg.width < 2 or agg.layers < 1 or agg.heads < 1 or agg.width % agg.heads or agg.width % 2:
            raise UserError(f"config model.aggregator: width (even), layers and heads >= 1, heads dividing width, "
                            f"got {agg.width}, {agg.layers}, {agg.heads}")
        if not 0 <= m.combine_layer <= m.num_blocks:
            raise UserError("config model.mlp.combine_layer must be within 0..num_blocks")
        # model.mlp.combine names an entry of the MLP's combines: checked where the MLP is built (YoloMLP)
        if m.combine == "attention" and (m.attention_heads < 1 or m.hidden % m.attention_heads):
            raise UserError(f"config model.mlp.attention_heads: a divisor of model.mlp.hidden ({m.hidden}), "
                            f"got {m.attention_heads}")

    def reads_depth_maps(self) -> bool:
        return self.surface_depth
