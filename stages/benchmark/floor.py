"""The floor of "candidates per blended hit" for a traversal that blends exactly in t* order.

A hit may be blended only once every Gaussian whose max-response point t* could lie before it has been
evaluated, and t* is known only by evaluating the Gaussian; the cheap lower bound of t* is where the ray enters
the Gaussian's box (t* lies in its cut-off ellipsoid, inside the box). So an exact traversal examines at least
every box the ray enters before the t* of the last hit it blends, and, when the ray became opaque, one accepted
hit after it (the tail rule's witness: any later hit will do); a ray that stays transparent needs every box it
enters. This counts those boxes with the PyTorch reference's hits (no BVH), on a sample of the rays.
"""

from __future__ import annotations

import torch

from models.gaussians import Gaussians
from models.tracer import TracerConfig
from models.tracer._torch_impl import evaluate_hits


def exact_order_floor(gaussians: Gaussians, origins: torch.Tensor, dirs: torch.Tensor, lowers: torch.Tensor,
                      uppers: torch.Tensor, config: TracerConfig, rays: int = 256, chunk: int = 8192,
                      seed: int = 0) -> dict:
    """Mean boxes an exact-order traversal must examine per blended hit, over ``rays`` sampled rays.

    gaussians: the traced scene (any device; computed on the CPU in float64); origins, dirs: [R, 3];
    lowers, uppers: [N, 3] the tracer's box bounds (models.tracer.bvh: the cut-off ellipsoids' AABBs).
    Returns {"floor": boxes / blended, "boxes_per_ray", "blended_per_ray", "rays"} and per sampled ray
    "picked" (its index in origins), "boxes", "blended".
    """
    g = torch.Generator().manual_seed(seed)
    pick = torch.randperm(origins.shape[0], generator=g)[:rays]
    o = origins.detach().cpu()[pick].double()
    d = dirs.detach().cpu()[pick].double()
    gs = gaussians.to(device="cpu", dtype=torch.float64)
    means, w2l, opac = gs.means, gs.world_to_local(), gs.opacities()
    lo, hi = lowers.detach().cpu().double(), uppers.detach().cpu().double()
    boxes, blended = [], []
    for a in range(0, o.shape[0], 32):  # ray groups: [32, N] per quantity, also at N = 1M
        ob, db = o[a:a + 32], d[a:a + 32]
        t, alpha, entry = _pairs(ob, db, means, w2l, opac, lo, hi, config, chunk)
        for r in range(ob.shape[0]):
            acc = torch.isfinite(t[r])                  # accepted hits, in id order
            tr, ar = t[r][acc], alpha[r][acc]
            order = torch.argsort(tr, stable=True)      # by t, ties by id (as the tracer)
            tr, ar = tr[order], ar[order]
            trans = torch.cat([torch.ones(1, dtype=torch.float64), torch.cumprod(1 - ar, 0)])  # T before each hit
            stop = (trans[:-1] < config.transmittance_threshold).nonzero()
            if len(stop):  # opaque: every box entered before the last blended hit's t*, and one accepted hit after
                b = int(stop[0])
                before = entry[r] <= tr[b - 1]
                witness_among = bool((before & torch.isfinite(t[r]) & (t[r] > tr[b - 1])).any())
                blended.append(b)
                boxes.append(int(before.sum()) + (0 if witness_among else 1))
            else:
                blended.append(len(tr))
                boxes.append(int(torch.isfinite(entry[r]).sum()))
    total_blended = max(sum(blended), 1)
    return {"floor": sum(boxes) / total_blended, "boxes_per_ray": sum(boxes) / len(boxes),
            "blended_per_ray": sum(blended) / len(blended), "rays": len(boxes),
            "picked": pick, "boxes": torch.tensor(boxes), "blended": torch.tensor(blended)}


def _pairs(o, d, means, w2l, opac, lo, hi, config, chunk):
    """[R, N] t* of the accepted hits (inf elsewhere), their alpha, and the box entry t (inf where missed)."""
    t_all, a_all, entry_all = [], [], []
    inv = 1.0 / torch.where(d == 0, 1e-30, d)
    for s in range(0, means.shape[0], chunk):
        e = min(means.shape[0], s + chunk)
        t, alpha, valid, *_ = evaluate_hits(o, d, means[s:e], w2l[s:e], opac[s:e], config)
        t_all.append(torch.where(valid, t, torch.inf))
        a_all.append(torch.where(valid, alpha, 0.0))
        ta = (lo[None, s:e] - o[:, None]) * inv[:, None]
        tb = (hi[None, s:e] - o[:, None]) * inv[:, None]
        t0, t1 = torch.minimum(ta, tb).amax(-1), torch.maximum(ta, tb).amin(-1)
        entry_all.append(torch.where((t0 <= t1) & (t1 > config.t_min), t0, torch.inf))
    return torch.cat(t_all, 1), torch.cat(a_all, 1), torch.cat(entry_all, 1)
