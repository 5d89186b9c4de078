"""Reconstruction settings: one dataclass, a comment per field; defaults are the reference's (REFERENCE.md)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from stages.config import reject_unknown


@dataclass
class LossWeights:
    diffuse: float = 5.0  # L1 on the first segment's diffuse layer
    specular: float = 3.0  # L1 on the path-traced specular estimate (after warm-up)
    depth: float = 2.5  # L1 on expected depth (distance along the ray)
    normal: float = 2.5  # L1 on the accumulated (unnormalised) normal
    roughness: float = 1.0
    f0: float = 1.0


@dataclass
class LearningRates:
    position_init: float = 1.6e-4  # x scene extent, decays exponentially to position_final
    position_final: float = 1.6e-6  # x scene extent
    normal: float = 0.0025
    roughness: float = 0.0025
    f0: float = 0.0025
    diffuse: float = 0.005
    opacity: float = 0.025
    scale: float = 0.005
    rotation: float = 0.001


@dataclass
class ReconstructConfig:
    iterations: int = 8000  # optimisation steps
    warmup: int = 750  # steps with primary rays only; then reflections (and far field) on
    rays_per_step: int = 0  # rays per step drawn from all training pixels; 0 = one whole view per step
    max_path_length: int = 3  # path segments (1 = no reflections)
    sampler: str = "vndf"  # reflection sampling: vndf | ndf (reference)
    loss: LossWeights = field(default_factory=LossWeights)
    lr: LearningRates = field(default_factory=LearningRates)
    adam_eps: float = 1e-15
    prune_every: int = 125  # pruning period (steps)
    prune_from: int = 1250  # first step that prunes
    prune_min_weight: float = 0.1  # keep Gaussians whose blending weight summed over a view, averaged over views,
    # is >= this at the reference's 768-pixel image height (scaled by pixel count: (H / 768)^2 at height H)
    prune_views: int = 8  # views traced to measure blending weights at a pruning step
    far_field: str = "auto"  # auto (only if reflections can see past the capture) | on | off
    far_field_count: int = 75000  # far-field Gaussians added at the end of warm-up
    far_field_escape: float = 0.01  # auto: on when more mirror-like reflections than this miss the init
    reflection_fill_count: int = 0  # with the far field: Gaussians along open mirror reflections (0 = off)
    mirror_stereo_count: int = 8000  # with the far field: Gaussians placed by stereo on planar mirrors (0 = off)
    highlight_fill: bool = True  # with the far field: emitters seen only in mirrors (reflection_fill.py)
    radiance_clamp: float = 0.0  # clamp target radiance (diffuse/specular) to this; 0 = off (real scenes: 5.0)
    kernel_p: int = 3  # tracer kernel exponent
    transmittance_threshold: float = 0.01  # tracer truncation
    threads: int = 2  # CPU tracer threads
    checkpoint_every: int = 1000  # steps between checkpoints (and at the end)
    log_every: int = 25  # steps between metrics-log lines
    seed: int = 0

    @classmethod
    def from_dict(cls, d: dict) -> "ReconstructConfig":
        d = dict(d)
        reject_unknown(cls, d, "reconstruct")
        for name, sub in (("loss", LossWeights), ("lr", LearningRates)):
            if name in d:
                sub_known = {f.name for f in fields(sub)}
                bad = set(d[name]) - sub_known
                if bad:
                    raise ValueError(f"unknown reconstruct.{name} key(s) {sorted(bad)}; known: {sorted(sub_known)}")
                d[name] = sub(**d[name])
        return cls(**d)
