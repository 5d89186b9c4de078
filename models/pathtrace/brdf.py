"""Cook-Torrance specular BRDF: GGX (Trowbridge-Reitz) NDF, Smith masking-shadowing,
Schlick Fresnel with RGB F0 (paper Sec. 3.1, "a subset of the Disney BRDF").

Conventions (shared with `sampling.py`):
- `n`: unit surface normal; `wo`: unit direction toward the viewer (minus the incoming
  camera ray); `wi`: unit reflected direction (toward the light); all world space.
- `h = normalize(wo + wi)` is the half vector (microfacet normal).
- `roughness` is perceptual, clamped to >= `MIN_ROUGHNESS` (0.01, as the reference),
  GGX `alpha = roughness^2`.
- Smith masking-shadowing `smith` is one of
    "height_correlated" (default): G2 = 1 / (1 + Lambda(wo) + Lambda(wi)), exact Smith G1;
    "separable": G2 = G1(wo) G1(wi), exact Smith G1;
    "schlick": the reference's Smith-Schlick G, G1 = c / (c (1 - k) + k), k = alpha / 2
      (Karis 2013's fit of Smith-GGX); G2 = G1(wo) G1(wi).
  Height-correlated is the default: it is the physically more accurate form (Heitz 2014)
  and, like separable, satisfies G2 <= G1(wo), so the VNDF sample weight is <= F.
- `eval_specular` returns the BRDF times the cosine, f_s(wo, wi) * (n . wi).

Everything is batched over leading dims, works in float32 and float64 and is
differentiable (no NaN gradients at the clamps: square roots and divisions take
clamped arguments, `torch.where` picks between finite branches).
"""

from __future__ import annotations

import math

import torch

MIN_ROUGHNESS = 0.01
SMITH_MODELS = ("height_correlated", "separable", "schlick")
DEFAULT_SMITH = "height_correlated"

# Guards: every sqrt / rsqrt / division takes an argument replaced (by `torch.where`, not
# `clamp`, so no gradient reaches the replaced entries) when it is at or below a floor.
# The floors keep values and gradients finite in float32 as well (1 / 1e-12^2 = 1e24).
_SQRT_FLOOR = 1e-30   # sqrt(x) := 0 for x <= floor
_NORM2_FLOOR = 1e-20  # normalize(v) := 0 for |v|^2 <= floor
_DEN_FLOOR = 1e-12    # denominators that vanish only at degenerate configurations


def positive(x: torch.Tensor, floor: float = _DEN_FLOOR) -> torch.Tensor:
    """x where x > floor, else floor (no gradient through the replaced entries)."""
    return torch.where(x > floor, x, torch.full_like(x, floor))


def check_smith(smith: str) -> None:
    if smith not in SMITH_MODELS:
        raise ValueError(f"smith={smith!r}: expected one of {SMITH_MODELS}")


def _check_vec3(name: str, v: torch.Tensor) -> None:
    if not isinstance(v, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(v).__name__}")
    if v.shape[-1:] != (3,):
        raise ValueError(f"{name} must have a trailing dimension of 3, got shape {tuple(v.shape)}")


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise dot product. [..., 3], [..., 3] -> [...]."""
    return (a * b).sum(-1)


def safe_normalize(v: torch.Tensor) -> torch.Tensor:
    """v / |v|; (near-)zero vectors map to zero with zero gradient. [..., 3] -> [..., 3]."""
    dd = dot(v, v)
    ok = dd > _NORM2_FLOOR
    inv = torch.rsqrt(torch.where(ok, dd, torch.ones_like(dd)))
    return torch.where(ok[..., None], v * inv[..., None], torch.zeros_like(v))


def safe_sqrt(x: torch.Tensor) -> torch.Tensor:
    """sqrt(x) for x > 1e-30, else 0; finite value and gradient everywhere."""
    ok = x > _SQRT_FLOOR
    return torch.where(ok, torch.sqrt(torch.where(ok, x, torch.ones_like(x))), torch.zeros_like(x))


def reflect(d: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Perfect-mirror reflection of direction `d` about the unit normal `n`:
    d - 2 (d . n) n. With d the camera ray direction (= -wo) this is the mirror
    direction 2 (wo . n) n - wo. [..., 3], [..., 3] -> [..., 3]."""
    return d - 2.0 * dot(d, n)[..., None] * n


def roughness_to_alpha(roughness: torch.Tensor) -> torch.Tensor:
    """Perceptual roughness -> GGX alpha = max(roughness, 0.01)^2. [...] -> [...]."""
    r = roughness.clamp_min(MIN_ROUGHNESS)
    return r * r


def ggx_d(n_dot_h: torch.Tensor, alpha: torch.Tensor,
          sin2_theta_h: torch.Tensor | None = None) -> torch.Tensor:
    """GGX / Trowbridge-Reitz normal distribution D(h) (1/sr; integral of D (n.h) = 1).

    D = alpha^2 / (pi (sin^2 + alpha^2 cos^2)^2) for n.h > 0, else 0.
    n_dot_h: [...]; alpha: [...] (> 0); sin2_theta_h: optional [...] = |n x h|^2, pass it
    when available: 1 - cos^2 cancels catastrophically near the mirror peak in float32.
    """
    c = n_dot_h.clamp(0.0, 1.0)
    if sin2_theta_h is None:
        sin2 = (1.0 - c) * (1.0 + c)
    else:
        sin2 = sin2_theta_h.clamp(0.0, 1.0)
    a2 = alpha * alpha
    t = sin2 + a2 * c * c
    t = positive(t, 1e-20)  # t >= alpha^2 >= 1e-8 unless h is degenerate (zero)
    d = a2 / (math.pi * t * t)
    return torch.where(n_dot_h > 0, d, torch.zeros_like(d))


def _smith_a(cos: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """a(c) = sqrt(c^2 + alpha^2 (1 - c^2)) with c clamped to [0, 1]: the Smith-GGX
    Lambda(c) = (a - c) / (2 c). [...] -> [...]."""
    c = cos.clamp(0.0, 1.0)
    return safe_sqrt(c * c + alpha * alpha * (1.0 - c) * (1.0 + c))


def smith_g1(n_dot_v: torch.Tensor, alpha: torch.Tensor, smith: str = DEFAULT_SMITH) -> torch.Tensor:
    """Smith masking G1(v) of GGX. [...] -> [...], 0 for n.v <= 0.

    "height_correlated" / "separable": exact G1 = 2c / (c + sqrt(alpha^2 + (1 - alpha^2) c^2));
    "schlick": c / (c (1 - k) + k), k = alpha / 2.
    """
    check_smith(smith)
    c = n_dot_v.clamp(0.0, 1.0)
    if smith == "schlick":
        k = 0.5 * alpha
        g = c / (c * (1.0 - k) + k)
    else:
        g = 2.0 * c / (c + _smith_a(c, alpha))  # a >= alpha >= 1e-4
    return torch.where(n_dot_v > 0, g, torch.zeros_like(g))


def smith_visibility(n_dot_o: torch.Tensor, n_dot_i: torch.Tensor, alpha: torch.Tensor,
                     smith: str = DEFAULT_SMITH) -> torch.Tensor:
    """V = G2 / (4 (n.wo) (n.wi)), written without dividing by the cosines, so it stays
    finite at grazing angles. Cosines are clamped to [0, 1]; the caller masks n.v <= 0.
    [...] -> [...].

    height_correlated: V = 0.5 / (c_i a_o + c_o a_i)
    separable:         V = 1 / ((c_o + a_o) (c_i + a_i))
    schlick:           V = 1 / (4 (c_o (1 - k) + k) (c_i (1 - k) + k)), k = alpha / 2
    """
    check_smith(smith)
    co = n_dot_o.clamp(0.0, 1.0)
    ci = n_dot_i.clamp(0.0, 1.0)
    if smith == "schlick":
        k = 0.5 * alpha
        return 0.25 / ((co * (1.0 - k) + k) * (ci * (1.0 - k) + k))
    ao, ai = _smith_a(co, alpha), _smith_a(ci, alpha)
    if smith == "height_correlated":
        return 0.5 / positive(ci * ao + co * ai)  # 0 only if c_o = c_i = 0 (masked)
    return 1.0 / ((co + ao) * (ci + ai))


def smith_g(n_dot_o: torch.Tensor, n_dot_i: torch.Tensor, alpha: torch.Tensor,
            smith: str = DEFAULT_SMITH) -> torch.Tensor:
    """Smith masking-shadowing G2(wo, wi) in [0, 1]; 0 if either cosine <= 0. [...] -> [...].

    height_correlated: 1 / (1 + Lambda(wo) + Lambda(wi)) = 2 c_o c_i / (c_i a_o + c_o a_i);
    separable / schlick: G1(wo) G1(wi).
    """
    g = 4.0 * n_dot_o.clamp(0.0, 1.0) * n_dot_i.clamp(0.0, 1.0) * smith_visibility(n_dot_o, n_dot_i, alpha, smith)
    return torch.where((n_dot_o > 0) & (n_dot_i > 0), g, torch.zeros_like(g))


FRESNEL_MODES = ("schlick_f90", "schlick", "dielectric")
DEFAULT_FRESNEL = "schlick_f90"
F90_SCALE = 50.0  # F90 = min(1, 50 mean(F0)): 1 from F0 = 0.02 up (every real dielectric and metal)
# "dielectric": the exact Fresnel of a dielectric (eta from F0) up to mean F0 = 0.08 (eta 1.79: Mitsuba's principled
# at specular 1, past every common dielectric), Schlick's (schlick_f90) from 0.2 (metals), linearly blended between
DIELECTRIC_F0 = (0.08, 0.2)


def fresnel_f90(f0: torch.Tensor, mode: str = DEFAULT_FRESNEL) -> torch.Tensor | None:
    """Grazing reflectance F90 of the Schlick Fresnel, [..., 1], or None for 1 (``mode``):

    "schlick": F90 = 1, the paper's form. A surface whose F0 is 0 (no specular lobe: the capture contract's
      matte materials, Mitsuba's principled at specular = 0, eta = 1) still reflects (1 - cos)^5 of what it
      sees, up to all of it at grazing angles.
    "schlick_f90" (default): F90 = min(1, 50 mean(F0)) (Schlick's F90 with Schueler's "specular occlusion"
      bound, as Filament and Unreal): the same as "schlick" from F0 = 0.02 up, and a F0 = 0 surface reflects
      nothing at any angle, as the ground truth (no real material has F0 < 0.02)."""
    if mode == "schlick":
        return None
    if mode not in ("schlick_f90", "dielectric"):
        raise ValueError(f"fresnel={mode!r}: expected one of {FRESNEL_MODES}")
    return (F90_SCALE * f0.mean(-1, keepdim=True)).clamp(0.0, 1.0)


def dielectric_weight(f0: torch.Tensor, mode: str = DEFAULT_FRESNEL) -> torch.Tensor | None:
    """[..., 1] the share of the exact dielectric Fresnel (``fresnel_dielectric``) in ``fresnel``'s F, or None
    (Schlick alone) unless ``mode`` is "dielectric": 1 up to mean F0 = 0.08, 0 from 0.2 (``DIELECTRIC_F0``).
    Schlick's curve is a fit to metals; for a dielectric it is 20 % low at 60 degrees (F0 0.04: 0.070 against
    0.089) and high past 75, so a glossy floor's highlights, F0 and roughness right, came out 15-25 % dark against
    Mitsuba's principled (whose dielectric lobe uses the exact Fresnel)."""
    if mode not in FRESNEL_MODES:
        raise ValueError(f"fresnel={mode!r}: expected one of {FRESNEL_MODES}")
    if mode != "dielectric":
        return None
    lo, hi = DIELECTRIC_F0
    return ((hi - f0.mean(-1, keepdim=True)) / (hi - lo)).clamp(0.0, 1.0)


DIFFUSE_LOBES = ("lambert", "disney")


def diffuse_view_factor(cos_o: torch.Tensor, roughness: torch.Tensor, f0: torch.Tensor,
                        lobe: str = "lambert") -> torch.Tensor | None:
    """[..., 1] how the diffuse radiance a surface sends towards the viewer depends on the viewing angle, or None
    (``lobe`` "lambert": it does not, the paper's). cos_o: [...] (n . wo); roughness: [...]; f0: [..., 3].

    "disney": the Disney diffuse of Mitsuba's ``principled`` (the capture's diffuse layer for those materials,
    models/synth/lobes.py), f = (1 - F_i / 2)(1 - F_o / 2) + R_r (F_o + F_i + F_o F_i (R_r - 1)), R_r = 2 r
    cos_d^2, F_x = (1 - cos_x)^5, averaged over a cosine-weighted hemisphere of incident light (uniform
    radiance), in closed form: with c = cos_o, cos_d^2 = (1 + wi . wo) / 2 and the moments E[F_i] = 1/21,
    E[F_i c_i] = 1/84, E[F_i c_i^2] = 1/252,

        h = 41/42 (1 - F_o / 2) + r [F_o (1 + 2c/3) + (1 - F_o)(1/21 + c/84)]
            + r^2 F_o [1/21 + c/42 + c^2/252 + (1 - c^2) 11/504].

    A smooth surface sends 0.6-0.75x as much towards grazing views as towards its normal (r 0 -> 0.1 at
    cos_o 0.05-0.1), a rough one up to 1.46x (r 1). The factor is 1 + w (h - 1) with w = min(1, 50 mean F0), the
    ``schlick_f90`` weight: a surface with no specular lobe (F0 = 0: Mitsuba's Lambertian ``diffuse``, lights)
    stays Lambertian. ``tests/test_brdf.py::test_disney_diffuse_factor_*`` integrates the synth lobe against it."""
    if lobe == "lambert":
        return None
    if lobe != "disney":
        raise ValueError(f"diffuse_lobe={lobe!r}: expected one of {DIFFUSE_LOBES}")
    c = cos_o.clamp(0.0, 1.0)
    m = 1.0 - c
    fo = (m * m) * (m * m) * m
    r = roughness.clamp(0.0, 1.0)
    h = ((41.0 / 42.0) * (1.0 - 0.5 * fo)
         + r * (fo * (1.0 + 2.0 * c / 3.0) + (1.0 - fo) * (1.0 / 21.0 + c / 84.0))
         + r * r * fo * (1.0 / 21.0 + c / 42.0 + c * c / 252.0 + (1.0 - c * c) * (11.0 / 504.0)))
    w = (F90_SCALE * f0.mean(-1)).clamp(0.0, 1.0)
    return (1.0 + w * (h - 1.0))[..., None]


def fresnel_dielectric(f0: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
    """Unpolarised Fresnel reflectance of a smooth dielectric seen from outside, eta = (1 + sqrt F0) / (1 - sqrt
    F0) per channel (F0 clamped below 0.99): F = 1/2 ((g - c) / (g + c))^2 (1 + ((c (g + c) - 1) / (c (g - c) +
    1))^2), g = sqrt(eta^2 - 1 + c^2), c = cos clamped to [0, 1]. F(c = 1) = F0, F(c = 0) = 1, and F0 = 0 (eta =
    1) gives 0 at every angle. f0: [..., 3]; cos: [...] -> [..., 3]."""
    c = cos.clamp(0.0, 1.0)[..., None]
    s = f0.clamp(1e-12, 0.99).sqrt()
    eta = (1 + s) / (1 - s)
    g = (eta * eta - 1 + c * c).clamp_min(0.0).sqrt()
    a = (g - c) / (g + c).clamp_min(1e-12)
    b = (c * (g + c) - 1) / (c * (g - c) + 1)
    return torch.where(f0 > 0, 0.5 * a * a * (1 + b * b), torch.zeros_like(a))


def fresnel(f0: torch.Tensor, cos: torch.Tensor, f90: torch.Tensor | None = None,
            dielectric: torch.Tensor | None = None) -> torch.Tensor:
    """F of the path tracer: Schlick's with grazing reflectance ``f90`` (``fresnel_schlick``), blended with the
    exact dielectric Fresnel by ``dielectric`` ([..., 1], ``dielectric_weight``; None: Schlick alone)."""
    schlick = fresnel_schlick(f0, cos, f90)
    if dielectric is None:
        return schlick
    return dielectric * fresnel_dielectric(f0, cos) + (1 - dielectric) * schlick


def fresnel_schlick(f0: torch.Tensor, cos: torch.Tensor, f90: torch.Tensor | None = None) -> torch.Tensor:
    """Schlick Fresnel F = F0 + (F90 - F0) (1 - cos)^5, cos = wo . h clamped to [0, 1], F90 = 1 when None.
    f0: [..., 3]; cos: [...]; f90: [..., 1] or None -> [..., 3]. F(cos = 1) = F0 exactly."""
    m = 1.0 - cos.clamp(0.0, 1.0)
    m2 = m * m
    w = (m2 * m2 * m)[..., None]
    return f0 + ((1.0 if f90 is None else f90) - f0) * w


def eval_specular(n: torch.Tensor, wo: torch.Tensor, wi: torch.Tensor, roughness: torch.Tensor,
                  f0: torch.Tensor, smith: str = DEFAULT_SMITH, f90: torch.Tensor | None = None,
                  dielectric: torch.Tensor | None = None) -> torch.Tensor:
    """Cook-Torrance specular BRDF times cosine: f_s(wo, wi) (n . wi)
    = F(wo . h) D(h) G2(wo, wi) / (4 (n . wo)) = F D V (n . wi).

    n, wo, wi: [..., 3] unit; roughness: [...]; f0: [..., 3] -> [..., 3].
    Zero where n.wo <= 0, n.wi <= 0 or n.h <= 0 (wo below the surface included).
    """
    for name, v in (("n", n), ("wo", wo), ("wi", wi), ("f0", f0)):
        _check_vec3(name, v)
    check_smith(smith)
    alpha = roughness_to_alpha(roughness)
    h = safe_normalize(wo + wi)
    co, ci = dot(n, wo), dot(n, wi)
    nh = dot(n, h)
    sin2 = dot(torch.linalg.cross(n, h), torch.linalg.cross(n, h))
    d = ggx_d(nh, alpha, sin2)
    v = smith_visibility(co, ci, alpha, smith)
    f = fresnel(f0, dot(wo, h), f90, dielectric)
    val = f * (d * v * ci.clamp(0.0, 1.0))[..., None]
    valid = (co > 0) & (ci > 0) & (nh > 0)
    return torch.where(valid[..., None], val, torch.zeros_like(val))
