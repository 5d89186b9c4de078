"""Sphere snap: after training, the chrome ball the cameras saw from one side becomes a lattice of discs on its
fitted sphere (the ball's trained Gaussians gone, the floor under it, a metal box and a metal cylinder beside it
kept), whose rendered normals are the sphere's from a side no camera saw and whose outline is the sphere's; a fit
the training views see through is left as trained."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from models.gaussians import Gaussians
from models.reconstruction import sphere_snap
from models.reconstruction.plane_fill import pixel_points
from models.reconstruction.sphere_snap import snap_spheres
from models.tracer import Tracer, TracerConfig
from tests.test_plane_fill import _view as plane_view
from tests.test_sphere_fill import BALL_C, BALL_R, BOX, CYL_R, CYL_X, CYL_Z, _cast, _rays


def _blobs(points: np.ndarray, f0: float, scale: float, rng) -> Gaussians:
    n = len(points)
    return Gaussians(
        means=torch.tensor(points, dtype=torch.float32),
        quats=torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32),
        log_scales=torch.full((n, 3), math.log(scale)),
        opacity_logits=torch.full((n,), -2.0),
        diffuse=torch.full((n, 3), 0.01 if f0 > 0.3 else 0.4),
        normals=torch.tensor(rng.normal(size=(n, 3)), dtype=torch.float32),
        roughness=torch.full((n,), 0.05 if f0 > 0.3 else 0.9),
        f0=torch.full((n, 3), f0),
    )


@pytest.fixture(scope="module")
def scene():
    """A "trained" model: a noisy shell of half-transparent shiny blobs on the ball's seen half (and a few inside
    it), the floor round and under the ball, the metal box and the metal cylinder."""
    rays = _rays()
    src = pixel_points(rays, 10**6)
    rng = np.random.default_rng(1)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] > -0.2]
    shell = BALL_C + (BALL_R * rng.uniform(0.93, 1.02, len(u)))[:, None] * u
    inside = BALL_C + rng.uniform(-0.1, 0.1, (50, 3))
    floor = np.c_[rng.uniform(-1.0, 1.0, 2000), np.zeros(2000), rng.uniform(-1.8, -0.2, 2000)]
    box = rng.uniform(BOX[0], BOX[1], (300, 3))
    a = rng.uniform(0, 2 * np.pi, 300)
    cyl = np.c_[CYL_X + CYL_R * np.cos(a), rng.uniform(0, 0.8, 300), CYL_Z + CYL_R * np.sin(a)]
    parts = {"ball": _blobs(shell, 0.7, 0.02, rng), "inside": _blobs(inside, 0.1, 0.02, rng),
             "floor": _blobs(floor, 0.04, 0.02, rng), "box": _blobs(box, 0.9, 0.02, rng),
             "cylinder": _blobs(cyl, 0.9, 0.02, rng)}
    labels = np.concatenate([[k] * len(g) for k, g in parts.items()])
    model = Gaussians.cat(list(parts.values()))
    size = float(np.ptp(np.quantile(src["points"], [0.005, 0.995], axis=0), axis=0).max())
    return rays, src, model, labels, size


def test_the_ball_becomes_discs_on_its_sphere_and_nothing_else_moves(scene):
    rays, src, model, labels, size = scene
    keep, lattice, stats = snap_spheres(model, src, rays.views, size)
    assert stats["spheres"] == 1 and stats["snapped"] == 1, stats
    gone = ~keep.numpy()
    assert gone[labels == "ball"].all() and gone[labels == "inside"].all()
    assert not gone[np.isin(labels, ["floor", "box", "cylinder"])].any()  # the floor under the ball stays
    assert stats["removed"] == int(gone.sum())
    n = int(math.ceil(4 * math.pi / sphere_snap.STEP ** 2))
    assert lattice is not None and len(lattice) == stats["added"] == n
    p = lattice.means.double().numpy()
    dist = np.linalg.norm(p - BALL_C, axis=1)
    r_lattice = BALL_R * (1 - sphere_snap.SINK * sphere_snap.STEP)
    assert np.abs(dist - r_lattice).max() < 3e-3  # the fit's error: a few mm
    radial = (p - BALL_C) / dist[:, None]
    normals = torch.nn.functional.normalize(lattice.normals.double(), dim=-1).numpy()
    assert (normals * radial).sum(1).min() > 0.9995
    # each disc is tangent to the sphere: its thin local z axis along the radial direction
    from models.gaussians.activations import quats_to_rotmats

    axis_z = quats_to_rotmats(lattice.quats.double())[:, :, 2].numpy()
    assert np.abs((axis_z * radial).sum(1)).min() > 0.9995
    ls = lattice.log_scales.double().numpy()
    assert np.allclose(ls[:, 2] - ls[:, 0], math.log(sphere_snap.THICKNESS))
    # the material the buffers give the ball (the shell's trained F0 of 0.7 is not it)
    assert np.allclose(lattice.f0.numpy(), 0.9, atol=1e-6) and np.allclose(lattice.roughness.numpy(), 0.05, atol=1e-6)
    assert lattice.diffuse.abs().max() < 1e-6
    assert (torch.sigmoid(lattice.opacity_logits) > 0.98).all()


def test_a_fit_the_views_see_through_is_left_as_trained(scene):
    rays, src, model, labels, size = scene
    shifted = dict(src)
    shiny = src["f0"].max(1) > 0.3
    ball = shiny & (np.linalg.norm(src["points"] - BALL_C, axis=1) < 1.1 * BALL_R)
    pts = src["points"].copy()
    pts[ball] += [0.0, 0.0, 0.5]  # the ball's points moved half a metre towards the cameras: into seen air
    shifted["points"] = pts
    keep, lattice, stats = snap_spheres(model, shifted, rays.views, size)
    assert stats["spheres"] == 1 and stats["snapped"] == 0 and lattice is None and bool(keep.all())
    assert any("left as trained" in note and "empty space" in note for note in stats["notes"]), stats["notes"]


def test_no_depth_no_snap():
    g = _blobs(np.zeros((5, 3)), 0.9, 0.1, np.random.default_rng(0))
    keep, lattice, stats = snap_spheres(g, None, [], 1.0)
    assert bool(keep.all()) and lattice is None and stats["snapped"] == 0


def test_the_snapped_ball_renders_the_spheres_normals_and_outline_from_an_unseen_side(scene):
    """Traced from behind the ball (no training camera stands there): the blended normals are the sphere's within
    a degree or two (neighbouring discs are 2.9 degrees apart; median 0.9 here), and the pixels the ball covers
    are the analytic sphere's but for its outline."""
    rays, src, model, labels, size = scene
    keep, lattice, _ = snap_spheres(model, src, rays.views, size)
    ball = lattice  # the ball alone, so that every ray that hits something hits it
    view = plane_view(0, BALL_C + [0.3, 0.4, -1.4], BALL_C, size=(64, 64), fl=70.0, cast=_cast)
    cam = view.camera
    d = torch.tensor(cam.ray_directions().reshape(-1, 3), dtype=torch.float32)
    o = torch.tensor(cam.origin, dtype=torch.float32).expand_as(d).contiguous()
    tracer = Tracer(TracerConfig(num_threads=2), "cpu")
    try:
        out = tracer.trace(o, d, ball)
    finally:
        tracer.close()
    opacity = (1 - out.transmittance).numpy()
    # the analytic sphere along the same rays
    od = o.double().numpy() - BALL_C
    dd = d.double().numpy()
    b = (od * dd).sum(1)
    disc = b * b - ((od * od).sum(1) - BALL_R ** 2)
    hit = disc > 0
    t = -b - np.sqrt(np.maximum(disc, 0))
    true_n = (od + t[:, None] * dd) / BALL_R
    n = torch.nn.functional.normalize(out.normal, dim=-1).double().numpy()
    core = hit & (disc > 0.15 * BALL_R ** 2)  # away from the outline (the normal is grazing there)
    angle = np.degrees(np.arccos(np.clip((n[core] * true_n[core]).sum(1), -1, 1)))
    assert np.median(angle) < 1.5 and np.quantile(angle, 0.95) < 3.0, (np.median(angle), np.quantile(angle, 0.95))
    assert opacity[core].min() > 0.99
    covered = opacity > 0.5
    # the outline: pixels covered but not on the sphere, or on it but not covered, at most a ring one pixel wide
    ring = 2 * math.pi * math.sqrt(hit.sum() / math.pi)
    assert (covered != hit).sum() < ring, ((covered & ~hit).sum(), (hit & ~covered).sum(), ring)


def test_a_ball_the_views_see_small_gets_a_coarser_lattice(scene, monkeypatch):
    """The lattice is no finer than ``PIXEL_SHARE`` of a pixel of the training view that sees the ball largest: with
    that share raised (as a ball far away or small would have it) the spheres' discs are fewer, spaced by it."""
    rays, src, model, labels, size = scene
    pixel = sphere_snap._nearest_footprint(BALL_C, rays.views)
    nearest = min(np.linalg.norm(BALL_C - v.camera.origin) / v.camera.fl_x for v in rays.views)
    assert pixel == pytest.approx(nearest)
    monkeypatch.setattr(sphere_snap, "PIXEL_SHARE", 0.2 * BALL_R / pixel)  # a spacing of 0.2 r
    _, lattice, stats = snap_spheres(model, src, rays.views, size)
    assert stats["snapped"] == 1 and len(lattice) == int(math.ceil(4 * math.pi / 0.2 ** 2))
    width = float(torch.exp(lattice.log_scales[0, 0]))
    assert width == pytest.approx(0.8 * 0.2 * BALL_R, rel=1e-3)
