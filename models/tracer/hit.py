"""Warp functions for one ray / one Gaussian: max-response hit and its gradient.

In the local frame x_l = M (x - mean) the Gaussian is the unit isotropic one; the
local ray o_l + t d_l keeps the world ray parameter t. The max response lies at the
local ray's closest point to the origin: t* = -(o_l . d_l) / (d_l . d_l), r^2 = |q|^2 with
q = o_l + t* d_l. q is computed as d_l x (o_l x d_l) / (d_l . d_l) (the same point): along a thin axis
(scale ratio 1e-6: local coordinates 1e6 times the others) o_l + t* d_l cancels two large numbers and
float32 lost the whole response, the triple product does not (``closest_point``).
"""

from __future__ import annotations

import warp as wp

from models.tracer.structs import vec16


@wp.func
def closest_point(o_l: wp.vec3, d_l: wp.vec3, dd: float) -> wp.vec3:
    """o_l + t* d_l, t* = -(o_l . d_l) / dd, as d_l x (o_l x d_l) / dd (no cancellation along thin axes)."""
    return wp.cross(d_l, wp.cross(o_l, d_l)) / dd


@wp.func
def int_power(x: float, p: int) -> float:
    """x^p for an integer p >= 0, by multiplication (cheaper than pow() in the traversal's inner loop)."""
    y = float(1.0)
    for _ in range(p):
        y = y * x
    return y


@wp.func
def kernel_response(r2: float, p: int) -> float:
    """exp(-r^(2p) / (2p)) from r^2."""
    return wp.exp(-int_power(r2, p) / float(2 * p))


@wp.func
def eval_hit(o: wp.vec3, d: wp.vec3, mean: wp.vec3, w2l: wp.mat33, opacity: float, s: float,
             p: int, alpha_min: float, alpha_max: float, t_min: float, obb_test: int):
    """(t, alpha, in_ellipsoid) as three floats (a tuple, not a vec3: the callers read them as scalars; a vec3
    read back after scalar stores stalled store-to-load forwarding once per candidate); alpha = 0 when rejected.

    The ray meets the cut-off ellipsoid (|x_l| <= s: alpha > alpha_min there and only there) when its local
    closest point q has |q| <= s; that test comes first and costs no more than a box test (``obb_test`` 0 is the
    ablation that evaluates the response of every candidate; the same test then rejects after it). Accepted hits
    therefore lie in the ellipsoid, hence in its world AABB (prepare.py), whatever the float rounding of the
    equivalent alpha > alpha_min.
    """
    if s <= 0.0:
        return 0.0, 0.0, 0.0
    o_l = w2l * (o - mean)
    d_l = w2l * d
    dd = wp.dot(d_l, d_l)
    if dd <= 0.0:
        return 0.0, 0.0, 0.0
    q = closest_point(o_l, d_l, dd)
    r2 = wp.dot(q, q)
    if obb_test != 0:
        if r2 > s * s:
            return 0.0, 0.0, 0.0
    t = -wp.dot(o_l, d_l) / dd
    if t <= t_min:
        return t, 0.0, 1.0
    if r2 > s * s:
        return t, 0.0, 1.0
    alpha = wp.min(alpha_max, opacity * kernel_response(r2, p))
    if alpha <= alpha_min:
        return t, 0.0, 1.0
    return t, alpha, 1.0


@wp.func
def eval_packed(o: wp.vec3, d: wp.vec3, rec: vec16, p: int, alpha_min: float, alpha_max: float,
                t_min: float, obb_test: int):
    """eval_hit on a packed record (see structs.vec16)."""
    mean = wp.vec3(rec[0], rec[1], rec[2])
    w2l = wp.mat33(rec[3], rec[4], rec[5], rec[6], rec[7], rec[8], rec[9], rec[10], rec[11])
    t, alpha, inside = eval_hit(o, d, mean, w2l, rec[12], rec[13], p, alpha_min, alpha_max, t_min, obb_test)
    return t, alpha, inside


@wp.func
def hit_less(t_a: float, id_a: int, t_b: float, id_b: int) -> int:
    """Order of hits: by t, ties by Gaussian id (as a stable sort over ids)."""
    if t_a < t_b:
        return 1
    if t_a == t_b and id_a < id_b:
        return 1
    return 0


@wp.func
def hit_grad_geometry(o: wp.vec3, d: wp.vec3, mean: wp.vec3, w2l: wp.mat33, opacity: float, alpha: float,
                      p: int, alpha_max: float, dl_dalpha: float, dl_dt: float,
                      g_mean: wp.array(dtype=wp.vec3), g_w2l: wp.array(dtype=wp.mat33),
                      g_opacity: wp.array(dtype=float), gid: int):
    """Chain dL/dalpha and dL/dt of one accepted hit to mean, M and opacity (atomics).

    r^2 is the minimum over t, so by the envelope theorem dr2/do_l = 2q, dr2/dd_l = 2 t q.
    dt/do_l = -d_l / dd, dt/dd_l = -(o_l + 2 t d_l) / dd. ``alpha`` is the forward's (replay buffer): unclamped it is
    opacity x response, so the response needs no exp here (dalpha/dr2 = -alpha r^(2p-2) / 2); one division by dd.
    """
    v = o - mean
    o_l = w2l * v
    d_l = w2l * d
    dd = wp.dot(d_l, d_l)
    inv_dd = 1.0 / dd
    t = -wp.dot(o_l, d_l) * inv_dd
    q = wp.cross(d_l, wp.cross(o_l, d_l)) * inv_dd  # closest_point, multiplied by 1 / dd
    g_r2 = float(0.0)
    if alpha < alpha_max:
        wp.atomic_add(g_opacity, gid, dl_dalpha * (alpha / opacity))
        g_r2 = dl_dalpha * (-0.5 * alpha * int_power(wp.dot(q, q), p - 1))
    g_ol = (2.0 * g_r2) * q - (dl_dt * inv_dd) * d_l
    g_dl = (2.0 * g_r2 * t) * q - (dl_dt * inv_dd) * (q + t * d_l)  # o_l + 2 t d_l = q + t d_l
    wp.atomic_add(g_w2l, gid, wp.outer(g_ol, v) + wp.outer(g_dl, d))
    wp.atomic_add(g_mean, gid, -(wp.transpose(w2l) * g_ol))
