"""Align a relative (affine-ambiguous) depth map to metric SfM depths: RANSAC over scale and shift.

A depth network predicts z-depth up to an unknown scale and shift per image
(REFERENCE.md, "Real scenes with network priors"). The SfM points an image
observes, projected into it, give sparse samples ``z_sfm`` at pixels where the
network says ``d``; ``z_sfm ~ scale * d + shift`` is fitted robustly (outliers:
points on reflections, mismatched tracks, network errors at silhouettes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_POINTS = 5  # fewer SfM samples than this cannot vouch for a fit


@dataclass
class DepthFit:
    scale: float
    shift: float
    inliers: int  # samples within the inlier threshold of the final fit
    samples: int  # samples the fit saw


def fit_scale_shift(d: np.ndarray, z: np.ndarray, *, threshold: float = 0.05, iterations: int = 256,
                    seed: int = 0, where: str = "depth") -> DepthFit:
    """Robust ``z ~ scale * d + shift``. ``d``, ``z``: ``[M]``. A sample is an inlier when its residual is
    below ``threshold`` x the median of ``z``. Minimal samples of 2 points, most inliers wins, least squares
    refit on the inliers. Raises ValueError (naming ``where``) with fewer than MIN_POINTS samples or a
    degenerate (constant) relative depth."""
    d = np.asarray(d, dtype=np.float64).reshape(-1)
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    if d.shape != z.shape:
        raise ValueError(f"{where}: {d.shape[0]} relative depths but {z.shape[0]} SfM depths")
    ok = np.isfinite(d) & np.isfinite(z)
    d, z = d[ok], z[ok]
    if len(d) < MIN_POINTS:
        raise ValueError(f"{where}: only {len(d)} SfM point(s) project into the image; need >= {MIN_POINTS} "
                         "to align the relative depth")
    if np.ptp(d) <= 1e-12:
        raise ValueError(f"{where}: the relative depth is constant ({d[0]:.4g}) where the SfM points fall; "
                         "cannot fit a scale")
    tol = threshold * float(np.median(np.abs(z)))
    rng = np.random.default_rng(seed)
    best, best_count = None, -1
    for _ in range(iterations):
        i, j = rng.choice(len(d), size=2, replace=False)
        if abs(d[i] - d[j]) <= 1e-12:
            continue
        a = (z[i] - z[j]) / (d[i] - d[j])
        b = z[i] - a * d[i]
        inl = np.abs(a * d + b - z) < tol
        count = int(inl.sum())
        if count > best_count:
            best, best_count = inl, count
    if best is None or best_count < 2:
        best = np.ones(len(d), dtype=bool)
    a, b = np.polyfit(d[best], z[best], 1) if np.ptp(d[best]) > 1e-12 else np.polyfit(d, z, 1)
    inliers = int((np.abs(a * d + b - z) < tol).sum())
    return DepthFit(scale=float(a), shift=float(b), inliers=inliers, samples=int(len(d)))


def align_to_points(rel, camera, xyz: np.ndarray, *, seed: int = 0, where: str = "depth") -> tuple[np.ndarray, DepthFit]:
    """Relative planar depth ``rel`` ``[H, W]`` of ``camera`` (a ``Camera``) aligned to world points ``xyz``
    ``[N, 3]`` (SfM points): the points in front of the camera are projected, ``fit_scale_shift`` maps ``rel``
    to their z-depth (points hidden behind other surfaces are RANSAC outliers), and the metric z becomes the
    capture format's distance along the ray. Returns (``[H, W, 1]`` float32 distance, 0 where the fitted z is
    not positive; the fit)."""
    pc = (np.asarray(xyz, np.float64) - camera.origin) @ camera.rotation  # world -> OpenGL camera space
    z = -pc[:, 2]
    front = z > 1e-9
    u = camera.fl_x * pc[front, 0] / z[front] + camera.cx
    v = -camera.fl_y * pc[front, 1] / z[front] + camera.cy
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    col, row = np.floor(u[inside]).astype(int), np.floor(v[inside]).astype(int)
    fit = fit_scale_shift(rel[row, col], z[front][inside], seed=seed, where=where)
    zz = fit.scale * np.asarray(rel, np.float64) + fit.shift
    ray_len = np.linalg.norm(camera.camera_directions(), axis=-1)
    dist = np.where(zz > 0, zz * ray_len, 0.0)
    return dist[:, :, None].astype(np.float32), fit
