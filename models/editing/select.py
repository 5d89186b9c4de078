"""Evaluate a Selection on a Gaussian scene: a boolean mask over the Gaussians."""

from __future__ import annotations

import torch

from models.gaussians import Gaussians

from .spec import Range, Selection


def _in_range(values: torch.Tensor, r: Range) -> torch.Tensor:
    """values [N] or [N, 3] -> [N] bool. For [N, 3], a scalar bound applies to the channel mean."""
    ok = torch.ones(values.shape[0], dtype=torch.bool, device=values.device)
    for bound, cmp in ((r.min, torch.ge), (r.max, torch.le)):
        if bound is None:
            continue
        if values.ndim == 1:
            ok &= cmp(values, bound)
        elif isinstance(bound, tuple):
            ok &= cmp(values, values.new_tensor(bound)).all(dim=-1)
        else:
            ok &= cmp(values.mean(dim=-1), bound)
    return ok


def select(g: Gaussians, sel: Selection) -> torch.Tensor:
    """[N] bool: Gaussians whose mean / stored values meet every criterion of ``sel``, minus its exclusions."""
    p = g.means.detach()
    mask = torch.ones(len(g), dtype=torch.bool, device=g.device)
    if sel.box is not None:
        lo, hi = p.new_tensor(sel.box[0]), p.new_tensor(sel.box[1])
        mask &= ((p >= lo) & (p <= hi)).all(dim=-1)
    if sel.sphere is not None:
        centre, radius = sel.sphere
        mask &= (p - p.new_tensor(centre)).norm(dim=-1) <= radius
    if sel.cylinder is not None:
        c = sel.cylinder
        d = p - p.new_tensor(c.centre)
        axis = p.new_tensor(c.axis)
        along = d @ axis  # [N]
        radial = (d - along[:, None] * axis).norm(dim=-1)
        mask &= (along.abs() <= 0.5 * c.height) & (radial <= c.radius)
    if sel.roughness is not None:
        mask &= _in_range(g.roughness.detach(), sel.roughness)
    if sel.f0 is not None:
        mask &= _in_range(g.f0.detach(), sel.f0)
    if sel.diffuse is not None:
        mask &= _in_range(g.diffuse.detach(), sel.diffuse)
    for ex in sel.exclude:
        mask &= ~select(g, ex)
    return mask
