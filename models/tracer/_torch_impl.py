"""Slow, obviously-correct PyTorch reference of the tracer forward.

Every ray is tested against ALL Gaussians (no BVH); differentiable by autograd,
float64 capable. Semantics are those documented in `output.TraceOutput`.
"""

from __future__ import annotations

import torch

from models.gaussians.scene import Gaussians
from models.tracer.config import TracerConfig
from models.tracer.output import FRONT_TRANSMITTANCE, TraceOutput


def cutoff_radius(opacities: torch.Tensor, p: int, alpha_min: float) -> torch.Tensor:
    """Opacity-adaptive cut-off radius s = (2p ln(opacity / alpha_min))^(1/(2p)) in local units (alpha > alpha_min
    exactly inside |x_l| < s); 0 when opacity <= alpha_min (masked out). [N] -> [N]."""
    ratio = torch.log(opacities.clamp_min(alpha_min) / alpha_min)
    return torch.where(opacities > alpha_min, (2 * p * ratio).clamp_min(0) ** (1.0 / (2 * p)),
                       torch.zeros_like(opacities))


def evaluate_hits(origins, dirs, means, w2l, opacities, config: TracerConfig):
    """Max-response hit of every ray with every Gaussian.

    origins, dirs: [R, 3]; means: [N, 3]; w2l: [N, 3, 3]; opacities: [N].
    Returns t [R, N], alpha [R, N] (clamped), valid [R, N] and the raw pieces used for
    ambiguity checks (unclamped alpha, |q| of the local closest point, cutoff s).
    """
    p = config.kernel_p
    o_l = torch.einsum("nij,rnj->rni", w2l, origins[:, None, :] - means[None])  # [R, N, 3]
    d_l = torch.einsum("nij,rj->rni", w2l, dirs)                                # [R, N, 3]
    dd = (d_l * d_l).sum(-1)
    t = -(o_l * d_l).sum(-1) / dd                                               # [R, N]
    # local closest point o_l + t d_l, as d_l x (o_l x d_l) / dd: no cancellation along thin axes (hit.py)
    closest = torch.linalg.cross(d_l, torch.linalg.cross(o_l, d_l, dim=-1), dim=-1) / dd[..., None]
    r2 = (closest * closest).sum(-1)
    response = torch.exp(-(r2**p) / (2 * p))
    raw_alpha = opacities[None] * response
    alpha = raw_alpha.clamp(max=config.alpha_max)
    s = cutoff_radius(opacities, p, config.alpha_min)
    radius = r2.sqrt()  # in the cut-off ellipsoid: |q| <= s (implied by alpha > alpha_min but for rounding)
    valid = (alpha > config.alpha_min) & (radius <= s[None]) & (t > config.t_min) & (s[None] > 0)
    return t, alpha, valid, raw_alpha, radius, s


def reference_trace(origins: torch.Tensor, dirs: torch.Tensor, gaussians: Gaussians,
                    config: TracerConfig | None = None, ray_chunk: int = 64,
                    return_ambiguous: bool = False, ambiguity_eps: float = 1e-4, ambiguity_scope: str = "all"):
    """Trace R rays through all Gaussians. origins, dirs: [R, 3] (any non-zero dirs).

    Returns TraceOutput; with return_ambiguous also a bool [R] marking rays with a
    decision (alpha vs alpha_min, T vs threshold, order of two hits, t vs t_min, ellipsoid)
    within ambiguity_eps of flipping, where a float32 kernel may legitimately differ.
    ambiguity_scope "blended": only the decisions up to the first accepted hit left unblended count (beyond it
    a flip changes neither the outputs nor the tail rule, only the count of accepted hits); for rays with
    hundreds of hits, where some near-tie far behind the threshold is all but certain.
    """
    if ambiguity_scope not in ("all", "blended"):
        raise ValueError(f"ambiguity_scope must be 'all' or 'blended', got {ambiguity_scope!r}")
    config = config or TracerConfig()
    dtype = gaussians.dtype
    origins = origins.to(dtype)
    dirs = dirs.to(dtype)
    if (dirs.norm(dim=-1) == 0).any():
        raise ValueError("dirs contains zero-length directions")
    means, w2l, opac = gaussians.means, gaussians.world_to_local(), gaussians.opacities()
    feats = torch.cat([gaussians.diffuse, gaussians.normals, gaussians.roughness[:, None], gaussians.f0], 1)
    parts = []
    for start in range(0, origins.shape[0], ray_chunk):
        parts.append(_trace_chunk(origins[start:start + ray_chunk], dirs[start:start + ray_chunk],
                                  means, w2l, opac, feats, config, ambiguity_eps, ambiguity_scope))
    if not parts:  # no rays
        parts.append(_trace_chunk(origins, dirs, means, w2l, opac, feats, config, ambiguity_eps, ambiguity_scope))
    cat = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    out = TraceOutput(
        diffuse=cat["out"][:, 0:3], normal=cat["out"][:, 3:6], roughness=cat["out"][:, 6],
        f0=cat["out"][:, 7:10], depth=cat["out"][:, 10], transmittance=cat["t_end"],
        hit_count=cat["hits"], blended_count=cat["blended"], front_depth=cat["front"],
    )
    return (out, cat["ambiguous"]) if return_ambiguous else out


def _trace_chunk(origins, dirs, means, w2l, opac, feats, config, eps, scope="all"):
    r, n = origins.shape[0], means.shape[0]
    t, alpha, valid, raw_alpha, radius, s = evaluate_hits(origins, dirs, means, w2l, opac, config)
    # sort accepted hits by t; rejected ones go to the end with alpha 0
    key = torch.where(valid, t.detach(), torch.full_like(t, float("inf")))
    key_sorted, order = torch.sort(key, dim=1, stable=True)
    valid_s = torch.gather(valid, 1, order)
    alpha_s = torch.where(valid_s, torch.gather(alpha, 1, order), torch.zeros_like(key))
    t_s = torch.gather(t, 1, order)
    f_s = torch.cat([feats[order], t_s[..., None]], -1)                     # [R, N, 11]
    one_minus = 1 - alpha_s
    trans = torch.cumprod(torch.cat([torch.ones_like(one_minus[:, :1]), one_minus[:, :-1]], 1), 1)
    blended = valid_s & (trans >= config.transmittance_threshold)
    w = torch.where(blended, trans * alpha_s, torch.zeros_like(alpha_s))
    t_end = torch.where(blended, one_minus, torch.ones_like(one_minus)).prod(1)
    hits = valid.sum(1).to(torch.int32)
    n_blended = blended.sum(1).to(torch.int32)
    truncated = hits > n_blended
    acc = (w[..., None] * f_s).sum(1)                                        # [R, 11]
    scale = torch.where(truncated, 1 / (1 - t_end), torch.ones_like(t_end))
    out = acc * scale[:, None]
    with torch.no_grad():  # the surface's front (TraceOutput.front_depth): the hits blended while T >= 0.5
        w_front = torch.where(blended & (trans >= FRONT_TRANSMITTANCE), w, torch.zeros_like(w))
        front_w = w_front.sum(1)
        front = torch.where(front_w > 0, (w_front * t_s).sum(1) / front_w.clamp_min(1e-30), torch.zeros_like(front_w))

    with torch.no_grad():
        relevant = torch.ones_like(valid)  # [R, N] hits whose decisions can change outputs or the tail rule
        relevant_s = torch.ones_like(valid_s)
        if scope == "blended":
            first_open = n_blended.long().clamp(max=n - 1)
            boundary = torch.where(truncated, key_sorted.gather(1, first_open[:, None])[:, 0],
                                   torch.full_like(t_end, float("inf")))
            relevant = t.detach() <= boundary[:, None] * (1 + eps) + eps
            relevant_s = torch.arange(n, device=t.device)[None] <= n_blended[:, None].long()
        cand = (s[None] > 0) & (t > config.t_min - eps) & relevant
        amb = (cand & ((raw_alpha - config.alpha_min).abs() < eps)).any(1)
        amb |= (cand & ((radius - s[None]).abs() < eps) & (raw_alpha > config.alpha_min - eps)).any(1)
        amb |= ((raw_alpha > config.alpha_min) & ((t - config.t_min).abs() < eps) & relevant).any(1)
        amb |= (valid_s & relevant_s & ((trans - config.transmittance_threshold).abs() < eps)).any(1)
        amb |= (blended & ((trans - FRONT_TRANSMITTANCE).abs() < eps)).any(1)  # in or out of the front depth
        if n > 1:
            gap = (key_sorted[:, 1:] - key_sorted[:, :-1]).abs()
            amb |= (valid_s[:, 1:] & relevant_s[:, 1:] & (gap < eps * (1 + key_sorted[:, :-1].abs()))).any(1)
    return {"out": out, "t_end": t_end, "hits": hits, "blended": n_blended, "front": front, "ambiguous": amb}
