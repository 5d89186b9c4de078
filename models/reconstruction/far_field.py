"""Far-field Gaussians: a coarse shell that reflections can hit beyond the captured geometry.

Reference recipe: M points, positions N(0, 1) clamped to +-3, times 4 x camera
extent; points near the cameras removed (here: inside the sphere of radius
``extent`` around the cameras' centre, where the captured scene lives); scale =
0.1 x nearest-neighbour distance, opacity 0.1, diffuse 0.2, normal 0, F0 0.04,
roughness 0. Here F0 is 0: the shell is what lies beyond the captured geometry, lit, not a surface to reflect in
(its zero normal already stops every path that reaches it). With the reference's 0.04 a test view that sees the
shell through a thin wall took its F0 into the wall's blend, and a matte wall whose truth reflects nothing showed
speckles of reflection (zoo_mirror_only, with the hole fill: specular 19.0 -> 19.9 dB tonemapped with the shell's
F0 set to 0 in the same model; the other rooms' shells are not seen, +-0.02).

Also removed here: points inside ``keep_out``, the box of the captured room (the trainer passes the 0.5-99.5 %
box of the scene's Gaussians and of the mirror fills', widened to hold every camera: the fills place what the
cameras see only in mirrors, often the half of the room behind them). The camera sphere alone is not where the
scene lives in a room whose cameras stand together: there the shell began inside the room, and its Gaussians
(opacity 0.1, zero normal) hung in the space no training camera looks at, in front of every test camera that
does (zoo_mirror_metal: ~60 % of each test pixel's weight in front of the true surface, all of it from
Gaussians outside every training frustum, and their zero normals switched the test views' reflections off).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from models.gaussians import Gaussians
from models.gaussians.activations import quats_to_rotmats


def far_field_gaussians(count: int, centre: np.ndarray, extent: float, seed: int, dtype=torch.float32,
                        keep_out: tuple[np.ndarray, np.ndarray] | None = None) -> Gaussians:
    """``count`` points drawn; those within ``extent`` of ``centre`` or inside the box ``keep_out`` = (lo, hi)
    are dropped."""
    rng = np.random.default_rng(seed)
    pos = np.clip(rng.normal(size=(count, 3)), -3, 3) * 4 * extent
    pos = pos[np.linalg.norm(pos, axis=1) > extent] + centre
    if keep_out is not None:
        lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in keep_out)
        pos = pos[~((pos >= lo) & (pos <= hi)).all(1)]
    if len(pos) < 2:
        raise ValueError(f"far field: {len(pos)} of {count} points left outside the cameras' sphere (radius "
                         f"{extent:.3g}) and the captured geometry's box; raise far_field_count")
    dist, _ = cKDTree(pos).query(pos, k=2)
    scale = np.maximum(0.1 * dist[:, 1], 1e-6)
    n = len(pos)
    t = dict(dtype=dtype)
    return Gaussians(
        means=torch.tensor(pos, **t),
        quats=torch.tensor([[1.0, 0, 0, 0]], **t).repeat(n, 1),
        log_scales=torch.tensor(np.log(scale), **t)[:, None].repeat(1, 3),
        opacity_logits=torch.full((n,), float(np.log(0.1 / 0.9)), **t),
        diffuse=torch.full((n, 3), 0.2, **t),
        normals=torch.zeros((n, 3), **t),
        roughness=torch.zeros((n,), **t),
        f0=torch.zeros((n, 3), **t),
    )


@torch.no_grad()
def clearance_factors(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, lo: torch.Tensor,
                      hi: torch.Tensor, margin: float, floor: float) -> torch.Tensor:
    """[N] factors (<= 1) to multiply each Gaussian's scales by, so that ``margin`` standard deviations of it along
    the world axis that separates it best from the box ``lo`` .. ``hi`` (the largest distance outside the box's
    slab on that axis over that deviation) fit in that distance: then the Gaussian's ``margin``-sigma ellipsoid lies
    wholly outside the box (the slab's face is a separating plane). Its mean does not move. One whose mean has
    entered the box shrinks to ``floor`` (a length) along that axis. 1 where nothing needs to change; applying the
    factors and computing them again gives 1 (up to float rounding)."""
    rot = quats_to_rotmats(quats)
    var = (rot * rot * torch.exp(2 * log_scales)[:, None, :]).sum(-1)  # [N, 3]: Sigma_aa = sum_i R_ai^2 s_i^2
    sigma = var.clamp_min(0).sqrt()
    outside = torch.maximum(lo - means, means - hi)  # [N, 3], > 0 outside that axis's slab
    axis = (outside / (margin * sigma).clamp_min(1e-30)).argmax(1, keepdim=True)
    d, s = outside.gather(1, axis).squeeze(1), sigma.gather(1, axis).squeeze(1)
    target = torch.clamp_min(d / margin, floor)
    return torch.clamp(target / s.clamp_min(1e-30), max=1.0)
