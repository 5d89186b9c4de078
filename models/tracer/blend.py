"""Shared end of every forward variant: the tail rule and the per-ray output writes."""

from __future__ import annotations

import warp as wp

from models.tracer.structs import RayOutputs


@wp.func
def write_outputs(ray: int, n_acc: int, blended: int, trans: float, c_diffuse: wp.vec3, c_depth: float,
                  c_normal: wp.vec3, c_rough: float, c_f0: wp.vec3, outs: RayOutputs):
    """Apply the tail rule (truncated: divide by 1 - T_end) and store."""
    scale = float(1.0)
    if blended < n_acc:
        scale = 1.0 / (1.0 - trans)
    outs.diffuse[ray] = scale * c_diffuse
    outs.depth[ray] = scale * c_depth
    outs.normal[ray] = scale * c_normal
    outs.roughness[ray] = scale * c_rough
    outs.f0[ray] = scale * c_f0
    outs.transmittance[ray] = trans
    outs.hit_count[ray] = n_acc
    outs.blended[ray] = blended
    outs.needed[ray] = 0
