"""Chain kernel: gradients wrt the activated geometry (M = S^-1 R^T, opacity) to the raw
parameters (quaternion wxyz before normalisation, log-scales, opacity logit), in Warp.

M[r][c] = R[c][r] / s_r, so dL/dlog s_r = -sum_c G_M[r][c] M[r][c] and
dL/dR[c][r] = G_M[r][c] / s_r; R(q) as activations.quats_to_rotmats, q = q_raw / |q_raw|.
"""

from __future__ import annotations

import warp as wp


@wp.kernel
def chain_kernel(quats: wp.array(dtype=wp.vec4), log_scales: wp.array(dtype=wp.vec3),
                 opacity_logits: wp.array(dtype=float), g_w2l: wp.array(dtype=wp.mat33),
                 g_opacity: wp.array(dtype=float), g_quats: wp.array(dtype=wp.vec4),
                 g_log_scales: wp.array(dtype=wp.vec3), g_logits: wp.array(dtype=float)):
    i = wp.tid()
    gm = g_w2l[i]
    if gm == wp.mat33(0.0) and g_opacity[i] == 0.0:
        # no ray of this trace reached the Gaussian (a reflection segment reaches few): its gradients are zero
        g_quats[i] = wp.vec4(0.0)
        g_log_scales[i] = wp.vec3(0.0)
        g_logits[i] = 0.0
        return
    qr = quats[i]
    norm = wp.max(wp.length(qr), 1.0e-12)
    q = qr / norm
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    rot = wp.mat33(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
                   2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
                   2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))
    ls = log_scales[i]
    inv_s = wp.vec3(wp.exp(-ls[0]), wp.exp(-ls[1]), wp.exp(-ls[2]))
    gls = wp.vec3(0.0)
    gr = wp.mat33(0.0)  # dL/dR
    for r in range(3):
        acc = float(0.0)
        for c in range(3):
            acc += gm[r, c] * rot[c, r] * inv_s[r]
            gr[c, r] = gm[r, c] * inv_s[r]
        gls[r] = -acc
    gw = 2.0 * (-z * gr[0, 1] + y * gr[0, 2] + z * gr[1, 0] - x * gr[1, 2] - y * gr[2, 0] + x * gr[2, 1])
    gx = 2.0 * (y * gr[0, 1] + z * gr[0, 2] + y * gr[1, 0] - 2.0 * x * gr[1, 1] - w * gr[1, 2]
                + z * gr[2, 0] + w * gr[2, 1] - 2.0 * x * gr[2, 2])
    gy = 2.0 * (-2.0 * y * gr[0, 0] + x * gr[0, 1] + w * gr[0, 2] + x * gr[1, 0] + z * gr[1, 2]
                - w * gr[2, 0] + z * gr[2, 1] - 2.0 * y * gr[2, 2])
    gz = 2.0 * (-2.0 * z * gr[0, 0] - w * gr[0, 1] + x * gr[0, 2] + w * gr[1, 0] - 2.0 * z * gr[1, 1]
                + y * gr[1, 2] + x * gr[2, 0] + y * gr[2, 1])
    gq = wp.vec4(gw, gx, gy, gz)
    g_quats[i] = (gq - q * wp.dot(q, gq)) / norm
    g_log_scales[i] = gls
    # dsigmoid/dx = s (1 - s) = e / (1 + e)^2 with e = exp(-|x|): 1 - s would round to 0 in
    # float32 for x > ~16.6 (and lose ~6e-8 / (1 - s) relative precision before that)
    e = wp.exp(-wp.abs(opacity_logits[i]))
    g_logits[i] = g_opacity[i] * e / ((1.0 + e) * (1.0 + e))
