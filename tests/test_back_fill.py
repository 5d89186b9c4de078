"""The back-face fill (models/reconstruction/back_fill.py): a thin table top seen only from above, between a
bright ceiling and a dim floor, gets a layer underneath lit by the floor (albedo x E_back); the floor, the
ceiling and a closed box get none; no training view sees a copy; the trainer appends them as fixed priors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from models.capture import Camera, View
from models.gaussians import Gaussians
from models.pathtrace.paths import PathConfig
from models.reconstruction.anchors import quats_z_to
from models.reconstruction.back_fill import back_fill
from models.tracer import Tracer, TracerConfig

F32 = torch.float32
HALF = 3.0  # floor and ceiling span [-HALF, HALF]^2
CEILING, TOP = 1.4, 0.7  # the table top halfway: both sides see the same solid angle of their plane
L_CEILING, L_FLOOR, L_TOP = 1.0, 0.2, 0.5


@pytest.fixture(scope="module")
def tracer():
    t = Tracer(TracerConfig(num_threads=2), "cpu")
    yield t
    t.close()


def _plane(centre, u, v, normal, half_u: float, half_v: float, spacing: float, radiance: float) -> Gaussians:
    """Opaque flat Gaussians on a rectangle, ``normal`` [3], diffuse ``radiance`` grey, matte."""
    a = torch.arange(-half_u + spacing / 2, half_u, spacing)
    b = torch.arange(-half_v + spacing / 2, half_v, spacing)
    aa, bb = torch.meshgrid(a, b, indexing="ij")
    c, u, v, n = (torch.tensor(x, dtype=F32) for x in (centre, u, v, normal))
    p = c + aa.reshape(-1, 1) * u + bb.reshape(-1, 1) * v
    k = len(p)
    nn = n.expand(k, 3).clone()
    return Gaussians(means=p, quats=quats_z_to(nn),
                     log_scales=torch.tensor([math.log(0.8 * spacing)] * 2 + [math.log(0.002)]).repeat(k, 1),
                     opacity_logits=torch.full((k,), 6.0), diffuse=torch.full((k, 3), radiance), normals=nn,
                     roughness=torch.ones(k), f0=torch.zeros(k, 3))


def _room(box: bool = False) -> tuple[Gaussians, slice, slice]:
    """Floor (dim), ceiling (bright), a table top seen from above (its top's radiance), optionally a closed box
    on the floor; the rows of the table top and of the box."""
    floor = _plane([0, 0, 0], [1, 0, 0], [0, 0, 1], [0, 1, 0], HALF, HALF, 0.1, L_FLOOR)
    ceiling = _plane([0, CEILING, 0], [1, 0, 0], [0, 0, 1], [0, -1, 0], HALF, HALF, 0.1, L_CEILING)
    top = _plane([0, TOP, 0], [1, 0, 0], [0, 0, 1], [0, 1, 0], 0.3, 0.3, 0.03, L_TOP)
    parts = [floor, ceiling, top]
    if box:  # a closed 0.12 m box at (1.2, 0.06, 0): every face's back is the box's inside
        s, c = 0.06, np.array([1.2, 0.06, 0.0])
        for axis in range(3):
            for sign in (-1, 1):
                n = np.zeros(3)
                n[axis] = sign
                u, v = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
                parts.append(_plane(c + s * n, u, v, n, s, s, 0.02, 0.3))
    rows_top = slice(len(floor) + len(ceiling), len(floor) + len(ceiling) + len(top))
    return Gaussians.cat(parts), rows_top, slice(rows_top.stop, None)


def _cameras(n: int = 8) -> list[View]:
    """Training cameras on a circle of radius 2 at 1.2 m, looking at (0, 0.45, 0): the table from above, the
    floor under its edges."""
    views = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = np.array([2 * math.cos(a), 1.2, 2 * math.sin(a)])
        fwd = np.array([0.0, 0.45, 0.0]) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -fwd, eye
        views.append(View(f"train_{i}", Camera(48, 36, 40.0, 40.0, 24.0, 18.0, c2w), "train"))
    return views


def _depths(scene: Gaussians, views: list[View], tracer: Tracer) -> list[np.ndarray]:
    from models.reconstruction.data import view_rays

    out = []
    for v in views:
        o, d = view_rays(v)
        t = tracer.trace(torch.tensor(np.ascontiguousarray(o), dtype=F32), torch.tensor(d, dtype=F32), scene)
        opacity = 1 - t.transmittance
        depth = torch.where(opacity > 0.5, t.depth / opacity.clamp_min(1e-6), torch.zeros_like(t.depth))
        out.append(depth.reshape(v.camera.height, v.camera.width).double().numpy())
    return out


def _size(scene: Gaussians) -> float:
    lo, hi = torch.quantile(scene.means.double(), 0.01, dim=0), torch.quantile(scene.means.double(), 0.99, dim=0)
    return float((hi - lo).norm())


def test_the_underside_of_a_table_top_seen_from_above_is_lit_by_the_floor(tracer):
    scene, rows_top, _ = _room()
    views = _cameras()
    copies, stats = back_fill(scene, views, _depths(scene, views, tracer), tracer.trace, PathConfig(), _size(scene))
    assert copies is not None
    top = scene.means[rows_top]
    n_top = len(top)
    # every copy sits just under the table top, facing down; most of the top has one
    p = copies.means
    assert bool(((p[:, [0, 2]].abs() <= 0.3 + 1e-4).all(1) & (p[:, 1] < TOP) & (p[:, 1] > TOP - 0.01)).all())
    torch.testing.assert_close(torch.nn.functional.normalize(copies.normals, dim=-1),
                               torch.tensor([0.0, -1.0, 0.0]).expand(len(copies), 3))
    assert len(copies) >= 0.7 * n_top, stats
    assert stats["count"] == len(copies)
    # albedo = L_TOP / E_front, E the same solid angle of ceiling above and floor below (the top halfway):
    # back = L_TOP x L_FLOOR / L_CEILING, to the sampling noise of 32 rays x 8 neighbours
    expected = L_TOP * L_FLOOR / L_CEILING
    assert abs(float(copies.diffuse.mean()) - expected) < 0.1 * expected
    assert float((copies.diffuse - expected).abs().max()) < 0.3 * expected
    # shape, opacity and specular material are the top's
    torch.testing.assert_close(copies.log_scales, scene.log_scales[rows_top][:1].expand(len(copies), 3))
    assert bool((copies.opacity_logits == 6.0).all()) and bool((copies.f0 == 0).all())


def test_no_copy_behind_a_floor_a_ceiling_or_inside_a_closed_box_and_none_a_training_view_sees(tracer):
    from models.reconstruction.data import view_rays

    scene, rows_top, rows_box = _room(box=True)
    views = _cameras()
    copies, stats = back_fill(scene, views, _depths(scene, views, tracer), tracer.trace, PathConfig(), _size(scene))
    assert copies is not None
    # the table top's only: nothing under the floor, above the ceiling or in the box
    p = copies.means
    assert bool(((p[:, [0, 2]].abs() <= 0.3 + 1e-4).all(1) & (p[:, 1] > TOP - 0.01) & (p[:, 1] < TOP)).all()), stats
    # the training views render the same with the copies
    with_copies = Gaussians.cat([scene, copies])
    for v in views:
        o, d = view_rays(v)
        o, d = torch.tensor(np.ascontiguousarray(o), dtype=F32), torch.tensor(d, dtype=F32)
        a, b = tracer.trace(o, d, scene).diffuse, tracer.trace(o, d, with_copies).diffuse
        assert float((a - b).abs().max()) < 0.02, v.name


def test_without_depths_nothing_is_carved_and_nothing_is_added(tracer):
    scene, _, _ = _room()
    views = _cameras(4)
    zeros = [np.zeros((v.camera.height, v.camera.width)) for v in views]
    copies, stats = back_fill(scene, views, zeros, tracer.trace, PathConfig(), _size(scene))
    assert copies is None and stats["carved"] == 0 and stats["count"] == 0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: the fill's CUDA path runs when one is present")
def test_the_fill_on_cuda_puts_the_same_layer_under_the_table_top(tracer):
    """The trainer calls the fill with its device's Gaussians and tracer (models/reconstruction/trainer.py
    ``fill_backs``): on CUDA the copies are those of the CPU, to the estimator's noise."""
    scene, rows_top, _ = _room()
    views = _cameras()
    cpu, _ = back_fill(scene, views, _depths(scene, views, tracer), tracer.trace, PathConfig(), _size(scene))
    gpu_tracer = Tracer(TracerConfig(), "cuda")
    try:
        on_gpu = scene.to("cuda")
        gpu, stats = back_fill(on_gpu, views, _depths(scene, views, tracer), gpu_tracer.trace, PathConfig(),
                               _size(scene))
    finally:
        gpu_tracer.close()
    assert gpu is not None and abs(len(gpu) - len(cpu)) <= 0.05 * len(cpu), stats
    expected = L_TOP * L_FLOOR / L_CEILING
    assert abs(float(gpu.diffuse.mean()) - expected) < 0.1 * expected
    assert bool((gpu.means[:, 1].cpu() < TOP).all())
