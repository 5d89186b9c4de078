"""Scoring an edit: the edited render against the edited ground truth, next to doing nothing (the unedited
render against the same truth), on every pixel and on the pixels the edit changed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.ndimage import label, uniform_filter

from models.capture import Capture, read_view_buffers
from models.capture.layers import SCORED

from .hdr import mu_law, peak
from .image import mse_to_psnr, psnr
from .scoring import evaluate_renders, ground_truth

CHANGED_THRESHOLD = 0.02  # a pixel is "changed by the edit" where ground truth final moved more than this x white
# ... after a 3x3 box filter of the signed difference: the two ground truths' Monte Carlo noise decorrelates
# wherever paths reach the edited object (indirect light), and unfiltered it marks scattered pixels everywhere
CHANGED_FILTER = 3
CHANGED_MIN_PIXELS = CHANGED_FILTER  # ... and a changed pixel lies in a connected (8-neighbour) group of at least
# this many: a real change, box-filtered, stays above the threshold over at least the filter's width (a thin pole
# moved: a strip 3 pixels wide; one strong pixel: a 3x3 block); groups of 1-2 pixels are the noise's filtered sum
# crossing the threshold by chance (zoo_thin move_rack: one view's whole "changed region" was 2 such pixels, and
# each view weighs the same in the mean)
MIDDLE_GREY = 0.18  # the key a capture's exposure maps to middle grey (Reinhard et al. 2002, "Photographic Tone
# Reproduction for Digital Images": a = 0.18); white = key / MIDDLE_GREY
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709


def capture_white(capture: Capture) -> float:
    """The radiance the changed-pixel rule calls white, in the capture's own units: the key of the unedited
    capture (the log-average luminance of its ground-truth final over every pixel above zero of every view that
    has diffuse and specular, Reinhard et al. 2002) divided by middle grey (0.18). A capture x 1000 has a white
    x 1000, so the changed pixels do not depend on the units radiance is written in; 1.0 where no pixel is
    positive. The zoo's rooms: 0.55-1.25."""
    total, count = 0.0, 0
    for view in capture.views:
        if "diffuse" not in view.buffers or "specular" not in view.buffers:
            continue
        lum = ground_truth(view.buffers)["final"].astype(np.float64) @ _LUMINANCE
        lum = lum[lum > 0]
        total, count = total + float(np.log(lum).sum()), count + lum.size
    return float(np.exp(total / count)) / MIDDLE_GREY if count else 1.0


def _final(buffers: dict, white: float) -> np.ndarray:
    """Ground-truth final (with emission) over ``white``, clamped to [0, 1]: only to find the changed pixels, not
    to score."""
    return np.clip(ground_truth(buffers)["final"] / white, 0, 1)


def changed_region_metrics(capture: Capture, truth: Capture, renders: Path, baseline_renders: Path) -> dict:
    """PSNR per layer on the pixels the edit changed (box-filtered ground-truth final, over the unedited capture's
    white (``capture_white``) and clamped to [0, 1], moved > CHANGED_THRESHOLD, in a connected group of at least CHANGED_MIN_PIXELS):
    the edited render vs the edited ground truth, and, as the do-nothing reference, the unedited render vs
    the same edited ground truth. ``<edited|unedited>_psnr_<layer>_tonemapped`` (the headline, as the scene's
    ``psnr_<layer>_tonemapped``): mu-law at the peak of the edited ground truth's final image; beside it
    ``<edited|unedited>_psnr_<layer>``: linear, no clamp, at the peak of that layer of the edited ground truth's
    whole view. The linear score weighs a window's or a lamp's error (radiance up to 10-100x a lit wall's) over
    everything else the edit changed. Those are means over the views that have changed pixels, each view
    weighing the same; ``pooled_<edited|unedited>_psnr_<layer>_tonemapped`` is one PSNR over every view's changed
    pixels together, each pixel weighing the same (zoo_mirror_metal's frosted_mirror: its mirror's 974 changed
    pixels in one view and 10 of Monte Carlo noise and indirect light in another counted half and half in the
    mean); ``changed_pixels``: their number over all views; ``changed_noise_pixels``: those above the threshold
    left out as groups of fewer than CHANGED_MIN_PIXELS; ``changed_white``: the white they were found at."""
    before = {v.name: v for v in capture.split("test")}
    white = capture_white(capture)
    out: dict[str, list] = {}
    pooled: dict[str, list] = {}  # every view's changed pixels' tonemapped squared errors, per key (pooled_*)
    changed = 0
    for view in truth.split("test"):
        if view.name not in before:
            raise ValueError(f"ground-truth view {view.name!r} has no test view of that name in the capture")
        h, w = view.camera.height, view.camera.width
        gt = ground_truth(view.buffers)
        diff = _final(view.buffers, white) - _final(before[view.name].buffers, white)
        diff = uniform_filter(diff, (CHANGED_FILTER, CHANGED_FILTER, 1))
        mask = np.abs(diff).max(axis=-1) > CHANGED_THRESHOLD
        groups, _ = label(mask, structure=np.ones((3, 3)))
        small = np.bincount(groups.ravel()) < CHANGED_MIN_PIXELS
        small[0] = False  # the unchanged pixels
        out.setdefault("changed_noise_pixels", []).append(int(small[groups].sum()))
        mask &= ~small[groups]
        out.setdefault("changed_fraction", []).append(float(mask.mean()))
        changed += int(mask.sum())
        if not mask.any():
            continue
        top = peak(gt["final"])
        for key, folder in (("edited", renders), ("unedited", baseline_renders)):
            pred = read_view_buffers(folder / f"{view.name}.exr", h, w)
            pred = {"diffuse": pred["diffuse"], "specular": pred["specular"], "final": pred["rgb"]}
            for layer in SCORED:
                out.setdefault(f"{key}_psnr_{layer}", []).append(
                    psnr(pred[layer], gt[layer], mask, peak=peak(gt[layer])))
                a, b = mu_law(pred[layer], top), mu_law(gt[layer], top)
                out.setdefault(f"{key}_psnr_{layer}_tonemapped", []).append(psnr(a, b, mask))
                pooled.setdefault(f"pooled_{key}_psnr_{layer}_tonemapped", []).append(
                    ((np.asarray(a, np.float64) - b) ** 2)[mask].ravel())
    noise = int(sum(out.pop("changed_noise_pixels", [])))
    return ({k: float(np.mean(v)) for k, v in out.items()} | {"changed_pixels": changed, "changed_noise_pixels": noise}
            | {k: mse_to_psnr(float(np.concatenate(v).mean())) for k, v in pooled.items()} | {"changed_white": white})


def _gain(changed: dict, key: str) -> float | None:
    """The edited score minus the unedited one, ``key`` naming both with ``{kind}``; None where either is
    missing."""
    a, b = (changed.get(key.format(kind=kind)) for kind in ("edited", "unedited"))
    return None if a is None or b is None else a - b


def changed_region_pooled_gain(changed: dict) -> float | None:
    """The tonemapped gain in dB of the edited render over the unedited one on every view's changed pixels
    pooled (``pooled_<edited|unedited>_psnr_final_tonemapped``: one PSNR over all of them, each pixel weighing
    the same); None where the edit was scored before they existed or no pixel changed."""
    return _gain(changed, "pooled_{kind}_psnr_final_tonemapped")


def changed_region_gains(changed: dict) -> tuple[float | None, float | None]:
    """(tonemapped, linear) gain in dB of the edited render over the unedited one on the changed pixels (the
    ``changed_region`` of ``evaluate_edit``); None where the scores are missing (no pixel changed, or an edit
    scored before the tonemapped ones existed)."""
    return _gain(changed, "{kind}_psnr_final_tonemapped"), _gain(changed, "{kind}_psnr_final")


def evaluate_edit(capture: Capture, truth: Capture, renders: Path, baseline_renders: Path) -> dict:
    """Edit metrics: the edited render vs the edited ground truth (every layer, as stages/evaluate), the
    unedited render vs the unedited ground truth (the scene's own metrics), and both on the changed pixels."""
    edited = evaluate_renders(truth, renders)
    unedited = evaluate_renders(capture, baseline_renders)
    keys = [f"{kind}_{layer}{suffix}" for kind, suffix in (("psnr", ""), ("ssim", ""), ("psnr", "_tonemapped"),
                                                          ("ssim", "_tonemapped"), ("psnr", "_clamped"),
                                                          ("psnr", "_srgb")) for layer in SCORED]
    return {
        "edited_vs_truth": {k: edited["mean"][k] for k in keys},
        "unedited_vs_truth": {k: unedited["mean"][k] for k in keys},
        "changed_region": changed_region_metrics(capture, truth, renders, baseline_renders),
        "views": {"edited": edited["views"], "unedited": unedited["views"]},
        "saturated": {"edited": edited["saturated"], "unedited": unedited["saturated"]},
        "definitions": edited["definitions"],
        "changed_threshold": CHANGED_THRESHOLD,
        "changed_filter": CHANGED_FILTER,
        "changed_min_pixels": CHANGED_MIN_PIXELS,
    }
