"""Edit stage: selections, each op's effect (checked against independent math), the BVH after a delete,
reflections following a moved object, spec errors, the demo edits against the synth scene they mirror,
and the CLI end to end (apply, ground truth, evaluate) on a tiny synthetic capture."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from models.capture import Camera
from models.editing import EditSpecError, apply_edit, parse_edit, parse_edits, parse_selection, select
from models.editing.ops import hsv_to_rgb, rgb_to_hsv
from models.gaussians import Gaussians, quats_to_rotmats, random_gaussians
from models.pathtrace.paths import PathConfig
from models.rendering import RenderConfig, render_view
from models.synth.cameras import intrinsics, look_at
from models.synth.edits import apply_edits
from models.synth.mitsuba_scene import material_entry, to_world_matrix
from models.synth.spec import parse_spec
from models.tracer import Tracer, TracerConfig
from stages.config import ConfigError, load_config


def scene(n: int = 300, seed: int = 0) -> Gaussians:
    return random_gaussians(n, torch.Generator().manual_seed(seed), extent=1.0, dtype=torch.float64)


def run(g: Gaussians, ops: list, sel: dict | None = None, name: str = "e"):
    spec = parse_edit(name, {"ops": ops, **({"select": sel} if sel is not None else {})})
    mask = select(g, spec.select) if spec.select is not None else None
    out, report = apply_edit(g, spec)
    return out, mask, report


def assert_unselected_unchanged(g: Gaussians, out: Gaussians, mask: torch.Tensor) -> None:
    for name, value in g.params().items():
        assert torch.equal(getattr(out, name)[: len(g)][~mask], value[~mask]), name


# ------------------------------------------------------------------------------------------- selection


def test_selection_shapes_values_and_exclusions():
    g = scene(500)
    p, f0, rough = g.means.numpy(), g.f0.numpy(), g.roughness.numpy()

    def sel(d):
        return select(g, parse_selection(d, "t")).numpy()

    box = np.all((p >= [-0.5, -1, -0.2]) & (p <= [0.5, 0.3, 1]), axis=1)
    assert np.array_equal(sel({"box": {"min": [-0.5, -1, -0.2], "max": [0.5, 0.3, 1]}}), box)
    sphere = np.linalg.norm(p - [0.2, 0.1, 0], axis=1) <= 0.6
    assert np.array_equal(sel({"sphere": {"centre": [0.2, 0.1, 0], "radius": 0.6}}), sphere)
    # tilted cylinder: distance to the axis line (cross product) and position along it
    c, a = np.array([0.1, 0.0, -0.1]), np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    along, radial = (p - c) @ a, np.linalg.norm(np.cross(p - c, a), axis=1)
    cyl = (np.abs(along) <= 0.5) & (radial <= 0.4)
    assert np.array_equal(sel({"cylinder": {"centre": c.tolist(), "axis": [2, 2, 0], "radius": 0.4, "height": 1.0}}), cyl)
    assert np.array_equal(sel({"roughness": {"min": 0.2, "max": 0.5}}), (rough >= 0.2) & (rough <= 0.5))
    assert np.array_equal(sel({"f0": {"max": 0.5}}), f0.mean(1) <= 0.5)  # a number bounds the channel mean
    assert np.array_equal(sel({"f0": {"min": [0.3, 0.0, 0.5]}}), np.all(f0 >= [0.3, 0.0, 0.5], axis=1))
    assert np.array_equal(sel({"diffuse": {"min": [0.5, 0, 0], "max": [1, 0.3, 1]}}),
                          np.all((g.diffuse.numpy() >= [0.5, 0, 0]) & (g.diffuse.numpy() <= [1, 0.3, 1]), axis=1))
    # criteria intersect; exclusions (themselves selections) are removed
    both = sel({"box": {"min": [-0.5, -1, -0.2], "max": [0.5, 0.3, 1]}, "f0": {"max": 0.5},
                "exclude": [{"sphere": {"centre": [0.2, 0.1, 0], "radius": 0.6}}, {"roughness": {"max": 0.1}}]})
    assert np.array_equal(both, box & (f0.mean(1) <= 0.5) & ~sphere & ~(rough <= 0.1))
    assert 0 < both.sum() < box.sum() and sel({"all": True}).all()


# ------------------------------------------------------------------------------------------- geometry ops


def test_rotate_moves_means_quaternions_and_normals_together():
    g = scene()
    axis, angle, pivot = np.array([1.0, 2.0, -0.5]), 37.0, np.array([0.1, 0.2, 0.3])
    out, mask, rep = run(g, [{"op": "rotate", "axis": axis.tolist(), "angle": angle, "pivot": pivot.tolist()}],
                         {"sphere": {"centre": [0, 0, 0], "radius": 0.8}})
    r = torch.from_numpy(Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(angle)).as_matrix())
    piv = torch.from_numpy(pivot)
    assert rep[0]["selected"] == int(mask.sum()) > 20
    torch.testing.assert_close(out.means[mask], (g.means[mask] - piv) @ r.T + piv, rtol=0, atol=1e-12)
    torch.testing.assert_close(quats_to_rotmats(out.quats[mask]), r @ quats_to_rotmats(g.quats[mask]), rtol=0, atol=1e-12)
    torch.testing.assert_close(out.normals[mask], g.normals[mask] @ r.T, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.quats.norm(dim=1), g.quats.norm(dim=1), rtol=0, atol=1e-12)  # raw norm kept
    # the covariance rotates: Sigma' = R Sigma R^T
    cov = lambda x: torch.linalg.inv(x.world_to_local().transpose(1, 2) @ x.world_to_local())  # noqa: E731
    torch.testing.assert_close(cov(out)[mask], r @ cov(g)[mask] @ r.T, rtol=1e-9, atol=1e-12)
    assert torch.equal(out.log_scales, g.log_scales) and torch.equal(out.f0, g.f0)
    assert_unselected_unchanged(g, out, mask)


def test_rotate_default_pivot_is_the_selection_centre():
    g = scene()
    out, mask, _ = run(g, [{"op": "rotate", "axis": [0, 1, 0], "angle": 90}], {"box": {"min": [0, 0, 0], "max": [1, 1, 1]}})
    p = g.means[mask]
    c = 0.5 * (p.amin(0) + p.amax(0))
    r = torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]], dtype=torch.float64)  # +90 deg about y
    torch.testing.assert_close(out.means[mask], (p - c) @ r.T + c, rtol=0, atol=1e-12)


def test_uniform_scale_and_translate():
    g = scene()
    out, mask, _ = run(g, [{"op": "scale", "factor": 1.7, "pivot": [0.5, 0, 0]}], {"box": {"min": [0, -1, -1], "max": [1, 1, 1]}})
    piv = torch.tensor([0.5, 0, 0], dtype=torch.float64)
    torch.testing.assert_close(out.means[mask], piv + 1.7 * (g.means[mask] - piv), rtol=0, atol=1e-12)
    torch.testing.assert_close(out.log_scales[mask], g.log_scales[mask] + math.log(1.7), rtol=0, atol=1e-12)
    # the whole Gaussian scales: world-to-local map divided by s, orientation and normals unchanged
    torch.testing.assert_close(out.world_to_local()[mask], g.world_to_local()[mask] / 1.7, rtol=1e-12, atol=1e-12)
    assert torch.equal(out.quats, g.quats) and torch.equal(out.normals, g.normals)
    assert_unselected_unchanged(g, out, mask)
    moved, mask, _ = run(g, [{"op": "translate", "offset": [0.1, -0.2, 0.3]}], {"f0": {"min": 0.5}})
    torch.testing.assert_close(moved.means[mask] - g.means[mask], torch.tensor([[0.1, -0.2, 0.3]]).double().expand(int(mask.sum()), 3))
    assert_unselected_unchanged(g, moved, mask)


def test_duplicate_appends_exactly_the_selected_gaussians():
    g = scene()
    out, mask, rep = run(g, [{"op": "duplicate", "offset": [2.0, 0, 0]}], {"sphere": {"centre": [0, 0, 0], "radius": 0.7}})
    n, k = len(g), int(mask.sum())
    assert len(out) == n + k and rep[0]["gaussians_after"] == n + k and 0 < k < n
    for name, value in g.params().items():
        assert torch.equal(getattr(out, name)[:n], value), name  # originals untouched, same indices
        copies = getattr(out, name)[n:]
        expect = value[mask] + torch.tensor([2.0, 0, 0], dtype=torch.float64) if name == "means" else value[mask]
        assert torch.equal(copies, expect), name


def _two_blobs() -> Gaussians:
    f = torch.float64
    return Gaussians(
        means=torch.tensor([[0.0, 0, 0], [1.0, 0, 0]], dtype=f), quats=torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=f),
        log_scales=torch.full((2, 3), math.log(0.1), dtype=f), opacity_logits=torch.full((2,), 4.0, dtype=f),
        diffuse=torch.tensor([[1.0, 0, 0], [0, 1.0, 0]], dtype=f), normals=torch.tensor([[0, 0, -1.0]] * 2, dtype=f),
        roughness=torch.full((2,), 0.5, dtype=f), f0=torch.full((2, 3), 0.04, dtype=f))


def test_delete_removes_gaussians_from_the_bvh():
    g = _two_blobs().to(dtype=torch.float32)
    tracer = Tracer(TracerConfig(num_threads=1), "cpu")
    origins = torch.tensor([[0.0, 0, -3], [1.0, 0, -3]])
    dirs = torch.tensor([[0.0, 0, 1], [0.0, 0, 1]])
    tracer.update(g)
    before = tracer.trace(origins, dirs, g)
    assert before.hit_count.tolist() == [1, 1] and (before.transmittance < 0.1).all()
    out, mask, rep = run(g, [{"op": "delete"}], {"sphere": {"centre": [0, 0, 0], "radius": 0.2}})
    assert mask.tolist() == [True, False] and len(out) == 1 and rep[0]["gaussians_after"] == 1
    tracer.update(out)
    after = tracer.trace(origins, dirs, out)
    assert after.hit_count.tolist() == [0, 1]  # the ray that hit the deleted Gaussian now misses
    assert after.transmittance[0] == 1 and torch.allclose(after.diffuse[1], before.diffuse[1])
    # a larger scene: the refit / rebuilt BVH after a delete traces like a fresh tracer
    big = random_gaussians(400, torch.Generator().manual_seed(3), scale=0.1)
    u = torch.linspace(-0.4, 0.4, 16)
    y, x = torch.meshgrid(u, u, indexing="ij")
    d = torch.nn.functional.normalize(torch.stack([x, y, torch.ones_like(x)], -1).reshape(-1, 3), dim=1)
    o = torch.tensor([0.0, 0, -3]).expand_as(d).contiguous()
    tracer.trace(o, d, big)
    pruned, _, _ = run(big, [{"op": "delete"}], {"box": {"min": [-0.5, -0.5, -1], "max": [0.5, 0.5, 1]}})
    a, b = tracer.trace(o, d, pruned), Tracer(TracerConfig(num_threads=1), "cpu").trace(o, d, pruned)
    assert torch.equal(a.hit_count, b.hit_count) and torch.allclose(a.diffuse, b.diffuse, atol=1e-6)
    assert (a.hit_count < tracer.trace(o, d, big).hit_count).any()


# ------------------------------------------------------------------------------------------- material ops


def test_material_ops_keep_the_stored_ranges():
    g = scene()
    sel = {"roughness": {"min": 0.3}}
    out, mask, _ = run(g, [{"op": "set_roughness", "value": 0.05}], sel)
    assert (out.roughness[mask] == 0.05).all()
    assert_unselected_unchanged(g, out, mask)
    out, mask, _ = run(g, [{"op": "shift_roughness", "delta": 0.5}], sel)
    assert torch.equal(out.roughness[mask], (g.roughness[mask] + 0.5).clamp(max=1.0)) and out.roughness.max() == 1.0
    out, mask, _ = run(g, [{"op": "multiply_roughness", "factor": 0.5}], sel)
    assert torch.equal(out.roughness[mask], g.roughness[mask] * 0.5)
    out, mask, _ = run(g, [{"op": "set_f0", "value": 0.9}, {"op": "set_diffuse", "value": [0.0, 0.1, 0.2]}], sel)
    assert (out.f0[mask] == 0.9).all()
    assert torch.equal(out.diffuse[mask], torch.tensor([0.0, 0.1, 0.2], dtype=torch.float64).expand(int(mask.sum()), 3))
    assert_unselected_unchanged(g, out, mask)
    out, mask, _ = run(g, [{"op": "set_f0", "value": [0.95, 0.64, 0.54]}], sel)
    assert torch.equal(out.f0[mask], torch.tensor([0.95, 0.64, 0.54], dtype=torch.float64).expand(int(mask.sum()), 3))


def test_hsv_shift_of_the_diffuse_colour():
    f = torch.float64
    g = _two_blobs()
    g.diffuse = torch.tensor([[0.8, 0.1, 0.1], [0.2, 0.4, 0.6]], dtype=f)
    out, mask, _ = run(g, [{"op": "shift_diffuse_hsv", "hue": 120}], {"all": True})
    torch.testing.assert_close(out.diffuse, torch.tensor([[0.1, 0.8, 0.1], [0.6, 0.2, 0.4]], dtype=f))
    out, _, _ = run(g, [{"op": "shift_diffuse_hsv", "saturation": 0.0, "value": 0.5}], {"all": True})
    torch.testing.assert_close(out.diffuse, torch.tensor([[0.4] * 3, [0.3] * 3], dtype=f))
    rgb = torch.rand(200, 3, generator=torch.Generator().manual_seed(1), dtype=f) * 2  # linear: may exceed 1
    torch.testing.assert_close(hsv_to_rgb(rgb_to_hsv(rgb)), rgb)


# ------------------------------------------------------------------------------------------- reflections


def _mirror_and_ball(centre) -> Gaussians:
    """A flat mirror of Gaussians at y = 0 (roughness 0, F0 1, black diffuse) and a red ball above it."""
    f = torch.float32
    u = torch.arange(-12, 13, dtype=f) * 0.1
    zz, xx = torch.meshgrid(u, u, indexing="ij")
    m = len(u) ** 2
    mirror = dict(means=torch.stack([xx.reshape(-1), torch.zeros(m), zz.reshape(-1)], 1),
                  log_scales=torch.tensor([math.log(0.07), math.log(0.0005), math.log(0.07)]).expand(m, 3),
                  normals=torch.tensor([0.0, 1, 0]).expand(m, 3), roughness=torch.zeros(m),
                  f0=torch.ones(m, 3), diffuse=torch.zeros(m, 3))
    offsets = torch.tensor([[0, 0, 0], [0.04, 0, 0], [-0.04, 0, 0], [0, 0.04, 0], [0, -0.04, 0], [0, 0, 0.04], [0, 0, -0.04]])
    b = len(offsets)
    ball = dict(means=torch.tensor(centre, dtype=f) + offsets, log_scales=torch.full((b, 3), math.log(0.04)),
                normals=torch.tensor([0.0, 1, 0]).expand(b, 3), roughness=torch.ones(b), f0=torch.zeros(b, 3),
                diffuse=torch.tensor([0.9, 0.05, 0.05]).expand(b, 3))
    n = m + b
    cat = {k: torch.cat([mirror[k], ball[k]]).contiguous() for k in mirror}
    # mirror opacity 0.6: up to 4 overlapping disks leave T >= 0.4^4 > 0.01, so no primary ray is truncated.
    # (A truncated ray's depth is already normalised by 1 - T (tracer tail rule) and models/pathtrace divides
    # by 1 - T again, putting the reflection origin up to 1% of the depth behind the mirror: self-hits.)
    opacity = torch.cat([torch.full((m,), math.log(0.6 / 0.4)), torch.full((b,), 6.0)])
    return Gaussians(quats=torch.tensor([1.0, 0, 0, 0]).expand(n, 4).contiguous(), opacity_logits=opacity, **cat)


def _project(camera: Camera, point) -> np.ndarray:
    """Pixel (column, row) of a world point (inverse of Camera.camera_directions)."""
    pc = camera.c2w[:3, :3].T @ (np.asarray(point, dtype=float) - camera.origin)
    return np.array([camera.cx + camera.fl_x * pc[0] / -pc[2] - 0.5, camera.cy - camera.fl_y * pc[1] / -pc[2] - 0.5])


def _red_centroid(img: np.ndarray) -> np.ndarray:
    w = np.clip(img[..., 0] - img[..., 1], 0, None)
    rows, cols = np.nonzero(w > 0.05)
    assert len(rows) >= 3, "no red reflection in the mirror"
    weights = w[rows, cols]
    return np.array([np.average(cols, weights=weights), np.average(rows, weights=weights)])


def test_reflection_of_a_moved_object_moves():
    camera = Camera(**intrinsics(48, 36, 50.0), c2w=look_at([0.0, 1.0, 2.0], [0.0, 0.0, 0.0]))
    config = RenderConfig(spp=1, max_path_length=2, denoise=False, path_views=0, video=False)
    tracer = Tracer(TracerConfig(num_threads=2), "cpu")
    g = _mirror_and_ball([0.0, 0.3, 0.0])
    moved, mask, _ = run(g, [{"op": "translate", "offset": [0.4, 0.0, 0.0]}], {"diffuse": {"min": [0.5, 0, 0]}})
    assert int(mask.sum()) == 7  # the ball, not the mirror
    imgs = [render_view(tracer.trace, camera, x, config, torch.Generator().manual_seed(0), PathConfig())
            for x in (g, moved)]
    for img, c in zip(imgs, ([0.0, 0.3, 0.0], [0.4, 0.3, 0.0])):
        image = [c[0], -c[1], c[2]]  # the mirror image of the ball's centre
        # the red seen in the specular layer sits where the mirror image projects (within a pixel)
        assert np.abs(_red_centroid(img["specular"]) - _project(camera, image)).max() < 1.0
        assert np.abs(_red_centroid(img["diffuse"]) - _project(camera, c)).max() < 1.0  # the ball itself
    old = np.round(_project(camera, [0.0, -0.3, 0.0])).astype(int)
    new = np.round(_project(camera, [0.4, -0.3, 0.0])).astype(int)
    assert imgs[0]["specular"][old[1], old[0], 0] > 0.3 and imgs[1]["specular"][old[1], old[0], 0] < 0.02
    assert imgs[0]["specular"][new[1], new[0], 0] < 0.02 and imgs[1]["specular"][new[1], new[0], 0] > 0.3


# ------------------------------------------------------------------------------------------- errors


def test_errors_name_the_edit_op_and_key():
    g = scene()
    with pytest.raises(EditSpecError, match=r"^edit 'move_ball' op 0 \(translate\): selection \{\"box\":\{\"min\":"
                       r"\[5,5,5\],\"max\":\[6,6,6\]\}\} selects no Gaussians \(of 300\)$"):
        run(g, [{"op": "translate", "offset": [1, 0, 0]}], {"box": {"min": [5, 5, 5], "max": [6, 6, 6]}}, name="move_ball")
    cases = [
        ({"ops": [{"op": "explode"}], "select": {"all": True}},
         r"edit 'e' op 0: unknown op 'explode' \(known ops: translate, rotate, scale, duplicate, delete, set_roughness"),
        ({"ops": [{"op": "translate", "ofset": [1, 0, 0]}], "select": {"all": True}},
         r"edit 'e' op 0 \(translate\): unknown key\(s\) 'ofset' \(known: offset, op, select\)"),
        ({"ops": [{"op": "delete", "select": {"boxx": {}}}]},
         r"edit 'e' op 0 \(delete\)\.select: unknown selection field\(s\) 'boxx' \(known: all, box, cylinder, diffuse, "
         r"exclude, f0, roughness, sphere\)"),
        ({"ops": [{"op": "delete"}]}, r"edit 'e' op 0 \(delete\): no selection"),
        ({"ops": [{"op": "set_roughness", "value": 2}], "select": {"all": True}},
         r"edit 'e' op 0 \(set_roughness\)\.value: must be <= 1\.0, got 2\.0"),
        ({"ops": [{"op": "delete"}], "select": {"exclude": [{"all": True}]}}, r"edit 'e'\.select: selects nothing by itself"),
        ({"ops": [{"op": "delete"}], "select": {"box": {"min": [1, 0, 0], "max": [0, 1, 1]}}},
         r"edit 'e'\.select\.box: min \[1\.0, 0\.0, 0\.0\] exceeds max"),
        ({"ops": [], "select": {"all": True}}, r"edit 'e'\.ops: must be a non-empty list"),
        ({"ops": [{"op": "delete"}], "select": {"all": True}, "ground_truht": []},
         r"edit 'e': unknown key\(s\) 'ground_truht' \(known: description, ground_truth, ops, relight, select, truth\)"),
    ]
    for spec, pattern in cases:
        with pytest.raises(EditSpecError, match=pattern):
            parse_edit("e", spec)


def test_config_schema_checks_edits():
    with pytest.raises(ConfigError, match=r"config edits\.bad\.ops\.0.*explode.*\(schema edit\.schema\.yaml\)"):
        load_config("demo", overrides={"edits": {"bad": {"ops": [{"op": "explode"}]}}})
    with pytest.raises(ConfigError, match=r"config unknown edits\.bad\.select option\(s\) \['boxx'\].*\(schema edit\.schema\.yaml\)"):
        load_config("demo", overrides={"edits": {"bad": {"select": {"boxx": {}}, "ops": [{"op": "delete"}]}}})


# ------------------------------------------------------------------------------------------- demo edits


def _surface_gaussians(spec, n: int = 600) -> tuple[Gaussians, np.ndarray]:
    """Points on every object's surface (same local samples per shape) carrying the object's buffer values
    (roughness, F0 as the synth stage writes them): what a well-trained model holds."""
    rng = np.random.default_rng(0)
    local = {"sphere": rng.normal(size=(n, 3)), "rectangle": np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]}
    local["sphere"] /= np.linalg.norm(local["sphere"], axis=1, keepdims=True)
    face = rng.integers(0, 6, n)
    cube = rng.uniform(-1, 1, (n, 3))
    cube[np.arange(n), face // 2] = np.where(face % 2, 1.0, -1.0)
    local["cube"] = cube
    means, rough, f0, names = [], [], [], []
    for obj in spec.objects:
        pts = np.c_[local[obj.shape], np.ones(n)] @ to_world_matrix(obj.transform).T
        entry = material_entry(obj, None)
        means.append(pts[:, :3])
        rough.append(np.full(n, entry.roughness))
        f0.append(np.tile(entry.f0_const, (n, 1)))
        names += [obj.name] * n
    k = n * len(spec.objects)
    t = lambda a: torch.tensor(np.concatenate(a), dtype=torch.float64)  # noqa: E731
    g = Gaussians(means=t(means), quats=torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(k, 4).clone(),
                  log_scales=torch.full((k, 3), math.log(0.01), dtype=torch.float64),
                  opacity_logits=torch.zeros(k, dtype=torch.float64), diffuse=torch.full((k, 3), 0.5, dtype=torch.float64),
                  normals=torch.zeros(k, 3, dtype=torch.float64), roughness=t(rough), f0=t(f0))
    return g, np.array(names)


def test_demo_edits_select_their_object_and_match_the_ground_truth_edit():
    cfg = load_config("demo")
    spec = parse_spec(cfg["synth"])
    edits = parse_edits(cfg["edits"])
    assert set(edits) == {"move_ball", "duplicate_ball", "glossy_floor", "metal_box"}
    g, names = _surface_gaussians(spec)
    targets = {"move_ball": "mirror_ball", "duplicate_ball": "mirror_ball", "glossy_floor": "floor", "metal_box": "box_a"}
    for name, edit in edits.items():
        caught = select(g, edit.select).numpy()
        target = names == targets[name]
        assert not (caught & ~target).any(), f"{name} catches {sorted(set(names[caught & ~target]))}"
        # the floor slab stops 3 cm short of the walls: every floor point but that rim
        expect = target & (np.abs(g.means.numpy()[:, [0, 2]]).max(1) < 1.97) if name == "glossy_floor" else target
        assert (caught | ~expect).all(), f"{name} misses {int((expect & ~caught).sum())} points of {targets[name]}"
        # the Gaussian edit lands where the ground-truth edit of the scene spec puts the object
        edited, _ = apply_edit(g, edit)
        truth, truth_names = _surface_gaussians(apply_edits(spec, list(edit.ground_truth)))
        if name in ("move_ball", "duplicate_ball"):
            mine = edited.means[len(g):] if name == "duplicate_ball" else edited.means[torch.from_numpy(target)]
            other = truth.means[torch.from_numpy(truth_names == ("mirror_ball_2" if name == "duplicate_ball" else "mirror_ball"))]
            torch.testing.assert_close(mine, other, rtol=0, atol=1e-9)
        else:
            sel = torch.from_numpy(caught)
            other = torch.from_numpy(truth_names == targets[name])
            torch.testing.assert_close(edited.roughness[sel], truth.roughness[other][: int(sel.sum())])
            torch.testing.assert_close(edited.f0[sel], truth.f0[other][: int(sel.sum())])


# ------------------------------------------------------------------------------------------- stage end to end


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A CI-sized demo capture (Mitsuba) and its dense initialisation as the model to edit."""
    pytest.importorskip("mitsuba")
    from models.capture import read_capture
    from models.gaussians import write_ply
    from models.initialisation.dense import InitConfig, dense_init
    from models.synth.render import render_capture

    root = tmp_path_factory.mktemp("edit")
    cfg = load_config("demo", presets=["ci"])
    render_capture(cfg["synth"], root / "capture", progress=False)
    capture = read_capture(root / "capture", layers=["depth", "diffuse", "mask"])
    model, _ = dense_init(capture, InitConfig.from_dict(cfg["init"]))
    model.opacity_logits.fill_(4.0)  # opaque surfaces: depth is the first surface, as after training
    write_ply(root / "model.ply", model)
    return root, cfg


def test_stage_cli_apply_truth_evaluate(tiny, capsys):
    from models.capture import read_capture
    from models.gaussians import read_ply
    from models.synth.render import scene_views
    from stages.edit.__main__ import main
    from stages.render.__main__ import main as render_main
    from stages.synth.__main__ import main as synth_main

    root, cfg = tiny
    # the init model has one roughness / F0 everywhere: select the ball by shape alone
    edit = {"select": {"sphere": {"centre": [-0.55, 0.35, -0.45], "radius": 0.4},
                       "exclude": [{"box": {"min": [-2, -1, -2], "max": [2, 0.03, 2]}}]},
            "ops": [{"op": "translate", "offset": [0.35, 0.0, 0.45]}],
            "ground_truth": cfg["edits"]["move_ball"]["ground_truth"]}
    render = json.dumps({"spp": 4, "path_views": 0, "video": False})
    common = ["--edit", "move_ball", "--edit-json", json.dumps(edit)]
    out = root / "edits" / "move_ball"
    assert main(["apply", *common, "--config-json", render, "--model", str(root / "model.ply"),
                 "--capture", str(root / "capture"), "--out", str(out), "--threads", "1"]) == 0
    # the ground truth: the synth stage renders the test views with the edit's ground_truth ops
    assert synth_main(["--config-json", json.dumps(cfg["synth"]), "--edits-json", json.dumps(edit["ground_truth"]),
                       "--splits", "test", "--name", "edit:move_ball", "--no-progress",
                       "--out", str(root / "truth")]) == 0
    assert render_main(["--config-json", render, "--model", str(root / "model.ply"), "--capture", str(root / "capture"),
                        "--out", str(root / "renders"), "--threads", "1"]) == 0
    assert main(["evaluate", "--edit", "move_ball", "--capture", str(root / "capture"), "--truth", str(root / "truth"),
                 "--renders", str(out / "renders" / "test"), "--baseline-renders", str(root / "renders" / "test"),
                 "--out", str(out / "metrics.json")]) == 0
    # the ground truth holds exactly the capture's test views (names and cameras)
    truth = read_capture(root / "truth", layers=["diffuse"])
    full = [(n, c) for n, s, c in scene_views(parse_spec(cfg["synth"])) if s == "test"]
    assert [v.name for v in truth.views] == [n for n, _ in full] and all(v.split == "test" for v in truth.views)
    for v, (_, c) in zip(truth.views, full):
        np.testing.assert_allclose(v.camera.c2w, c.c2w)
    # ... rendered with the capture's sampler seeds: most pixels (those the edit does not reach) are identical
    capture = read_capture(root / "capture", layers=["diffuse"])
    same = [np.mean(np.all(v.buffers["diffuse"] == capture.views[-len(truth.views) + i].buffers["diffuse"], axis=-1))
            for i, v in enumerate(truth.views)]
    assert min(same) > 0.3, same
    stage = json.loads((out / "stage.json").read_text())
    model = read_ply(root / "model.ply")
    assert stage["ops"][0]["selected"] > 10 and len(read_ply(out / "model" / "gaussians.ply")) == len(model)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["render_spp"] == 4 and metrics["ops"][0]["op"] == "translate"
    for key in ("edited_vs_truth", "unedited_vs_truth"):
        assert all(np.isfinite(metrics[key][f"psnr_{layer}"]) for layer in ("final", "diffuse", "specular"))
    assert 0.01 < metrics["changed_region"]["changed_fraction"] < 0.5
    # on the changed pixels: tonemapped (the headline, mu-law at the view's peak) and linear, edited and not
    changed = metrics["changed_region"]
    assert all(np.isfinite(changed[f"{kind}_psnr_{layer}{suffix}"]) for kind in ("edited", "unedited")
               for layer in ("final", "diffuse", "specular") for suffix in ("", "_tonemapped")), changed
    # ... and pooled over every view's changed pixels (each pixel weighing the same), their count beside
    assert all(np.isfinite(changed[f"pooled_{kind}_psnr_{layer}_tonemapped"]) for kind in ("edited", "unedited")
               for layer in ("final", "diffuse", "specular")), changed
    views = read_capture(root / "truth", layers=["diffuse"]).views
    pixels = sum(v.camera.width * v.camera.height for v in views)
    assert changed["changed_pixels"] == round(changed["changed_fraction"] * pixels) > 0
    # pooled = the changed pixels' squared error averaged over all views, each pixel weighing the same: each
    # view scored alone, its MSE weighted by its changed pixels, gives the pooled MSE back
    from models.capture.types import Capture
    from models.metrics.edits import changed_region_metrics

    capture, truth = read_capture(root / "capture"), read_capture(root / "truth")
    alone = [changed_region_metrics(capture, Capture([v], truth.meta), out / "renders" / "test",
                                    root / "renders" / "test") for v in truth.views]
    alone = [a for a in alone if a["changed_pixels"]]
    assert len(alone) >= 2  # a pooling over one view would prove nothing
    for kind in ("edited", "unedited"):
        for a in alone:  # one view: pooled = its own PSNR
            assert a[f"pooled_{kind}_psnr_final_tonemapped"] == pytest.approx(a[f"{kind}_psnr_final_tonemapped"])
        mse = sum(10 ** (-a[f"{kind}_psnr_final_tonemapped"] / 10) * a["changed_pixels"] for a in alone)
        mse /= sum(a["changed_pixels"] for a in alone)
        assert changed[f"pooled_{kind}_psnr_final_tonemapped"] == pytest.approx(-10 * np.log10(mse), abs=1e-6)
    # the moved ball shows where the ground truth has it: on the pixels where the edited truth is nearer than
    # the unedited capture (the ball's new silhouette), the edited render's depth matches the truth's
    from models.capture.exr import read_exr_channels

    truth = read_capture(root / "truth", layers=["depth", "mask"])
    capture = read_capture(root / "capture", layers=["depth"])
    errors = {"edited": [], "unedited": []}
    for view in truth.views:
        before = next(v for v in capture.views if v.name == view.name).buffers["depth"][..., 0]
        after = view.buffers["depth"][..., 0]
        new = (after < 0.9 * before) & (view.buffers["mask"][..., 0] > 0.99)
        for key, folder in (("edited", out / "renders" / "test"), ("unedited", root / "renders" / "test")):
            ch = read_exr_channels(folder / f"{view.name}.exr")
            # expected termination depth
            pred = ch["depth.Z"] / np.maximum(1 - ch["transmittance.Y"], 1e-6)
            errors[key] += list(np.abs(pred[new] - after[new]) / after[new])
    assert len(errors["edited"]) >= 10
    median = {k: float(np.median(v)) for k, v in errors.items()}
    assert median["edited"] < 0.1 and median["edited"] < 0.5 * median["unedited"], median  # seen: 0.073 vs 0.26
    # one-line errors naming the edit
    capsys.readouterr()
    bad = {"select": {"box": {"min": [5, 5, 5], "max": [6, 6, 6]}}, "ops": [{"op": "delete"}]}
    assert main(["apply", "--edit", "gone", "--edit-json", json.dumps(bad), "--config-json", render,
                 "--model", str(root / "model.ply"), "--capture", str(root / "capture"), "--out", str(root / "x")]) == 1
    assert capsys.readouterr().err.startswith("error: edit 'gone' op 0 (delete): selection {\"box\"")
    assert main(["apply", "--edit", "nope", "--scene", "demo", "--model", str(root / "model.ply"),
                 "--capture", str(root / "capture"), "--out", str(root / "x")]) == 1
    assert "unknown edit 'nope' (known: move_ball, duplicate_ball, glossy_floor, metal_box)" in capsys.readouterr().err


def test_synth_set_material_replaces_the_material():
    """The ground truth of material-type edits (diffuse -> metal): the synth stage's set_material op."""
    spec = parse_spec(load_config("demo")["synth"])
    metal = {"type": "principled", "base_color": [0.95, 0.64, 0.54], "metallic": 1.0, "roughness": 0.15}
    edited = apply_edits(spec, [{"op": "set_material", "object": "box_a", "material": metal}])
    entry = material_entry(edited.object("box_a"), None)
    assert entry.roughness == 0.15 and entry.f0_const == (0.95, 0.64, 0.54) and not entry.principled
    assert edited.object("box_a").transform == spec.object("box_a").transform
    assert [o for o in edited.objects if o.name != "box_a"] == [o for o in spec.objects if o.name != "box_a"]
    with pytest.raises(ValueError, match=r"edits\[0\]\.material\.texture: unknown texture 'marble'"):
        apply_edits(spec, [{"op": "set_material", "object": "box_a", "material": {"type": "diffuse", "texture": "marble"}}])
    with pytest.raises(ValueError, match=r"edits\[0\]: missing required key\(s\) 'material'"):
        apply_edits(spec, [{"op": "set_material", "object": "box_a"}])


def _lamp_edit(tmp, scale: float = 1.0) -> dict:
    """``changed_region_metrics`` of an edit that puts a lamp (radiance 50) and a dim patch (0.05) where there was
    a wall (0.3), every radiance x ``scale``: render A gets the lamp 10 % low and the patch exact, render B the lamp
    exact and the patch 3x too bright; "none" is the unedited wall."""
    from models.capture.exr import write_exr_channels
    from models.capture.types import Capture, CaptureMeta, View
    from models.metrics.edits import changed_region_metrics

    h, w = 16, 24
    cam = Camera(w, h, 20.0, 20.0, w / 2, h / 2, look_at((0, 0, 2.0), (0, 0, 0)))
    wall = np.full((h, w, 3), 0.3, np.float32)
    after = wall.copy()
    after[4:12, 4:10] = 50.0
    after[4:12, 12:20] = 0.05
    renders = {"a": after.copy(), "b": after.copy(), "none": wall.copy()}
    renders["a"][4:12, 4:10] = 45.0
    renders["b"][4:12, 12:20] = 0.15

    def capture(diffuse):
        return Capture([View("test_000", cam, "test", {"diffuse": diffuse, "specular": np.zeros_like(diffuse)})],
                       CaptureMeta())

    for name, img in renders.items():
        (tmp / name).mkdir(parents=True)
        img = img * scale
        write_exr_channels(tmp / name / "test_000.exr", {
            **{c: img[..., i] for i, c in enumerate("RGB")}, **{f"diffuse.{c}": img[..., i] for i, c in enumerate("RGB")},
            **{f"specular.{c}": np.zeros((h, w), np.float32) for c in "RGB"}})
    return {name: changed_region_metrics(capture(wall * scale), capture(after * scale), tmp / name, tmp / "none")
            for name in ("a", "b")}


def test_changed_region_scores_tonemapped_weigh_dim_pixels_as_the_headline(tmp_path):
    """Linear at the view's peak, render B (lamp exact, dim patch 3x too bright) scores higher: the lamp's error
    rules. Tonemapped (mu-law at the view's peak, the headline), render A (lamp 10 % low, patch exact) does, as the
    eye would have it. Doing nothing is worse than either under both."""
    scores = _lamp_edit(tmp_path)
    a, b = scores["a"], scores["b"]
    assert 0.1 < a["changed_fraction"] < 0.6
    assert b["edited_psnr_final"] > a["edited_psnr_final"] + 10
    assert a["edited_psnr_final_tonemapped"] > b["edited_psnr_final_tonemapped"] + 5
    for s in (a, b):
        assert s["unedited_psnr_final_tonemapped"] < s["edited_psnr_final_tonemapped"]
        assert s["unedited_psnr_final"] < s["edited_psnr_final"]


def test_changed_region_scores_do_not_depend_on_the_capture_units(tmp_path):
    """The changed pixels are found at the unedited capture's white (its key over middle grey), so a capture x 1000
    (a lamp at 4000, a wall at 200) finds the same ones and scores the same; only the white scales."""
    one, big = _lamp_edit(tmp_path / "one"), _lamp_edit(tmp_path / "big", scale=1000.0)
    for name in ("a", "b"):
        assert one[name]["changed_pixels"] > 0
        assert big[name]["changed_white"] == pytest.approx(1000 * one[name]["changed_white"], rel=1e-6)
        for key, value in one[name].items():
            if key != "changed_white":
                assert big[name][key] == pytest.approx(value, abs=1e-6), key


def test_changed_region_leaves_out_noise_groups_smaller_than_the_filter(tmp_path):
    """A view whose only "change" is Monte Carlo noise (four speckles round one pixel: after the 3x3 box filter only
    that pixel crosses the threshold) adds no changed pixels and no score: the edit scores as on the real view
    alone (zoo_thin move_rack: 2 such pixels made one of three views, +1.67 -> +2.54 dB without them)."""
    from models.capture.exr import write_exr_channels
    from models.capture.types import Capture, CaptureMeta, View
    from models.metrics.edits import CHANGED_THRESHOLD, capture_white, changed_region_metrics

    h, w = 16, 24
    cam = Camera(w, h, 20.0, 20.0, w / 2, h / 2, look_at((0, 0, 2.0), (0, 0, 0)))
    wall = np.full((h, w, 3), 0.3, np.float32)
    lamp = wall.copy()
    lamp[4:12, 4:10] = 5.0

    def capture(images):
        return Capture([View(f"test_00{i}", cam, "test", {"diffuse": img, "specular": np.zeros_like(img)})
                        for i, img in enumerate(images)], CaptureMeta())

    white = capture_white(capture([wall, wall]))
    noisy = wall.copy()
    noisy[[6, 6, 8, 8], [10, 12, 10, 12]] += 3 * CHANGED_THRESHOLD * white  # 4/9 of it at (7, 11), 2/9 round it
    edited = lamp.copy()
    edited[4:12, 4:10] = 4.5
    for name, images in (("edited", [edited, wall]), ("none", [wall, wall])):
        (tmp_path / name).mkdir()
        for i, img in enumerate(images):
            write_exr_channels(tmp_path / name / f"test_00{i}.exr", {
                **{c: img[..., k] for k, c in enumerate("RGB")},
                **{f"diffuse.{c}": img[..., k] for k, c in enumerate("RGB")},
                **{f"specular.{c}": np.zeros((h, w), np.float32) for c in "RGB"}})
    both = changed_region_metrics(capture([wall, wall]), capture([lamp, noisy]), tmp_path / "edited", tmp_path / "none")
    assert both["changed_noise_pixels"] == 1
    one = changed_region_metrics(capture([wall]), capture([lamp]), tmp_path / "edited", tmp_path / "none")
    assert one["changed_noise_pixels"] == 0 and both["changed_pixels"] == one["changed_pixels"] > 40
    for key in ("edited_psnr_final_tonemapped", "unedited_psnr_final_tonemapped", "pooled_edited_psnr_final_tonemapped"):
        assert both[key] == pytest.approx(one[key], abs=1e-9), key
