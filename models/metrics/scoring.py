"""Score renders against ground truth per layer (diffuse, specular, final) on the test split.

Ground truth (``ground_truth``): "final" is the capture's diffuse + specular + emission (its R,G,B), "diffuse" is
diffuse + emission (``models.capture.layers.diffuse_radiance``: the Gaussians carry lights seen directly as
view-independent radiance, so the rendered diffuse layer holds them), "specular" the specular layer. A capture
without an ``emission`` layer scores against diffuse, specular and their sum, as before.

Per view and layer (``score_layer``; definitions in ``DEFINITIONS``, written into metrics.json), HDR-safe:
``psnr_<layer>`` / ``ssim_<layer>`` linear with the ground truth's peak (``peak_<layer>``), the headline
``psnr_<layer>_tonemapped`` / ``ssim_<layer>_tonemapped`` after mu-law on radiance / peak (``models.metrics.hdr``);
for comparison with LDR numbers ``psnr_<layer>_clamped`` (clamp to [0, 1], peak 1) and ``psnr_<layer>_srgb`` /
``ssim_<layer>_srgb`` (clamp + sRGB curve, the PNGs); ``saturated`` lists the views and layers where a score
has stopped measuring (``hdr.saturation``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.capture import Capture, read_view_buffers
from models.capture.color import linear_to_srgb  # the display tonemap: clamp + sRGB curve
from models.capture.layers import SCORED, diffuse_radiance

from . import hdr
from .image import SSIM_DEFINITION, psnr, ssim

DEFINITIONS = {
    "psnr_<layer>": "linear radiance, no clamp, peak = peak_<layer> (max of the view's ground-truth layer over "
                    "pixels and channels; 1 if that is not positive)",
    "ssim_<layer>": "SSIM of linear radiance, no clamp, data range L = peak_<layer>",
    "psnr_<layer>_tonemapped": "headline: PSNR-mu, mu-law (mu = 5000) of radiance / peak_<layer>, no clamp "
                               "(Kalantari & Ramamoorthi 2017), peak 1",
    "ssim_<layer>_tonemapped": "headline: SSIM of the same mu-law images, L = 1",
    "psnr_<layer>_clamped": "radiance clamped to [0, 1], peak 1 (psnr_<layer> before HDR-safe scoring; blind above 1)",
    "psnr_<layer>_srgb": "clamp to [0, 1] + sRGB curve, as the PNGs (psnr_<layer>_tonemapped before; blind above 1)",
    "ssim_<layer>_srgb": "SSIM of the same sRGB images, L = 1 (ssim_<layer>_tonemapped before)",
    "<region>_psnr_<layer>": "as psnr_<layer> (the whole view's peak) on the region's pixels",
    "ssim": SSIM_DEFINITION,
    "saturated": f"views / layers where > {hdr.SATURATED_FRACTION:.0%} of ground-truth pixels exceed 1 (the clamped "
                 f"scores ignore errors there) or a PSNR is > {hdr.SATURATED_DB:.0f} dB or not finite",
}


def ground_truth(buffers: dict) -> dict[str, np.ndarray]:
    """The scored layers of a capture view: diffuse (+ emission), specular, final = their sum."""
    diffuse = diffuse_radiance(buffers)
    return {"diffuse": diffuse, "specular": buffers["specular"], "final": diffuse + buffers["specular"]}


def ground_truth_names(capture: Capture) -> dict[str, str]:
    """What each scored layer's ground truth is, for metrics.json."""
    emission = any("emission" in v.buffers for v in capture.split("test"))
    plus = " + emission" if emission else ""
    return {"diffuse": f"diffuse{plus}", "specular": "specular", "final": f"diffuse + specular{plus}"}


def score_layer(pred: np.ndarray, target: np.ndarray, layer: str) -> dict[str, float]:
    """Every score of one layer of one view (keys of ``DEFINITIONS`` with ``<layer>`` filled in), plus
    ``peak_<layer>`` and ``over1_<layer>`` (fraction of ground-truth pixels above 1)."""
    top = hdr.peak(target)
    mp, mt = hdr.mu_law(pred, top), hdr.mu_law(target, top)
    sp, st = linear_to_srgb(pred), linear_to_srgb(target)
    return {
        f"psnr_{layer}": psnr(pred, target, peak=top),
        f"ssim_{layer}": ssim(pred, target, peak=top),
        f"psnr_{layer}_tonemapped": psnr(mp, mt),
        f"ssim_{layer}_tonemapped": ssim(mp, mt),
        f"psnr_{layer}_clamped": psnr(np.clip(pred, 0, 1), np.clip(target, 0, 1)),
        f"psnr_{layer}_srgb": psnr(sp, st),
        f"ssim_{layer}_srgb": ssim(sp, st),
        f"peak_{layer}": top,
        f"over1_{layer}": hdr.over_one(target),
    }


def region_mask(view, box_min, box_max) -> np.ndarray:
    """[H, W] bool: pixels whose ground-truth surface point (camera + ray x depth) lies in the world box."""
    points = view.camera.origin + view.camera.ray_directions() * view.buffers["depth"].astype(np.float64)
    inside = np.all((points >= np.asarray(box_min)) & (points <= np.asarray(box_max)), axis=-1)
    if "mask" in view.buffers:
        inside &= view.buffers["mask"][..., 0] > 0.5
    return inside


def evaluate_renders(capture: Capture, renders: Path, regions: dict | None = None) -> dict:
    """Per-view and mean metrics (module docstring); ``regions``: name -> {min: [x, y, z], max: [x, y, z]} world
    boxes, each scored (PSNR per layer, linear, the view's peak) on the pixels whose ground-truth surface is
    inside it. ``saturated``: [{view, layer, reasons}] (empty when every score measures something)."""
    per_view, saturated = {}, []
    for view in capture.split("test"):
        exr = renders / f"{view.name}.exr"
        if not exr.is_file():
            raise FileNotFoundError(f"render of test view {view.name!r} missing: {exr}")
        pred = read_view_buffers(exr, view.camera.height, view.camera.width)
        gt = ground_truth(view.buffers)
        pred = {"diffuse": pred["diffuse"], "specular": pred["specular"], "final": pred["rgb"]}
        row = {}
        for layer in SCORED:
            scores = score_layer(pred[layer], gt[layer], layer)
            row.update(scores)
            reasons = hdr.saturation({k: v for k, v in scores.items() if k.startswith("psnr_")},
                                     scores[f"over1_{layer}"])
            if reasons:
                saturated.append({"view": view.name, "layer": layer, "reasons": reasons})
        for name, box in (regions or {}).items():
            m = region_mask(view, box["min"], box["max"])
            row[f"{name}_pixels"] = int(m.sum())
            for layer in SCORED:
                if m.any():
                    row[f"{name}_psnr_{layer}"] = psnr(pred[layer], gt[layer], m, peak=row[f"peak_{layer}"])
        per_view[view.name] = row
    keys = dict.fromkeys(k for r in per_view.values() for k in r)
    mean = {k: float(np.mean([r[k] for r in per_view.values() if k in r])) for k in keys}
    return {"mean": mean, "views": per_view, "saturated": saturated,
            "ground_truth": ground_truth_names(capture), "definitions": DEFINITIONS,
            "lpips": "not computed: LPIPS needs network weights that cannot be fetched here"}
