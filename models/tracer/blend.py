"""Front-to-back compositing shared by every forward variant: the per-ray state, the per-hit step, and the
tail rule with the per-ray output writes."""

from __future__ import annotations

import warp as wp

from models.tracer import output
from models.tracer.structs import GaussianData, RayOutputs, Replay

FRONT_TRANSMITTANCE = wp.constant(output.FRONT_TRANSMITTANCE)  # TraceOutput.front_depth


@wp.struct
class Blend:
    """One ray's compositing state: sums of w f over the blended hits (w = T alpha), T, and their count.
    A value in Warp (a wp.func gets a copy): the step returns the updated state."""

    trans: float        # transmittance in front of the next hit
    diffuse: wp.vec3
    depth: float
    normal: wp.vec3
    roughness: float
    f0: wp.vec3
    front_depth: float  # sum of w t over the hits blended while T >= FRONT_TRANSMITTANCE (the surface's front)
    front_weight: float  # sum of their w
    blended: int        # hits blended (= the sorted replay prefix)


@wp.func
def blend_start() -> Blend:
    """Nothing blended: T = 1, zero sums."""
    acc = Blend()
    acc.trans = 1.0
    return acc


@wp.func
def blend_slot(acc: Blend, g: GaussianData, rep: Replay, ray: int, slot: int) -> Blend:
    """Composite the hit in replay slot ``slot`` behind the blended ones; stores its incoming T for the backward."""
    gid = rep.ids[ray, slot]
    a = rep.alpha[ray, slot]
    w = acc.trans * a
    acc.diffuse += w * g.diffuse[gid]
    acc.normal += w * g.normal[gid]
    acc.f0 += w * g.f0[gid]
    acc.roughness += w * g.roughness[gid]
    acc.depth += w * rep.t[ray, slot]
    if acc.trans >= FRONT_TRANSMITTANCE:
        acc.front_depth += w * rep.t[ray, slot]
        acc.front_weight += w
    rep.trans[ray, slot] = acc.trans
    acc.trans = acc.trans * (1.0 - a)
    acc.blended += 1
    return acc


@wp.func
def write_outputs(ray: int, n_acc: int, acc: Blend, outs: RayOutputs):
    """Apply the tail rule (truncated: divide by 1 - T_end) and store."""
    scale = float(1.0)
    if acc.blended < n_acc:
        scale = 1.0 / (1.0 - acc.trans)
    outs.diffuse[ray] = scale * acc.diffuse
    outs.depth[ray] = scale * acc.depth
    outs.normal[ray] = scale * acc.normal
    outs.roughness[ray] = scale * acc.roughness
    outs.f0[ray] = scale * acc.f0
    outs.transmittance[ray] = acc.trans
    front = float(0.0)
    if acc.front_weight > 0.0:
        front = acc.front_depth / acc.front_weight
    outs.front_depth[ray] = front
    outs.hit_count[ray] = n_acc
    outs.blended[ray] = acc.blended
    outs.needed[ray] = 0
