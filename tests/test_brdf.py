"""Specular BRDF and sampler checks against deterministic quadrature (models.pathtrace).

Frame used with `_numeric`: n = +z, wo = (-sin theta_o, 0, cos theta_o); the mirror
direction is at (theta_o, phi = 0).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pytest
import scipy.stats
import torch

from tests import _numeric as nm
from models.pathtrace.brdf import (
    SMITH_MODELS,
    eval_specular,
    dielectric_weight,
    diffuse_view_factor,
    fresnel,
    fresnel_dielectric,
    fresnel_f90,
    fresnel_schlick,
    ggx_d,
    reflect,
    smith_g,
    smith_g1,
)
from models.pathtrace.sampling import (
    compare_sampler_variance,
    format_variance_table,
    pdf_ndf,
    pdf_vndf,
    sample_ndf,
    sample_specular,
    sample_vndf,
)

F64 = torch.float64
SAMPLERS = {"vndf": (sample_vndf, pdf_vndf), "ndf": (sample_ndf, pdf_ndf)}


def _local_batch(roughness: float, theta_o: float, m: int, seed: int, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=dtype).expand(m, 3)
    wo = torch.from_numpy(nm.view_dir(theta_o)).to(dtype).expand(m, 3)
    r = torch.full((m,), roughness, dtype=dtype)
    u1, u2 = torch.rand(m, generator=g, dtype=dtype), torch.rand(m, generator=g, dtype=dtype)
    return n, wo, r, u1, u2


def _random_batch(m: int, seed: int, dtype=F64, max_theta_deg: float = 85.0):
    """Random normals, views above the surface within max_theta, roughness in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    n = torch.randn(m, 3, generator=g, dtype=dtype)
    n = n / n.norm(dim=-1, keepdim=True)
    t = torch.randn(m, 3, generator=g, dtype=dtype)
    t = t - (t * n).sum(-1, keepdim=True) * n
    t = t / t.norm(dim=-1, keepdim=True)
    th = torch.rand(m, generator=g, dtype=dtype) * math.radians(max_theta_deg)
    wo = torch.cos(th)[:, None] * n + torch.sin(th)[:, None] * t
    r = torch.rand(m, generator=g, dtype=dtype)
    r[: m // 8] = 0.01  # near-mirror rows
    f0 = torch.rand(m, 3, generator=g, dtype=dtype)
    u1, u2 = torch.rand(m, generator=g, dtype=dtype), torch.rand(m, generator=g, dtype=dtype)
    return n, wo, r, f0, u1, u2


@lru_cache(maxsize=None)
def _albedo_quadrature(roughness: float, theta_deg: float) -> tuple[float, float]:
    """(E, error estimate) of the F0 = 1 directional albedo: orders 6 and 10 compared."""
    th = math.radians(theta_deg)
    e6 = float(nm.directional_albedo(eval_specular, roughness, th, 6)[0])
    e10 = float(nm.directional_albedo(eval_specular, roughness, th, 10)[0])
    return e10, abs(e10 - e6)


# ------------------------------------------------------------------ BRDF pieces


def test_fresnel_schlick_endpoints():
    f0 = torch.tensor([[0.0, 0.04, 1.0]], dtype=F64)
    assert torch.equal(fresnel_schlick(f0, torch.ones(1, dtype=F64)), f0)  # F(1) = F0
    assert torch.allclose(fresnel_schlick(f0, torch.zeros(1, dtype=F64)), torch.ones(1, 3, dtype=F64))


def test_fresnel_f90_matte_reflects_nothing_real_materials_unchanged():
    """schlick_f90: F0 = 0 (a matte surface: no specular lobe in the capture) gives F = 0 at every angle; from
    mean F0 = 0.02 up F90 = 1, so every real dielectric (0.04) and metal keeps the paper's Schlick exactly."""
    cos = torch.linspace(0.0, 1.0, 11, dtype=F64)
    f0 = torch.tensor([[0.0, 0.0, 0.0], [0.04, 0.04, 0.04], [0.02, 0.02, 0.02], [1.0, 0.7, 0.3]], dtype=F64)
    f0b = f0[:, None, :].expand(4, 11, 3)
    f = fresnel_schlick(f0b, cos.expand(4, 11), fresnel_f90(f0b, "schlick_f90"))
    paper = fresnel_schlick(f0b, cos.expand(4, 11))
    assert torch.all(f[0] == 0)
    assert torch.equal(f[1:], paper[1:])
    assert torch.allclose(f[1:, 0], torch.ones(3, 3, dtype=F64))  # F(0) = F90 = 1
    assert fresnel_f90(f0, "schlick") is None
    small = torch.full((1, 3), 0.004, dtype=F64)  # between: F90 = 50 F0 = 0.2, F between F0 and F90
    assert torch.allclose(fresnel_schlick(small, torch.zeros(1, dtype=F64), fresnel_f90(small)),
                          torch.full((1, 3), 0.2, dtype=F64))
    with pytest.raises(ValueError, match="fresnel='fresnel'"):
        fresnel_f90(f0, "fresnel")


def test_fresnel_dielectric_is_snells_and_blends_to_schlick_for_metals():
    """"dielectric": the exact unpolarised Fresnel of a dielectric with eta = (1 + sqrt F0) / (1 - sqrt F0), here
    against s- and p-reflectances from Snell's law (F0 0.04 is eta 1.5: 0.0892 at 60 degrees, where Schlick gives
    0.070); F(1) = F0, F(0) = 1, F0 = 0 reflects nothing; up to mean F0 0.08 it is the whole term, from 0.2 it is
    schlick_f90's, linear in between; the other modes have no dielectric share."""
    cos = torch.linspace(0.02, 1.0, 50, dtype=F64)
    for f in (0.02, 0.04, 0.08, 0.3):
        eta = (1 + math.sqrt(f)) / (1 - math.sqrt(f))
        ct = torch.sqrt(1 - (1 - cos ** 2) / eta ** 2)
        rs = ((cos - eta * ct) / (cos + eta * ct)) ** 2
        rp = ((eta * cos - ct) / (eta * cos + ct)) ** 2
        f0 = torch.full((50, 3), f, dtype=F64)
        assert torch.allclose(fresnel_dielectric(f0, cos)[:, 0], (rs + rp) / 2, atol=1e-12)
    f0 = torch.tensor([[0.04] * 3, [0.0] * 3], dtype=F64)
    half = torch.full((2,), 0.5, dtype=F64)
    assert fresnel_dielectric(f0, half)[0, 0].item() == pytest.approx(0.0892, abs=5e-4)
    assert fresnel_schlick(f0, half)[0, 0].item() == pytest.approx(0.07, abs=1e-9)
    assert torch.allclose(fresnel_dielectric(f0, torch.ones(2, dtype=F64)), f0)
    assert fresnel_dielectric(f0, torch.zeros(2, dtype=F64))[0, 0].item() == pytest.approx(1.0)
    assert torch.all(fresnel_dielectric(f0[1:].expand(50, 3), cos) == 0)
    grey = torch.tensor([0.04, 0.08, 0.14, 0.2, 0.9], dtype=F64)[:, None].expand(5, 3)
    w = dielectric_weight(grey, "dielectric")
    assert torch.allclose(w[:, 0], torch.tensor([1.0, 1.0, 0.5, 0.0, 0.0], dtype=F64))
    c = torch.full((5,), 0.3, dtype=F64)
    both = fresnel(grey, c, fresnel_f90(grey, "dielectric"), w)
    assert torch.allclose(both[:2], fresnel_dielectric(grey, c)[:2])
    assert torch.allclose(both[3:], fresnel_schlick(grey, c)[3:])
    assert torch.allclose(both[2], 0.5 * (fresnel_dielectric(grey, c)[2] + fresnel_schlick(grey, c)[2]))
    assert dielectric_weight(grey, "schlick_f90") is None and dielectric_weight(grey, "schlick") is None
    with pytest.raises(ValueError, match="fresnel='fresnell'"):
        dielectric_weight(grey, "fresnell")


def test_ggx_d_projected_area_normalised():
    # int D(h) (n.h) dw_h = 2 pi int_0^1 D(c) c dc = 1, including near-mirror alpha = 1e-4.
    for alpha in (1e-4, 0.01, 0.25, 1.0):
        b = nm.refined_breaks(0.0, 1.0, [1.0], smallest=1e-3 * alpha * alpha)
        c, w = nm.gauss_panels(b, 10)
        d = ggx_d(torch.from_numpy(c), torch.tensor(alpha, dtype=F64)).numpy()
        assert abs(2 * math.pi * np.sum(w * d * c) - 1.0) < 1e-8, alpha


def test_smith_forms_relations():
    c = torch.linspace(0.0, 1.0, 101, dtype=F64)
    ci, co = torch.meshgrid(c, c, indexing="ij")
    for alpha in (1e-4, 0.09, 0.5, 1.0):
        a = torch.tensor(alpha, dtype=F64)
        g1o, g1i = smith_g1(co, a), smith_g1(ci, a)
        hc, sep = smith_g(co, ci, a, "height_correlated"), smith_g(co, ci, a, "separable")
        sch = smith_g(co, ci, a, "schlick")
        assert torch.allclose(sep, g1o * g1i)
        assert torch.all(hc >= sep - 1e-15) and torch.all(hc <= torch.minimum(g1o, g1i) + 1e-15)
        assert torch.all(sch <= sep + 1e-15)  # Schlick G1 (k = alpha/2) <= exact Smith G1
        assert torch.all((hc >= 0) & (hc <= 1))
    # exact Smith G1 = 1 / (1 + Lambda), Lambda = (-1 + sqrt(1 + alpha^2 tan^2)) / 2
    cc = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    lam = 0.5 * (-1 + torch.sqrt(1 + 0.3**2 * (1 - cc**2) / cc**2))
    assert torch.allclose(smith_g1(cc, torch.tensor(0.3, dtype=F64)), 1 / (1 + lam))


def test_eval_specular_zero_below_and_reciprocal():
    n, wo, r, f0, _, _ = _random_batch(256, seed=3)
    wi = reflect(-wo, n)
    wi = wi + 0.3 * torch.randn(wi.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
    wi = wi / wi.norm(dim=-1, keepdim=True)
    f = eval_specular(n, wo, wi, r, f0)
    ci, co = (n * wi).sum(-1), (n * wo).sum(-1)
    assert torch.all(f[ci <= 0] == 0) and torch.all(f >= 0)
    # f_s is reciprocal: f(wo, wi) / cos_i == f(wi, wo) / cos_o
    up = ci > 0
    g = eval_specular(n[up], wi[up], wo[up], r[up], f0[up])
    assert torch.allclose(f[up] / ci[up, None], g / co[up, None], rtol=1e-10, atol=0)
    # wo below the surface
    assert torch.all(eval_specular(n, -wo, wi, r, f0) == 0)


def test_bad_arguments_raise():
    n, wo, r, f0, u1, u2 = _random_batch(4, seed=0)
    with pytest.raises(ValueError, match="smith"):
        eval_specular(n, wo, wo, r, f0, smith="ggx")
    with pytest.raises(ValueError, match="f0"):
        eval_specular(n, wo, wo, r, f0[:, :2])
    with pytest.raises(ValueError, match="roughness"):
        sample_vndf(n, wo, r[:2], f0, u1, u2)
    with pytest.raises(ValueError, match="method"):
        sample_specular(n, wo, r, f0, u1, u2, method="cosine")


# ------------------------------------------------------------------ samplers


@pytest.mark.parametrize("name", SAMPLERS)
@pytest.mark.parametrize("smith", SMITH_MODELS)
def test_weight_is_eval_over_pdf(name, smith):
    """The simplified weight equals eval_specular(wi) / pdf(wi); returned pdf = pdf(wi)."""
    sample, pdf = SAMPLERS[name]
    n, wo, r, f0, u1, u2 = _random_batch(4096, seed=1)
    s = sample(n, wo, r, f0, u1, u2, smith)
    p = pdf(n, wo, s.wi, r)
    assert torch.allclose(s.pdf, p, rtol=1e-6, atol=0)
    v = s.valid
    assert v.float().mean() > 0.8
    ref = eval_specular(n[v], wo[v], s.wi[v], r[v], f0[v], smith) / p[v, None]
    assert torch.allclose(s.weight[v], ref, rtol=1e-4, atol=1e-12)
    assert torch.all(s.weight[~v] == 0)
    f0 = f0 * 0.03  # F90 = 50 mean F0 < 1 on most rows: the same identity with the bounded grazing term
    f90 = fresnel_f90(f0)
    assert (f90 < 1).float().mean() > 0.5
    s = sample(n, wo, r, f0, u1, u2, smith, f90)
    ref = eval_specular(n[v], wo[v], s.wi[v], r[v], f0[v], smith, f90[v]) / p[v, None]
    assert torch.allclose(s.weight[v], ref, rtol=1e-4, atol=1e-12)
    assert torch.allclose(s.wi.norm(dim=-1), torch.ones_like(r), atol=1e-12)
    f0 = f0 * 5  # mean F0 over 0-0.3: exact dielectric, blended and Schlick rows (fresnel = "dielectric")
    f90, diel = fresnel_f90(f0, "dielectric"), dielectric_weight(f0, "dielectric")
    assert ((diel > 0) & (diel < 1)).float().mean() > 0.1 and (diel == 1).float().mean() > 0.2
    s = sample(n, wo, r, f0, u1, u2, smith, f90, diel)
    ref = eval_specular(n[v], wo[v], s.wi[v], r[v], f0[v], smith, f90[v], diel[v]) / p[v, None]
    assert torch.allclose(s.weight[v], ref, rtol=1e-4, atol=1e-12)


@pytest.mark.parametrize("name", SAMPLERS)
@pytest.mark.parametrize("roughness", [0.01, 0.3, 1.0])
@pytest.mark.parametrize("theta_deg", [0.0, 45.0, 80.0])
def test_pdf_integrates_to_one(name, roughness, theta_deg):
    _, pdf = SAMPLERS[name]
    th = math.radians(theta_deg)
    # 1e-6: the NDF pdf has an integrable 1/|wo + wi| point singularity at wi = -wo.
    mass = nm.pdf_mass(pdf, roughness, th, order=6, smallest=min(1e-6, 1e-3 * max(roughness, 0.01) ** 2))
    assert abs(mass - 1.0) < 1e-6


@pytest.mark.parametrize("roughness,theta_deg", [(0.5, 60.0), (1.0, 80.0)])
def test_vndf_below_surface_mass_matches_invalid_fraction(roughness, theta_deg):
    """VNDF may reflect below the surface; that pdf mass is the fraction of invalid samples."""
    th = math.radians(theta_deg)
    below = nm.pdf_mass(pdf_vndf, roughness, th, order=6, theta_range=(math.pi / 2, math.pi), smallest=1e-4)
    above = nm.pdf_mass(pdf_vndf, roughness, th, order=6, theta_range=(0.0, math.pi / 2), smallest=1e-4)
    assert abs(above + below - 1.0) < 1e-8 and below > 0.01
    m = 1 << 16
    n, wo, r, u1, u2 = _local_batch(roughness, th, m, seed=5)
    s = sample_vndf(n, wo, r, torch.ones(m, 3, dtype=F64), u1, u2)
    frac = 1.0 - s.valid.double().mean().item()
    assert abs(frac - below) < 4 * math.sqrt(below * (1 - below) / m)  # binomial 4 sigma


@pytest.mark.parametrize("name", SAMPLERS)
@pytest.mark.parametrize("roughness,theta_deg", [(0.5, 45.0), (0.15, 70.0)])
def test_sample_histogram_matches_pdf(name, roughness, theta_deg):
    """Chi-square of sampled (theta, phi) counts against the quadrature of the pdf per bin."""
    sample, pdf = SAMPLERS[name]
    th = math.radians(theta_deg)
    a = roughness**2
    t_edges = np.unique(np.clip(th + np.array([-4, -1.5, -0.5, 0, 0.5, 1.5, 4]) * a, 1e-3, math.pi / 2))
    t_edges = np.concatenate([[0.0], t_edges, [math.pi / 2, math.pi]])
    t_edges = np.unique(t_edges)
    p_edges = np.array([-math.pi, -2.5 * a, -0.8 * a, 0.0, 0.8 * a, 2.5 * a, math.pi])
    expected_p = nm.binned_mass(pdf, roughness, th, t_edges, p_edges)
    assert abs(expected_p.sum() - 1.0) < 1e-6
    m = 1 << 16
    n, wo, r, u1, u2 = _local_batch(roughness, th, m, seed=7)
    s = sample(n, wo, r, torch.ones(m, 3, dtype=F64), u1, u2)
    t, p = nm.to_theta_phi(s.wi)
    obs, _, _ = np.histogram2d(t, p, bins=[t_edges, p_edges])
    exp = expected_p * m
    keep = exp > 5  # chi-square validity; lump the rest into one bin
    obs_k = np.append(obs[keep], obs[~keep].sum())
    exp_k = np.append(exp[keep], exp[~keep].sum())
    if exp_k[-1] == 0:
        obs_k, exp_k = obs_k[:-1], exp_k[:-1]
    assert keep.sum() >= 20
    chi2 = float(np.sum((obs_k - exp_k) ** 2 / exp_k))
    assert scipy.stats.chi2.sf(chi2, len(exp_k) - 1) > 1e-4, chi2


@pytest.mark.parametrize("name", SAMPLERS)
@pytest.mark.parametrize("roughness", [0.05, 0.3, 1.0])
@pytest.mark.parametrize("theta_deg", [0.0, 45.0, 80.0])
def test_white_furnace_mc_matches_quadrature(name, roughness, theta_deg):
    """F0 = 1: MC mean of the sample weight == directional albedo by quadrature, <= 1.

    Tolerance: 4 standard errors of the MC mean, plus twice the quadrature error
    estimate, plus 1/m: weights are in [0, ~2] and an event of probability p < 1/m is
    typically absent from the sample, biasing the mean by O(p) without showing in the
    standard error (GGX tails; at roughness 0.05 the worst gap seen was 3e-6).
    """
    sample, _ = SAMPLERS[name]
    e, qerr = _albedo_quadrature(roughness, theta_deg)
    assert qerr < 1e-6
    assert e <= 1.0 + 1e-9  # energy never created
    m = 1 << 16
    n, wo, r, u1, u2 = _local_batch(roughness, math.radians(theta_deg), m, seed=11)
    w = sample(n, wo, r, torch.ones(m, 3, dtype=F64), u1, u2).weight
    assert torch.equal(w[:, 0], w[:, 1]) and torch.equal(w[:, 0], w[:, 2])
    mean, se = w[:, 0].mean().item(), w[:, 0].std().item() / math.sqrt(m)
    assert abs(mean - e) <= 4 * se + 2 * qerr + 1.0 / m, (mean, e, se)
    assert mean <= 1.0 + 4 * se


@pytest.mark.parametrize("smith", SMITH_MODELS)
def test_albedo_analytic_roughness_one(smith):
    """alpha = 1, normal view: D = 1/pi, G2 = 2 c / (1 + c) for every Smith form here, so
    E = int_0^1 c / (1 + c) dc = 1 - ln 2 (an anchor independent of the samplers)."""
    from functools import partial

    e = nm.directional_albedo(partial(eval_specular, smith=smith), 1.0, 0.0, order=8)
    assert np.allclose(e, 1.0 - math.log(2.0), rtol=0, atol=1e-10)


def test_near_mirror_albedo_quadrature():
    # roughness 0.01 (alpha = 1e-4): E = 1 - O(alpha^2) at moderate view angles.
    e, qerr = _albedo_quadrature(0.01, 45.0)
    assert 1 - 1e-6 < e <= 1.0 and qerr < 1e-8


@pytest.mark.parametrize("name", SAMPLERS)
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_near_mirror_reproduces_reflection(name, dtype):
    """Roughness 0.01 (and 0, clamped to it): sampled wi clusters on reflect(-wo, n).

    GGX has a heavy tail (P(tan theta_h > x) = alpha^2 / (alpha^2 + x^2)), so a fixed
    fraction of samples deviates more than any bound ~ alpha: we assert on quantiles
    (seen: median 1.7e-4, 90 % 5.3e-4, 99 % 1.7e-3 rad for views up to 80 deg).
    """
    sample, _ = SAMPLERS[name]
    n, wo, _, f0, u1, u2 = _random_batch(8192, seed=2, dtype=dtype, max_theta_deg=80.0)
    mirror = reflect(-wo, n)
    for rough in (0.01, 0.0):
        s = sample(n, wo, torch.full_like(u1, rough), f0, u1, u2)
        dev = torch.linalg.cross(s.wi, mirror).norm(dim=-1).double()
        assert torch.quantile(dev, 0.5) < 3e-4
        assert torch.quantile(dev, 0.9) < 1e-3
        assert s.valid.all()
    # F0 = 0 near normal incidence: Schlick F(wo.h ~ 1) ~ F0 = 0
    n1, wo1, r1, u1_, u2_ = _local_batch(0.01, 0.0, 1024, seed=3, dtype=dtype)
    s0 = sample(n1, wo1, r1, torch.zeros(1024, 3, dtype=dtype), u1_, u2_)
    assert s0.weight.abs().max() < 1e-6


@pytest.mark.parametrize("name", SAMPLERS)
def test_float32_matches_float64(name):
    sample, _ = SAMPLERS[name]
    b64 = _random_batch(2048, seed=9)
    b64[2].clamp_(min=0.05)
    s64 = sample(*b64)
    s32 = sample(*(x.float() for x in b64))
    both = s64.valid & s32.valid
    assert (s64.valid != s32.valid).float().mean() < 1e-2
    assert torch.allclose(s32.wi[both].double(), s64.wi[both], atol=1e-4)
    assert torch.allclose(s32.weight[both].double(), s64.weight[both], atol=1e-4, rtol=1e-4)


def test_wo_below_surface_gives_zero():
    n, wo, r, f0, u1, u2 = _random_batch(512, seed=4)
    for sample in (sample_vndf, sample_ndf):
        s = sample(n, -wo, r, f0, u1, u2)
        assert not s.valid.any() and torch.all(s.weight == 0) and torch.all(s.pdf == 0)
        assert torch.isfinite(s.wi).all()


# ------------------------------------------------------------------ gradients


def test_eval_specular_gradcheck():
    n, wo, r, f0, u1, u2 = _random_batch(16, seed=6, max_theta_deg=70.0)
    r = (0.1 + 0.9 * torch.rand(16, generator=torch.Generator().manual_seed(1), dtype=F64)).requires_grad_()
    f0 = f0.clone().requires_grad_()
    wi = sample_vndf(n, wo, r.detach(), f0.detach(), u1, u2).wi
    keep = (wi * n).sum(-1) > 0.05
    n, wo, wi, r, f0 = n[keep], wo[keep], wi[keep], r.detach()[keep].requires_grad_(), f0.detach()[keep].requires_grad_()
    for smith in SMITH_MODELS:
        assert torch.autograd.gradcheck(lambda r_, f_: eval_specular(n, wo, wi, r_, f_, smith), (r, f0))


@pytest.mark.parametrize("name", SAMPLERS)
def test_sample_weight_gradcheck(name):
    sample, _ = SAMPLERS[name]
    n, wo, _, f0, u1, u2 = _random_batch(16, seed=8, max_theta_deg=60.0)
    r = 0.2 + 0.7 * torch.rand(16, generator=torch.Generator().manual_seed(2), dtype=F64)
    s = sample(n, wo, r, f0, u1, u2)
    keep = s.valid & ((s.wi * n).sum(-1) > 0.05)
    args = [x[keep] for x in (n, wo, u1, u2)]
    r, f0 = r[keep].requires_grad_(), f0[keep].requires_grad_()
    assert torch.autograd.gradcheck(
        lambda r_, f_: torch.cat([sample(args[0], args[1], r_, f_, args[2], args[3]).weight,
                                  sample(args[0], args[1], r_, f_, args[2], args[3]).wi], -1), (r, f0))


# ------------------------------------------------------------------ variance


def test_compare_sampler_variance_vndf_not_worse():
    res = compare_sampler_variance((0.1, 0.5, 1.0), (0.0, 60.0, 85.0), n=1 << 13)
    assert len(res["ratio"]) == 9
    for i in range(9):
        if res["angle_deg"][i] == 0.0:  # identical estimators at normal incidence
            assert res["ratio"][i] == pytest.approx(1.0, rel=0.05)
        else:
            assert res["var_vndf"][i] < res["var_ndf"][i]
    assert "ndf/vndf" in format_variance_table(res)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("name", SAMPLERS)
def test_cuda_matches_cpu(name):
    sample, pdf = SAMPLERS[name]
    batch = _random_batch(4096, seed=12)
    s_cpu = sample(*batch)
    s_gpu = sample(*(x.cuda() for x in batch))
    assert torch.equal(s_cpu.valid, s_gpu.valid.cpu())
    assert torch.allclose(s_cpu.wi, s_gpu.wi.cpu(), atol=1e-10)
    assert torch.allclose(s_cpu.weight, s_gpu.weight.cpu(), rtol=1e-9, atol=1e-12)
    n, wo, r = batch[0], batch[1], batch[2]
    assert torch.allclose(pdf(n, wo, s_cpu.wi, r), pdf(n.cuda(), wo.cuda(), s_gpu.wi, r.cuda()).cpu(), rtol=1e-9)


# ----------------------------------------------------------------- view-dependent diffuse (Disney, principled)

@pytest.mark.parametrize("roughness", [0.0, 0.1, 0.5, 1.0])
def test_disney_diffuse_factor_matches_mitsuba_principled_under_uniform_light(roughness):
    """The closed form of ``diffuse_view_factor`` ("disney", F0 >= 0.02) against Mitsuba's own ``principled`` at
    specular 0 (whose full evaluation is its diffuse lobe: tests/test_synth_lobes.py), base colour 1, integrated
    over a stratified cosine-weighted hemisphere of light directions: the radiance towards the viewer under
    uniform unit radiance, at viewing angles from the normal to 88 degrees."""
    mi = pytest.importorskip("mitsuba")
    from models.synth.mitsuba_scene import mitsuba
    mi = mitsuba()
    import drjit as dr

    bsdf = mi.load_dict({"type": "principled", "base_color": {"type": "rgb", "value": [1.0, 1.0, 1.0]},
                         "roughness": roughness, "metallic": 0.0, "specular": 0.0})
    k = 256
    u1, u2 = np.meshgrid((np.arange(k) + 0.5) / k, (np.arange(k) + 0.5) / k, indexing="ij")
    u1, u2 = u1.ravel(), u2.ravel()
    ci, si = np.sqrt(u1), np.sqrt(1 - u1)  # cosine-weighted: cos_i^2 uniform
    light = np.stack([si * np.cos(2 * np.pi * u2), si * np.sin(2 * np.pi * u2), ci])
    cosines = np.array([1.0, 0.8, 0.5, 0.3, 0.15, 0.07, 0.035])
    ours = diffuse_view_factor(torch.tensor(cosines, dtype=torch.float64),
                               torch.full((len(cosines),), roughness, dtype=torch.float64),
                               torch.full((len(cosines), 3), 0.04, dtype=torch.float64), "disney")[:, 0].numpy()
    for c, h in zip(cosines, ours):
        si_ = dr.zeros(mi.SurfaceInteraction3f, len(u1))
        si_.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        si_.wi = mi.Vector3f(np.full(len(u1), math.sqrt(1 - c * c), np.float32), np.zeros(len(u1), np.float32),
                             np.full(len(u1), c, np.float32))
        value = np.asarray(bsdf.eval(mi.BSDFContext(), si_, mi.Vector3f(*light.astype(np.float32))))[0]
        truth = float(np.mean(value * np.pi / ci))  # f cos_i / pdf, pdf = cos_i / pi
        assert abs(h - truth) <= 2e-3 * truth, (roughness, c, h, truth)


def test_disney_diffuse_factor_limits():
    """Lambert: no factor. F0 = 0 (no specular lobe: a Lambertian or a light): exactly 1 at every angle. F0 >= 0.02:
    darker towards grazing on a smooth surface (0.6 at 90 degrees), brighter on a rough one; between, blended."""
    c = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    r0, r1 = torch.zeros(11, dtype=torch.float64), torch.ones(11, dtype=torch.float64)
    f0 = lambda v: torch.full((11, 3), v, dtype=torch.float64)  # noqa: E731
    assert diffuse_view_factor(c, r0, f0(0.04), "lambert") is None
    assert torch.equal(diffuse_view_factor(c, r0, f0(0.0), "disney"), torch.ones(11, 1, dtype=torch.float64))
    smooth = diffuse_view_factor(c, r0, f0(0.04), "disney")[:, 0]
    assert torch.all(smooth[1:] >= smooth[:-1])  # monotone towards the normal
    assert smooth[0] == pytest.approx(41 / 84) and smooth[-1] == pytest.approx(41 / 42)
    rough = diffuse_view_factor(c, r1, f0(0.04), "disney")[:, 0]
    assert rough[0] > 1.4 and rough[-1] > 1.0
    half = diffuse_view_factor(c, r0, f0(0.01), "disney")[:, 0]  # w = 0.5
    assert torch.allclose(half, 1 + 0.5 * (smooth - 1))
    with pytest.raises(ValueError, match="diffuse_lobe='phong'"):
        diffuse_view_factor(c, r0, f0(0.04), "phong")
