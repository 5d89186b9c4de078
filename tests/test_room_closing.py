"""Room closing (models/reconstruction/room_closing.py): walls no training view looks at, placed where sharp
reflections in curved mirrors agree on them; a side whose reflections agree best at infinity stays open."""

import math

import numpy as np
import pytest
import torch

from models.gaussians import Gaussians
from models.reconstruction.data import build_rayset
from models.reconstruction.plane_fill import extend_plane_fill, pixel_points, plane_fill_gaussians
from models.reconstruction.reflection_fill import shiny
from models.reconstruction.room_closing import close_room
from models.synth import render_capture
from models.tracer import Tracer, TracerConfig
from stages.config import load_config


@pytest.fixture(scope="module")
def spheres(tmp_path_factory):
    """zoo_spheres, small: chrome spheres (roughness 0 / 0.1 / 0.3) seen by cameras that circle their front; the
    wall behind the cameras (z = 2) and the ceiling (y = 2.5) are in no training frame, only in the spheres."""
    cfg = load_config("zoo_spheres", presets=["ci"],
                      overrides={"synth": {"resolution": [128, 96], "spp": 4,
                                           "cameras": {"train": {"count": 20}, "test": {"count": 0}}}})
    capture = render_capture(cfg["synth"], tmp_path_factory.mktemp("spheres") / "capture", progress=False)
    return build_rayset(capture, "train")


def _seen_surfaces(rays) -> Gaussians:
    """What a warmed-up model holds: opaque surfels on the training pixels' points (no far field), the mirrors'
    left out (thick surfels there would stop the reflections leaving them)."""
    src = pixel_points(rays, max_points=60000)
    matte = ~shiny(src["f0"], src["roughness"][:, None])
    src = {k: v[matte] for k, v in src.items()}
    n = len(src["points"])
    f = torch.float32
    return Gaussians(means=torch.tensor(src["points"], dtype=f), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                     log_scales=torch.full((n, 3), math.log(0.03)), opacity_logits=torch.full((n,), 3.0),
                     diffuse=torch.tensor(src["diffuse"], dtype=f), normals=torch.tensor(src["normals"], dtype=f),
                     roughness=torch.tensor(src["roughness"], dtype=f), f0=torch.tensor(src["f0"], dtype=f))


def test_the_walls_only_curved_mirrors_show_are_placed_where_they_are(spheres):
    rays = spheres
    _, stats = plane_fill_gaussians(rays)
    room = stats["room"]
    n_bound = len(room.bound)
    assert room.hi[1] < 2.2 and room.hi[2] < 1.9  # the first box ends below the ceiling and before the wall
    tracer = Tracer(TracerConfig(num_threads=2))
    walls, points, info = close_room(room, rays, tracer.trace, _seen_surfaces(rays), count=8000)
    assert walls is not None and info["added"] == len(walls.means) <= 8000, info
    placed = {"y": None, "z": None}
    for n, d, inl in room.bound[n_bound:]:  # the walls join the bounds, facing back into the room, no inliers
        assert len(inl) == 0
        axis = int(np.argmax(np.abs(n)))
        placed["xyz"[axis]] = d / n[axis]
    assert placed["y"] is not None and abs(placed["y"] - 2.5) < 0.15, info  # the ceiling
    assert placed["z"] is not None and abs(placed["z"] - 2.0) < 0.15, info  # the wall behind the cameras
    assert "+y at" in info["walls"] and "+z at" in info["walls"]
    # every wall Gaussian lies on a placed wall, inside the room's other bounds, matte, facing into the room
    on_y = (walls.means[:, 1] - placed["y"]).abs() < 1e-3
    on_z = (walls.means[:, 2] - placed["z"]).abs() < 1e-3
    assert bool((on_y | on_z).all()) and on_y.any() and on_z.any()
    assert float(walls.means[:, 0].abs().max()) < 2.1 and float(walls.means[:, 1].min()) > -0.1
    assert float(walls.f0.max()) < 0.3 and float(walls.roughness.min()) > 0.3 and bool((walls.diffuse >= 0).all())
    assert torch.allclose(walls.normals[on_z], torch.tensor([0.0, 0.0, -1.0]), atol=1e-3)
    # the plane fill then reaches them: the side walls and the floor run on to the new wall
    grown, more = extend_plane_fill(room, rays, points, count=8000)
    assert grown is not None and "z" in more["grown"] and float(grown.means[:, 2].max()) > placed["z"] - 0.1


def test_a_side_whose_reflections_agree_at_infinity_stays_open(spheres):
    """Reflections that show a sky (radiance by direction alone) agree best infinitely far away: no wall there,
    and the decision says the sweep's minimum was its far edge."""
    rays = spheres
    t = rays.targets
    d = rays.dirs
    n = torch.nn.functional.normalize(t["normal"], dim=-1)
    r = d - 2 * (d * n).sum(-1, keepdim=True) * n  # what each mirror pixel reflects: a sky, by direction
    sky = 0.5 + 0.45 * torch.stack([torch.sin(7 * r[:, 0]), torch.cos(5 * r[:, 1]), torch.sin(6 * r[:, 2] + 1)], -1)
    rays.targets = dict(t, specular=sky * t["f0"])
    try:
        _, stats = plane_fill_gaussians(rays)
        room = stats["room"]
        walls, points, info = close_room(room, rays, Tracer(TracerConfig(num_threads=2)).trace,
                                         _seen_surfaces(rays), count=8000)
    finally:
        rays.targets = t
    assert walls is None and points is None and info["walls"] == "none", info
    assert any("far edge" in note for note in info["notes"]), info


def test_lights_placed_beyond_a_wall_move_in_front_of_it(spheres):
    """``keep_inside``: the highlight fill's lights above a ceiling the closing placed would be hidden by it;
    they move onto the room's side, one grid spacing in front; points inside stay where they are."""
    from models.reconstruction.room_closing import keep_inside

    _, stats = plane_fill_gaussians(spheres)
    room = stats["room"]
    assert keep_inside(torch.zeros(3, 3), room) == 0  # no wall placed: nothing moves
    room.bound.append((np.array([0.0, -1.0, 0.0]), -2.5, np.zeros(0, dtype=np.int64)))  # a ceiling at y = 2.5
    points = torch.tensor([[0.0, 2.7, 0.0], [0.5, 1.0, 0.2], [0.1, 2.5, -0.3]])
    before = points.clone()
    assert keep_inside(points, room) == 2
    assert torch.allclose(points[:, 1], torch.tensor([2.5 - room.h, 1.0, 2.5 - room.h]))
    assert torch.equal(points[1], before[1]) and torch.equal(points[:, [0, 2]], before[:, [0, 2]])
