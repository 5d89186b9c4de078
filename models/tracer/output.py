"""Per-ray outputs of a trace."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from models.capture.layers import TRACED, channels

# TraceOutput.front_depth: the hits blended while the transmittance in front of them is at least this (the Warp
# kernels' compositing step, models/tracer/blend.py, and the PyTorch twin read it here)
FRONT_TRANSMITTANCE = 0.5

# Differentiable per-ray layers, in the order the kernels pack them, with their channel count.
LAYERS: dict[str, int] = channels(TRACED)


@dataclass
class TraceOutput:
    """Front-to-back blended layers for R rays.

    Blending: w_i = T_i alpha_i over accepted hits sorted by t, T_0 = 1,
    T_{i+1} = T_i (1 - alpha_i); a hit is blended while T_i >= transmittance_threshold.
    Tail rule (all five layers alike, including depth): when accepted hits were left
    unblended ("truncated"), the remaining transmittance T_end is filled with the
    running weight-normalised average sum(w f) / sum(w); since sum(w) = 1 - T_end this
    is out = sum(w f) / (1 - T_end). Without truncation out = sum(w f) (background 0).
    """

    diffuse: torch.Tensor        # [R, 3] blended linear diffuse RGB
    depth: torch.Tensor          # [R]    expected ray parameter t (distance when dirs are unit)
    normal: torch.Tensor         # [R, 3] blended normal, NOT normalised
    roughness: torch.Tensor      # [R]    blended perceptual roughness
    f0: torch.Tensor             # [R, 3] blended base reflectance
    transmittance: torch.Tensor  # [R]    T_end after the last blended hit (before the tail fill)
    hit_count: torch.Tensor      # [R] int32 accepted hits (alpha > alpha_min, in box, t > t_min); the traversals
    #                              that stop early count those found: blended + 1 on a truncated ray (interval)
    blended_count: torch.Tensor  # [R] int32 hits blended before the transmittance threshold
    # [R] (detached) the surface's front: sum(w t) / sum(w) over the blended hits whose incoming T is >= 0.5 (the
    # first blended hit always is); 0 where nothing is blended. Where a reflection starts (models/pathtrace/paths.py):
    # seen at an angle the depth above lies INSIDE a surface by the shell's spread behind its front half
    front_depth: torch.Tensor | None = None
    # Diagnostics (Warp tracer only; None from the reference).
    candidates: torch.Tensor | None = None      # [R] int32 BVH leaves (world AABBs) visited
    obb_candidates: torch.Tensor | None = None  # [R] int32 candidates whose cut-off ellipsoid the ray meets
    overflow_rays: int = 0                      # rays whose replay buffer overflowed (then re-run)
    replay_capacity: int = 0                    # replay slots per ray used by the final launch
    extra: dict = field(default_factory=dict)

    def opacity(self) -> torch.Tensor:
        """[R, 1] accumulated opacity the layers are blended over (detached): 1 for truncated rays, whose
        layers the tail rule already normalised, else 1 - T_end. ``layer / opacity()`` is the value
        conditional on the ray terminating (never divided twice)."""
        truncated = (self.hit_count > self.blended_count).reshape(-1, 1)
        opacity = (1.0 - self.transmittance.detach().reshape(-1, 1)).clamp_min(1e-6)
        return torch.where(truncated, torch.ones_like(opacity), opacity)

    def layer(self, name: str) -> torch.Tensor:
        """One differentiable layer as [R, C]."""
        if name not in LAYERS:
            raise ValueError(f"unknown layer {name!r}; expected one of {list(LAYERS)}")
        value = getattr(self, name)
        return value.reshape(value.shape[0], -1)
