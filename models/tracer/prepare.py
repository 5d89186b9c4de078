"""Per-Gaussian preparation kernel: activations, packed traversal record and world bounds (of
the cut-off ellipsoid, not of its oriented box: up to 1.4x tighter per axis for rotated Gaussians).

One pass over the raw parameters (same math as models.gaussians.activations and
_torch_impl.cutoff_radius) feeding the BVH refit/rebuild and the tracer kernels.
"""

from __future__ import annotations

import warp as wp

from models.tracer.structs import vec16

BOUND_PAD = wp.constant(1.0 + 1.0e-5)  # relative slack of the bounds (float32 rounding of R S and the hit point)


@wp.kernel
def prepare_kernel(means: wp.array(dtype=wp.vec3), quats: wp.array(dtype=wp.vec4),
                   log_scales: wp.array(dtype=wp.vec3), opacity_logits: wp.array(dtype=float),
                   p: int, alpha_min: float,
                   packed: wp.array(dtype=vec16), lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    q = quats[i]
    q = q / wp.max(wp.length(q), 1.0e-12)
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    # rotation matrix (columns = local axes in world), as activations.quats_to_rotmats
    rot = wp.mat33(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
                   2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
                   2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))
    ls = log_scales[i]
    s = wp.vec3(wp.exp(ls[0]), wp.exp(ls[1]), wp.exp(ls[2]))
    opacity = 1.0 / (1.0 + wp.exp(-opacity_logits[i]))
    cutoff = float(0.0)
    if opacity > alpha_min:
        cutoff = wp.pow(wp.max(float(2 * p) * wp.log(opacity / alpha_min), 0.0), 1.0 / float(2 * p))
    m = means[i]
    rec = vec16()
    rec[0] = m[0]
    rec[1] = m[1]
    rec[2] = m[2]
    for r in range(3):
        for c in range(3):
            rec[3 + 3 * r + c] = rot[c, r] / s[r]   # M = S^-1 R^T
    rec[12] = opacity
    rec[13] = cutoff
    packed[i] = rec
    # world AABB of the ellipsoid {mean + R S u : |u| <= cutoff} (where alpha > alpha_min): half extent along axis
    # r is cutoff |row r of R S|, padded by BOUND_PAD so float rounding never puts an accepted hit outside it
    half = wp.vec3(0.0)
    for r in range(3):
        ex = rot[r, 0] * s[0]
        ey = rot[r, 1] * s[1]
        ez = rot[r, 2] * s[2]
        half[r] = cutoff * wp.sqrt(ex * ex + ey * ey + ez * ez) * BOUND_PAD
    lowers[i] = m - half
    uppers[i] = m + half
