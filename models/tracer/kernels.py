"""Tracer kernel entry points: one source for CPU and CUDA.

forward_kernel: per ray, dispatches to the t-interval traversal (kernels_interval, the default)
or an ablation: the single traversal (kernels_single), the repeated k-buffer (kernels_kbuffer), the
best-first ordered BVH (kernels_ordered). backward_kernel: reverse replay of the sorted replay-buffer prefix
(kernels_backward). fused_kernel: forward, per-pixel L1 loss gradient and backward in one
thread per ray. Semantics (tail rule, outputs) are those of `output.TraceOutput`.
"""

from __future__ import annotations

import warp as wp

from models.tracer.kernels_backward import backward_ray
from models.tracer.kernels_interval import forward_interval
from models.tracer.kernels_kbuffer import forward_kbuffer
from models.tracer.kernels_ordered import forward_ordered
from models.tracer.kernels_single import forward_single
from models.tracer.ordered_bvh import OrderedBvh
from models.tracer.wide_bvh import WideBvh
from models.tracer.structs import (
    GaussianData,
    GaussianGrads,
    L1Loss,
    RayGrads,
    RayOutputs,
    Replay,
    TraceParams,
)


@wp.func
def forward_ray(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, rep: Replay,
                outs: RayOutputs, ob: OrderedBvh, wb: WideBvh) -> int:
    if prm.traversal == 0:
        return forward_interval(ray, o, d, g, prm, rep, outs, wb)
    if prm.traversal == 3:
        status = forward_ordered(ray, o, d, g, prm, rep, outs, ob)
        if status >= 0:
            return status
        # node heap overflow: this ray falls back to the single traversal (uses the wp.Bvh)
    if prm.traversal == 2:
        return forward_kbuffer(ray, o, d, g, prm, rep, outs)
    return forward_single(ray, o, d, g, prm, rep, outs)


@wp.kernel
def forward_kernel(origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), g: GaussianData,
                   prm: TraceParams, rep: Replay, outs: RayOutputs, ob: OrderedBvh, wb: WideBvh, offset: int):
    ray = wp.tid() + offset  # a launch covers rays offset .. offset + dim - 1 of the whole arrays
    forward_ray(ray, origins[ray], dirs[ray], g, prm, rep, outs, ob, wb)


@wp.kernel
def backward_kernel(origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), g: GaussianData,
                    prm: TraceParams, rep: Replay, outs: RayOutputs, up: RayGrads, grads: GaussianGrads,
                    offset: int):
    ray = wp.tid() + offset
    backward_ray(ray, origins[ray], dirs[ray], g, prm, rep, outs, up, grads)


@wp.func
def l1_term(out: float, target: float, scale: float) -> wp.vec2:
    """(loss, dloss/dout) of scale * |out - target|; sign(0) = 0 as torch."""
    diff = out - target
    s = float(0.0)
    if diff > 0.0:
        s = 1.0
    elif diff < 0.0:
        s = -1.0
    return wp.vec2(scale * wp.abs(diff), scale * s)


@wp.kernel
def fused_kernel(origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), g: GaussianData,
                 prm: TraceParams, rep: Replay, outs: RayOutputs, targets: RayGrads, loss: L1Loss,
                 up: RayGrads, ray_loss: wp.array(dtype=float), grads: GaussianGrads, ob: OrderedBvh,
                 wb: WideBvh, offset: int):
    """Forward, L1 loss gradient into `up` (per ray) and backward, in one thread per ray."""
    ray = wp.tid() + offset
    ok = forward_ray(ray, origins[ray], dirs[ray], g, prm, rep, outs, ob, wb)
    if ok == 0:
        return
    total = float(0.0)
    w_d = loss.weights[0] * loss.inv_rays / 3.0
    w_z = loss.weights[1] * loss.inv_rays
    w_n = loss.weights[2] * loss.inv_rays / 3.0
    w_r = loss.weights[3] * loss.inv_rays
    w_f = loss.weights[4] * loss.inv_rays / 3.0
    gd = wp.vec3(0.0)
    gn = wp.vec3(0.0)
    gf = wp.vec3(0.0)
    gz = float(0.0)
    gr = float(0.0)
    if w_d != 0.0:
        for c in range(3):
            e = l1_term(outs.diffuse[ray][c], targets.diffuse[ray][c], w_d)
            total += e[0]
            gd[c] = e[1]
    if w_z != 0.0:
        e = l1_term(outs.depth[ray], targets.depth[ray], w_z)
        total += e[0]
        gz = e[1]
    if w_n != 0.0:
        for c in range(3):
            e = l1_term(outs.normal[ray][c], targets.normal[ray][c], w_n)
            total += e[0]
            gn[c] = e[1]
    if w_r != 0.0:
        e = l1_term(outs.roughness[ray], targets.roughness[ray], w_r)
        total += e[0]
        gr = e[1]
    if w_f != 0.0:
        for c in range(3):
            e = l1_term(outs.f0[ray][c], targets.f0[ray][c], w_f)
            total += e[0]
            gf[c] = e[1]
    ray_loss[ray] = total
    up.diffuse[ray] = gd
    up.depth[ray] = gz
    up.normal[ray] = gn
    up.roughness[ray] = gr
    up.f0[ray] = gf
    up.transmittance[ray] = 0.0
    backward_ray(ray, origins[ray], dirs[ray], g, prm, rep, outs, up, grads)
