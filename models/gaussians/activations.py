"""Activations from raw (optimised) Gaussian parameters to physical values.

Raw parameters live in `Gaussians`; everything here is differentiable torch.
"""

from __future__ import annotations

import torch


def normalize_quats(quats: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (wxyz). quats: [N, 4] raw -> [N, 4] unit norm."""
    return quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def quats_to_rotmats(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from quaternions (wxyz, normalised here). [N, 4] -> [N, 3, 3].

    Columns of R are the Gaussian's local axes in world space.
    """
    w, x, y, z = normalize_quats(quats).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b, wxyz. [..., 4] x [..., 4] -> [..., 4] (rotation b first, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=-1)


def scales_from_log(log_scales: torch.Tensor) -> torch.Tensor:
    """Standard deviations along the local axes. [N, 3] -> [N, 3]."""
    return torch.exp(log_scales)


def opacities_from_logits(opacity_logits: torch.Tensor) -> torch.Tensor:
    """Opacity in (0, 1). [N] -> [N]."""
    return torch.sigmoid(opacity_logits)


def world_to_local(quats: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    """Linear part of the world-to-local map x_l = M (x - mean), M = S^-1 R^T.

    In the local frame the Gaussian is the unit isotropic one. [N,4],[N,3] -> [N, 3, 3].
    """
    rot = quats_to_rotmats(quats)
    inv_s = torch.exp(-log_scales)
    return inv_s[:, :, None] * rot.transpose(-1, -2)


def roughness_to_ggx_alpha(roughness: torch.Tensor) -> torch.Tensor:
    """Perceptual roughness -> GGX alpha (= roughness^2). [N] -> [N]."""
    return roughness * roughness
