"""A trained model as a standard 3DGS PLY for common splat viewers (issue #21).

Our ``gaussians.ply`` keeps the 3DGS field names but not their meaning: ``f_dc`` holds LINEAR diffuse radiance
(HDR, emitters exceed 1), and a far-field shell (reconstruction/far_field.py) surrounds the scene out to ~12 x the
camera extent. A 3DGS viewer reads ``f_dc`` as display colour (0.5 + C0 * f_dc), so the scene looks dark and sits
inside a grey sphere. The export writes what those viewers expect:

- ``f_dc`` = (sRGB(diffuse) - 0.5) / C0 with sRGB = models/capture/color.py's ``linear_to_srgb`` (clamp to [0, 1],
  then the sRGB curve): displayable colour, emitters saturate to their clamped colour;
- ``f_rest_0..44`` = 0 (degree-3 layout, for loaders that expect the fixed 62-float vertex), ``nx,ny,nz`` = 0;
- ``opacity`` (logit), ``scale_0..2`` (log standard deviation) and ``rot_0..3`` (w, x, y, z) are already the 3DGS
  conventions; quaternions are normalised, and scales are multiplied by ``scale_factor`` (our tracer's kernel
  may be flatter than a Gaussian, model.yaml ``tracer.kernel_p``);
- optionally without the far-field shell (``far_field_mask``) and without emitters (diffuse > 1 in a channel).

Written as binary little-endian float32 in the field order of the 3DGS reference implementation.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from models.capture.color import linear_to_srgb
from models.gaussians.ply import SH_C0
from models.gaussians.scene import Gaussians

SH_REST = 45  # f_rest_0..44: spherical-harmonic degrees 1-3, 15 coefficients x 3 channels
FIELDS = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
          + [f"f_rest_{i}" for i in range(SH_REST)]
          + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
DC_MAX = 0.5 / SH_C0  # |f_dc| that maps to colour 0 or 1


@dataclass
class FarFieldCut:
    """The sphere outside which Gaussians count as far field: ``|mean - centre| > radius``."""

    centre: np.ndarray  # [3]
    radius: float
    basis: str  # how centre and radius were chosen (for provenance and logs)


def far_field_cut(means: np.ndarray, factor: float, camera_origins: np.ndarray | None = None,
                  extent: float | None = None) -> FarFieldCut:
    """The sphere that keeps the captured scene: centre = the cameras' mean centre (where the reconstruction centres
    the shell) or, without cameras, the per-axis median of the means; radius = ``factor`` x the larger of the
    capture's camera extent (the shell lies outside 1 x extent) and the Gaussians' median distance from the centre
    (the scene's robust inner radius: a room captured from its middle reaches far past the cameras' sphere).
    The median holds while the shell is under half of the Gaussians (the reconstruction adds ~10%).
    means: [N, 3]; camera_origins: [V, 3]."""
    if not factor > 0:
        raise ValueError(f"far-field factor must be > 0, got {factor}")
    if len(means) == 0:
        raise ValueError("no Gaussians to export")
    if camera_origins is not None:
        centre, where = np.mean(camera_origins, axis=0), "the cameras' centre"
    else:
        centre, where = np.median(means, axis=0), "the Gaussians' median"
    inner = float(np.median(np.linalg.norm(means - centre, axis=1)))
    basis = f"median distance {inner:.4g}"
    if extent is not None and extent > inner:
        inner, basis = float(extent), f"camera extent {extent:.4g}"
    return FarFieldCut(centre, factor * inner, f"{factor:g} x {basis} from {where}")


def far_field_mask(means: np.ndarray, cut: FarFieldCut) -> np.ndarray:
    """True for the Gaussians outside the cut's sphere. means: [N, 3] -> [N] bool."""
    return np.linalg.norm(means - cut.centre, axis=1) > cut.radius


def emitter_mask(diffuse: np.ndarray) -> np.ndarray:
    """True for Gaussians whose linear diffuse radiance exceeds 1 in any channel. diffuse: [N, 3] -> [N] bool."""
    return (diffuse > 1.0).any(axis=1)


def kernel_scale_factor(kernel_p: int) -> float:
    """Scale that gives a plain Gaussian the 2D footprint integral of our kernel exp(-r^(2p) / (2p)):
    sqrt((2p)^(1/p) / (2p) * Gamma(1/p)); 1 for p = 1, 0.90 for p = 3."""
    if not isinstance(kernel_p, int) or kernel_p < 1:
        raise ValueError(f"kernel_p must be an int >= 1, got {kernel_p!r}")
    two_p = 2 * kernel_p
    return math.sqrt(two_p ** (1 / kernel_p) / two_p * math.gamma(1 / kernel_p))


def standard_3dgs_vertices(gaussians: Gaussians, keep: np.ndarray | None = None,
                           scale_factor: float = 1.0) -> np.ndarray:
    """The kept Gaussians as a structured float32 array with ``FIELDS``. keep: [N] bool (None: all)."""
    if scale_factor <= 0:
        raise ValueError(f"scale factor must be > 0, got {scale_factor}")
    p = {k: v.detach().cpu().double().numpy() for k, v in gaussians.params().items()}
    if keep is not None:
        p = {k: v[keep] for k, v in p.items()}
    n = len(p["means"])
    srgb = linear_to_srgb(p["diffuse"])
    f_dc = np.clip((srgb - 0.5) / SH_C0, -DC_MAX, DC_MAX)
    quats = p["quats"] / np.maximum(np.linalg.norm(p["quats"], axis=1, keepdims=True), 1e-12)
    columns = {"x": p["means"][:, 0], "y": p["means"][:, 1], "z": p["means"][:, 2],
               "opacity": p["opacity_logits"]}
    for i in range(3):
        columns[f"f_dc_{i}"] = f_dc[:, i]
        columns[f"scale_{i}"] = p["log_scales"][:, i] + math.log(scale_factor)
    for i in range(4):
        columns[f"rot_{i}"] = quats[:, i]
    data = np.zeros(n, dtype=[(name, "<f4") for name in FIELDS])  # normals and f_rest stay 0
    for name, col in columns.items():
        data[name] = col
    bad = [name for name in FIELDS if not np.isfinite(data[name]).all()]
    if bad:
        raise ValueError(f"non-finite values in field(s) {bad} of the exported Gaussians")
    return data


def write_3dgs_ply(path: str | os.PathLike, vertices: np.ndarray) -> Path:
    """Write ``vertices`` (from ``standard_3dgs_vertices``) as a binary little-endian PLY, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        PlyData([PlyElement.describe(vertices, "vertex")], byte_order="<").write(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
