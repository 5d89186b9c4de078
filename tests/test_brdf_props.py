"""Property tests (hypothesis) of the specular BRDF and samplers at the extremes:
roughness in [0, 1] (0 clamps to 0.01), F0 in {0, 1} or random, grazing and
below-surface views, uniforms at 0 and 1, float32 and float64, every Smith form."""

from __future__ import annotations

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from models.pathtrace.brdf import SMITH_MODELS, eval_specular
from models.pathtrace.sampling import sample_ndf, sample_vndf

EDGE_FLOATS = st.one_of(st.sampled_from([0.0, 1e-7, 0.5, 1.0 - 1e-7, 1.0]), st.floats(0.0, 1.0))
F0 = st.one_of(st.sampled_from([0.0, 1.0]).map(lambda v: (v, v, v)),
               st.tuples(EDGE_FLOATS, EDGE_FLOATS, EDGE_FLOATS))
# view angle from the normal: grazing (pi/2 - tiny, pi/2) and below the surface included
THETA_O = st.one_of(st.sampled_from([0.0, 1.0, math.pi / 2 - 1e-4, math.pi / 2 - 1e-7, math.pi / 2,
                                     math.pi / 2 + 1e-3, math.pi]),
                    st.floats(0.0, math.pi))
CASE = st.fixed_dictionaries({
    "roughness": EDGE_FLOATS, "f0": F0, "theta_o": THETA_O, "phi_o": st.floats(-math.pi, math.pi),
    "n_theta": st.floats(0.0, math.pi), "n_phi": st.floats(-math.pi, math.pi),
    "u1": EDGE_FLOATS, "u2": EDGE_FLOATS,
    "dtype": st.sampled_from([torch.float32, torch.float64]), "smith": st.sampled_from(SMITH_MODELS),
})
PROPS = settings(max_examples=int(__import__("os").environ.get("BRDF_PROPS_EXAMPLES", 100)), deadline=None)


def _unit(theta, phi):
    return [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)]


def _inputs(c, grad: bool):
    dt = c["dtype"]
    n = torch.tensor([_unit(c["n_theta"], c["n_phi"])], dtype=torch.float64)
    # wo at angle theta_o from n, in an arbitrary direction around it
    t = torch.linalg.cross(n, torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64))
    if t.norm() < 1e-6:
        t = torch.linalg.cross(n, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))
    t = t / t.norm()
    b = torch.linalg.cross(n, t)
    dx, dy, dz = _unit(c["theta_o"], c["phi_o"])
    wo = dx * t + dy * b + dz * n
    wo = wo / wo.norm()
    r = torch.tensor([c["roughness"]], dtype=dt, requires_grad=grad)
    f0 = torch.tensor([c["f0"]], dtype=dt, requires_grad=grad)
    return (n.to(dt).requires_grad_(grad), wo.to(dt).requires_grad_(grad), r, f0,
            torch.tensor([c["u1"]], dtype=dt), torch.tensor([c["u2"]], dtype=dt))


def _check_sample(sample, c, energy_bound: bool):
    n, wo, r, f0, u1, u2 = _inputs(c, grad=True)
    s = sample(n, wo, r, f0, u1, u2, c["smith"])
    for name, v in s._asdict().items():
        if v.dtype != torch.bool:
            assert torch.isfinite(v).all(), (name, v)
    assert torch.all(s.weight >= 0) and torch.all(s.pdf >= 0)
    if energy_bound:  # VNDF: weight = F G2 / G1(wo) <= F <= 1 per channel for F0 in [0, 1]
        tol = 1e-6 if c["dtype"] == torch.float32 else 1e-12
        assert torch.all(s.weight <= 1.0 + tol), s.weight
    if s.valid.item():
        assert abs(s.wi.norm().item() - 1.0) < 1e-5
        assert (s.wi * n).sum().item() > -1e-6  # validity is decided in the local frame
    else:
        assert torch.all(s.weight == 0)
    if (n * wo).sum().item() <= 0:
        assert not s.valid.item() and s.pdf.item() == 0
    (s.weight.sum() + s.wi.sum() + s.pdf.clamp(max=1e6).sum() * 1e-6).backward()
    for name, v in (("n", n), ("wo", wo), ("roughness", r), ("f0", f0)):
        assert v.grad is not None and torch.isfinite(v.grad).all(), (name, v.grad)


@PROPS
@given(CASE)
def test_vndf_finite_bounded_and_differentiable(c):
    _check_sample(sample_vndf, c, energy_bound=True)


@PROPS
@given(CASE)
def test_ndf_finite_and_differentiable(c):
    # Half-vector sampling has no per-sample bound: weight = F G2 (wo.h)/((n.h)(n.wo)) can
    # exceed 1 (only its mean, the albedo, is <= 1; see test_brdf.py).
    _check_sample(sample_ndf, c, energy_bound=False)


@PROPS
@given(CASE, st.floats(0.0, math.pi), st.floats(-math.pi, math.pi))
def test_eval_specular_finite_nonnegative_and_differentiable(c, theta_i, phi_i):
    n, wo, r, f0, _, _ = _inputs(c, grad=True)
    wi = torch.tensor([_unit(theta_i, phi_i)], dtype=c["dtype"], requires_grad=True)
    f = eval_specular(n, wo, wi, r, f0, c["smith"])
    assert torch.isfinite(f).all() and torch.all(f >= 0)
    if (n * wo).sum().item() <= 0:
        assert torch.all(f == 0)
    f.sum().backward()
    for name, v in (("n", n), ("wo", wo), ("wi", wi), ("roughness", r), ("f0", f0)):
        assert torch.isfinite(v.grad).all(), (name, v.grad)
