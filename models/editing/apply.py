"""Apply a named edit to a Gaussian scene: every op of the spec on its selection, in order."""

from __future__ import annotations

import logging

import torch

from models.gaussians import Gaussians
from models.pathtrace.paths import PathConfig, TraceFn

from .ops import apply_op
from .select import select
from .spec import EditSpec, EditSpecError

log = logging.getLogger("models.editing")


def apply_edit(g: Gaussians, spec: EditSpec, trace_fn: TraceFn | None = None,
               path: PathConfig | None = None) -> tuple[Gaussians, list[dict]]:
    """``g`` with every op of ``spec`` applied in order, and per op what its selection caught.
    ``trace_fn`` (``Tracer.trace``) and ``path`` (the model's path settings) serve the ops that trace the scene
    (``set_albedo``); without a trace_fn those raise. Raises EditSpecError when a selection catches no Gaussian
    or an op refuses its input."""
    report = []
    shared = select(g, spec.select) if spec.select is not None else None  # the edit's selection
    for i, op in enumerate(spec.ops):
        sel = op.select if op.select is not None else spec.select
        mask = select(g, op.select) if op.select is not None else shared
        n = int(mask.sum())
        if n == 0:
            raise EditSpecError(f"edit {spec.name!r} op {i} ({op.kind}): selection {sel.text} selects no "
                                f"Gaussians (of {len(g)})")
        before = len(g)
        p = g.means.detach()[mask]
        bounds = [[round(x, 4) for x in p.amin(0).tolist()], [round(x, 4) for x in p.amax(0).tolist()]]
        try:
            g = apply_op(g, op, mask, trace_fn, path)
        except EditSpecError:
            raise
        except ValueError as e:
            raise EditSpecError(f"edit {spec.name!r} op {i} ({op.kind}): {e}") from None
        if shared is not None and len(g) != before:  # keep the edit's selection aligned with the model
            shared = shared[~mask] if op.kind == "delete" else torch.cat([shared, shared.new_zeros(len(g) - before)])
        row = {"op": op.kind, "selection": sel.text, "selected": n, "selected_bounds": bounds,
               "gaussians_before": before, "gaussians_after": len(g)}
        log.info("edit %r op %d (%s): selection caught %d of %d Gaussians (means within %s .. %s) -> %d Gaussians",
                 spec.name, i, op.kind, n, before, bounds[0], bounds[1], len(g))
        report.append(row)
    return g, report
