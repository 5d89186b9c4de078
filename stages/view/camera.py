"""The browser's camera <-> our pinhole Camera (models/capture/camera.py, OpenGL c2w).

viser reports a camera as position t and orientation wxyz with ``P_world = [R | t] p_camera`` in the
OpenCV convention (+Z forward, +Y down, +X right), a vertical field of view and the canvas aspect
(width / height). Our Camera is OpenGL (-Z forward, +Y up): c2w_gl = c2w_cv @ diag(1, -1, -1, 1).
The browser draws the background image over the whole canvas (stretched), so the rendered image
covers exactly the canvas' frustum whatever its pixel count; we pick the pixel count.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from models.capture import Camera

GL_FROM_CV = np.diag([1.0, -1.0, -1.0])  # flips camera Y and Z (OpenCV <-> OpenGL camera axes)


def viewport_size(aspect: float, pixels: int) -> tuple[int, int]:
    """(width, height) with width / height ~ ``aspect`` and width * height ~ ``pixels``."""
    if not (math.isfinite(aspect) and aspect > 0):
        raise ValueError(f"aspect must be a positive number, got {aspect!r}")
    if pixels < 1:
        raise ValueError(f"pixels must be >= 1, got {pixels}")
    # neither side beyond ``pixels`` (a canvas of absurd aspect gets a thin image, not an enormous one)
    height = min(max(1, round(math.sqrt(pixels / aspect))), pixels)
    width = min(max(1, round(height * aspect)), pixels)
    return width, height


def resize_camera(camera: Camera, pixels: int) -> Camera:
    """``camera`` with about ``pixels`` pixels: same pose, field of view and aspect, principal point centred
    (the browser's camera has no lens shift)."""
    w, h = viewport_size(camera.width / camera.height, pixels)
    return Camera(w, h, camera.fl_x * w / camera.width, camera.fl_y * h / camera.height, w / 2, h / 2, camera.c2w)


def camera_from_viser(position, wxyz, fov_y: float, aspect: float, pixels: int) -> Camera:
    """Our Camera for a viser camera state (position [3], wxyz [4], vertical fov in radians, canvas
    width / height), rendered with about ``pixels`` pixels. The horizontal focal length follows the
    canvas aspect (not the rounded pixel aspect), so the image maps exactly onto the canvas."""
    if not (0 < fov_y < math.pi):
        raise ValueError(f"fov_y must be in (0, pi) radians, got {fov_y!r}")
    q, t = np.asarray(wxyz, dtype=np.float64), np.asarray(position, dtype=np.float64)
    if q.shape != (4,) or t.shape != (3,) or not (np.isfinite(q).all() and np.isfinite(t).all()):
        raise ValueError(f"camera pose must be a finite wxyz [4] and position [3], got {wxyz!r}, {position!r}")
    width, height = viewport_size(aspect, pixels)
    w, x, y, z = (float(v) for v in q)
    r_cv = Rotation.from_quat([x, y, z, w]).as_matrix()  # scipy: xyzw
    c2w = np.eye(4)
    c2w[:3, :3] = r_cv @ GL_FROM_CV
    c2w[:3, 3] = t
    tan_y = math.tan(fov_y / 2)
    fl_y = height / 2 / tan_y
    fl_x = width / 2 / (aspect * tan_y)
    return Camera(width, height, fl_x, fl_y, width / 2, height / 2, c2w)


def viser_from_camera(camera: Camera, look_distance: float = 1.0) -> dict:
    """The viser camera state showing what ``camera`` sees: position, wxyz (OpenCV), fov (vertical,
    radians), look_at (``look_distance`` ahead), up_direction (the camera's up) and aspect. The principal
    point must be the image centre (the browser has no lens shift)."""
    if abs(camera.cx - camera.width / 2) > 1e-3 or abs(camera.cy - camera.height / 2) > 1e-3:
        raise ValueError(f"the browser camera has no lens shift: principal point ({camera.cx}, {camera.cy}) is "
                         f"not the image centre ({camera.width / 2}, {camera.height / 2})")
    r_cv = camera.rotation @ GL_FROM_CV
    x, y, z, w = Rotation.from_matrix(r_cv).as_quat()
    forward = -camera.rotation[:, 2]
    return {
        "position": camera.origin,
        "wxyz": np.array([w, x, y, z]),
        "fov": 2 * math.atan(camera.height / 2 / camera.fl_y),
        "look_at": camera.origin + look_distance * forward,
        "up_direction": camera.rotation[:, 1].copy(),
        "aspect": (camera.width / camera.fl_x) / (camera.height / camera.fl_y),
    }


def z_depth(camera: Camera, distance: np.ndarray) -> np.ndarray:
    """Distance along the unit ray [H, W] -> depth along the optical axis [H, W] (what viser composites with)."""
    d = camera.camera_directions()  # z = -1
    return distance / np.linalg.norm(d, axis=-1)


def box_from_pixels(camera: Camera, distance: np.ndarray, hit: np.ndarray,
                    rect) -> tuple[np.ndarray, np.ndarray] | None:
    """World box around what the image rectangle ``rect`` = (x0, y0, x1, y1) (fractions of width / height,
    top-left origin) shows: the bounds of the visible surface points (distance [H, W] along unit rays, where
    ``hit`` [H, W]), deepened away from the camera by their largest extent (a surface shows its front only),
    plus a 5% margin. None when the rectangle shows no surface."""
    x0, y0, x1, y1 = (float(v) for v in rect)
    h, w = distance.shape
    c0, c1 = int(np.floor(min(x0, x1) * w)), int(np.ceil(max(x0, x1) * w))
    r0, r1 = int(np.floor(min(y0, y1) * h)), int(np.ceil(max(y0, y1) * h))
    c0, r0 = max(c0, 0), max(r0, 0)
    c1, r1 = min(max(c1, c0 + 1), w), min(max(r1, r0 + 1), h)
    dirs = camera.ray_directions()[r0:r1, c0:c1]
    t, ok = distance[r0:r1, c0:c1], hit[r0:r1, c0:c1]
    if not ok.any():
        return None
    p = camera.origin + dirs[ok] * t[ok][:, None]
    lo, hi = p.min(axis=0), p.max(axis=0)
    size = float((hi - lo).max())
    forward = -camera.rotation[:, 2]
    hi = hi + np.maximum(forward, 0) * size
    lo = lo + np.minimum(forward, 0) * size
    margin = 0.05 * max(size, 1e-3)
    return lo - margin, hi + margin
