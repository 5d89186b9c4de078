"""Scene normalisation of a posed capture, and similarity alignment of two camera sets (Umeyama).

SfM recovers a scene up to a similarity: its frame and scale are arbitrary. The
capture is normalised as ``x_capture = scale * (x_colmap - centre)`` with ``centre``
the mean camera centre and ``scale`` putting the farthest camera at
``target_radius``; cameras, SfM points and depth buffers (distances) move
together. The pair (centre, scale) is recorded in ``capture.yaml``
(``extra.normalisation``) so results map back to the COLMAP model's frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.capture import Capture

from .photos import PosesError


@dataclass
class Normalisation:
    centre: np.ndarray  # [3] in the original (COLMAP) frame
    scale: float  # x_capture = scale * (x_original - centre)

    def apply_points(self, xyz: np.ndarray) -> np.ndarray:
        return self.scale * (np.asarray(xyz, dtype=np.float64) - self.centre)

    def record(self) -> dict:
        return {"centre": [float(c) for c in self.centre], "scale": float(self.scale),
                "formula": "x_capture = scale * (x_colmap - centre)"}


def normalisation_of(capture: Capture, target_radius: float = 1.0) -> Normalisation:
    """Centre = mean camera centre; scale puts the farthest camera at ``target_radius``."""
    centres = np.stack([v.camera.origin for v in capture.views])
    centre = centres.mean(axis=0)
    radius = float(np.linalg.norm(centres - centre, axis=1).max())
    if not radius > 1e-12:
        raise PosesError(f"cannot normalise the scene: all {len(centres)} cameras share one position "
                         f"{centre.tolist()} (no baseline)")
    return Normalisation(centre=centre, scale=target_radius / radius)


def normalise_capture(capture: Capture, norm: Normalisation) -> None:
    """Move ``capture`` (in place) into the normalised frame: camera centres, and depth (a distance) x scale."""
    for view in capture.views:
        c2w = view.camera.c2w.copy()
        c2w[:3, 3] = norm.apply_points(c2w[:3, 3])
        view.camera.c2w = c2w
        if "depth" in view.buffers:
            view.buffers["depth"] = (view.buffers["depth"] * norm.scale).astype(np.float32)
    capture.meta.extent = capture.camera_extent()
    capture.meta.extra["normalisation"] = norm.record()


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum ||dst - (s R src + t)||^2 (Umeyama 1991). ``src``, ``dst``: [N, 3]."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama needs two [N, 3] point sets with N >= 3, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0
    r = u @ sign @ vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(d) @ sign) / var_s)
    t = mu_d - s * r @ mu_s
    return s, r, t


def pose_errors(estimated: list[np.ndarray], truth: list[np.ndarray]) -> dict:
    """Align the estimated camera-to-world poses [4, 4] to the true ones by a similarity of their centres, then
    rotation error (degrees) and position error (fraction of the true cameras' extent: the radius of the sphere
    around their mean that bounds them) per camera."""
    est_c = np.stack([p[:3, 3] for p in estimated])
    true_c = np.stack([p[:3, 3] for p in truth])
    s, r, t = umeyama(est_c, true_c)
    aligned_c = (s * (r @ est_c.T)).T + t
    extent = float(np.linalg.norm(true_c - true_c.mean(0), axis=1).max())
    rot_err = []
    for p, q in zip(estimated, truth):
        rel = (r @ p[:3, :3]).T @ q[:3, :3]
        rot_err.append(float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0)))))
    pos_err = np.linalg.norm(aligned_c - true_c, axis=1) / extent
    return {"rotation_deg": np.array(rot_err), "position_frac": pos_err, "scale": s, "extent": extent}
