"""Scoring a photos run against a rendered truth (issue #23, the photos path on unseen rooms).

A synthetic room rendered as photos only (8-bit sRGB PNG, no buffers, no poses) goes through ``poses`` ->
``buffers`` -> ``init`` -> ``reconstruct`` like any real capture; its reconstruction lives in the frame COLMAP
chose, normalised (``x_capture = scale * (x_colmap - centre)``, recorded in capture.yaml). To score it against
the exact renderer's test views, those views are moved into that frame by the similarity that maps the TRUE
train camera centres (the ones the photos were rendered from) onto the POSED ones (Umeyama, least squares over
every registered photo). The test cameras therefore never have to register: they keep their true pose relative to
the scene, the reconstruction's pose errors included in what is scored.

Beside the moved views, ``photos_truth`` reports what limits such a run:

- poses: per registered photo, rotation error (degrees) and position error (fraction of the camera extent)
  after that alignment, and how many photos COLMAP dropped;
- network: per predicted buffer, its error against the renderer's exact buffer of the same train view (PSNR
  tonemapped for diffuse / specular, mean angle for normals, beside the trivial every-normal-faces-the-camera
  baseline, median relative error for depth, mean absolute error for roughness / F0), compared in the posed
  frame (normals rotated, depth scaled);
- reconstruction: what is left, read against the same room trained on exact buffers (the batch report).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.capture import Camera, Capture, CaptureMeta, View

from .normalise import pose_errors, umeyama
from .photos import PosesError


@dataclass
class Similarity:
    """x_posed = scale * rotation @ x_true + translation."""

    scale: float
    rotation: np.ndarray  # [3, 3]
    translation: np.ndarray  # [3]

    def apply_points(self, xyz: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(xyz, np.float64) @ self.rotation.T + self.translation

    def apply_c2w(self, c2w: np.ndarray) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = self.rotation @ c2w[:3, :3]
        out[:3, 3] = self.apply_points(c2w[:3, 3])
        return out

    def record(self) -> dict:
        return {"scale": float(self.scale), "rotation": self.rotation.tolist(),
                "translation": [float(x) for x in self.translation],
                "formula": "x_posed = scale * rotation @ x_true + translation"}


def matched_views(reference: Capture, posed: Capture) -> list[tuple[View, View]]:
    """(true view, posed view) pairs of the photos COLMAP registered, matched by name (the photo's file stem)."""
    true_by_name = {v.name: v for v in reference.views}
    pairs = [(true_by_name[v.name], v) for v in posed.views if v.name in true_by_name]
    if len(pairs) < 3:
        raise PosesError(f"only {len(pairs)} posed views share a name with the rendered photos "
                         f"({sorted(true_by_name)[:4]}... vs {[v.name for v in posed.views][:4]}...); aligning the "
                         "two frames needs >= 3")
    return pairs


def similarity_to_posed(reference: Capture, posed: Capture) -> tuple[Similarity, dict]:
    """The similarity from the true frame to the posed one (camera centres, least squares) and the pose errors."""
    pairs = matched_views(reference, posed)
    true_c = np.stack([t.camera.origin for t, _ in pairs])
    posed_c = np.stack([p.camera.origin for _, p in pairs])
    s, r, t = umeyama(true_c, posed_c)
    sim = Similarity(s, r, t)
    errors = pose_errors([p.camera.c2w for _, p in pairs], [t_.camera.c2w for t_, _ in pairs])
    report = {
        "registered": len(pairs),
        "photos": len(reference.views),
        "unregistered": sorted(set(v.name for v in reference.views) - set(p.name for _, p in pairs)),
        "rotation_deg_mean": float(errors["rotation_deg"].mean()),
        "rotation_deg_max": float(errors["rotation_deg"].max()),
        "position_frac_mean": float(errors["position_frac"].mean()),
        "position_frac_max": float(errors["position_frac"].max()),
        "per_view": {p.name: {"rotation_deg": round(float(a), 4), "position_frac": round(float(b), 5)}
                     for (_, p), a, b in zip(pairs, errors["rotation_deg"], errors["position_frac"])},
    }
    return sim, report


def moved_view(view: View, sim: Similarity) -> View:
    """``view`` in the posed frame: camera moved, depth (a distance) scaled, world-space normals rotated."""
    cam = view.camera
    camera = Camera(cam.width, cam.height, cam.fl_x, cam.fl_y, cam.cx, cam.cy, sim.apply_c2w(cam.c2w))
    buffers = dict(view.buffers)
    if "depth" in buffers:
        buffers["depth"] = (buffers["depth"] * sim.scale).astype(np.float32)
    if "normal" in buffers:
        buffers["normal"] = (buffers["normal"] @ sim.rotation.T).astype(np.float32)
    return View(view.name, camera, view.split, buffers)


def _psnr_tonemapped(pred: np.ndarray, target: np.ndarray, peak: float) -> float:
    from models.metrics import hdr
    from models.metrics.image import psnr

    return float(psnr(hdr.mu_law(pred, peak), hdr.mu_law(target, peak)))


def buffer_errors(predicted: Capture, reference: Capture, sim: Similarity) -> dict:
    """The network's buffers of each train view against the renderer's (moved into the posed frame): per layer the
    mean over views, and per view. Views are matched by name; the truth is resampled to the prediction's size
    (nearest) when the two differ."""
    true_by_name = {v.name: moved_view(v, sim) for v in reference.views}
    per_view: dict[str, dict] = {}
    for view in predicted.split("train"):
        truth = true_by_name.get(view.name)
        if truth is None:
            continue
        scores = {}
        peak = float(np.max(truth.buffers["rgb"])) if "rgb" in truth.buffers else 1.0
        for layer in ("diffuse", "specular", "normal", "depth", "roughness", "f0"):
            if layer not in view.buffers or layer not in truth.buffers:
                continue
            p = view.buffers[layer].astype(np.float64)
            t = _nearest(truth.buffers[layer], p.shape[:2]).astype(np.float64)
            if layer in ("diffuse", "specular"):
                scores[f"{layer}_psnr_tonemapped"] = _psnr_tonemapped(p, t, peak)
            elif layer == "normal":
                pn = p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-8)
                tn = t / np.maximum(np.linalg.norm(t, axis=-1, keepdims=True), 1e-8)
                valid = np.linalg.norm(t, axis=-1) > 0.5
                cos = np.clip((pn * tn).sum(-1), -1, 1)[valid]
                scores["normal_angle_deg"] = float(np.degrees(np.arccos(cos)).mean()) if cos.size else float("nan")
                # the trivial baseline: every normal facing the camera (its +z axis, OpenGL convention)
                facing = np.clip(tn @ view.camera.c2w[:3, 2], -1, 1)[valid]
                scores["normal_angle_deg_facing_camera"] = (float(np.degrees(np.arccos(facing)).mean())
                                                            if facing.size else float("nan"))
            elif layer == "depth":
                valid = (t[..., 0] > 0) & np.isfinite(t[..., 0]) & (p[..., 0] > 0)
                rel = np.abs(p[..., 0] - t[..., 0])[valid] / t[..., 0][valid]
                scores["depth_relative_error_median"] = float(np.median(rel)) if rel.size else float("nan")
            else:
                scores[f"{layer}_mae"] = float(np.abs(p - t).mean())
        per_view[view.name] = scores
    if not per_view:
        return {"views": 0}
    keys = sorted({k for s in per_view.values() for k in s})
    mean = {k: float(np.nanmean([s[k] for s in per_view.values() if k in s])) for k in keys}
    return {"views": len(per_view), "mean": mean, "per_view": per_view}


def _nearest(arr: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    h, w = arr.shape[:2]
    if (h, w) == tuple(shape):
        return arr
    rows = ((np.arange(shape[0]) + 0.5) * h / shape[0]).astype(int)
    cols = ((np.arange(shape[1]) + 0.5) * w / shape[1]).astype(int)
    return arr[rows][:, cols]


def photos_truth(truth: Capture, reference: Capture, posed: Capture, predicted: Capture | None = None,
                 split: str = "test", truth_scene: str | None = None) -> tuple[Capture, dict]:
    """The ``split`` views of ``truth`` (a synthetic capture with exact buffers) moved into ``posed``'s frame,
    as a capture of test views, and the record of what limits the photos run (``photos_path`` in capture.yaml).

    ``reference``: the capture the photos were rendered from (its true train cameras); ``posed``: the poses stage's
    capture of those photos; ``predicted``: the buffers stage's capture (network buffers), for the network's
    errors."""
    views = truth.split(split)
    if not views:
        raise PosesError(f"the rendered truth has no {split!r} views to score the photos run against")
    sim, poses = similarity_to_posed(reference, posed)
    moved = [moved_view(v, sim) for v in views]
    for v in moved:
        v.split = "test"
    record = {"similarity": sim.record(), "poses": poses,
              "normalisation": posed.meta.extra.get("normalisation"),
              "truth_scene": truth_scene, "truth_views": [v.name for v in views]}
    if predicted is not None:
        record["network"] = buffer_errors(predicted, reference, sim)
    meta = CaptureMeta(source="synthetic (moved into the photos reconstruction's frame)",
                       color_space=truth.meta.color_space, units=posed.meta.units,
                       extra={"photos_path": record})
    out = Capture(moved, meta)
    out.meta.extent = out.camera_extent()
    return out, record
