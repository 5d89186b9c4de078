"""Gaussians along the reflected frusta: placed only on mirror reflections that pass through the scene,
spread along them inside the scene's box, coloured specular / F0."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from models.gaussians import Gaussians
from models.tracer._torch_impl import reference_trace
from models.reconstruction.data import RaySet
from models.reconstruction.reflection_fill import (box_exit, diffuse_level, footprint_angle, highlight_fill_gaussians,
                                                light_points, matte_material, near_seen_light,
                                                reflection_fill_gaussians, reflection_spread, seen_empty,
                                                snap_to_planes, sweep_box_scale)


def _gaussians(means: torch.Tensor, scale: float, opacity: float) -> Gaussians:
    n = len(means)
    return Gaussians(means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                     log_scales=torch.full((n, 3), math.log(scale)),
                     opacity_logits=torch.full((n,), math.log(opacity / (1 - opacity))),
                     diffuse=torch.full((n, 3), 0.5), normals=torch.zeros(n, 3), roughness=torch.full((n,), 0.5),
                     f0=torch.full((n, 3), 0.04))


def _scene() -> Gaussians:
    """Faint corners spanning the box [-1, 1]^3, and an opaque ceiling over the x < 0 half at z = 0.95."""
    corners = torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    g = torch.linspace(-1, 1, 21)
    xs, ys = torch.meshgrid(g[g < -0.05], g, indexing="ij")
    ceiling = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.full((xs.numel(),), 0.95)], -1)
    a, b = _gaussians(corners, 0.01, 0.1), _gaussians(ceiling, 0.08, 0.99)
    return Gaussians(**{k: torch.cat([getattr(a, k), getattr(b, k)]) for k in a.params()})


def _mirror_rays(f0: float = 0.9) -> RaySet:
    """Cameras looking straight down at a floor mirror (z = -0.9, normal +z): reflections go straight up."""
    g = torch.linspace(-0.8, 0.8, 12)
    xs, ys = torch.meshgrid(g, g, indexing="ij")
    n = xs.numel()
    origins = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.full((n,), 0.8)], -1)
    dirs = torch.tensor([[0.0, 0.0, -1.0]]).repeat(n, 1)
    colour = torch.tensor([0.2, 0.5, 3.0])  # the radiance the mirror shows
    targets = {"depth": torch.full((n, 1), 1.7), "normal": torch.tensor([[0.0, 0, 1]]).repeat(n, 1),
               "f0": torch.full((n, 3), f0), "roughness": torch.zeros(n, 1),
               "specular": (f0 * colour).repeat(n, 1), "diffuse": torch.zeros(n, 3)}
    return RaySet(origins, dirs, torch.ones(n, dtype=torch.bool), targets, torch.zeros(n, dtype=torch.long), [])


def test_fill_follows_open_reflections_only():
    scene, rays = _scene(), _mirror_rays()
    fill, stats = reflection_fill_gaussians(rays, reference_trace, scene, count=400, per_ray=4)
    assert stats["mirror_rays"] == 144 and 0 < stats["open_rays"] < 144
    assert fill is not None and len(fill) == stats["added"] <= 400 and len(fill) % 4 == 0
    means = fill.means
    assert (means[:, 0] > -0.05).all(), "nothing under the opaque ceiling"  # its reflections are blocked
    assert (means[:, 2] > -0.9).all() and (means[:, 2] < 1.1 + 1e-4).all()  # mirror .. the padded box top
    # each open reflection gets per_ray Gaussians at distinct heights above its own mirror point
    xy = means[:, :2].reshape(-1, 4, 2)
    assert torch.allclose(xy, xy[:, :1].expand_as(xy), atol=1e-5)
    assert (means[:, 2].reshape(-1, 4).diff(dim=1) > 0).all()
    torch.testing.assert_close(fill.diffuse, torch.tensor([[0.2, 0.5, 3.0]]).expand(len(fill), 3))
    assert torch.isfinite(fill.log_scales).all()
    # unseen_material: the room's matte roughness (the scene's non-mirror Gaussians: 0.5, not a constant) and F0 0,
    # not the room's F0 (0.04): nothing supervises it, and a guessed sheen shows where the truth reflects nothing
    assert (fill.roughness == 0.5).all() and (fill.f0 == 0).all()
    # normals face back along the reflected ray they were found on (straight up from the floor mirror): a view
    # that looks at them directly traces their sheen; a zero normal would stop every path there
    torch.testing.assert_close(fill.normals, torch.tensor([[0.0, 0.0, -1.0]]).expand(len(fill), 3))


def test_matte_material_ignores_mirrors_and_falls_back_without_matte_gaussians():
    g = _gaussians(torch.zeros(5, 3), 0.1, 0.5)
    g.roughness[:] = torch.tensor([0.8, 0.9, 1.0, 0.0, 0.0])
    g.f0[:] = torch.tensor([0.02, 0.03, 0.05, 0.95, 0.95])[:, None]
    assert matte_material(g) == pytest.approx((0.9, 0.03))  # the two mirrors (F0 0.95, roughness 0) left out
    g.roughness[:], g.f0[:] = 0.0, 0.9
    assert matte_material(g) == (1.0, 0.04)


def test_highlight_fill_puts_emitters_where_bright_open_reflections_leave_the_box():
    """A lamp (radiance 10) over the mirror's |x| > 0.3 parts; the rest reflects dim colour. Under the opaque
    ceiling (x < 0) the lamp's reflections are blocked: emitters only for the open, bright ones (x > 0.3)."""
    rays = _mirror_rays()
    x = rays.origins[:, 0]
    lamp = x.abs() > 0.3
    rays.targets["specular"][lamp] = 0.9 * 10.0
    rays.targets["diffuse"][:] = 0.5  # the brightest lit surface: 0.5, so the lamp (10) stands out
    lights, stats = highlight_fill_gaussians(rays, reference_trace, _scene())
    assert stats["mirror_rays"] == 144
    want = (x > 0.3).sum().item()
    assert lights is not None and stats["highlight_rays"] == want and len(lights) == stats["added"] == want
    torch.testing.assert_close(lights.means[:, :2].sort(0).values, rays.origins[x > 0.3, :2].sort(0).values)
    assert torch.allclose(lights.means[:, 2], torch.full((want,), 1.1), atol=0.01)  # the padded box top
    torch.testing.assert_close(lights.diffuse, torch.full((want, 3), 10.0))
    spacing = 1.6 / 11  # the mirror grid: emitters tile the lamp's patch
    torch.testing.assert_close(lights.log_scales.exp(), torch.full((want, 3), spacing), atol=1e-4, rtol=1e-4)
    assert (torch.sigmoid(lights.opacity_logits) - 0.5).abs().max() < 1e-6 and (lights.roughness == 1).all()


def _lamp_under_ceiling():
    """A lamp (radiance 10) over the mirror's |x| > 0.3 parts, the brightest lit surface 0.5, and ``_scene()``'s
    opaque ceiling over x < 0 (marked, for the tests that need it, as the plane fill): (rays, the mirror points'
    x, scene, ceiling mask)."""
    rays = _mirror_rays()
    x = rays.origins[:, 0]
    rays.targets["specular"][x.abs() > 0.3] = 0.9 * 10.0
    rays.targets["diffuse"][:] = 0.5
    scene = _scene()
    return rays, x, scene, torch.arange(len(scene)) >= 8  # _scene(): 8 faint corners, then the ceiling


def test_highlight_fill_says_how_many_highlights_end_on_the_plane_fill():
    """The same lamp; the opaque ceiling over x < 0, marked as the plane fill, blocks the x < -0.3 highlights:
    with ``on_fill=False`` they are counted and noted (a light on an unseen ceiling gets no emitters); the
    emitters (x > 0.3) are the same as without the mask, and without it nothing is counted."""
    rays, x, scene, ceiling = _lamp_under_ceiling()
    lights, stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=ceiling)  # on_fill off (default)
    plain, plain_stats = highlight_fill_gaussians(rays, reference_trace, scene)
    assert stats["on_fill"] == (x < -0.3).sum().item() and plain_stats["on_fill"] == 0
    assert stats["on_fill_added"] == 0 and plain_stats["on_fill_added"] == 0
    on_fill = [n for n in stats["notes"] if "end on the plane fill" in n]
    assert len(on_fill) == 1 and f"{stats['on_fill']} of {(x.abs() > 0.3).sum().item()} highlight" in on_fill[0]
    assert stats["notes"][1:] == plain_stats["notes"]  # the sweep's own note (box scale at its edge) kept
    assert not any("plane fill" in n for n in plain_stats["notes"])
    torch.testing.assert_close(lights.means, plain.means)
    _, seen = highlight_fill_gaussians(rays, reference_trace, scene, fill=~ceiling)  # blocked by seen geometry
    assert seen["on_fill"] == 0 and not any("plane fill" in n for n in seen["notes"])


def test_highlight_fill_puts_emitters_on_the_plane_fill_where_highlights_end_on_it():
    """A lamp on an unseen ceiling (the plane fill over x < 0 at z = 0.95, the lamp's reflections x < -0.3):
    with ``on_fill`` each highlight that ends on the fill gets an emitter just in front of the fill's front, over its
    own mirror point, with the reflection's radiance; the open highlights' emitters (x > 0.3, on the swept box)
    are unchanged."""
    rays, x, scene, ceiling = _lamp_under_ceiling()
    lights, stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=ceiling, on_fill=True)
    plain, _ = highlight_fill_gaussians(rays, reference_trace, scene)
    want = (x < -0.3).sum().item()
    assert stats["on_fill"] == stats["on_fill_added"] == want and stats["added"] == len(plain)
    assert not any("plane fill" in n for n in stats["notes"])
    assert len(lights) == len(plain) + want
    torch.testing.assert_close(lights.means[:len(plain)], plain.means)  # the open ones first, as before
    on = lights.means[len(plain):]
    torch.testing.assert_close(on[:, :2].sort(0).values, rays.origins[x < -0.3, :2].sort(0).values)
    # in front of the ceiling Gaussians (centres z = 0.95, sigma 0.08): between their front and their centre
    assert (on[:, 2] > 0.95 - 3 * 0.08).all() and (on[:, 2] < 0.95).all()
    torch.testing.assert_close(lights.diffuse[len(plain):], torch.full((want, 3), 10.0))
    assert torch.isfinite(lights.log_scales).all() and (lights.roughness == 1).all()


def test_highlight_fill_on_the_plane_fill_leaves_out_a_highlight_among_dark_reflections(monkeypatch):
    """``on_fill_purity``: the lamp's highlights ending on the unseen ceiling (x < -0.3) keep their emitters, but a
    stray highlight among dark reflections there (a rough reflector's blurred highlight: x = -0.07, where the rest
    of the fill's reflections are dark) gets none: of the reflections ending near it only 1 in 4 is a highlight.
    Without the purity test it gets one."""
    import models.reconstruction.reflection_fill as rf

    monkeypatch.setattr(rf, "PURITY_RADIUS", 0.08)  # x the fill's 2 m: the mirror grid's next neighbours (0.145 m)
    rays, x, scene, ceiling = _lamp_under_ceiling()
    y = rays.origins[:, 1]
    dark = (x.abs() <= 0.3)
    rays.targets["specular"][dark] = 0.9 * 0.1  # dark reflections (below the lit surfaces' level)
    stray = int(torch.nonzero((x > -0.1) & (x < 0) & (y > 0) & (y < 0.1)).reshape(-1)[0])
    rays.targets["specular"][stray] = 0.9 * 10.0
    lights, stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=ceiling, on_fill=True,
                                             on_fill_purity=0.5)
    loose, loose_stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=ceiling, on_fill=True)
    lamp = int((x < -0.3).sum())
    assert stats["on_fill"] == loose_stats["on_fill"] == lamp + 1
    assert loose_stats["on_fill_added"] == lamp + 1 and loose_stats["on_fill_impure"] == 0
    assert stats["on_fill_added"] == lamp and stats["on_fill_impure"] == 1
    on = lights.means[stats["added"]:]
    assert (on[:, 0] < -0.3).all() and (loose.means[loose_stats["added"]:, 0] > -0.1).sum() == 1


def test_the_on_fill_purity_weighs_highlights_and_dark_reflections_drawn_at_their_own_rates(monkeypatch):
    """``on_fill_purity`` compares the highlights and the dark reflections that end near an emitter; the two are
    drawn down to ``max_count`` and 4 x ``max_count`` at their own rates, so each counts for the share it stands
    for. The lamp on the unseen ceiling with a wide neighbourhood (0.4 m: its rim sees the dark reflections beside
    it): every lamp end is pure with all 48 drawn, and still with 20 drawn (unweighted, the
    20 counted against all 24 dark ones left 3 of them out)."""
    import models.reconstruction.reflection_fill as rf

    monkeypatch.setattr(rf, "PURITY_RADIUS", 0.2)
    for max_count, placed in [(4000, 48), (20, 20), (12, 12)]:
        rays, x, scene, ceiling = _lamp_under_ceiling()
        rays.targets["specular"][x.abs() <= 0.3] = 0.9 * 0.1  # dark reflections beside the lamp
        _, stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=ceiling, on_fill=True,
                                            on_fill_purity=0.5, max_count=max_count)
        assert stats["on_fill"] == 48 and stats["on_fill_impure"] == 0 and stats["on_fill_added"] == placed


def test_highlight_fill_leaves_out_highlights_whose_footprint_holds_a_light_seen_directly(monkeypatch):
    """``skip_seen_lights``: the lamp's highlights, on the unseen ceiling (x < -0.3) and open (x > 0.3), with a
    light the cameras see directly along the mirror grid's two outer edges (x = -0.9 on the ceiling, x = 0.9 at the
    swept box's top). Each pixel spans 0.1 rad of reflection (a curved mirror's): 1.8 m up, a footprint of 0.18 m
    holds the seen light for the outermost column (x = -0.8 / 0.8, 0.1 m from it) and not the next (0.245 m):
    those 12 + 12 get no emitter, the rest keep theirs, unmoved. With a flat mirror's footprint (1 mrad), or the
    option off, every highlight keeps its emitter."""
    import models.reconstruction.reflection_fill as rf

    ys = torch.linspace(-0.8, 0.8, 12, dtype=torch.float64)
    seen = torch.cat([torch.stack([torch.full_like(ys, -0.9), ys, torch.full_like(ys, 0.95)], -1),
                      torch.stack([torch.full_like(ys, 0.9), ys, torch.full_like(ys, 1.1)], -1)]).numpy()
    monkeypatch.setattr(rf, "light_points", lambda rays: seen)
    for spread, skipped in [(0.1, 12), (1e-3, 0)]:
        monkeypatch.setattr(rf, "footprint_angle", lambda rays, index, a=spread: torch.full((len(index),), a))
        rays, x, scene, ceiling = _lamp_under_ceiling()
        lights, stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=ceiling, on_fill=True,
                                                 skip_seen_lights=True)
        plain, plain_stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=ceiling, on_fill=True)
        assert plain_stats["seen_light"] == 0 and plain_stats["added"] == plain_stats["on_fill_added"] == 48
        assert stats["seen_light"] == 2 * skipped
        assert stats["added"] == stats["on_fill_added"] == 48 - skipped
        kept = plain.means[(plain.means[:, 0].abs() < 0.75) if skipped else slice(None)]
        torch.testing.assert_close(lights.means.sort(0).values, kept.sort(0).values)


def test_reflection_spread_is_the_pixel_angle_on_a_flat_mirror_and_wide_on_a_ball():
    """One pixel's spread of reflection: on a flat mirror the angle between neighbouring pixels' rays (a mirror
    keeps angles), on a ball 0.4 m across 3 m away many times that; neighbours on another surface (a depth jump)
    or a matte one do not count, and a pixel with none has 0."""
    from models.capture import View
    from models.capture.camera import Camera

    cam = Camera(width=16, height=12, fl_x=40.0, fl_y=40.0, cx=8.0, cy=6.0, c2w=np.eye(4))  # looks down -z
    d = torch.tensor(cam.ray_directions().reshape(-1, 3))
    n = len(d)
    o = torch.zeros(n, 3, dtype=torch.float64)

    def rays_of(depth, normal, f0):
        t = {"depth": depth.reshape(-1, 1), "normal": normal, "f0": f0.reshape(-1, 1).repeat(1, 3),
             "roughness": torch.zeros(n, 1, dtype=torch.float64)}
        view = View(name="v", camera=cam, split="train", buffers={})
        return RaySet(o, d, torch.ones(n, dtype=torch.bool), t, torch.zeros(n, dtype=torch.long), [view])

    # a flat mirror z = -2 facing the camera
    flat = rays_of(2.0 / -d[:, 2], torch.tensor([[0.0, 0, 1]], dtype=torch.float64).repeat(n, 1),
                   torch.full((n,), 0.9, dtype=torch.float64))
    centre = 6 * 16 + 8
    pixel = max(float(torch.arccos((d[centre] * d[j]).sum().clamp(-1, 1))) for j in (centre - 1, centre + 1,
                                                                                    centre - 16, centre + 16))
    spread = reflection_spread(flat, torch.tensor([centre]))
    assert spread.item() == pytest.approx(pixel, rel=1e-6) and pixel == pytest.approx(1 / 40, rel=0.01)
    # a ball of radius 0.2 at 3 m: what misses it is a matte wall at 4 m
    c, radius = torch.tensor([0.0, 0.0, -3.0], dtype=torch.float64), 0.2
    b = (d @ c)
    disc = b * b - (c @ c - radius * radius)
    hit = disc > 0
    depth = torch.where(hit, b - disc.clamp_min(0).sqrt(), 4.0 / -d[:, 2])
    normal = torch.nn.functional.normalize(torch.where(hit[:, None], d * depth[:, None] - c,
                                                       torch.tensor([0.0, 0, 1], dtype=torch.float64)), dim=-1)
    ball = rays_of(depth, normal, torch.where(hit, 0.9, 0.0))
    assert hit[centre] and hit.sum() >= 5
    wide = reflection_spread(ball, torch.tensor([centre]))
    assert wide.item() > 5 * pixel  # ~2 x (pixel footprint 3/40 m) / (radius 0.2 m) rad, less the view's turn
    alone = torch.nonzero(hit).reshape(-1)
    lonely = [int(i) for i in alone if not any(bool(hit[j]) for j in (i - 1, i + 1, i - 16, i + 16))]
    if lonely:
        assert (reflection_spread(ball, torch.tensor(lonely)) == 0).all()
    matte = rays_of(depth, normal, torch.zeros(n, dtype=torch.float64))
    assert reflection_spread(matte, torch.tensor([centre])).item() == 0.0
    # the glossy lobe widens it: 2 alpha = 2 roughness^2 more
    flat.targets["roughness"][:] = 0.25
    assert footprint_angle(flat, torch.tensor([centre])).item() == pytest.approx(pixel + 2 * 0.25 ** 2, rel=1e-6)
    # footprint test: a light 0.1 m from where a 2 m reflection ends is in a 0.1 rad footprint, not a 0.04 one
    ends, starts = torch.tensor([[0.0, 0.0, 2.0]] * 2), torch.zeros(2, 3)
    light = np.array([[0.1, 0.0, 2.0]])
    assert near_seen_light(ends, starts, torch.tensor([0.1, 0.04]), light).tolist() == [True, False]
    assert not near_seen_light(ends, starts, torch.tensor([0.1, 0.1]), None).any()


def test_light_points_are_the_pixels_that_show_a_light_at_their_depth():
    from models.capture import View
    from models.capture.camera import Camera

    cam = Camera(width=4, height=2, fl_x=4.0, fl_y=4.0, cx=2.0, cy=1.0, c2w=np.eye(4))
    emission = np.zeros((2, 4, 3), np.float32)
    emission[0, 1] = 5.0
    views = [View(name="v", camera=cam, split="train", buffers={"emission": emission})]
    d = torch.tensor(cam.ray_directions().reshape(-1, 3))
    rays = RaySet(torch.zeros(8, 3, dtype=torch.float64), d, torch.ones(8, dtype=torch.bool),
                  {"depth": torch.full((8, 1), 2.0, dtype=torch.float64)}, torch.zeros(8, dtype=torch.long), views)
    np.testing.assert_allclose(light_points(rays), (2.0 * d[1:2]).numpy())
    views[0].buffers["emission"] = np.zeros((2, 4, 3), np.float32)
    assert light_points(rays) is None


def test_highlight_fill_on_the_plane_fill_puts_emitters_on_the_rooms_plane_under_the_fill():
    """``on_fill_plane``: the emitters of highlights ending on the fill go where their rays cross the room's plane
    the fill lies on (z = 0.95), ``PLANE_OFFSET`` x the fill's side in front of it, not at the fill's front (where a
    grazing ray meets the fill's support, short of the plane); moved along the ray, a grazing ray's emitter moves
    sideways too (``snap_to_planes`` with the offset along the normal, from either side of the plane); a plane the
    ray heads into, or one farther than the tolerance, takes nothing."""
    from models.reconstruction.reflection_fill import PLANE_OFFSET

    rays, x, scene, ceiling = _lamp_under_ceiling()
    ceiling_plane = ((0.0, 0.0, 1.0), 0.95)
    lights, stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=ceiling, on_fill=True,
                                             on_fill_planes=[ceiling_plane, ((0.0, 0.0, -1.0), 0.9)])
    front, front_stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=ceiling, on_fill=True)
    want = int((x < -0.3).sum())
    assert stats["on_plane"] == stats["on_fill_added"] == want and front_stats["on_plane"] == 0
    on, was = lights.means[stats["added"]:], front.means[front_stats["added"]:]
    side = 2.0  # the fill (the ceiling Gaussians): y from -1 to 1
    torch.testing.assert_close(on[:, 2], torch.full((want,), 0.95 - PLANE_OFFSET * side))
    torch.testing.assert_close(on[:, :2], was[:, :2])  # straight up: the same place on the ceiling
    r = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, 0.2], [1.0, 0.0, 0.2], [1.0, 0.0, -0.2]]), dim=-1)
    pts = torch.tensor([[0.0, 0.0, 0.9], [0.0, 0.0, 0.5], [0.0, 0.0, 0.9], [0.0, 0.0, 0.97]])
    r = torch.cat([r, r[:1]])
    moved, took = snap_to_planes(pts, r, [ceiling_plane], 0.1, 0.01, past=0.1, offset_along_ray=False)
    torch.testing.assert_close(moved[0], torch.tensor([0.04 / 0.2, 0.0, 0.94]))  # 0.2 m sideways
    torch.testing.assert_close(moved[1:3], pts[1:3])  # 0.45 from the plane; heading away from it
    torch.testing.assert_close(moved[3], torch.tensor([-0.03 / 0.2, 0.0, 0.94]))  # 2 cm past it: back onto it
    assert took.tolist() == [True, False, False, True]


def test_highlight_fill_puts_no_emitters_on_a_mirror_like_planes_fill():
    """A highlight that ends on the fill of a mirror-like plane (F0 0.9, roughness 0: zoo_corridor's metal walls'
    unseen parts) is that plane reflecting the light, not the light: with ``on_fill`` it gets no emitter, and it is
    not counted among those that end on the fill; the open highlights' emitters are unchanged."""
    rays, x, scene, ceiling = _lamp_under_ceiling()
    scene.f0[ceiling], scene.roughness[ceiling] = 0.9, 0.0  # the fill a metal plane's
    lights, stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=ceiling, on_fill=True)
    plain, _ = highlight_fill_gaussians(rays, reference_trace, scene)
    assert stats["on_fill"] == stats["on_fill_added"] == 0
    torch.testing.assert_close(lights.means, plain.means)


def test_highlight_fill_ends_highlights_on_walls_placed_later():
    """``walls`` (planes placed after warm-up: a ceiling room closing found at z = 1.05, above the scene's box top
    1.0 and under the swept box's 1.1) with ``on_fill``: the open highlights (x > 0.3) end on it, not on the
    swept box: one placement per light, on the room's plane. Without ``on_fill`` the walls are not traced."""
    rays = _mirror_rays()
    x = rays.origins[:, 0]
    rays.targets["specular"][x > 0.3] = 0.9 * 10.0
    rays.targets["diffuse"][:] = 0.5
    scene = _scene()
    g = torch.linspace(-1, 1, 26)
    xs, ys = torch.meshgrid(g, g, indexing="ij")
    wall = _gaussians(torch.stack([xs.reshape(-1), ys.reshape(-1), torch.full((xs.numel(),), 1.05)], -1), 0.05,
                      0.99)
    fill = torch.zeros(len(scene), dtype=torch.bool)
    lights, stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=fill, on_fill=True, walls=wall)
    want = (x > 0.3).sum().item()
    assert stats["highlight_rays"] == 0 and stats["on_fill"] == stats["on_fill_added"] == want == len(lights)
    assert (lights.means[:, 2] < 1.05).all() and (lights.means[:, 2] > 1.05 - 3 * 0.05).all()
    torch.testing.assert_close(lights.diffuse, torch.full((want, 3), 10.0))
    plain, plain_stats = highlight_fill_gaussians(rays, reference_trace, scene, fill=fill, walls=wall)
    assert plain_stats["highlight_rays"] == want and plain_stats["on_fill"] == 0
    assert torch.allclose(plain.means[:, 2], torch.full((want,), 1.1), atol=0.01)  # the swept box, as without


def _lamp_over_mirror(lamp_z: float = 1.6, half: float = 0.4) -> RaySet:
    """Five cameras (four of them off to the sides) looking at a floor mirror (z = -0.9); the square lamp
    |x|, |y| < ``half`` at height ``lamp_z`` (above the scene's box, whose top is z = 1): a mirror pixel is
    at 1500 random points; bright (10) when its reflection hits the lamp, dim (0.2) otherwise."""
    xy = torch.rand(1500, 2, generator=torch.Generator().manual_seed(0)) * 1.6 - 0.8  # irregular, like pixels
    on_mirror = torch.cat([xy, torch.full((len(xy), 1), -0.9)], -1)
    cams = torch.tensor([[0.0, 0.0, 0.8], [0.6, 0.0, 0.6], [-0.6, 0.0, 0.6], [0.0, 0.6, 0.6], [0.0, -0.6, 0.6]])
    origins = cams.repeat_interleave(len(on_mirror), 0)
    mirror = on_mirror.repeat(len(cams), 1)
    dist = (mirror - origins).norm(dim=-1, keepdim=True)
    dirs = (mirror - origins) / dist
    refl = dirs * torch.tensor([1.0, 1.0, -1.0])
    at_lamp = mirror + ((lamp_z - mirror[:, 2]) / refl[:, 2])[:, None] * refl
    lit = (at_lamp[:, :2].abs() < half).all(-1)
    n = len(origins)
    radiance = torch.where(lit[:, None], torch.full((n, 3), 10.0), torch.full((n, 3), 0.2))
    targets = {"depth": dist, "normal": torch.tensor([[0.0, 0, 1]]).repeat(n, 1), "f0": torch.full((n, 3), 0.9),
               "roughness": torch.zeros(n, 1), "specular": 0.9 * radiance, "diffuse": torch.full((n, 3), 0.5)}
    return RaySet(origins, dirs, torch.ones(n, dtype=torch.bool), targets,
                  torch.arange(len(cams)).repeat_interleave(len(on_mirror)), [])


def test_highlight_fill_finds_a_lamp_beyond_the_box_by_plane_sweep():
    """The lamp hangs 0.6 above the box of the Gaussians: at the box's top the views' highlight exits would
    not overlap; the sweep finds the box scale where they do, so the emitters lie on the lamp."""
    corners = torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    scene = _gaussians(corners, 0.01, 0.1)  # faint: every reflection is open
    rays = _lamp_over_mirror()
    lights, stats = highlight_fill_gaussians(rays, reference_trace, scene)
    assert lights is not None and stats["highlight_rays"] > 200, stats
    assert abs(stats["box_scale"] * 1.1 - 1.6) < 0.06  # box half-size 1.1 (padded), lamp at 1.6
    assert (lights.means[:, 2] - 1.6).abs().max() < 0.06
    assert (lights.means[:, :2].abs() < 0.4 + 0.05).all()  # on the lamp's square
    _, _, purity, notes = sweep_box_scale(*_open_rays(rays), torch.full((3,), -1.1), torch.full((3,), 1.1))
    assert purity[0] < max(purity) - 0.05 and not notes  # the unscaled box is clearly worse; a true minimum


def test_highlight_fill_moves_emitters_onto_a_wall_placed_just_beyond_them():
    """``planes``: a ceiling room closing placed at z = 1.75, 0.15 beyond the lamp the sweep found at 1.6 (two
    sweep steps of the padded box's half-size 1.1 allow 0.22): every emitter moves along its ray onto it (one
    box step short). A ceiling at 2.0 is farther than that: a lamp hanging below it stays where the sweep put it."""
    corners = torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    scene = _gaussians(corners, 0.01, 0.1)
    rays = _lamp_over_mirror()
    swept, _ = highlight_fill_gaussians(rays, reference_trace, scene)
    lights, stats = highlight_fill_gaussians(rays, reference_trace, scene, planes=[(np.array([0.0, 0, 1]), 1.75)])
    assert stats["snapped"] == len(lights) == len(swept) > 200, stats
    assert bool(stats["snapped_rows"].all()) and len(stats["snapped_rows"]) == len(lights)
    assert (lights.means[:, 2] - 1.75).abs().max() < 0.01 and (lights.means[:, 2] < 1.75).all()
    # each moved along its own ray: back along the move, the mirror point it left, and a camera's ray to that
    # point reflects into the move's direction
    move = torch.nn.functional.normalize(lights.means - swept.means, dim=-1)
    mirror = swept.means - ((swept.means[:, 2] + 0.9) / move[:, 2])[:, None] * move
    assert (mirror[:, :2].abs() < 0.8 + 1e-4).all()
    cams = torch.unique(rays.origins, dim=0)
    seen = torch.nn.functional.normalize(mirror[:, None] - cams[None], dim=-1) * torch.tensor([1.0, 1.0, -1.0])
    assert ((seen - move[:, None]).norm(dim=-1).min(dim=1).values < 1e-3).all()
    far, far_stats = highlight_fill_gaussians(rays, reference_trace, scene, planes=[(np.array([0.0, 0, 1]), 2.0)])
    assert far_stats["snapped"] == 0 and torch.equal(far.means, swept.means)
    assert not bool(far_stats["snapped_rows"].any()) and len(far_stats["snapped_rows"]) == len(far)


def test_snap_to_planes_takes_the_first_wall_ahead_within_the_tolerance():
    pos = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    r = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 0.0, -1.0],
                                                    [1.0, 0.0, 0.0]]), dim=-1)
    planes = [(np.array([0.0, 0.0, 1.0]), 0.2), (np.array([1.0, 0.0, 0.0]), 0.1)]  # a ceiling, a near side wall
    pos, moved = snap_to_planes(pos, r, planes, torch.full((3,), 0.25), offset=0.0)
    assert moved.tolist() == [True, True, False, True]  # the third heads away from both walls
    torch.testing.assert_close(pos[0], torch.tensor([0.0, 0.0, 0.2]))  # straight up onto the ceiling
    torch.testing.assert_close(pos[1], torch.tensor([0.1, 0.0, 0.1]))  # the side wall comes first on its ray
    torch.testing.assert_close(pos[2], torch.zeros(3))
    torch.testing.assert_close(pos[3], torch.tensor([0.1, 0.0, 0.0]))
    pos = torch.zeros(1, 3)
    assert not snap_to_planes(pos, r[:1], planes, torch.full((3,), 0.1), offset=0.0)[1].any()  # 0.2 short: > 0.1
    pos = torch.tensor([[0.0, 0.0, 0.15]])  # 0.05 short along the ray, offset 0.1: stays, never moves back
    torch.testing.assert_close(snap_to_planes(pos, r[:1], planes, torch.full((3,), 0.25), offset=0.1)[0], pos)


def test_emitters_the_sweep_left_beyond_a_plane_the_buffers_show_are_reported():
    """A light whose reflections left the box above a ceiling the buffers show (zoo_mirror_only: 1,373 emitters up
    to 0.6 m above it, at the box's back face): the statistics count them and a note names the plane; a handful
    beyond, or none, makes no note. Nothing moves (log only)."""
    from models.reconstruction.reflection_fill import BEYOND_NOTE, _note_beyond_known

    ceiling = (np.array([0.0, 1.0, 0.0]), 2.45)  # outward normal up, one grid spacing under y = 2.5
    above = torch.stack([torch.linspace(-0.5, 0.5, 80), torch.linspace(2.6, 3.1, 80), torch.full((80,), 1.0)], -1)
    below = torch.stack([torch.zeros(40), torch.full((40,), 2.3), torch.linspace(-1.0, 0.0, 40)], -1)
    pos = torch.cat([above, below])
    before = pos.clone()
    stats = {"notes": []}
    _note_beyond_known(pos, [ceiling, (np.array([0.0, -1.0, 0.0]), 0.05)], tol=0.01, stats=stats)
    assert stats["beyond_known"] == 80 and torch.equal(pos, before)
    (note,) = stats["notes"]
    assert "80 of the 120 emitters" in note and "[0.0, 1.0, 0.0]" in note and "up to 0.65 past it" in note
    few = torch.cat([above[: BEYOND_NOTE - 1], below])
    stats = {"notes": []}
    _note_beyond_known(few, [ceiling], tol=0.01, stats=stats)
    assert stats["beyond_known"] == BEYOND_NOTE - 1 and stats["notes"] == []
    stats = {"notes": []}
    _note_beyond_known(below, [ceiling], tol=0.01, stats=stats)
    assert stats["beyond_known"] == 0 and stats["notes"] == []


@pytest.mark.parametrize("lamp_z", [5.0, 8.0])
def test_box_scale_search_extends_past_its_range_for_a_far_lamp(lamp_z):
    """A lamp at 4.5-7x the box's half-size: the first range (1-3) ends at its edge, so the search goes on and
    finds it (the highlight fill used to stop at 3.00, the edge)."""
    rays = _lamp_over_mirror(lamp_z=lamp_z, half=0.4 * lamp_z / 1.6)  # the same patch in the mirror
    scale, scales, purity, notes = sweep_box_scale(*_open_rays(rays), torch.full((3,), -1.1), torch.full((3,), 1.1))
    assert scales[-1] > 3.0 and not notes, (scale, notes)
    assert abs(scale * 1.1 - lamp_z) < 0.2 * lamp_z  # far away the views' rays are nearly parallel: a flat peak


def test_box_scale_search_says_when_it_ends_at_its_edge():
    rays = _lamp_over_mirror(lamp_z=8.0, half=2.0)
    scale, scales, _, notes = sweep_box_scale(*_open_rays(rays), torch.full((3,), -1.1), torch.full((3,), 1.1),
                                              max_scale=4.0)
    assert scale == scales[-1] == 4.0 and len(notes) == 1 and "edge of the search" in notes[0]


def _open_rays(rays: RaySet):
    d = rays.dirs
    x = rays.origins + d * rays.targets["depth"]
    r = d * torch.tensor([1.0, 1.0, -1.0])
    return x, r, rays.targets["specular"][:, 0] > 1.0


def test_no_highlight_fill_without_bright_reflections():
    rays = _mirror_rays()
    rays.targets["diffuse"][:] = 2.0  # the reflections (luminance 0.62) are no brighter than lit surfaces
    lights, stats = highlight_fill_gaussians(rays, reference_trace, _scene())
    assert lights is None and stats["added"] == 0 and stats["mirror_rays"] == 144


def test_no_fill_without_mirrors():
    fill, stats = reflection_fill_gaussians(_mirror_rays(f0=0.04), reference_trace, _scene(), count=400)
    assert fill is None and stats["added"] == 0


def test_box_exit():
    x = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    r = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [1.0, 1.0, 0.0]]), dim=-1)
    t = box_exit(x, r, torch.full((3,), -1.0), torch.full((3,), 1.0))
    torch.testing.assert_close(t, torch.tensor([1.0, 0.5 * math.sqrt(2)]))


def test_seen_empty_is_the_space_in_front_of_the_depth_buffer():
    from models.capture import View
    from models.capture.camera import Camera

    cam = Camera(width=8, height=8, fl_x=8.0, fl_y=8.0, cx=4.0, cy=4.0, c2w=np.eye(4))  # looks down -z
    depth = np.full((8, 8, 1), 2.0, np.float32)
    mask = np.ones((8, 8, 1), np.float32)
    mask[0, 0] = 0  # this pixel sees nothing: all of it is empty
    view = View(name="v", camera=cam, split="train", buffers={"depth": depth, "mask": mask})
    pts = torch.tensor([[0.0, 0, -1], [0, 0, -3], [5, 0, -1], [0, 0, 1], [-0.45, 0.45, -1.0], [-2.25, 2.25, -5.0]])
    empty = seen_empty(pts, [view])
    assert empty.tolist() == [True, False, False, False, True, True]  # in front | behind | outside | behind the camera | no-hit pixel, near and far


@pytest.mark.parametrize("with_layer", [True, False])
def test_diffuse_level_leaves_out_the_lights_seen_directly(with_layer):
    """The highlight threshold is the brightest LIT surface: a window filling 5 % of the frames (radiance 10)
    must not become the level, or no reflection of another light would count as a highlight (zoo_lamps, zoo_lshape,
    zoo_thin, zoo_mirror_metal: 0 highlight rays). Views without an emission layer cannot say which pixels are
    lights: the level is then the plain percentile."""
    from models.capture import View
    from models.capture.camera import Camera

    views, diffuse = [], []
    for i in range(2):
        cam = Camera(width=20, height=10, fl_x=10.0, fl_y=10.0, cx=10.0, cy=5.0, c2w=np.eye(4))
        emission = np.zeros((10, 20, 3), np.float32)
        emission[:, :1] = 9.5  # one column of 20: 5 % of the pixels show the window
        rad = np.full((10, 20, 3), 0.5, np.float32) + emission
        rad[0, 5:] = np.linspace(0.1, 0.5, 15)[:, None]  # some spread below the lit maximum
        views.append(View(name=f"v{i}", camera=cam, split="train",
                          buffers={"emission": emission} if with_layer else {}))
        diffuse.append(torch.tensor(rad.reshape(-1, 3)))
    n = 400
    rays = RaySet(torch.zeros(n, 3), torch.tensor([[0.0, 0, -1]]).repeat(n, 1), torch.ones(n, dtype=torch.bool),
                  {"diffuse": torch.cat(diffuse)}, torch.arange(2).repeat_interleave(200), views)
    level = diffuse_level(rays, torch.Generator().manual_seed(0))
    assert level == pytest.approx(0.5 if with_layer else 10.0, rel=1e-3)
    # a subset of the rays is no longer the views' pixels in order: nothing is known to be a light there
    subset = rays.subset(torch.arange(300))
    assert diffuse_level(subset, torch.Generator().manual_seed(0)) == pytest.approx(10.0, rel=1e-3)
