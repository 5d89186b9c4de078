"""Anchored Gaussians: Gaussians a fill placed where the cameras see only reflections (mirror stereo, the
reflection fill) are surfels that keep their depth: along the direction they were seen from (their local z axis,
rotation frozen) each may move at most ``depth`` times its initial size from where the fill put it and grow at
most ``depth`` times; across it (along the surface) at most ``spread`` times. A projection after each optimiser
step.

Why: a reflection constrains where its Gaussians are far less than a direct view does (the same colour along a
reflected ray fits at many depths and sizes, and one mirror gives few baselines), and nothing else sees them. In a
room whose cameras all look one way (zoo_mirror_metal), free mirror-stereo Gaussians of the unseen half grew from
~0.1 m to 0.4-2.8 m and drifted in front of the true surface of a test view looking back (~62% of its pixel
weight). Bounding every direction alike removed those floaters but left holes where the sparse fill had grown to
cover the surface; along it the views do constrain them, so there they may spread."""

from __future__ import annotations

import dataclasses
import math

import torch

from models.gaussians.activations import quats_to_rotmats


def quats_z_to(axis: torch.Tensor) -> torch.Tensor:
    """[N, 4] wxyz unit quaternions whose rotation takes the local z axis onto ``axis`` [N, 3] (unit): the
    shortest arc, half-way quaternion (1 + z.a, z x a); a = -z (no shortest arc) turns about x."""
    w = 1 + axis[:, 2]
    q = torch.stack([w, -axis[:, 1], axis[:, 0], torch.zeros_like(w)], dim=1)
    opposite = w < 1e-6
    q[opposite] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=q.dtype, device=q.device)
    return q / q.norm(dim=1, keepdim=True)


def facing_surfels(gaussians):
    """The same Gaussians rotated so that their local z axis is their normal (the direction the fill saw them
    along; the normal's own axis where it is zero): for the isotropic Gaussians a fill makes, the same
    distribution, now with the thin axis an anchor bounds. Anisotropic ones would turn: anchor fills only."""
    normals = gaussians.normals.detach()
    length = normals.norm(dim=1, keepdim=True)
    axis = torch.where(length > 1e-6, normals / length.clamp_min(1e-12), torch.tensor([0.0, 0.0, 1.0]).to(normals))
    return dataclasses.replace(gaussians, quats=quats_z_to(axis).to(gaussians.quats))


class Anchors:
    """The anchored Gaussians of a trainer's parameters: their indices [M], anchor positions [M, 3], frozen
    rotations [M, 4] and their local z axes [M, 3], depth and lateral radii [M] and largest log-scales [M, 3],
    kept aligned with the parameters through pruning and appending."""

    FIELDS = ("index", "centre", "quats", "axis", "depth_radius", "lateral_radius", "max_log_scale")

    def __init__(self, device: torch.device, dtype: torch.dtype = torch.float32):
        f = dict(dtype=dtype, device=device)
        self.index = torch.zeros(0, dtype=torch.long, device=device)
        self.centre, self.axis = torch.zeros((0, 3), **f), torch.zeros((0, 3), **f)
        self.quats = torch.zeros((0, 4), **f)
        self.depth_radius, self.lateral_radius = torch.zeros(0, **f), torch.zeros(0, **f)
        self.max_log_scale = torch.zeros((0, 3), **f)

    def __len__(self) -> int:
        return len(self.index)

    def append(self, first: int, gaussians, depth: float, spread: float) -> None:
        """Anchor ``gaussians`` (Gaussians, appended to the parameters at indices ``first``..) where they are
        now: along their local z axis within ``depth`` x their largest initial scale and scale <= ``depth`` x,
        across it within / <= ``spread`` x; their rotation stays."""
        if depth <= 0 or len(gaussians) == 0:
            return
        f = dict(dtype=self.centre.dtype, device=self.centre.device)
        means, log_scales = gaussians.means.detach().to(**f), gaussians.log_scales.detach().to(**f)
        quats = gaussians.quats.detach().to(**f)
        size = log_scales.amax(1).exp()
        spread = max(spread, depth)
        self.hold(torch.arange(first, first + len(means), device=self.index.device), means, quats,
                  depth * size, spread * size,
                  log_scales + torch.tensor([math.log(spread), math.log(spread), math.log(depth)], **f))

    def hold(self, index: torch.Tensor, centre: torch.Tensor, quats: torch.Tensor, depth_radius: torch.Tensor,
             lateral_radius: torch.Tensor, max_log_scale: torch.Tensor) -> None:
        """Anchor the parameters' rows ``index`` [M]: rotation ``quats`` [M, 4] (frozen), the mean within
        ``depth_radius`` [M] of ``centre`` [M, 3] along the rotation's local z axis and within ``lateral_radius``
        [M] (inf: free) across it, log-scales at most ``max_log_scale`` [M, 3] (inf: free)."""
        f = dict(dtype=self.centre.dtype, device=self.centre.device)
        quats = quats.to(**f)
        new = {
            "index": index.to(self.index.device), "centre": centre.to(**f), "quats": quats,
            "axis": quats_to_rotmats(quats)[:, :, 2], "depth_radius": depth_radius.to(**f),
            "lateral_radius": lateral_radius.to(**f), "max_log_scale": max_log_scale.to(**f),
        }
        for name in self.FIELDS:
            setattr(self, name, torch.cat([getattr(self, name), new[name]]))

    def keep(self, keep: torch.Tensor) -> None:
        """Follow a pruning that keeps the parameters' rows where ``keep`` [N] bool."""
        if not len(self):
            return
        kept = keep[self.index]
        new_index = torch.cumsum(keep.long(), 0) - 1
        for name in self.FIELDS:
            setattr(self, name, getattr(self, name)[kept])
        self.index = new_index[self.index]

    @torch.no_grad()
    def project(self, means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor) -> None:
        """Move the anchored Gaussians back into their bounds (means, rotations, log-scales), in place."""
        if not len(self):
            return
        offset = means[self.index] - self.centre
        along = (offset * self.axis).sum(1, keepdim=True)
        across = offset - along * self.axis
        along = torch.maximum(torch.minimum(along, self.depth_radius[:, None]), -self.depth_radius[:, None])
        shrink = (self.lateral_radius[:, None] / across.norm(dim=1, keepdim=True).clamp_min(1e-30)).clamp(max=1.0)
        means[self.index] = self.centre + along * self.axis + across * shrink
        quats[self.index] = self.quats
        log_scales[self.index] = torch.minimum(log_scales[self.index], self.max_log_scale)

    def state_dict(self) -> dict:
        return {name: getattr(self, name) for name in self.FIELDS}

    def load_state_dict(self, state: dict) -> None:
        device = self.index.device
        for name in self.FIELDS:
            setattr(self, name, state[name].to(device))
