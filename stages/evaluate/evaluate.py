"""Compare renders with ground truth per layer (diffuse, specular, final) on the test split.

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
from stages.render.render import tonemap

from .metrics import psnr, ssim

LAYERS = ("diffuse", "specular", "final")


def evaluate_renders(capture: Capture, renders: Path) -> dict:
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
        for layer in LAYERS:
            p, t = np.clip(pred[layer], 0, 1), np.clip(gt[layer], 0, 1)
            row[f"psnr_{layer}"] = psnr(p, t)
            row[f"ssim_{layer}"] = ssim(p, t)
            row[f"psnr_{layer}_tonemapped"] = psnr(tonemap(pred[layer]), tonemap(gt[layer]))
            row[f"ssim_{layer}_tonemapped"] = ssim(tonemap(pred[layer]), tonemap(gt[layer]))
        per_view[view.name] = row
    keys = next(iter(per_view.values())).keys() if per_view else []
    mean = {k: float(np.mean([r[k] for r in per_view.values()])) for k in keys}
    return {"mean": mean, "views": per_view, "lpips": "not computed: LPIPS needs network weights that cannot be fetched here"}
