"""The far-field shell stays outside the captured geometry (models/reconstruction/far_field.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.gaussians.activations import quats_to_rotmats
from models.reconstruction.far_field import clearance_factors, far_field_gaussians


def test_keep_out_box_removes_exactly_the_points_inside_it():
    """Same draws as without the box, minus the points inside it; every point stays outside the cameras'
    sphere; the recipe's materials (opacity 0.1, zero normal) unchanged, and F0 0: the shell reflects nothing."""
    centre, extent = np.array([0.5, 1.0, -0.2]), 1.0
    free = far_field_gaussians(5000, centre, extent, seed=3)
    lo, hi = centre - np.array([3.0, 1.5, 2.5]), centre + np.array([2.5, 1.5, 3.0])  # a room past the sphere
    boxed = far_field_gaussians(5000, centre, extent, seed=3, keep_out=(lo, hi))
    pos = free.means.double().numpy()
    inside = ((pos >= lo) & (pos <= hi)).all(1)
    assert 100 < inside.sum() < len(pos) - 100  # the case: the box holds some of the shell, not all
    np.testing.assert_array_equal(boxed.means.double().numpy(), pos[~inside])
    kept = boxed.means.double().numpy()
    assert not ((kept >= lo) & (kept <= hi)).all(1).any()
    assert (np.linalg.norm(kept - centre, axis=1) > extent).all()
    assert float(boxed.opacities().max()) == pytest.approx(0.1) and not boxed.normals.any()
    assert not boxed.f0.any() and not free.f0.any()


def test_a_box_that_swallows_the_shell_is_an_error_naming_the_count():
    centre = np.zeros(3)
    with pytest.raises(ValueError, match=r"far field: 0 of 200 points left .* raise far_field_count"):
        far_field_gaussians(200, centre, 1.0, seed=0, keep_out=(centre - 100.0, centre + 100.0))


def test_clearance_shrinks_far_gaussians_until_their_ellipsoid_leaves_the_box(seed=5):
    """``clearance_factors`` (``far_field_margin``): random anisotropic Gaussians round a box, some far outside it,
    some reaching into it, some with their mean inside. After scaling by the factors, every one whose mean is
    outside has its whole margin-sigma ellipsoid outside the box (checked on 2000 points of its surface); those
    already clear keep their scales exactly; those inside are at the floor along their separating axis; and the
    factors computed again are 1 (a projection: applying it every step does not shrink further)."""
    g = torch.Generator().manual_seed(seed)
    n, margin, floor = 400, 2.0, 1e-3
    lo, hi = torch.tensor([-1.0, 0.0, -2.0], dtype=torch.float64), torch.tensor([1.0, 2.5, 2.0], dtype=torch.float64)
    means = lo - 0.6 * (hi - lo) + torch.rand(n, 3, generator=g, dtype=torch.float64) * 2.2 * (hi - lo)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    log_scales = torch.log(torch.rand(n, 3, generator=g, dtype=torch.float64) * 1.5 + 0.01)
    factor = clearance_factors(means, quats, log_scales, lo, hi, margin, floor)
    assert ((factor > 0) & (factor <= 1)).all()
    inside = ((means >= lo) & (means <= hi)).all(1)
    assert 20 < inside.sum() < n - 100 and 50 < (factor < 1)[~inside].sum() and (factor == 1).sum() > 50
    new = log_scales + factor.log()[:, None]
    rot, s = quats_to_rotmats(quats), torch.exp(new)
    u = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g, dtype=torch.float64), dim=1)
    surface = means[:, None, :] + margin * torch.einsum("nij,nj,kj->nki", rot, s, u)  # [N, K, 3]
    hit = ((surface > lo + 1e-9) & (surface < hi - 1e-9)).all(-1).any(1)
    assert not hit[~inside].any()
    old_surface = means[:, None, :] + margin * torch.einsum("nij,nj,kj->nki", rot, torch.exp(log_scales), u)
    reached = ((old_surface > lo) & (old_surface < hi)).all(-1).any(1) & ~inside
    assert reached.sum() > 30 and (factor[reached] < 1).all()  # those that reached in were shrunk
    var = (rot * rot * s[:, None, :] ** 2).sum(-1).sqrt()
    assert (var.min(1).values[inside] <= floor * (1 + 1e-9)).all()  # inside: down to the floor on some axis
    again = clearance_factors(means, quats, new, lo, hi, margin, floor)
    torch.testing.assert_close(again, torch.ones_like(again), atol=1e-9, rtol=0)
