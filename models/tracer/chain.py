"""Gather kernels: the backward's per-thread gradient rows summed, and the geometry part taken from the activated
values (M = S^-1 R^T, opacity) to the raw parameters (quaternion wxyz before normalisation, log-scales, opacity
logit), in one pass over the Gaussians (or over those the rows list as touched) that also clears the rows for the
next backward.

M[r][c] = R[c][r] / s_r, so dL/dlog s_r = -sum_c G_M[r][c] M[r][c] and
dL/dR[c][r] = G_M[r][c] / s_r; R(q) as activations.quats_to_rotmats, q = q_raw / |q_raw|.
"""

from __future__ import annotations

import warp as wp


@wp.func
def chain_quat(qr: wp.vec4, gr: wp.mat33) -> wp.vec4:
    """dL/dq_raw from dL/dR (R of the normalised q)."""
    norm = wp.max(wp.length(qr), 1.0e-12)
    q = qr / norm
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    gw = 2.0 * (-z * gr[0, 1] + y * gr[0, 2] + z * gr[1, 0] - x * gr[1, 2] - y * gr[2, 0] + x * gr[2, 1])
    gx = 2.0 * (y * gr[0, 1] + z * gr[0, 2] + y * gr[1, 0] - 2.0 * x * gr[1, 1] - w * gr[1, 2]
                + z * gr[2, 0] + w * gr[2, 1] - 2.0 * x * gr[2, 2])
    gy = 2.0 * (-2.0 * y * gr[0, 0] + x * gr[0, 1] + w * gr[0, 2] + x * gr[1, 0] + z * gr[1, 2]
                - w * gr[2, 0] + z * gr[2, 1] - 2.0 * y * gr[2, 2])
    gz = 2.0 * (-2.0 * z * gr[0, 0] - w * gr[0, 1] + x * gr[0, 2] + w * gr[1, 0] - 2.0 * z * gr[1, 1]
                + y * gr[1, 2] + x * gr[2, 0] + y * gr[2, 1])
    gq = wp.vec4(gw, gx, gy, gz)
    return (gq - q * wp.dot(q, gq)) / norm


@wp.func
def rotation(qr: wp.vec4) -> wp.mat33:
    q = qr / wp.max(wp.length(qr), 1.0e-12)
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    return wp.mat33(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
                    2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
                    2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


@wp.struct
class GatherArgs:
    """The gather's arrays: the raw geometry parameters, the per-thread rows (flat, as launch.GradRows) and the
    raw-parameter gradients it writes (PARAM_SHAPES order after the rows)."""

    quats: wp.array(dtype=wp.vec4)
    log_scales: wp.array(dtype=wp.vec3)
    opacity_logits: wp.array(dtype=float)
    rows_means: wp.array(dtype=wp.vec3)
    rows_w2l: wp.array(dtype=wp.mat33)
    rows_opacity: wp.array(dtype=float)
    rows_diffuse: wp.array(dtype=wp.vec3)
    rows_normal: wp.array(dtype=wp.vec3)
    rows_roughness: wp.array(dtype=float)
    rows_f0: wp.array(dtype=wp.vec3)
    g_means: wp.array(dtype=wp.vec3)
    g_quats: wp.array(dtype=wp.vec4)
    g_log_scales: wp.array(dtype=wp.vec3)
    g_logits: wp.array(dtype=float)
    g_diffuse: wp.array(dtype=wp.vec3)
    g_normal: wp.array(dtype=wp.vec3)
    g_roughness: wp.array(dtype=float)
    g_f0: wp.array(dtype=wp.vec3)


GRAD_OUTPUTS = ("means", "quats", "log_scales", "logits", "diffuse", "normal", "roughness", "f0")


def gather_args(quats: wp.array, log_scales: wp.array, opacity_logits: wp.array, rows: dict[str, wp.array],
                grads: list[wp.array]) -> GatherArgs:
    """The struct of one gather: ``rows`` by launch.GRAD_FIELDS name, ``grads`` in GRAD_OUTPUTS (= PARAM_SHAPES)
    order."""
    a = GatherArgs()
    a.quats, a.log_scales, a.opacity_logits = quats, log_scales, opacity_logits
    for k, v in rows.items():
        setattr(a, f"rows_{k}", v)
    for k, v in zip(GRAD_OUTPUTS, grads, strict=True):
        setattr(a, f"g_{k}", v)
    return a


@wp.func
def gather_one(i: int, n: int, threads: int, a: GatherArgs):
    """Gaussian i: the sum over ``threads`` rows of n (row k holds Gaussian i at k * n + i), each row entry set
    back to zero; then the raw-parameter gradients."""
    gmean = wp.vec3(0.0)
    gm = wp.mat33(0.0)
    gop = float(0.0)
    gdif = wp.vec3(0.0)
    gnor = wp.vec3(0.0)
    grou = float(0.0)
    gf0 = wp.vec3(0.0)
    for k in range(threads):
        j = k * n + i
        gmean += a.rows_means[j]
        gm += a.rows_w2l[j]
        gop += a.rows_opacity[j]
        gdif += a.rows_diffuse[j]
        gnor += a.rows_normal[j]
        grou += a.rows_roughness[j]
        gf0 += a.rows_f0[j]
        a.rows_means[j] = wp.vec3(0.0)
        a.rows_w2l[j] = wp.mat33(0.0)
        a.rows_opacity[j] = 0.0
        a.rows_diffuse[j] = wp.vec3(0.0)
        a.rows_normal[j] = wp.vec3(0.0)
        a.rows_roughness[j] = 0.0
        a.rows_f0[j] = wp.vec3(0.0)
    a.g_means[i] = gmean
    a.g_diffuse[i] = gdif
    a.g_normal[i] = gnor
    a.g_roughness[i] = grou
    a.g_f0[i] = gf0
    if gm == wp.mat33(0.0) and gop == 0.0:
        # no ray of this trace reached the Gaussian (a reflection segment reaches few): its gradients are zero
        a.g_quats[i] = wp.vec4(0.0)
        a.g_log_scales[i] = wp.vec3(0.0)
        a.g_logits[i] = 0.0
        return
    qr = a.quats[i]
    rot = rotation(qr)
    ls = a.log_scales[i]
    inv_s = wp.vec3(wp.exp(-ls[0]), wp.exp(-ls[1]), wp.exp(-ls[2]))
    gls = wp.vec3(0.0)
    gr = wp.mat33(0.0)  # dL/dR
    for r in range(3):
        acc = float(0.0)
        for c in range(3):
            acc += gm[r, c] * rot[c, r] * inv_s[r]
            gr[c, r] = gm[r, c] * inv_s[r]
        gls[r] = -acc
    a.g_quats[i] = chain_quat(qr, gr)
    a.g_log_scales[i] = gls
    # dsigmoid/dx = s (1 - s) = e / (1 + e)^2 with e = exp(-|x|): 1 - s would round to 0 in
    # float32 for x > ~16.6 (and lose ~6e-8 / (1 - s) relative precision before that)
    e = wp.exp(-wp.abs(a.opacity_logits[i]))
    a.g_logits[i] = gop * e / ((1.0 + e) * (1.0 + e))


@wp.kernel
def gather_kernel(n: int, threads: int, start: int, a: GatherArgs):
    """Every Gaussian, i = start + tid (a dense gather)."""
    gather_one(wp.tid() + start, n, threads, a)


@wp.kernel
def gather_touched_kernel(n: int, threads: int, row: int, ids: wp.array(dtype=wp.int32),
                          touched: wp.array(dtype=wp.int32), a: GatherArgs):
    """The Gaussians row ``row`` lists as touched (``ids``; ``touched`` = every row's flags, flat like the rows),
    each gathered by the first row that flags it, so once, whichever launch runs first; the outputs of the
    Gaussians no row touched are left as they are (zero)."""
    i = ids[wp.tid()]
    for k in range(row):
        if touched[k * n + i] != 0:
            return
    gather_one(i, n, threads, a)


@wp.kernel
def clear_touched_kernel(ids: wp.array(dtype=wp.int32), touched: wp.array(dtype=wp.int32)):
    """One row's flags back to zero (its listed Gaussians)."""
    touched[ids[wp.tid()]] = 0
