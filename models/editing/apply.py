"""Apply a named edit to a Gaussian scene: every op of the spec on its selection, in order."""

from __future__ import annotations

import logging

import torch

from models.gaussians import Gaussians
from models.pathtrace.paths import PathConfig, TraceFn

from .ops import apply_op
from .relight import DIFFUSE_OPS, GEOMETRY_OPS, relight
from .select import select
from .spec import EditSpec, EditSpecError

log = logging.getLogger("models.editing")


def apply_edit(g: Gaussians, spec: EditSpec, trace_fn: TraceFn | None = None,
               path: PathConfig | None = None) -> tuple[Gaussians, list[dict]]:
    """``g`` with every op of ``spec`` applied in order, and per op what its selection caught; then, where the spec
    says so (``relight``: auto = after ops that move geometry, relight.py), the light follows the edit (a last
    report row, op ``relight``). ``trace_fn`` (``Tracer.trace``) and ``path`` (the model's path settings) serve
    the ops that trace the scene (``set_albedo``, the relight); without a trace_fn those raise, and an auto
    relight is left out (the viewer's live edits). Raises EditSpecError when a selection catches no Gaussian or an
    op refuses its input."""
    report = []
    original = g
    source = torch.arange(len(g))  # the row of the input each row of the model comes from
    edited = torch.zeros(len(g), dtype=torch.bool)  # rows of the input that a geometry op moved, copied or deleted
    moved = torch.zeros(len(g), dtype=torch.bool)  # rows of the model that a geometry op moved or created
    fixed = torch.zeros(len(g), dtype=torch.bool)  # rows of the model whose diffuse an op set
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
        mask = mask.cpu()  # the bookkeeping below lives on the CPU whatever the model's device
        if op.kind in GEOMETRY_OPS:
            edited[source[mask]] = True
        if op.kind == "delete":
            source, moved, fixed = source[~mask], moved[~mask], fixed[~mask]
        elif op.kind == "duplicate":
            source, moved, fixed = torch.cat([source, source[mask]]), torch.cat([moved, mask[mask]]), \
                torch.cat([fixed, fixed[mask]])
        elif op.kind in GEOMETRY_OPS:
            moved |= mask
        if op.kind in DIFFUSE_OPS:
            fixed |= torch.cat([mask, mask.new_zeros(len(g) - len(mask))])
        row = {"op": op.kind, "selection": sel.text, "selected": n, "selected_bounds": bounds,
               "gaussians_before": before, "gaussians_after": len(g)}
        log.info("edit %r op %d (%s): selection caught %d of %d Gaussians (means within %s .. %s) -> %d Gaussians",
                 spec.name, i, op.kind, n, before, bounds[0], bounds[1], len(g))
        report.append(row)
    wanted = spec.relight is True or (spec.relight == "auto" and any(op.kind in GEOMETRY_OPS for op in spec.ops))
    if wanted and trace_fn is None and spec.relight is True:
        raise EditSpecError(f"edit {spec.name!r}: relight traces the scene to follow the light: it needs a tracer "
                            "(apply_edit(..., trace_fn=tracer.trace, path=...), as the edit stage passes)")
    if wanted and trace_fn is not None:
        # with relight: true a recolour (set_diffuse ...) relights too: what it recoloured lights its neighbours
        changed_before = edited | torch.zeros(len(original), dtype=torch.bool).index_fill_(0, source[fixed], True)
        g, stats = relight(original, g, source, changed_before, moved | fixed, fixed, trace_fn, path)
        log.info("edit %r relight: %s", spec.name, stats)
        report.append({"op": "relight", **stats})
    return g, report
