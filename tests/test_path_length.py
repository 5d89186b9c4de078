"""The path-length decision (models/reconstruction/path_length.py) on analytic rooms of flat, opaque Gaussians."""

from __future__ import annotations

import math

import pytest
import torch

from models.gaussians import Gaussians
from models.pathtrace.paths import PathConfig
from models.reconstruction.path_length import carried_throughput, cosine_directions, going_on, needed_length
from models.tracer import Tracer, TracerConfig


def _box(mirror_faces: set[int], spacing: float = 0.08, thickness: float = 0.01) -> Gaussians:
    """Surfels tiling the six inner faces of the box [-1, 1]^3 (face 2 * axis + (0: at -1, 1: at +1)), normals
    inwards, opaque; faces in ``mirror_faces``: F0 0.95, roughness 0 (a mirror), the others matte (F0 0.04,
    roughness 0.8), every diffuse 0.5. ``thickness``: scale across the face, in units of ``spacing`` (0.7: round
    blobs, as training leaves a mirror)."""
    ticks = torch.arange(-1 + spacing / 2, 1, spacing, dtype=torch.float64)
    u, v = torch.meshgrid(ticks, ticks, indexing="ij")
    parts = []
    for face in range(6):
        axis, side = face // 2, face % 2
        means = torch.zeros(u.numel(), 3, dtype=torch.float64)
        others = [a for a in range(3) if a != axis]
        means[:, others[0]], means[:, others[1]] = u.reshape(-1), v.reshape(-1)
        means[:, axis] = 1.0 if side else -1.0
        log_scales = torch.full_like(means, math.log(0.7 * spacing))
        log_scales[:, axis] = math.log(thickness * spacing)
        normal = torch.zeros(3, dtype=torch.float64)
        normal[axis] = -1.0 if side else 1.0
        mirror = face in mirror_faces
        parts.append(dict(means=means, log_scales=log_scales, normals=normal.expand_as(means),
                          f0=torch.full_like(means, 0.95 if mirror else 0.04),
                          roughness=torch.full((len(means),), 0.0 if mirror else 0.8, dtype=torch.float64)))
    cat = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    n = len(cat["means"])
    return Gaussians(means=cat["means"].float(), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                     log_scales=cat["log_scales"].float(), opacity_logits=torch.full((n,), 6.0),
                     diffuse=torch.full((n, 3), 0.5), normals=cat["normals"].float().contiguous(),
                     roughness=cat["roughness"].float(), f0=cat["f0"].float())


def _carried(mirror_faces: set[int], limit: int = 8, thickness: float = 0.01,
             stats: dict | None = None) -> list[torch.Tensor]:
    """Reflections leaving 2000 random points of the mirror at x = -1 (face 0)."""
    g = torch.Generator().manual_seed(0)
    pts = torch.cat([torch.full((2000, 1), -1.0), torch.rand(2000, 2, generator=g) * 1.6 - 0.8], dim=1)
    normals = torch.tensor([[1.0, 0.0, 0.0]]).repeat(2000, 1)
    tracer = Tracer(TracerConfig(num_threads=2))
    path = PathConfig(origin_offset=0.01, min_throughput=0.01, origin_grazing=1.0, back_normal="flip")  # as training
    return carried_throughput(pts, normals, tracer.trace, _box(mirror_faces, thickness=thickness), path, limit, g,
                              stats)


def test_cosine_directions_are_cosine_distributed_around_the_normal():
    n = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]]), dim=-1).repeat(200_000, 1)
    w = cosine_directions(n, torch.Generator().manual_seed(1))
    cos = (w * n).sum(-1)
    assert torch.allclose(w.norm(dim=-1), torch.ones(len(w)), atol=1e-5) and bool((cos >= 0).all())
    # cos^2 is uniform on [0, 1] for a cosine-weighted hemisphere: mean 1/2, and E[cos] = 2/3
    assert float((cos ** 2).mean()) == pytest.approx(0.5, abs=0.005)
    assert float(cos.mean()) == pytest.approx(2 / 3, abs=0.005)


def test_a_hall_of_mirrors_needs_the_limit_a_mirror_among_matte_walls_does_not():
    """All six faces mirrors: nothing ever leaves the box and 0.95^k stays above 0.2 for 30 bounces, so every
    reflection still carries light after any length: the decision takes the limit. Only face 0 a mirror: its
    reflections end on matte walls (0.04 at most); one that comes back to the mirror never reaches it (the
    opposite face is matte), so after 3 segments nothing carries more than 0.2: the paper's 3. (Training's paths, as
    the decision's: a fixed offset. With the renders' grazing offset, ``PathConfig.origin_grazing`` 0.1, a few
    reflections near the box's edges start past the adjacent mirror and leave: 1.2 % after 3 segments and 6.4 %
    after 8, against 0.7 % and 2.4 % here.)"""
    hall = _carried(set(range(6)))
    assert going_on(hall, 3, 0.2) > 0.99 and going_on(hall, 8, 0.2) > 0.95
    assert needed_length(hall, 3, 8, 0.2, 0.05) == 8
    single = _carried({0})
    assert going_on(single, 3, 0.2) == 0.0
    assert needed_length(single, 3, 8, 0.2, 0.05) == 3


def test_two_facing_mirrors_need_a_length_between():
    """Faces 0 and 1 mirrors (x = -1 and +1), the rest matte: a reflection bounces between them until it drifts
    onto a matte face; steep ones take many bounces, most (in a cube) few. The fraction still carrying light falls
    with the length, and the decision stops where it drops below the allowed fraction."""
    pair = _carried({0, 1})
    fractions = [going_on(pair, k, 0.2) for k in range(3, 9)]
    assert all(a >= b for a, b in zip(fractions, fractions[1:])) and fractions[0] > 0.05
    chosen = needed_length(pair, 3, 8, 0.2, 0.05)
    assert 3 < chosen <= 8
    assert going_on(pair, chosen, 0.2) <= 0.05 or chosen == 8
    assert going_on(pair, chosen - 1, 0.2) > 0.05


def test_a_thick_mirror_meets_itself_from_behind_and_that_is_not_a_second_mirror():
    """A mirror of round blobs (scale 0.7 of their spacing across the face too, as training leaves a mirror:
    mirror_book's are 1-2 cm balls): a reflection leaving it obliquely meets the next blob of the same mirror,
    whose normal points along the ray. Taken as a reflection of the mirror in itself it would carry on at 0.95
    (mirror_book: 24 % still carrying after 3 segments, so the decision took the limit); met from behind, the
    ray goes on through it. The single thick mirror needs the paper's 3, and a hall of thick mirrors still the
    limit (its reflections pass their own mirror's blobs and meet the other mirrors from the front)."""
    from models.pathtrace.paths import trace_paths
    g = torch.Generator().manual_seed(0)
    pts = torch.cat([torch.full((2000, 1), -1.0), torch.rand(2000, 2, generator=g) * 1.6 - 0.8], dim=1)
    normals = torch.tensor([[1.0, 0.0, 0.0]]).repeat(2000, 1)
    dirs = cosine_directions(normals, g)
    tracer = Tracer(TracerConfig(num_threads=2))
    path = PathConfig(origin_offset=0.01, min_throughput=0.01, max_path_length=8)
    with torch.no_grad():  # what the decision measured before: every hit reflects
        plain = trace_paths(tracer.trace, pts + 0.01 * dirs, dirs, _box({0}, thickness=0.7), path, g)
    assert float((plain.throughput[1] > 0.2).double().mean()) > 0.05  # the mirror "reflects itself"
    stats: dict = {}
    single = _carried({0}, thickness=0.7, stats=stats)
    assert stats["back"] > 0.05 * 2000 and stats["rays"] >= 2000
    assert going_on(single, 3, 0.2) < 0.01
    assert needed_length(single, 3, 8, 0.2, 0.05) == 3
    hall = _carried(set(range(6)), thickness=0.7)
    assert going_on(hall, 8, 0.2) > 0.5
    assert needed_length(hall, 3, 8, 0.2, 0.05) == 8
