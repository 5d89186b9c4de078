"""The edit stage's library: apply a named edit, render the edited scene, score it against ground truth."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import uniform_filter
from tqdm import tqdm

from models.capture import Capture, read_view_buffers
from models.gaussians import Gaussians
from stages.evaluate.evaluate import LAYERS, evaluate_renders
from stages.evaluate.metrics import psnr
from stages.render.render import RenderConfig, render_view, write_layers

from .ops import apply_op
from .select import select
from .spec import EditSpec, EditSpecError

log = logging.getLogger("stages.edit")

CHANGED_THRESHOLD = 0.02  # a pixel is "changed by the edit" where ground truth final moved more than this
# ... after a 3x3 box filter of the signed difference: the two ground truths' Monte Carlo noise decorrelates
# wherever paths reach the edited object (indirect light), and unfiltered it marks scattered pixels everywhere
CHANGED_FILTER = 3


def apply_edit(g: Gaussians, spec: EditSpec) -> tuple[Gaussians, list[dict]]:
    """``g`` with every op of ``spec`` applied in order, and per op what its selection caught.
    Raises EditSpecError when a selection catches no Gaussian."""
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
        g = apply_op(g, op, mask)
        if shared is not None and len(g) != before:  # keep the edit's selection aligned with the model
            shared = shared[~mask] if op.kind == "delete" else torch.cat([shared, shared.new_zeros(len(g) - before)])
        row = {"op": op.kind, "selection": sel.text, "selected": n, "selected_bounds": bounds,
               "gaussians_before": before, "gaussians_after": len(g)}
        log.info("edit %r op %d (%s): selection caught %d of %d Gaussians (means within %s .. %s) -> %d Gaussians",
                 spec.name, i, op.kind, n, before, bounds[0], bounds[1], len(g))
        report.append(row)
    return g, report


def render_test_views(tracer, capture: Capture, g: Gaussians, config: RenderConfig, out_dir: Path) -> dict:
    """Render the capture's test views (train if none) into ``out_dir`` (EXR + png/); seconds per view."""
    import time

    tracer.update(g, rebuild=True)
    generator = torch.Generator().manual_seed(config.seed)
    timings = {}
    for view in tqdm(capture.split("test") or capture.split("train"), desc="render edit", unit="view"):
        t0 = time.perf_counter()
        img = render_view(tracer.trace, view.camera, g, config, generator)
        timings[view.name] = round(time.perf_counter() - t0, 3)
        write_layers(out_dir, view.name, img)
    return timings


def _final(buffers: dict) -> np.ndarray:
    return np.clip(buffers["diffuse"] + buffers["specular"], 0, 1)


def changed_region_metrics(capture: Capture, truth: Capture, renders: Path, baseline_renders: Path) -> dict:
    """PSNR per layer on the pixels the edit changed (box-filtered ground-truth final moved > CHANGED_THRESHOLD):
    the edited render vs the edited ground truth, and, as the do-nothing reference, the unedited render vs
    the same edited ground truth."""
    before = {v.name: v for v in capture.split("test")}
    out: dict[str, list] = {}
    for view in truth.split("test"):
        if view.name not in before:
            raise ValueError(f"ground-truth view {view.name!r} has no test view of that name in the capture")
        h, w = view.camera.height, view.camera.width
        gt = {"diffuse": view.buffers["diffuse"], "specular": view.buffers["specular"]}
        gt["final"] = gt["diffuse"] + gt["specular"]
        diff = _final(view.buffers) - _final(before[view.name].buffers)
        diff = uniform_filter(diff, (CHANGED_FILTER, CHANGED_FILTER, 1))
        mask = np.abs(diff).max(axis=-1) > CHANGED_THRESHOLD
        out.setdefault("changed_fraction", []).append(float(mask.mean()))
        if not mask.any():
            continue
        for key, folder in (("edited", renders), ("unedited", baseline_renders)):
            pred = read_view_buffers(folder / f"{view.name}.exr", h, w)
            pred = {"diffuse": pred["diffuse"], "specular": pred["specular"], "final": pred["rgb"]}
            for layer in LAYERS:
                out.setdefault(f"{key}_psnr_{layer}", []).append(
                    psnr(np.clip(pred[layer], 0, 1), np.clip(gt[layer], 0, 1), mask))
    return {k: float(np.mean(v)) for k, v in out.items()}


def evaluate_edit(capture: Capture, truth: Capture, renders: Path, baseline_renders: Path) -> dict:
    """Edit metrics: the edited render vs the edited ground truth (every layer, as stages/evaluate), the
    unedited render vs the unedited ground truth (the scene's own metrics), and both on the changed pixels."""
    edited = evaluate_renders(truth, renders)
    unedited = evaluate_renders(capture, baseline_renders)
    keys = [f"psnr_{layer}" for layer in LAYERS] + [f"ssim_{layer}" for layer in LAYERS] + \
        [f"psnr_{layer}_tonemapped" for layer in LAYERS]
    return {
        "edited_vs_truth": {k: edited["mean"][k] for k in keys},
        "unedited_vs_truth": {k: unedited["mean"][k] for k in keys},
        "changed_region": changed_region_metrics(capture, truth, renders, baseline_renders),
        "views": {"edited": edited["views"], "unedited": unedited["views"]},
        "changed_threshold": CHANGED_THRESHOLD,
        "changed_filter": CHANGED_FILTER,
    }
