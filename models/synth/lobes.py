"""The diffuse and specular lobes of Mitsuba 3's ``principled`` BSDF, recomputed in Dr.Jit.

Mitsuba's ``principled`` ignores lobe selection in ``BSDFContext``, so the split
integrator evaluates each lobe itself, as Mitsuba 3.9's ``principled`` does for the
features the scene spec exposes (no flatness, sheen, spec_tint, spec_trans, clearcoat,
anisotropy). Diffuse (Disney diffuse + retro-reflection):

    f_d * |cos_o| = (1 - metallic) * |cos_o| * base_color / pi * (f_diff + f_retro)
    f_diff  = (1 - Fi / 2) (1 - Fo / 2),   Fx = (1 - |cos_x|)^5 (Schlick weight)
    f_retro = Rr (Fo + Fi + Fo Fi (Rr - 1)), Rr = 2 roughness cos_d^2, cos_d = <wh, wo>

Specular (GGX, alpha = max(0.001, roughness^2), Smith G, Mitsuba's MicrofacetDistribution):

    f_s * |cos_o| = F D G / (4 |cos_i|),  wh = normalize(wi + wo)
    F = (1 - metallic) F_dielectric(<wi, wh>, eta) + metallic Schlick(base_color, <wi, wh>)
    eta = 2 / (1 - sqrt(0.08 specular)) - 1          (so F0 of the dielectric part = 0.08 specular)

Both are active only for reflection on the front side (cos_i > 0, cos_o > 0), as Mitsuba.
``tests/test_synth_lobes.py`` checks diffuse + specular against Mitsuba's full evaluation
(relative error < 1e-5; ~5e-7 seen) and the diffuse lobe alone against a specular = 0
surface, whose Mitsuba specular lobe is identically zero.
"""

from __future__ import annotations

from .mitsuba_scene import mitsuba


def _schlick_weight(dr, c):
    m = dr.clip(1.0 - c, 0.0, 1.0)
    return dr.square(dr.square(m)) * m


def principled_diffuse_eval(wi, wo, base_color, roughness, metallic, active):
    """BSDF x |cos_o| of the diffuse lobe; wi, wo local (shading frame). -> mi.Color3f"""
    mi = mitsuba()
    import drjit as dr

    cos_i, cos_o = mi.Frame3f.cos_theta(wi), mi.Frame3f.cos_theta(wo)
    active = active & (cos_i > 0.0) & (cos_o > 0.0) & (metallic < 1.0)
    wh = dr.normalize(wi + wo)
    wh = dr.mulsign(wh, mi.Frame3f.cos_theta(wh))
    fo, fi = _schlick_weight(dr, dr.abs(cos_o)), _schlick_weight(dr, dr.abs(cos_i))
    f_diff = (1.0 - 0.5 * fi) * (1.0 - 0.5 * fo)
    cos_d = dr.dot(wh, wo)
    rr = 2.0 * roughness * dr.square(cos_d)
    f_retro = rr * (fo + fi + fo * fi * (rr - 1.0))
    value = (1.0 - metallic) * dr.abs(cos_o) * base_color * dr.inv_pi * (f_diff + f_retro)
    return dr.select(active, value, mi.Color3f(0.0))


def principled_specular_eval(wi, wo, base_color, roughness, metallic, specular, active):
    """BSDF x |cos_o| of the specular (GGX) lobe; wi, wo local (shading frame). -> mi.Color3f"""
    mi = mitsuba()
    import drjit as dr

    cos_i, cos_o = mi.Frame3f.cos_theta(wi), mi.Frame3f.cos_theta(wo)
    eta = 2.0 / (1.0 - dr.sqrt(0.08 * specular)) - 1.0
    wh = dr.normalize(wi + wo)
    wh = dr.mulsign(wh, mi.Frame3f.cos_theta(wh))
    cos_ih = dr.dot(wi, wh)
    f_dielectric = mi.fresnel(cos_ih, eta)[0]
    f_metal = dr.lerp(_schlick_weight(dr, dr.abs(cos_ih)), 1.0, base_color)
    fresnel = (1.0 - metallic) * f_dielectric + metallic * f_metal
    alpha = dr.maximum(0.001, dr.square(roughness))
    dist = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, alpha)
    value = fresnel * dist.eval(wh) * dist.G(wi, wo, wh) / (4.0 * dr.abs(cos_i))
    active = (active & (cos_i > 0.0) & (cos_o > 0.0) & (cos_ih > 0.0) & (dr.dot(wo, wh) > 0.0)
              & (f_dielectric > 0.0))  # as Mitsuba: no specular lobe at all when eta = 1 (specular = 0)
    return dr.select(active, value, mi.Color3f(0.0))
