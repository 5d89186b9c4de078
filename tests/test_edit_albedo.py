"""set_albedo (models/editing/albedo.py): a Lambertian of albedo a sends a x the cosine-weighted mean of the
radiance the rest of the model sends it. Checked inside closed spheres of Gaussians (CPU Warp tracer) against
closed forms: a furnace, a half-bright sphere (the cosine law), a mirror that alone carries the light; the
selection does not light itself; normals, determinism, the spec and its errors."""

from __future__ import annotations

import math

import pytest
import torch

from models.editing import EditSpecError, apply_edit, parse_edit
from models.editing.albedo import MIN_NORMAL, shading_normals
from models.gaussians import Gaussians
from models.pathtrace.paths import PathConfig
from models.tracer import Tracer, TracerConfig
from stages.config import load_config

F64 = torch.float64
SHELL = 3000  # Gaussians on the unit sphere: closed (every ray from inside ends with T < 0.01)


@pytest.fixture(scope="module")
def tracer():
    t = Tracer(TracerConfig(num_threads=2), "cpu")
    yield t
    t.close()


def _quat_z_to(n: torch.Tensor) -> torch.Tensor:
    """[k, 4] wxyz rotations taking local +z to the unit normals n [k, 3]."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(n)
    w = 1.0 + (n * z).sum(-1, keepdim=True)
    q = torch.cat([w, torch.linalg.cross(z, n)], -1)
    q[w[:, 0] < 1e-9] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=F64)
    return torch.nn.functional.normalize(q, dim=-1)


def _surfels(points, normals, size: float, thick: float, diffuse, roughness: float = 1.0, f0: float = 0.0) -> dict:
    """Flat opaque Gaussians (disks across ``normals``) as a parameter dict."""
    k = len(points)
    return dict(means=points, quats=_quat_z_to(torch.nn.functional.normalize(normals, dim=-1)),
                log_scales=torch.tensor([math.log(size), math.log(size), math.log(thick)], dtype=F64).repeat(k, 1),
                opacity_logits=torch.full((k,), 6.0, dtype=F64),
                diffuse=torch.as_tensor(diffuse, dtype=F64).expand(k, 3).clone(), normals=normals.clone(),
                roughness=torch.full((k,), roughness, dtype=F64), f0=torch.full((k, 3), f0, dtype=F64))


def _shell(diffuse_of) -> dict:
    """The unit sphere (Fibonacci points, inward normals), each Gaussian's diffuse = diffuse_of(points) [k, 3]."""
    i = torch.arange(SHELL, dtype=F64) + 0.5
    y = 1 - 2 * i / SHELL
    phi = math.pi * (3 - math.sqrt(5)) * i
    p = torch.stack([(1 - y * y).sqrt() * phi.cos(), y, (1 - y * y).sqrt() * phi.sin()], -1)
    shell = _surfels(p, -p, 0.8 * math.sqrt(4 * math.pi / SHELL), 0.005, [0.0, 0.0, 0.0])
    shell["diffuse"] = diffuse_of(p)
    return shell


def _scene(*parts: dict) -> Gaussians:
    return Gaussians(**{k: torch.cat([p[k] for p in parts]).to(torch.float32).contiguous() for k in parts[0]})


def _edit(g, tracer, value, samples=64, max_path_length=2, radius=0.2):
    spec = parse_edit("paint", {"select": {"sphere": {"centre": [0, 0, 0], "radius": radius}},
                                "ops": [{"op": "set_albedo", "value": value, "samples": samples}]})
    return apply_edit(g, spec, trace_fn=tracer.trace, path=PathConfig(max_path_length=max_path_length))


def _plates(gap: float, diffuse) -> dict:
    """Two 3 x 3 plates facing each other across y = 0 (a concave selection: each sees the other)."""
    u = torch.linspace(-0.04, 0.04, 3, dtype=F64)
    xx, zz = torch.meshgrid(u, u, indexing="ij")
    p = torch.stack([xx.reshape(-1), torch.zeros(9, dtype=F64), zz.reshape(-1)], -1)
    up = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64).expand(9, 3)
    low = _surfels(p - torch.tensor([0, gap / 2, 0], dtype=F64), up, 0.03, 0.002, diffuse)
    high = _surfels(p + torch.tensor([0, gap / 2, 0], dtype=F64), -up, 0.03, 0.002, diffuse)
    return {k: torch.cat([low[k], high[k]]) for k in low}


# ------------------------------------------------------------------------------------------- closed forms


def test_furnace_gives_albedo_times_the_uniform_radiance(tracer):
    """Uniform radiance L all around: E / pi = L, so every selected Gaussian gets a x L, at any path length.
    The selection (two plates facing each other, radiance 100) does not light itself."""
    light = torch.tensor([0.2, 0.5, 1.0], dtype=F64)
    shell = _shell(lambda p: light.expand(len(p), 3))
    d = torch.nn.functional.normalize(torch.randn(2000, 3, generator=torch.Generator().manual_seed(0)), dim=1)
    assert tracer.trace(torch.zeros_like(d), d, _scene(shell)).transmittance.max() <= 0.01  # closed
    g = _scene(shell, _plates(0.1, [100.0, 100.0, 100.0]))
    albedo = torch.tensor([0.5, 0.8, 0.3], dtype=F64)
    for length in (1, 2, 3):
        edited, report = _edit(g, tracer, albedo.tolist(), max_path_length=length)
        assert report[0]["selected"] == 18
        got = edited.diffuse[SHELL:].double()
        torch.testing.assert_close(got, (albedo * light).expand(18, 3), rtol=0.03, atol=0)  # seen: 5e-5
        assert torch.equal(edited.diffuse[:SHELL], g.diffuse[:SHELL])  # only the selection changes


def test_cosine_law_under_a_half_bright_sphere(tracer):
    """Upper half of the sphere bright, lower black, Gaussians at the centre tilted by theta from +y: the bright
    half-space fills (1 + cos theta) / 2 of the cosine-weighted hemisphere."""
    light = torch.tensor([1.0, 2.0, 4.0], dtype=F64)
    shell = _shell(lambda p: torch.where(p[:, 1:2] > 0, light, torch.zeros(3, dtype=F64)))
    theta = torch.tensor([0.0, 30, 60, 90, 120, 150, 180], dtype=F64).deg2rad()
    normals = torch.stack([theta.sin(), theta.cos(), torch.zeros_like(theta)], -1)
    probes = _surfels(torch.zeros(len(theta), 3, dtype=F64), normals, 0.01, 0.001, [100.0, 100.0, 100.0])
    edited, _ = _edit(_scene(shell, probes), tracer, [0.5, 0.5, 0.5], samples=1024)
    fraction = edited.diffuse[SHELL:].double() / (0.5 * light)
    expect = ((1 + theta.cos()) / 2)[:, None].expand(-1, 3)
    torch.testing.assert_close(fraction, expect, rtol=0, atol=0.02)  # seen: 0.0052 (1024 stratified rays)
    assert fraction[0, 0] > 0.99 and fraction[-1, 0] < 0.01  # facing the bright half vs facing away
    assert (fraction[1:, 0] < fraction[:-1, 0]).all()


def test_light_seen_only_in_a_mirror_counts_from_path_length_2(tracer):
    """A patch facing down onto a mirror (F0 1, roughness 0, black diffuse) in a bright sphere: with reflections
    (max_path_length 2, the incident radiance is what the model renders) it gets ~ a x L; from the diffuse cache
    alone (length 1) only the rim of the hemisphere the mirror does not cover."""
    light = torch.tensor([1.0, 1.0, 1.0], dtype=F64)
    u = torch.arange(-9, 10, dtype=F64) * 0.1
    xx, zz = torch.meshgrid(u, u, indexing="ij")
    keep = (xx ** 2 + zz ** 2).reshape(-1) < 0.93 ** 2
    p = torch.stack([xx.reshape(-1), torch.full((361,), -0.3, dtype=F64), zz.reshape(-1)], -1)[keep]
    mirror = _surfels(p, torch.tensor([[0.0, 1.0, 0.0]], dtype=F64).expand(len(p), 3), 0.07, 0.002,
                      [0.0, 0.0, 0.0], roughness=0.0, f0=1.0)
    down = _surfels(torch.zeros(1, 3, dtype=F64), torch.tensor([[0.0, -1.0, 0.0]], dtype=F64), 0.01, 0.001,
                    [0.0, 0.0, 0.0])
    g = _scene(_shell(lambda q: light.expand(len(q), 3)), mirror, down)
    got = {k: _edit(g, tracer, [0.5, 0.5, 0.5], samples=512, max_path_length=k, radius=0.05)[0].diffuse[-1, 0].item()
           for k in (1, 2)}
    assert got[1] < 0.5 * 0.2, got  # the mirror (radius 0.93 at depth 0.3) covers ~91% of it; seen: 0.045
    assert abs(got[2] - 0.5) < 0.5 * 0.03, got  # seen: 0.50000


# ------------------------------------------------------------------------------------------- choices


def test_the_selection_does_not_light_or_shadow_itself(tracer):
    """The selection's old radiance (100 vs 0) changes nothing: it is left out of the traced scene."""
    g = _scene(_shell(lambda p: torch.full((len(p), 3), 0.4, dtype=F64)), _plates(0.1, [0.0, 0.0, 0.0]))
    bright = Gaussians(**{**g.params(), "diffuse": torch.cat([g.diffuse[:SHELL], torch.full((18, 3), 100.0)])})
    a, _ = _edit(g, tracer, [0.7, 0.7, 0.7])
    b, _ = _edit(bright, tracer, [0.7, 0.7, 0.7])
    assert torch.equal(a.diffuse, b.diffuse)
    torch.testing.assert_close(a.diffuse[SHELL:].double(), torch.full((18, 3), 0.28, dtype=F64), rtol=0.03, atol=0)
    c, _ = _edit(g, tracer, [0.7, 0.7, 0.7])
    assert torch.equal(a.diffuse, c.diffuse)  # seeded: the same edit gives the same model


def test_unreliable_normals_are_replaced():
    """Normals shorter than MIN_NORMAL: the mean of the selected neighbours' normals, else outward from the
    selection's centre."""
    k = 6
    p = torch.stack([torch.linspace(-0.1, 0.1, k, dtype=F64), torch.zeros(k, dtype=F64), torch.zeros(k, dtype=F64)], -1)
    n = torch.tensor([[0.0, 2.0, 0.0]], dtype=F64).repeat(k, 1)  # stored normals need not be unit
    n[2] = torch.tensor([0.3 * MIN_NORMAL, 0.0, 0.0], dtype=F64)
    g = Gaussians(**{**_surfels(p, torch.tensor([[0.0, 1.0, 0.0]], dtype=F64).expand(k, 3), 0.02, 0.001, [0.5] * 3),
                     "normals": n})
    mask = torch.ones(k, dtype=torch.bool)
    torch.testing.assert_close(shading_normals(g, mask), torch.tensor([[0.0, 1.0, 0.0]], dtype=F64).expand(k, 3))
    g.normals = torch.zeros(k, 3, dtype=F64)  # no reliable neighbour: outward from the centre (x = 0)
    torch.testing.assert_close(shading_normals(g, mask)[[0, -1]], torch.tensor([[-1.0, 0, 0], [1.0, 0, 0]], dtype=F64))


# ------------------------------------------------------------------------------------------- spec and errors


def test_spec_accepts_set_albedo_and_names_bad_values():
    op = parse_edit("e", {"select": {"all": True}, "ops": [{"op": "set_albedo", "value": [0.9, 0.7, 0.1]}]}).ops[0]
    assert op.kind == "set_albedo" and op.params == {"value": (0.9, 0.7, 0.1), "samples": 64}
    op = parse_edit("e", {"select": {"all": True}, "ops": [{"op": "set_albedo", "value": [0, 0, 1], "samples": 8}]})
    assert op.ops[0].params["samples"] == 8
    at = r"^edit 'gold' op 0 \(set_albedo\)"
    cases = [
        ({"value": [1.2, 0.5, 0.5]}, at + r"\.value\[0\]: must be <= 1\.0, got 1\.2$"),
        ({"value": [0.5, -0.1, 0.5]}, at + r"\.value\[1\]: must be >= 0\.0, got -0\.1$"),
        ({"value": [0.5, 0.5]}, at + r"\.value: must be a list of 3 numbers, got \[0\.5, 0\.5\]$"),
        ({"value": 0.5}, at + r"\.value: must be a list of 3 numbers"),
        ({}, at + r": missing 'value'$"),
        ({"value": [0.5] * 3, "samples": 0}, at + r"\.samples: must be an integer >= 1, got 0$"),
        ({"value": [0.5] * 3, "samples": 2.5}, at + r"\.samples: must be an integer >= 1, got 2\.5$"),
        ({"value": [0.5] * 3, "albedo": 1}, at + r": unknown key\(s\) 'albedo' \(known: op, samples, select, value\)"),
    ]
    for extra, pattern in cases:
        with pytest.raises(EditSpecError, match=pattern):
            parse_edit("gold", {"select": {"all": True}, "ops": [{"op": "set_albedo", **extra}]})
    # the workflow's schema (scene configs) knows the op and its keys
    edit = {"select": {"all": True}, "ops": [{"op": "set_albedo", "value": [0.9, 0.7, 0.1], "samples": 16}]}
    assert load_config("demo", overrides={"edits": {"gold": edit}})["edits"]["gold"] == edit


def test_set_albedo_needs_a_tracer_and_something_to_light_it(tracer):
    g = _scene(_plates(0.1, [1.0, 1.0, 1.0]))
    spec = parse_edit("gold", {"select": {"box": {"min": [-1, 0, -1], "max": [1, 1, 1]}},
                               "ops": [{"op": "set_albedo", "value": [0.9, 0.7, 0.1]}]})
    with pytest.raises(EditSpecError, match=r"^edit 'gold' op 0 \(set_albedo\): set_albedo traces the scene .* needs "
                       r"a tracer \(apply_edit\(\.\.\., trace_fn=tracer\.trace"):
        apply_edit(g, spec)
    spec = parse_edit("gold", {"select": {"all": True}, "ops": [{"op": "set_albedo", "value": [0.9, 0.7, 0.1]}]})
    with pytest.raises(EditSpecError, match=r"^edit 'gold' op 0 \(set_albedo\): .*nothing is left to light"):
        apply_edit(g, spec, trace_fn=tracer.trace)
