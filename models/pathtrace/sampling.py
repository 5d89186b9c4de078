"""Importance sampling of the specular reflection direction (GGX Cook-Torrance).

Two samplers, same interface and conventions as `brdf.py` (wo toward the viewer, wi the
sampled reflected direction, all unit world-space vectors):

- `sample_vndf` (default, preferred): visible-normal sampling of GGX (Heitz 2018,
  "Sampling the GGX Distribution of Visible Normals"). pdf(wi) = D_wo(h) / (4 wo.h)
  = D(h) G1(wo) / (4 n.wo) = D(h) / (2 (n.wo + a_o)); weight = F G2 / G1(wo).
- `sample_ndf`: the reference's half-vector sampling, h ~ D(h) (n.h).
  pdf(wi) = D(h) (n.h) / (4 |wo.h|); weight = F G2 (wo.h) / ((n.h) (n.wo)).

Both weights are `eval_specular(wi) / pdf(wi)` written with D cancelled and without a
1/(n.wo) factor (via `smith_visibility`), so they stay finite at grazing view angles and
at roughness 0.01 in float32. A sample is invalid (weight 0) when wo is below the
surface, the sampled wi is below the surface, or (NDF only) the sampled microfacet faces
away from wo. The pdf is that of the sampling routine over the whole sphere of wi (it
integrates to 1, the mass of invalid samples included).

`compare_sampler_variance` measures the variance of the single-sample directional-albedo
estimator (F0 = 1) for both samplers; `python -m models.pathtrace.sampling` prints it.
"""

from __future__ import annotations

import argparse
import math
from typing import NamedTuple

import torch

from models.pathtrace.brdf import (
    DEFAULT_SMITH,
    _check_vec3,
    _smith_a,
    check_smith,
    dot,
    fresnel,
    ggx_d,
    positive,
    roughness_to_alpha,
    safe_normalize,
    safe_sqrt,
    smith_visibility,
)


class SpecularSample(NamedTuple):
    wi: torch.Tensor      # [..., 3] sampled reflected direction (unit, world space)
    pdf: torch.Tensor     # [...] solid-angle density of the sampler at wi (0 if wo is below)
    weight: torch.Tensor  # [..., 3] f_s cos / pdf for valid samples, 0 otherwise
    valid: torch.Tensor   # [...] bool: wo and wi above the surface, microfacet visible


def tangent_frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Orthonormal tangents (t, b) with t x b = n (Duff et al. 2017, branchless).
    n: [..., 3] unit -> ([..., 3], [..., 3])."""
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    t = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    bt = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return t, bt


def _to_local(v, t, b, n):
    return torch.stack([dot(v, t), dot(v, b), dot(v, n)], dim=-1)


def _to_world(v, t, b, n):
    return v[..., 0:1] * t + v[..., 1:2] * b + v[..., 2:3] * n


def _check_inputs(n, wo, roughness, f0, u1, u2, smith):
    for name, v in (("n", n), ("wo", wo), ("f0", f0)):
        _check_vec3(name, v)
    for name, v in (("roughness", roughness), ("u1", u1), ("u2", u2)):
        if not isinstance(v, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(v).__name__}")
        if v.shape != n.shape[:-1]:
            raise ValueError(f"{name} has shape {tuple(v.shape)}, expected {tuple(n.shape[:-1])}")
    check_smith(smith)


def _finish(n, t, b, wo_l, h_l, f0, pdf, factor, extra_valid, f90=None, dielectric=None):
    """Shared tail: reflect wo about h in the local frame, weight = F(wo.h) * factor."""
    wo_h = dot(wo_l, h_l)
    wi_l = 2.0 * wo_h[..., None] * h_l - wo_l
    wi = safe_normalize(_to_world(wi_l, t, b, n))
    valid = (wo_l[..., 2] > 0) & (wi_l[..., 2] > 0) & extra_valid
    f = fresnel(f0, wo_h, f90, dielectric)
    w = f * factor(wi_l[..., 2].clamp(0.0, 1.0))[..., None]
    weight = torch.where(valid[..., None], w, torch.zeros_like(w))
    pdf = torch.where(wo_l[..., 2] > 0, pdf, torch.zeros_like(pdf))
    return SpecularSample(wi, pdf, weight, valid)


def sample_vndf(n: torch.Tensor, wo: torch.Tensor, roughness: torch.Tensor, f0: torch.Tensor,
                u1: torch.Tensor, u2: torch.Tensor, smith: str = DEFAULT_SMITH,
                f90: torch.Tensor | None = None, dielectric: torch.Tensor | None = None) -> SpecularSample:
    """Visible-normal (VNDF) sampling of GGX, Heitz 2018.

    n, wo: [R, 3] unit; roughness: [R]; f0: [R, 3]; u1, u2: [R] uniform in [0, 1].
    Leading batch dims other than R are allowed. Returns `SpecularSample`:
    pdf = D(h) / (2 (c_o + a_o)), weight = F(wo.h) G2(wo, wi) / G1(wo)
    (height-correlated: F c_i (c_o + a_o) / (c_i a_o + c_o a_i); separable: F G1(wi);
    the visible-normal density always uses the exact Smith-GGX G1(wo)).
    """
    _check_inputs(n, wo, roughness, f0, u1, u2, smith)
    alpha = roughness_to_alpha(roughness)
    t, b = tangent_frame(n)
    wo_l = _to_local(wo, t, b, n)
    co = wo_l[..., 2]
    # Stretch to the alpha = 1 configuration (wo below the surface: computed as grazing,
    # then masked).
    vh = safe_normalize(torch.stack([alpha * wo_l[..., 0], alpha * wo_l[..., 1],
                                     co.clamp_min(0.0)], dim=-1))
    lensq = vh[..., 0] ** 2 + vh[..., 1] ** 2
    side = lensq > 1e-20  # else normal incidence: any tangent will do
    inv_len = torch.rsqrt(torch.where(side, lensq, torch.ones_like(lensq)))
    zero = torch.zeros_like(lensq)
    t1 = torch.where(side[..., None],
                     torch.stack([-vh[..., 1] * inv_len, vh[..., 0] * inv_len, zero], dim=-1),
                     torch.stack([torch.ones_like(lensq), zero, zero], dim=-1))
    t2 = torch.linalg.cross(vh, t1)
    # Uniform disk point, warped onto the projected visible hemisphere.
    r = torch.sqrt(u1.clamp(0.0, 1.0))
    phi = 2.0 * math.pi * u2
    p1, p2 = r * torch.cos(phi), r * torch.sin(phi)
    s = 0.5 * (1.0 + vh[..., 2])
    p2 = (1.0 - s) * safe_sqrt(1.0 - p1 * p1) + s * p2
    nh = (p1[..., None] * t1 + p2[..., None] * t2
          + safe_sqrt(1.0 - p1 * p1 - p2 * p2)[..., None] * vh)
    # Unstretch.
    h_l = safe_normalize(torch.stack([alpha * nh[..., 0], alpha * nh[..., 1],
                                      nh[..., 2].clamp_min(0.0)], dim=-1))
    ao = _smith_a(co, alpha)
    coc = co.clamp(0.0, 1.0)
    pdf = ggx_d(h_l[..., 2], alpha, h_l[..., 0] ** 2 + h_l[..., 1] ** 2) / (2.0 * (coc + ao))

    def factor(ci):  # G2 / G1(wo) = 4 V c_o c_i (c_o + a_o) / (2 c_o), <= 1 for all three
        # Smith forms (Schlick G1 <= exact G1); the clamp only removes float32 rounding.
        return (2.0 * smith_visibility(coc, ci, alpha, smith) * ci * (coc + ao)).clamp(max=1.0)

    return _finish(n, t, b, wo_l, h_l, f0, pdf, factor, h_l[..., 2] > 0, f90, dielectric)


def sample_ndf(n: torch.Tensor, wo: torch.Tensor, roughness: torch.Tensor, f0: torch.Tensor,
               u1: torch.Tensor, u2: torch.Tensor, smith: str = DEFAULT_SMITH,
               f90: torch.Tensor | None = None, dielectric: torch.Tensor | None = None) -> SpecularSample:
    """Half-vector (NDF) sampling of GGX, h ~ D(h) (n.h), as the reference tracer.

    Shapes as `sample_vndf`. tan^2(theta_h) = alpha^2 u1 / (1 - u1), phi_h = 2 pi u2.
    pdf = D(h) (n.h) / (4 |wo.h|), weight = F(wo.h) G2 (wo.h) / ((n.h) (n.wo)),
    invalid (weight 0) also when wo.h <= 0 (back-facing microfacet).
    """
    _check_inputs(n, wo, roughness, f0, u1, u2, smith)
    alpha = roughness_to_alpha(roughness)
    t, b = tangent_frame(n)
    wo_l = _to_local(wo, t, b, n)
    co = wo_l[..., 2].clamp(0.0, 1.0)
    u = u1.clamp(0.0, 1.0)
    a2 = alpha * alpha
    den = (1.0 - u) + a2 * u
    cos2 = (1.0 - u) / den
    sin2 = a2 * u / den
    cos_h, sin_h = safe_sqrt(cos2), safe_sqrt(sin2)
    phi = 2.0 * math.pi * u2
    h_l = torch.stack([sin_h * torch.cos(phi), sin_h * torch.sin(phi), cos_h], dim=-1)
    wo_h = dot(wo_l, h_l)
    pdf = ggx_d(cos_h, alpha, sin2) * cos_h / (4.0 * positive(wo_h.abs()))

    def factor(ci):  # 4 V c_i (wo.h) / (n.h)
        return 4.0 * smith_visibility(co, ci, alpha, smith) * ci * wo_h.clamp_min(0.0) / positive(cos_h)

    return _finish(n, t, b, wo_l, h_l, f0, pdf, factor, (wo_h > 0) & (cos2 > 0), f90, dielectric)


def sample_specular(n, wo, roughness, f0, u1, u2, method: str = "vndf",
                    smith: str = DEFAULT_SMITH, f90: torch.Tensor | None = None,
                    dielectric: torch.Tensor | None = None) -> SpecularSample:
    """Dispatch on `method` in {"vndf", "ndf"}; f90: the Schlick grazing reflectance ([..., 1], None = 1);
    dielectric: the exact dielectric Fresnel's share ([..., 1], ``brdf.dielectric_weight``; None = Schlick)."""
    if method == "vndf":
        return sample_vndf(n, wo, roughness, f0, u1, u2, smith, f90, dielectric)
    if method == "ndf":
        return sample_ndf(n, wo, roughness, f0, u1, u2, smith, f90, dielectric)
    raise ValueError(f"method={method!r}: expected 'vndf' or 'ndf'")


def _half_vector_terms(n, wo, wi, roughness):
    """Upper-hemisphere half vector h = +-normalize(wo + wi) and GGX D(h).
    Returns alpha, c_o, wo.h (signed, for the sign-corrected h), n.h, D."""
    alpha = roughness_to_alpha(roughness)
    s = wo + wi
    up = dot(n, s) >= 0
    h = safe_normalize(torch.where(up[..., None], s, -s))
    nh = dot(n, h)
    nxh = torch.linalg.cross(n, h)
    d = ggx_d(nh, alpha, dot(nxh, nxh))
    # wo . h = |wo + wi| / 2 for unit wo, wi: exact near wi = -wo where the dot product
    # of the normalised sum cancels catastrophically.
    half = 0.5 * safe_sqrt(dot(s, s))
    wo_h = torch.where(up, half, -half)
    return alpha, dot(n, wo), wo_h, nh, d


def pdf_vndf(n: torch.Tensor, wo: torch.Tensor, wi: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """Solid-angle density of `sample_vndf` at wi over the whole sphere (wi below the
    surface included). n, wo, wi: [..., 3]; roughness: [...] -> [...]."""
    alpha, co, wo_h, nh, d = _half_vector_terms(n, wo, wi, roughness)
    coc = co.clamp(0.0, 1.0)
    p = d / (2.0 * (coc + _smith_a(coc, alpha)))
    return torch.where((co > 0) & (wo_h > 0) & (nh > 0), p, torch.zeros_like(p))


def pdf_ndf(n: torch.Tensor, wo: torch.Tensor, wi: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """Solid-angle density of `sample_ndf` at wi over the whole sphere (the map h -> wi is
    one-to-one; h is the upper-hemisphere half vector, back-facing ones included).
    n, wo, wi: [..., 3]; roughness: [...] -> [...]."""
    alpha, co, wo_h, nh, d = _half_vector_terms(n, wo, wi, roughness)
    p = d * nh / (4.0 * positive(wo_h.abs()))
    return torch.where((co > 0) & (nh > 0), p, torch.zeros_like(p))


# ----------------------------------------------------------------------------------------
# Variance measurement
# ----------------------------------------------------------------------------------------

DEFAULT_ROUGHNESS = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0)
DEFAULT_ANGLES_DEG = (0.0, 30.0, 60.0, 75.0, 85.0, 89.0)


def compare_sampler_variance(roughness_values=DEFAULT_ROUGHNESS, angles=DEFAULT_ANGLES_DEG,
                             n: int = 1 << 16, seed: int = 0, smith: str = DEFAULT_SMITH,
                             dtype: torch.dtype = torch.float64) -> dict:
    """Variance of the one-sample estimator of the directional albedo (F0 = 1) with VNDF
    and NDF sampling, per (roughness, view angle) setting (same uniforms for both).

    angles: view angles theta_o between n and wo, degrees. Returns columns (lists, one
    entry per setting, roughness-major): "roughness", "angle_deg", "albedo_vndf",
    "albedo_ndf", "var_vndf", "var_ndf", "ratio" (= var_ndf / var_vndf; inf when
    var_vndf == 0), "invalid_vndf", "invalid_ndf" (fraction of zero-weight samples),
    plus scalars "n", "seed", "smith".
    """
    if n < 2:
        raise ValueError(f"n={n}: need at least 2 samples")
    gen = torch.Generator().manual_seed(seed)
    u1 = torch.rand(n, generator=gen, dtype=dtype)
    u2 = torch.rand(n, generator=gen, dtype=dtype)
    nrm = torch.tensor([0.0, 0.0, 1.0], dtype=dtype).expand(n, 3)
    f0 = torch.ones(n, 3, dtype=dtype)
    cols = {k: [] for k in ("roughness", "angle_deg", "albedo_vndf", "albedo_ndf", "var_vndf",
                            "var_ndf", "ratio", "invalid_vndf", "invalid_ndf")}
    for rough in roughness_values:
        r = torch.full((n,), float(rough), dtype=dtype)
        for ang in angles:
            th = math.radians(float(ang))
            wo = torch.tensor([math.sin(th), 0.0, math.cos(th)], dtype=dtype).expand(n, 3)
            stats = {}
            for name, fn in (("vndf", sample_vndf), ("ndf", sample_ndf)):
                s = fn(nrm, wo, r, f0, u1, u2, smith)
                w = s.weight[:, 0]
                stats[name] = (w.mean().item(), w.var().item(), 1.0 - s.valid.double().mean().item())
            cols["roughness"].append(float(rough))
            cols["angle_deg"].append(float(ang))
            for name in ("vndf", "ndf"):
                cols[f"albedo_{name}"].append(stats[name][0])
                cols[f"var_{name}"].append(stats[name][1])
                cols[f"invalid_{name}"].append(stats[name][2])
            vv, vn = stats["vndf"][1], stats["ndf"][1]
            cols["ratio"].append(vn / vv if vv > 0 else math.inf)
    cols.update(n=n, seed=seed, smith=smith)
    return cols


def format_variance_table(result: dict) -> str:
    """Plain-text table of a `compare_sampler_variance` result."""
    head = (f"{'rough':>6} {'theta_o':>7} {'E_vndf':>8} {'E_ndf':>8} {'var_vndf':>10} "
            f"{'var_ndf':>10} {'ndf/vndf':>9} {'inv_vndf':>8} {'inv_ndf':>8}")
    lines = [f"directional albedo (F0 = 1), one-sample estimator variance, n = {result['n']}, "
             f"smith = {result['smith']}", head, "-" * len(head)]
    for i in range(len(result["roughness"])):
        lines.append(
            f"{result['roughness'][i]:6.2f} {result['angle_deg'][i]:7.1f} "
            f"{result['albedo_vndf'][i]:8.4f} {result['albedo_ndf'][i]:8.4f} "
            f"{result['var_vndf'][i]:10.3e} {result['var_ndf'][i]:10.3e} {result['ratio'][i]:9.3g} "
            f"{result['invalid_vndf'][i]:8.3f} {result['invalid_ndf'][i]:8.3f}")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description="VNDF vs NDF sampling variance (directional albedo, F0 = 1)")
    p.add_argument("--n", type=int, default=1 << 16, help="samples per setting")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--smith", default=DEFAULT_SMITH, choices=("height_correlated", "separable", "schlick"))
    args = p.parse_args(argv)
    print(format_variance_table(compare_sampler_variance(n=args.n, seed=args.seed, smith=args.smith)))


if __name__ == "__main__":
    main()
