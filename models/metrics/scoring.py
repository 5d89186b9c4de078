"""Score renders against ground truth per layer (diffuse, specular, final) on the test split.

Ground truth (``ground_truth``): "final" is the capture's diffuse + specular + emission (its R,G,B), "diffuse" is
diffuse + emission (``models.capture.layers.diffuse_radiance``: the Gaussians carry lights seen directly as
view-independent radiance, so the rendered diffuse layer holds them), "specular" the specular layer. A capture
without an ``emission`` layer scores against diffuse, specular and their sum, as before.

Per view and layer (``score_layer``; definitions in ``DEFINITIONS``, written into metrics.json), HDR-safe:
``psnr_<layer>`` / ``ssim_<layer>`` linear at the view's reference peak (``peak``: the maximum of its ground-truth
final image, the same for every layer), the headline ``psnr_<layer>_tonemapped`` / ``ssim_<layer>_tonemapped``
after mu-law on radiance / peak (``models.metrics.hdr``). One peak per view, not one per layer: a layer is a
part of one image, and a view with almost no reflection (specular peak 0.02 in an image peaking at 0.29) would
otherwise have its specular errors magnified 15 times over what they are in the picture (``peak_<layer>`` still
records each layer's own maximum);
for comparison with LDR numbers ``psnr_<layer>_clamped`` (clamp to [0, 1], peak 1) and ``psnr_<layer>_srgb`` /
``ssim_<layer>_srgb`` (clamp + sRGB curve, the PNGs); ``saturated`` lists the views and layers where a score
has stopped measuring (``hdr.saturation``). With LPIPS weights (``lpips.load_lpips``, the evaluate stage's
``evaluate.lpips``) also ``lpips_<layer>`` on the same sRGB images; ``lpips`` says which weights, or how to turn it on.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.capture import Capture, read_view_buffers
from models.capture.color import linear_to_srgb  # the display tonemap: clamp + sRGB curve
from models.capture.layers import SCORED, diffuse_radiance

from . import hdr
from .image import SSIM_DEFINITION, psnr, ssim
from .lpips import MIN_SIZE as LPIPS_MIN_SIZE
from .lpips import LpipsWeights, lpips_images

SHINY_F0 = 0.3  # ground-truth F0 above this: a metal / mirror pixel (normal scores)
DARK = 1e-4  # a ground-truth layer below this x the view's peak in every channel is dark (dark_error_share)

DEFINITIONS = {
    "peak": "the view's reference peak: max of its ground-truth final image (diffuse + specular + emission) over "
            "pixels and channels, 1 if that is not positive; every layer of the view is scored at it",
    "peak_<layer>": "max of the view's ground-truth layer (information only; scores use peak)",
    "psnr_<layer>": "linear radiance, no clamp, at the view's peak",
    "ssim_<layer>": "SSIM of linear radiance, no clamp, data range L = the view's peak",
    "psnr_<layer>_tonemapped": "headline: PSNR-mu, mu-law (mu = 5000) of radiance / the view's peak, no clamp "
                               "(Kalantari & Ramamoorthi 2017), peak 1",
    "ssim_<layer>_tonemapped": "headline: SSIM of the same mu-law images, L = 1",
    "psnr_<layer>_clamped": "radiance clamped to [0, 1], peak 1 (psnr_<layer> before HDR-safe scoring; blind above 1)",
    "psnr_<layer>_srgb": "clamp to [0, 1] + sRGB curve, as the PNGs (psnr_<layer>_tonemapped before; blind above 1)",
    "ssim_<layer>_srgb": "SSIM of the same sRGB images, L = 1 (ssim_<layer>_tonemapped before)",
    "lpips_<layer>": "LPIPS v0.1, AlexNet (Zhang et al. 2018), of the clamp + sRGB images (as ssim_<layer>_srgb) "
                     "mapped to [-1, 1]; lower is better; only with evaluate.lpips (see 'lpips')",
    "<region>_psnr_<layer>": "as psnr_<layer> (the view's peak) on the region's pixels: it moves with whatever "
                             "else the view shows (a lamp in view raises the peak and the score)",
    "<region>_psnr_<layer>_clamped": "as psnr_<layer>_clamped (peak 1) on the region's pixels: the same scale in "
                                     "every view (the region scores before HDR-safe scoring were these)",
    "<region>_psnr_<layer>_tonemapped": "as psnr_<layer>_tonemapped (mu-law at the view's peak) on the region's "
                                        "pixels",
    "seen_fraction": "share of the view's pixels whose ground-truth surface point a training camera sees directly "
                     "(projected into each training view, its distance within 3 % of that view's depth buffer at "
                     "one of the 3 x 3 nearest pixels); pixels with no surface (depth not finite or <= 0) are in "
                     "neither part. Needs depth in the training views, else absent",
    "<seen|unseen>_psnr_<layer>_tonemapped": "as psnr_<layer>_tonemapped on the pixels a training camera sees "
                                             "directly / does not (seen_fraction): what cannot be learnt from the "
                                             "training views but through reflections or priors",
    "unseen_error_share_<layer>": "share of the view's tonemapped squared error (psnr_<layer>_tonemapped) on the "
                                  "unseen pixels",
    "dark_fraction_<layer>": f"share of the view's pixels where the ground-truth layer is dark: every channel "
                             f"below {DARK:g} x the view's peak (the specular of a matte surface, the diffuse of "
                             "a metal one: exactly 0 in a synthetic truth)",
    "dark_error_share_<layer>": "share of the view's tonemapped squared error (psnr_<layer>_tonemapped) on those "
                                "pixels: light where there is none. The mu-law reads 0.02 under a peak of 10 as "
                                "0.3 of its range, so a small leak there costs much (zoo_corridor's diffuse: 75-94 "
                                "%, the metal walls' diffuse)",
    "psnr_final_tonemapped_true_<diffuse|specular>": "what limits the final image: psnr_final_tonemapped of our "
                                                     "render with the ground truth's diffuse (+ emission) / specular "
                                                     "layer in place of ours; the layer whose truth lifts it most is "
                                                     "the one to improve",
    "normal_angle_deg": "median angle (degrees) between our rendered normal (normalised) and the ground truth's, over "
                        "the pixels where both exist; a novel view's normals are what its reflections are made of",
    "shiny_normal_angle_deg[_p90]": "the same (median, 90th percentile) on the mirror-like and metal pixels "
                                    f"(ground-truth F0 > {SHINY_F0}), where a few degrees turn a reflection",
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


def score_layer(pred: np.ndarray, target: np.ndarray, layer: str, reference: float | None = None) -> dict[str, float]:
    """Every score of one layer of one view (keys of ``DEFINITIONS`` with ``<layer>`` filled in), plus
    ``peak_<layer>`` (the layer's own maximum) and ``over1_<layer>`` (fraction of ground-truth pixels above 1).
    ``reference``: the peak the linear and tonemapped scores are taken at (the view's ``peak``; default: the
    layer's own)."""
    top = hdr.peak(target) if reference is None else reference
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
        f"peak_{layer}": hdr.peak(target),
        f"over1_{layer}": hdr.over_one(target),
    }


def surface_points(view) -> tuple[np.ndarray, np.ndarray]:
    """([H, W, 3] float64 each pixel's ground-truth surface point, camera + unit ray x depth (a distance), [H, W]
    bool the pixel has a surface: a finite depth > 0; the others get the camera's centre)."""
    depth = view.buffers["depth"][..., 0].astype(np.float64)
    surface = np.isfinite(depth) & (depth > 0)
    return view.camera.origin + view.camera.ray_directions() * np.where(surface, depth, 0.0)[..., None], surface


def region_mask(view, box_min, box_max) -> np.ndarray:
    """[H, W] bool: pixels whose ground-truth surface point (camera + ray x depth) lies in the world box."""
    points, surface = surface_points(view)
    inside = surface & np.all((points >= np.asarray(box_min)) & (points <= np.asarray(box_max)), axis=-1)
    if "mask" in view.buffers:
        inside &= view.buffers["mask"][..., 0] > 0.5
    return inside


SEEN_TOLERANCE = 0.03  # relative distance within which a training view's depth buffer counts as the same surface


def seen_mask(view, train_views) -> tuple[np.ndarray, np.ndarray] | None:
    """([H, W] bool seen, [H, W] bool has a surface) of a test ``view``: its ground-truth surface points (camera +
    ray x depth) that some training view sees directly (projects inside it, in front, and its depth buffer at one
    of the 3 x 3 pixels nearest the projection is within ``SEEN_TOLERANCE`` of the point's distance: a neighbour
    keeps edges and grazing surfaces seen). None when a training view has no depth buffer (nothing to test)."""
    if not train_views or any("depth" not in t.buffers for t in train_views):
        return None
    points, surface = surface_points(view)
    points = points.reshape(-1, 3)
    todo = surface.reshape(-1).copy()
    seen = np.zeros(len(points), dtype=bool)
    for t in train_views:
        cam = t.camera
        ref = t.buffers["depth"][..., 0].astype(np.float64)
        idx = np.flatnonzero(todo & ~seen)
        if not len(idx):
            break
        u, v, z = cam.project(points[idx])
        dist = np.linalg.norm(points[idx] - cam.origin, axis=1)
        front = z > 1e-9
        iu, iv = np.floor(np.where(front, u, -10)).astype(np.int64), np.floor(np.where(front, v, -10)).astype(np.int64)
        hit = np.zeros(len(idx), dtype=bool)
        for du in (-1, 0, 1):
            for dv in (-1, 0, 1):
                cu, cv = iu + du, iv + dv
                ok = front & (cu >= 0) & (cu < cam.width) & (cv >= 0) & (cv < cam.height)
                r = np.full(len(idx), np.nan)
                r[ok] = ref[cv[ok], cu[ok]]
                with np.errstate(invalid="ignore"):
                    hit |= ok & (np.abs(r - dist) <= SEEN_TOLERANCE * dist)
        seen[idx[hit]] = True
    return seen.reshape(surface.shape), surface


LPIPS_OFF = ("not computed: LPIPS needs local weight files (nothing is downloaded); turn it on with evaluate.lpips: "
             "{backbone: <torchvision AlexNet state dict, alexnet-owt-7be5be79.pth>, lin: <the lpips package's "
             "weights/v0.1/alex.pth>} in the scene config, snakemake --config or stages.evaluate --config-json")


def _seen_scores(view, train, tonemapped: dict) -> dict:
    """seen_fraction, <seen|unseen>_psnr_<layer>_tonemapped, unseen_error_share_<layer> (``DEFINITIONS``) of a
    test view (``tonemapped``: layer -> (ours, truth) mu-law images); {} when the training views have no depth."""
    masks = seen_mask(view, train)
    if masks is None:
        return {}
    seen, surface = masks
    unseen = surface & ~seen
    row = {"seen_fraction": float(seen.sum() / max(surface.sum(), 1))}
    for layer in SCORED:
        mp, mt = tonemapped[layer]
        err = ((mp - mt) ** 2).mean(-1)
        for name, m in (("seen", seen), ("unseen", unseen)):
            if m.any():
                row[f"{name}_psnr_{layer}_tonemapped"] = psnr(mp, mt, m)
        total = float(err[surface].sum())
        row[f"unseen_error_share_{layer}"] = float(err[unseen].sum() / total) if total > 0 else 0.0
    return row


def _dark_scores(gt: dict, tonemapped: dict, peak: float) -> dict:
    """dark_fraction_<layer>, dark_error_share_<layer> (``DEFINITIONS``) for the diffuse and specular layers
    (``tonemapped``: layer -> (ours, truth) mu-law images)."""
    row = {}
    for layer in ("diffuse", "specular"):
        dark = (np.asarray(gt[layer]) < DARK * peak).all(-1)
        mp, mt = tonemapped[layer]
        err = ((mp - mt) ** 2).mean(-1)
        total = float(err.sum())
        row[f"dark_fraction_{layer}"] = float(dark.mean())
        row[f"dark_error_share_{layer}"] = float(err[dark].sum() / total) if total > 0 else 0.0
    return row


def _normal_scores(view, rendered: dict) -> dict:
    """normal_angle_deg, shiny_normal_angle_deg[_p90] (``DEFINITIONS``); {} without normals on either side."""
    if "normal" not in view.buffers or "normal" not in rendered:
        return {}
    truth, ours = view.buffers["normal"].astype(np.float64), rendered["normal"].astype(np.float64)
    length = np.linalg.norm(ours, axis=-1)
    both = (np.linalg.norm(truth, axis=-1) > 0.5) & (length > 1e-6)
    cos = (truth * ours).sum(-1) / np.maximum(length, 1e-12)
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    row = {}
    if both.any():
        row["normal_angle_deg"] = float(np.median(angle[both]))
    if "f0" in view.buffers:
        shiny = both & (view.buffers["f0"].max(-1) > SHINY_F0)
        if shiny.any():
            row["shiny_normal_angle_deg"] = float(np.median(angle[shiny]))
            row["shiny_normal_angle_deg_p90"] = float(np.percentile(angle[shiny], 90))
    return row


def evaluate_renders(capture: Capture, renders: Path, regions: dict | None = None,
                     lpips: LpipsWeights | None = None) -> dict:
    """Per-view and mean metrics (module docstring); ``regions``: name -> {min: [x, y, z], max: [x, y, z]} world
    boxes, each scored (PSNR per layer: linear at the view's peak, clamped at peak 1, mu-law) on the pixels whose
    ground-truth surface is inside it. ``saturated``: [{view, layer, reasons}] (empty when every score measures
    something). ``lpips``:
    weights (``models.metrics.lpips.load_lpips``) to add ``lpips_<layer>`` on the clamped sRGB images."""
    per_view, saturated = {}, []
    train = capture.split("train")
    for view in capture.split("test"):
        if lpips is not None and min(view.camera.height, view.camera.width) < LPIPS_MIN_SIZE:
            raise ValueError(f"LPIPS (AlexNet) needs views of at least {LPIPS_MIN_SIZE} x {LPIPS_MIN_SIZE} pixels; "
                             f"test view {view.name!r} is {view.camera.width} x {view.camera.height} (leave "
                             "evaluate.lpips unset for it)")
        exr = renders / f"{view.name}.exr"
        if not exr.is_file():
            raise FileNotFoundError(f"render of test view {view.name!r} missing: {exr}")
        rendered = read_view_buffers(exr, view.camera.height, view.camera.width)
        gt = ground_truth(view.buffers)
        pred = {"diffuse": rendered["diffuse"], "specular": rendered["specular"], "final": rendered["rgb"]}
        row = {"peak": hdr.peak(gt["final"]), **_normal_scores(view, rendered)}
        tonemapped = {layer: (hdr.mu_law(pred[layer], row["peak"]), hdr.mu_law(gt[layer], row["peak"]))
                      for layer in SCORED}  # (ours, truth): the region and seen scores
        for layer in SCORED:
            scores = score_layer(pred[layer], gt[layer], layer, reference=row["peak"])
            row.update(scores)
            if lpips is not None:
                row[f"lpips_{layer}"] = lpips_images(linear_to_srgb(pred[layer]), linear_to_srgb(gt[layer]), lpips)
            reasons = hdr.saturation({k: v for k, v in scores.items() if k.startswith("psnr_")},
                                     scores[f"over1_{layer}"])
            if reasons:
                saturated.append({"view": view.name, "layer": layer, "reasons": reasons})
        row.update(_dark_scores(gt, tonemapped, row["peak"]))
        for layer, other in (("diffuse", "specular"), ("specular", "diffuse")):
            row[f"psnr_final_tonemapped_true_{layer}"] = psnr(hdr.mu_law(gt[layer] + pred[other], row["peak"]),
                                                             tonemapped["final"][1])
        for name, box in (regions or {}).items():
            m = region_mask(view, box["min"], box["max"])
            row[f"{name}_pixels"] = int(m.sum())
            for layer in SCORED:
                if m.any():
                    row[f"{name}_psnr_{layer}"] = psnr(pred[layer], gt[layer], m, peak=row["peak"])
                    row[f"{name}_psnr_{layer}_clamped"] = psnr(np.clip(pred[layer], 0, 1), np.clip(gt[layer], 0, 1), m)
                    row[f"{name}_psnr_{layer}_tonemapped"] = psnr(*tonemapped[layer], m)
        if "depth" in view.buffers:
            row.update(_seen_scores(view, train, tonemapped))
        per_view[view.name] = row
    keys = dict.fromkeys(k for r in per_view.values() for k in r)
    mean = {k: float(np.mean([r[k] for r in per_view.values() if k in r])) for k in keys}
    return {"mean": mean, "views": per_view, "saturated": saturated,
            "ground_truth": ground_truth_names(capture), "definitions": DEFINITIONS,
            "lpips": f"{lpips.describe()}, on clamped sRGB" if lpips is not None else LPIPS_OFF}
