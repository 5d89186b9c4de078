"""The diffuse lobe of Mitsuba 3's ``principled`` BSDF, recomputed in Dr.Jit.

Mitsuba's ``principled`` ignores lobe selection in ``BSDFContext``, so the split
integrator evaluates the diffuse lobe itself. This is the Disney diffuse +
retro-reflection term exactly as Mitsuba 3.9's ``principled`` evaluates it for
the features the scene spec exposes (no flatness, sheen, spec_trans, clearcoat):

    f_d * |cos_o| = (1 - metallic) * |cos_o| * base_color / pi * (f_diff + f_retro)
    f_diff  = (1 - Fi / 2) (1 - Fo / 2),   Fx = (1 - |cos_x|)^5 (Schlick weight)
    f_retro = Rr (Fo + Fi + Fo Fi (Rr - 1)), Rr = 2 roughness cos_d^2, cos_d = <wh, wo>

active only for reflection on the front side (cos_i > 0, cos_o > 0), as Mitsuba.
``tests/test_synth_lobes.py`` checks it against Mitsuba's own evaluation of a
specular = 0 principled surface (whose specular lobe is identically zero).
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
