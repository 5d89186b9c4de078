"""Sphere completion: cameras on one side of a chrome ball see its near half; the fill covers the rest of THAT
sphere (on it, radial normals, the ball's material, away from what was seen, nothing where a view saw through),
and nothing for the other shiny things in the frames: a planar mirror, a metal cylinder, a metal box."""

from __future__ import annotations

import numpy as np
import pytest

from models.reconstruction.data import RaySet
from models.reconstruction.plane_fill import pixel_points
from models.reconstruction.sphere_fill import find_spheres, fit_sphere, sphere_fill_gaussians
from tests.test_plane_fill import _rays as plane_rays
from tests.test_plane_fill import _view as plane_view

BALL_C, BALL_R = np.array([0.0, 0.3, -1.0]), 0.3
CYL_X, CYL_Z, CYL_R, CYL_H = 0.9, -1.1, 0.2, 0.8  # vertical metal cylinder, y in [0, CYL_H]
BOX = (np.array([-1.1, 0.0, -1.4]), np.array([-0.7, 0.4, -1.0]))  # a metal box
MIRROR_Z = -2.0  # the back wall is a mirror in x in [-1, 1], y in [0.2, 1.8]


def _cast(o: np.ndarray, d: np.ndarray) -> dict[str, np.ndarray]:
    """Nearest surface along each ray (d unit [N, 3]): depth, normal, diffuse, f0, roughness."""
    n = len(d)
    o = np.broadcast_to(np.asarray(o, float), d.shape)
    best = np.full(n, np.inf)
    out = {"normal": np.zeros((n, 3)), "diffuse": np.zeros((n, 3)), "f0": np.zeros((n, 3)),
           "roughness": np.ones((n, 1))}

    def take(t, normal, diffuse, f0, rough):
        ok = np.isfinite(t) & (t > 1e-6) & (t < best)
        best[ok] = t[ok]
        out["normal"][ok] = normal[ok] if normal.ndim == 2 else normal
        out["diffuse"][ok], out["f0"][ok], out["roughness"][ok] = diffuse, f0, rough

    with np.errstate(divide="ignore", invalid="ignore"):
        # room: floor y = 0, ceiling 2, walls x = +-2, z = -2 (the mirror's wall), z = 2
        for axis, pos, sign, colour in [(1, 0.0, 1, (0.6, 0.5, 0.4)), (1, 2.0, -1, (0.8, 0.8, 0.8)),
                                        (0, -2.0, 1, (0.3, 0.6, 0.3)), (0, 2.0, -1, (0.5, 0.5, 0.7)),
                                        (2, -2.0, 1, (0.7, 0.7, 0.7)), (2, 2.0, -1, (0.9, 0.2, 0.2))]:
            t = (pos - o[:, axis]) / d[:, axis]
            t = np.where(d[:, axis] * sign < 0, t, np.inf)
            normal = np.zeros(3)
            normal[axis] = sign
            x = o + t[:, None] * d
            mirror = (axis == 2) & (pos == MIRROR_Z) & (np.abs(x[:, 0]) < 1) & (x[:, 1] > 0.2) & (x[:, 1] < 1.8)
            take(np.where(mirror, np.inf, t), normal, colour, 0.0, 1.0)
            if axis == 2 and pos == MIRROR_Z:
                take(np.where(mirror, t - 1e-4, np.inf), normal, 0.0, 0.95, 0.0)
        # the ball
        oc = o - BALL_C
        b = (oc * d).sum(1)
        disc = b * b - ((oc * oc).sum(1) - BALL_R ** 2)
        t = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
        take(t, (o + t[:, None] * d - BALL_C) / BALL_R, 0.0, 0.9, 0.05)
        # the cylinder's side
        oc2, d2 = (o - [CYL_X, 0, CYL_Z])[:, [0, 2]], d[:, [0, 2]]
        a2, b2 = (d2 * d2).sum(1), (oc2 * d2).sum(1)
        disc = b2 * b2 - a2 * ((oc2 * oc2).sum(1) - CYL_R ** 2)
        t = np.where(disc >= 0, (-b2 - np.sqrt(np.maximum(disc, 0))) / a2, np.inf)
        y = o[:, 1] + t * d[:, 1]
        t = np.where((y >= 0) & (y <= CYL_H), t, np.inf)
        side = o + t[:, None] * d - [CYL_X, 0, CYL_Z]
        side[:, 1] = 0
        take(t, side / CYL_R, 0.0, 0.9, 0.15)
        # the box (slabs)
        lo, hi = BOX
        t1, t2 = (lo - o) / d, (hi - o) / d
        tn, tf = np.minimum(t1, t2).max(1), np.maximum(t1, t2).min(1)
        t = np.where((tn <= tf) & (tn > 0), tn, np.inf)
        face = np.argmax(np.minimum(t1, t2), axis=1)
        normal = np.zeros((n, 3))
        normal[np.arange(n), face] = -np.sign(d[np.arange(n), face])
        take(t, normal, 0.0, 0.9, 0.2)
    out["depth"] = np.where(np.isfinite(best), best, 0.0)[:, None]
    return out


def _rays() -> RaySet:
    """Cameras on the front half (z > -1) round the ball, looking at it from above."""
    return plane_rays([plane_view(i, (1.4 * np.sin(a), 1.0, -1.0 + 1.4 * np.cos(a)), BALL_C, size=(96, 72), fl=60.0,
                                  cast=_cast) for i, a in enumerate(np.radians(np.linspace(-60, 60, 6)))])


@pytest.fixture(scope="module")
def scene():
    rays = _rays()
    src = pixel_points(rays, 10**6)
    return rays, src


def test_fit_sphere_recovers_a_noisy_cap_and_refuses_a_plane():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(2000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] > 0.3]  # a cap of ~70 degrees
    c, r = np.array([0.5, -0.2, 1.0]), 0.4
    p = c + r * u + rng.normal(scale=0.002, size=u.shape)
    n = u + rng.normal(scale=0.01, size=u.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    fc, fr = fit_sphere(p, n)
    assert np.abs(fc - c).max() < 5e-3 and abs(fr - r) < 3e-3
    plane = np.c_[rng.uniform(-1, 1, (500, 2)), np.zeros(500)]
    normals = np.tile([0.0, 0.0, 1.0], (500, 1))
    fit = fit_sphere(plane, normals)
    assert fit is None or fit[1] > 1e3 or not np.isfinite(fit[1])


def test_only_the_ball_is_a_sphere(scene):
    _, src = scene
    size = float(np.ptp(np.quantile(src["points"], [0.005, 0.995], axis=0), axis=0).max())
    spacing = 0.02
    spheres, notes = find_spheres(src, link=3 * spacing, size=size)
    assert len(spheres) == 1, notes
    s = spheres[0]
    assert np.abs(s["centre"] - BALL_C).max() < 5e-3 and abs(s["radius"] - BALL_R) < 5e-3, notes
    # the mirror, the cylinder and the box were tried and refused (one line each, or counted)
    assert sum("not a sphere" in x for x in notes) + sum("no sphere" in x for x in notes) >= 2, notes


def test_the_fill_covers_the_balls_far_side_only(scene):
    rays, src = scene
    size = float(np.ptp(np.quantile(src["points"], [0.005, 0.995], axis=0), axis=0).max())
    g, stats = sphere_fill_gaussians(src, rays, size)
    assert g is not None and stats["spheres"] == 1 and stats["added"] == len(g) > 50, stats
    p, n = g.means.double().numpy(), g.normals.double().numpy()
    radial = (p - BALL_C) / np.linalg.norm(p - BALL_C, axis=1, keepdims=True)
    assert np.abs(np.linalg.norm(p - BALL_C, axis=1) - BALL_R).max() < 5e-3  # on the ball
    assert (n * radial).sum(1).min() > 0.999                                   # facing out of it
    # the unseen side: away from the cameras (all at z > -1 + 1.4 cos 60), or under the ball
    assert ((p[:, 2] < BALL_C[2] + 0.1) | (p[:, 1] < BALL_C[1] - 0.1)).all()
    assert g.f0.min() > 0.85 and g.roughness.max() < 0.1 and g.diffuse.max() < 0.05  # the ball's material
    # away from what the cameras saw (1.5 lattice spacings)
    from scipy.spatial import cKDTree

    h = np.pi * BALL_R / 24
    assert cKDTree(src["points"]).query(p)[0].min() > 1.5 * h - 1e-6
    # most of it on the cap facing away from the cameras (radial z < -0.5: a quarter of the lattice, 4 pi / (pi / 24)^2
    # points in all), and that cap mostly covered (what a view saw through, near the silhouette, stays open)
    back = radial[:, 2] < -0.5
    lattice = 4 * np.pi / (np.pi / 24) ** 2
    assert back.sum() > 0.6 * len(g) and back.sum() > 0.5 * lattice / 4, (back.sum(), len(g))


def test_no_shiny_points_no_fill():
    rays = _rays()
    src = pixel_points(rays, 10**6)
    src = dict(src, f0=np.zeros_like(src["f0"]))
    g, stats = sphere_fill_gaussians(src, rays, 4.0)
    assert g is None and stats["spheres"] == 0 and stats["added"] == 0
