"""BVH over the world bounds of the Gaussians' oriented boxes (wp.Bvh).

Each Gaussian's box is {mean + R S u : |u|_inf <= s}, the unit cube of its local frame
scaled by the opacity-adaptive cutoff s; its world AABB has half extents s |R S| 1.
Refit when only the parameters moved; rebuild when the number of Gaussians changes,
on request, or always (ablation `always_rebuild`).
"""

from __future__ import annotations

import time

import torch
import warp as wp

from models.tracer._torch_impl import cutoff_radius
from models.tracer.interop import to_warp


def world_bounds(means: torch.Tensor, l2w: torch.Tensor, cutoff: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """AABBs of the oriented boxes. means [N, 3], l2w = R S [N, 3, 3], cutoff [N] -> lowers, uppers [N, 3]."""
    half = cutoff[:, None] * l2w.abs().sum(-1)
    return means - half, means + half


class GaussianBvh:
    """Holds the wp.Bvh and the bound arrays it references (refit reads them in place)."""

    def __init__(self, device: str):
        self.device = device
        self.bvh: wp.Bvh | None = None
        self.lowers: wp.array | None = None
        self.uppers: wp.array | None = None
        self.count = -1
        self.last_update_s = 0.0   # wall time of the last update
        self.last_was_rebuild = False

    def update(self, means: torch.Tensor, quats_unit_rot: torch.Tensor, scales: torch.Tensor,
               opacities: torch.Tensor, kernel_p: int, alpha_min: float, rebuild: bool = False) -> torch.Tensor:
        """Recompute bounds; refit or rebuild. rot [N,3,3], scales [N,3]. Returns cutoff [N]."""
        start = time.perf_counter()
        with torch.no_grad():
            cutoff = cutoff_radius(opacities.float(), kernel_p, alpha_min)
            l2w = quats_unit_rot.float() * scales.float()[:, None, :]
            lowers, uppers = world_bounds(means.float(), l2w, cutoff)
        n = means.shape[0]
        self.last_was_rebuild = rebuild or self.bvh is None or n != self.count
        if n == 0:
            self.bvh, self.count = None, 0
        elif self.last_was_rebuild:
            self.lowers = to_warp(lowers, wp.vec3, self.device)
            self.uppers = to_warp(uppers, wp.vec3, self.device)
            self.bvh = wp.Bvh(self.lowers, self.uppers)
            self.count = n
        else:
            wp.copy(self.lowers, to_warp(lowers, wp.vec3, self.device))
            wp.copy(self.uppers, to_warp(uppers, wp.vec3, self.device))
            self.bvh.refit()
        self.last_update_s = time.perf_counter() - start
        return cutoff

    @property
    def id(self) -> int:
        return 0 if self.bvh is None else int(self.bvh.id)
