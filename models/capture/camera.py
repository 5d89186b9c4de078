"""Pinhole camera of the capture format (nerfstudio / OpenGL convention)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import CaptureError

# Largest deviation of R^T R from I (and of det R from 1) accepted as a rotation.
ORTHONORMAL_TOL = 1e-4


@dataclass
class Camera:
    """Pinhole camera. ``c2w`` is camera-to-world, OpenGL convention: the camera
    looks down -Z, +Y is up, +X right (as nerfstudio's ``transform_matrix``).

    Pixel (u, v) (column, row; top-left origin) sees the camera-space direction
    ((u + 0.5 - cx) / fl_x, -(v + 0.5 - cy) / fl_y, -1).
    """

    width: int
    height: int
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    c2w: np.ndarray = field(repr=False)  # [4, 4] float64

    def __post_init__(self) -> None:
        self.c2w = np.asarray(self.c2w, dtype=np.float64)

    @property
    def origin(self) -> np.ndarray:
        """Camera centre in world space. # [3]"""
        return self.c2w[:3, 3].copy()

    @property
    def rotation(self) -> np.ndarray:
        """Camera-to-world rotation. # [3, 3]"""
        return self.c2w[:3, :3].copy()

    def camera_directions(self, offset: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
        """Unnormalised camera-space ray directions (z = -1) through the point ``offset`` (column, row; (0.5,
        0.5): the centre) of each pixel. # [H, W, 3]"""
        u = (np.arange(self.width, dtype=np.float64) + offset[0] - self.cx) / self.fl_x
        v = -(np.arange(self.height, dtype=np.float64) + offset[1] - self.cy) / self.fl_y
        uu, vv = np.meshgrid(u, v)  # [H, W]
        return np.stack([uu, vv, -np.ones_like(uu)], axis=-1)

    def ray_directions(self, offset: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
        """Unit world-space ray directions through pixel centres (or the point ``offset`` of each pixel, as
        ``camera_directions``). # [H, W, 3] float64"""
        d = self.camera_directions(offset) @ self.c2w[:3, :3].T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, v, z): continuous pixel coordinates (column, row; pixel (i, j) spans [i, i + 1) x [j, j + 1)) and
        the depth in front of the camera (z > 0 is in front) of world ``points`` [N, 3]; the inverse of
        ``camera_directions``. u and v are meaningless where z <= 0. # [N] float64 each"""
        local = (np.asarray(points, dtype=np.float64) - self.origin) @ self.rotation  # world -> camera
        z = -local[:, 2]
        zs = np.where(z > 1e-12, z, 1.0)
        return self.fl_x * local[:, 0] / zs + self.cx, -self.fl_y * local[:, 1] / zs + self.cy, z

    def check(self, where: str) -> None:
        """Raise CaptureError (naming ``where``) unless intrinsics and pose are valid."""
        if self.width <= 0 or self.height <= 0:
            raise CaptureError(f"{where}: image size must be positive, got {self.width}x{self.height}")
        for name in ("fl_x", "fl_y"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise CaptureError(f"{where}: focal length {name}={value} must be positive and finite")
        for name in ("cx", "cy"):
            if not np.isfinite(getattr(self, name)):
                raise CaptureError(f"{where}: principal point {name}={getattr(self, name)} is not finite")
        if self.c2w.shape != (4, 4):
            raise CaptureError(f"{where}: transform_matrix must be 4x4, got shape {self.c2w.shape}")
        if not np.all(np.isfinite(self.c2w)):
            raise CaptureError(f"{where}: transform_matrix has NaN/Inf entries")
        if not np.allclose(self.c2w[3], [0, 0, 0, 1], atol=1e-6):
            raise CaptureError(f"{where}: transform_matrix last row must be [0, 0, 0, 1], got {self.c2w[3].tolist()}")
        r = self.c2w[:3, :3]
        err = np.abs(r.T @ r - np.eye(3)).max()
        det = np.linalg.det(r)
        if err > ORTHONORMAL_TOL or abs(det - 1.0) > ORTHONORMAL_TOL:
            raise CaptureError(
                f"{where}: rotation of transform_matrix is not orthonormal "
                f"(max |R^T R - I| = {err:.2e}, det = {det:.6f}; scale or shear in camera-to-world is not allowed)"
            )
