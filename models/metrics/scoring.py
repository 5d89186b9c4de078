"""Score renders against ground truth per layer (diffuse, specular, final) on the test split.

Ground truth "final" is diffuse + specular: the light sources seen directly
(the capture's ``emission`` layer) are not part of the reconstructed scene.
Metrics are reported in linear space (radiance clamped to [0, 1], peak 1) and
after the display tonemap of the PNGs (clamp + sRGB curve), which is what
image comparisons in papers use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.capture import Capture, read_view_buffers
from models.capture.color import linear_to_srgb  # the display tonemap: clamp + sRGB curve
from models.capture.layers import SCORED

from .image import psnr, ssim


def region_mask(view, box_min, box_max) -> np.ndarray:
    """[H, W] bool: pixels whose ground-truth surface point (camera + ray x depth) lies in the world box."""
    points = view.camera.origin + view.camera.ray_directions() * view.buffers["depth"].astype(np.float64)
    inside = np.all((points >= np.asarray(box_min)) & (points <= np.asarray(box_max)), axis=-1)
    if "mask" in view.buffers:
        inside &= view.buffers["mask"][..., 0] > 0.5
    return inside


def evaluate_renders(capture: Capture, renders: Path, regions: dict | None = None) -> dict:
    """Per-view and mean metrics; ``regions``: name -> {min: [x, y, z], max: [x, y, z]} world boxes, each
    scored (PSNR per layer, linear) on the pixels whose ground-truth surface lies inside it."""
    per_view = {}
    for view in capture.split("test"):
        exr = renders / f"{view.name}.exr"
        if not exr.is_file():
            raise FileNotFoundError(f"render of test view {view.name!r} missing: {exr}")
        pred = read_view_buffers(exr, view.camera.height, view.camera.width)
        gt = {"diffuse": view.buffers["diffuse"], "specular": view.buffers["specular"]}
        gt["final"] = gt["diffuse"] + gt["specular"]
        pred = {"diffuse": pred["diffuse"], "specular": pred["specular"], "final": pred["rgb"]}
        row = {}
        for layer in SCORED:
            p, t = np.clip(pred[layer], 0, 1), np.clip(gt[layer], 0, 1)
            row[f"psnr_{layer}"] = psnr(p, t)
            row[f"ssim_{layer}"] = ssim(p, t)
            row[f"psnr_{layer}_tonemapped"] = psnr(linear_to_srgb(pred[layer]), linear_to_srgb(gt[layer]))
            row[f"ssim_{layer}_tonemapped"] = ssim(linear_to_srgb(pred[layer]), linear_to_srgb(gt[layer]))
        for name, box in (regions or {}).items():
            m = region_mask(view, box["min"], box["max"])
            row[f"{name}_pixels"] = int(m.sum())
            for layer in SCORED:
                if m.any():
                    row[f"{name}_psnr_{layer}"] = psnr(np.clip(pred[layer], 0, 1), np.clip(gt[layer], 0, 1), m)
        per_view[view.name] = row
    keys = dict.fromkeys(k for r in per_view.values() for k in r)
    mean = {k: float(np.mean([r[k] for r in per_view.values() if k in r])) for k in keys}
    return {"mean": mean, "views": per_view, "lpips": "not computed: LPIPS needs network weights that cannot be fetched here"}
