"""The far-field shell stays outside the captured geometry (models/reconstruction/far_field.py)."""

from __future__ import annotations

import numpy as np
import pytest

from models.reconstruction.far_field import far_field_gaussians


def test_keep_out_box_removes_exactly_the_points_inside_it():
    """Same draws as without the box, minus the points inside it; every point stays outside the cameras'
    sphere; the recipe's materials (opacity 0.1, zero normal) unchanged."""
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


def test_a_box_that_swallows_the_shell_is_an_error_naming_the_count():
    centre = np.zeros(3)
    with pytest.raises(ValueError, match=r"far field: 0 of 200 points left .* raise far_field_count"):
        far_field_gaussians(200, centre, 1.0, seed=0, keep_out=(centre - 100.0, centre + 100.0))
