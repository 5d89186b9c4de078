"""Dense initialisation (no densification later): unproject, voxelise, one Gaussian per voxel.

Reference recipe (REFERENCE.md, "Dense init"): unproject the depth of every
training view at low resolution (long side 128), colour from the diffuse buffer,
voxelise with voxel = 1/400 of the scene (1/50 for real scenes), keep voxels with
>= 2 samples, one Gaussian per voxel; isotropic scale = sqrt(mean squared distance
to the 3 nearest neighbours); opacity 0.1, roughness 0.1, F0 0.04, normal 0.

Coarser levels (``coarse_levels``, not in the reference): a sample alone in its voxel is dropped by the
recipe, and a surface seen from far or at a grazing angle (a pixel's footprint wider than the voxel) gives
only such samples: on the zoo's 128 x 96 rooms half of all samples were dropped, and seen walls up to 0.8 m
across got no Gaussian at all (no densification ever fills them: a test view looked through the hole). The
dropped samples are voxelised again at 2x, 4x, 8x the voxel, and a coarse voxel with >= ``min_samples``
samples gets a Gaussian where no Gaussian lies within 1.5 of its edge (a hole, not a sparse patch of a
covered surface): the agreement of two samples still decides, at the footprint's scale.

Discs (``flatten`` < 1, not in the reference; 0.3 by default, 1 = the reference's spheres): a Gaussian whose
voxel's samples agree on a normal
(the normal buffer's, averaged with the colour; the mean at least 0.9 long) starts as a disc in that plane, its
thickness ``flatten`` x its width, instead of a sphere. A sphere on a wall or a window reaches past the surface's
outline by its radius and shows it to views the training ones do not share (zoo_lshape: a window's Gaussians up
to 0.33 m across, spilling its light onto the wall round it in the test views). Measured over the zoo batch (seven
rooms, fast, same captures, one run each): final tonemapped up in six rooms (mean +0.37 dB), edits up in 12 of 14,
a mirror-and-metal room's metal normals in the test views 33.9 -> 1.5 degrees (median); the README has the rows.

"The scene" size is the largest side of the bounding box of the unprojected
points between their 1st and 99th percentiles (robust to stray far samples).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from models.capture import Capture, CaptureError, View
from models.capture.layers import diffuse_radiance
from models.gaussians import Gaussians
from models.settings import from_dict, setting


@dataclass
class InitConfig:
    """Dense initialisation settings (the ``init`` config section)."""

    resolution: int = setting(128, "long side (pixels) of the grid each training view is unprojected at",
                              minimum=4, maximum=4096)
    voxel_fraction: float = setting(1 / 400, "voxel edge as a fraction of the scene size (real scenes: 1/50)",
                                    exclusiveMinimum=0, maximum=1)
    min_samples: int = setting(2, "a voxel needs this many unprojected samples to get a Gaussian", minimum=1)
    coarse_levels: int = setting(3, "samples in voxels below min_samples are voxelised again at 2x .. 2^k x the "
                                 "voxel, filling the holes (nothing within 1.5 coarse voxels) of surfaces seen "
                                 "from far; 0 = the reference recipe (zoo_lshape: 0.8 m of seen wall empty)",
                                 minimum=0, maximum=8)
    opacity: float = setting(0.1, "initial opacity of every Gaussian", exclusiveMinimum=0, exclusiveMaximum=1)
    roughness: float = setting(0.1, "initial roughness", minimum=0, maximum=1)
    f0: float = setting(0.04, "initial base reflectance (grey)", minimum=0, maximum=1)
    scale_factor: float = setting(1.0, "multiplies the 3-NN scale (real scenes in the reference: 0.1 init scale)",
                                  exclusiveMinimum=0)
    seed: int = setting(0, "reserved for sampling choices; the recipe itself is deterministic")
    source: str = setting("auto", "auto: depth + diffuse buffers when every training view has them, else SfM "
                          "points | depth | sfm", enum=["auto", "depth", "sfm"])

    flatten: float = setting(0.3, "a Gaussian whose voxel's samples agree on a normal (the normal buffer's; their "
                             "mean at least 0.9 long) starts as a disc in that plane, its thickness this x its "
                             "width; 1 = the reference's spheres (no normal buffer: spheres)", minimum=0.01,
                             maximum=1.0)

    @classmethod
    def from_dict(cls, d: dict) -> "InitConfig":
        return from_dict(cls, d, "init")


def quats_z_to(normals: np.ndarray) -> np.ndarray:
    """[n, 4] unit quaternions (w, x, y, z) of the rotations taking e_z to the unit ``normals`` [n, 3] (a disc's
    thin local z axis along its normal): axis e_z x n, (1 + n_z, -n_y, n_x, 0) normalised; n = -e_z (w = 0) turns
    about x."""
    q = np.stack([1.0 + normals[:, 2], -normals[:, 1], normals[:, 0], np.zeros(len(normals))], 1)
    q[q[:, 0] < 1e-6] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _sample_view(view: View, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """World points [M, 3] and diffuse colours + normals [M, 6] of one view on a low-resolution pixel grid (normals
    0 without a normal buffer)."""
    cam = view.camera
    for layer in ("depth", "diffuse"):
        if layer not in view.buffers:
            raise CaptureError(f"view {view.name!r}: dense init needs the {layer!r} buffer")
    step = max(cam.width, cam.height) / resolution
    step = max(step, 1.0)
    # pixel centres of the low-resolution grid, sampled (nearest) in the full-resolution buffers:
    # averaging depth across silhouettes would create floating points.
    xs = np.minimum(((np.arange(int(np.floor(cam.width / step))) + 0.5) * step).astype(int), cam.width - 1)
    ys = np.minimum(((np.arange(int(np.floor(cam.height / step))) + 0.5) * step).astype(int), cam.height - 1)
    dirs = cam.ray_directions()[np.ix_(ys, xs)]  # [h, w, 3]
    depth = view.buffers["depth"][np.ix_(ys, xs)][..., 0].astype(np.float64)
    colour = diffuse_radiance(view.buffers)[np.ix_(ys, xs)].astype(np.float64)  # + emission: lights start lit
    valid = np.isfinite(depth) & (depth > 0)
    if "mask" in view.buffers:
        valid &= view.buffers["mask"][np.ix_(ys, xs)][..., 0] > 0.5
    points = cam.origin + dirs[valid] * depth[valid, None]
    if "normal" in view.buffers:  # carried with the colour (voxel means): the discs' planes (InitConfig.flatten)
        normal = view.buffers["normal"][np.ix_(ys, xs)][..., :3].astype(np.float64)
    else:
        normal = np.zeros_like(colour)
    return points, np.concatenate([colour, normal], -1)[valid]


def unproject_views(views: list[View], resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Unprojected points [M, 3] and diffuse colours [M, 3] of all ``views``."""
    points, attrs = _unproject(views, resolution)
    return points, attrs[:, :3]


def _unproject(views: list[View], resolution: int) -> tuple[np.ndarray, np.ndarray]:
    samples = [_sample_view(v, resolution) for v in views]
    return np.concatenate([s[0] for s in samples]), np.concatenate([s[1] for s in samples])


def dense_init(capture: Capture, config: InitConfig = InitConfig()) -> tuple[Gaussians, dict]:
    """Gaussians from the training views' depth + diffuse buffers, and a summary dict for logs/provenance."""
    train = capture.split("train")
    if not train:
        raise CaptureError("capture has no training views")
    points, attrs = _unproject(train, config.resolution)  # [M, 6]: colour + normal, averaged per voxel alike
    if len(points) < 4:
        raise CaptureError(f"dense init: only {len(points)} valid depth samples in {len(train)} training views")
    lo, hi = np.percentile(points, [1, 99], axis=0)
    scene_size = float((hi - lo).max())
    voxel = scene_size * config.voxel_fraction
    mean_pos, mean_attrs, counts, inverse = _voxelise(points, attrs, lo, voxel)
    n_vox = len(counts)
    keep = counts >= config.min_samples
    means, voxel_attrs = mean_pos[keep], mean_attrs[keep]
    coarse = []
    rest = ~keep[inverse]  # the samples the recipe drops
    for level in range(1, config.coarse_levels + 1):
        if not rest.any() or not len(means):
            break
        size = voxel * 2 ** level
        pos, col, cnt, inv = _voxelise(points[rest], attrs[rest], lo, size)
        ok = cnt >= config.min_samples
        hole = ok & (cKDTree(means).query(pos, distance_upper_bound=1.5 * size)[0] > 1.5 * size)
        means, voxel_attrs = np.concatenate([means, pos[hole]]), np.concatenate([voxel_attrs, col[hole]])
        coarse.append(int(hole.sum()))
        rest[np.flatnonzero(rest)[ok[inv]]] = False
    if len(means) < 4:
        raise CaptureError(
            f"dense init: only {len(means)} voxels hold >= {config.min_samples} samples "
            f"(voxel {voxel:.4g}); lower voxel_fraction or raise resolution"
        )
    gaussians, scale = gaussians_from_points(means, voxel_attrs[:, :3], config, normals=voxel_attrs[:, 3:])
    n = len(means)
    summary = {
        "views": len(train),
        "samples": int(len(points)),
        "scene_size": scene_size,
        "voxel": voxel,
        "voxels": int(n_vox),
        "gaussians": int(n),
        "coarse": coarse,  # Gaussians added at 2x, 4x, ... the voxel (holes of surfaces seen from far)
        "median_scale": float(np.median(scale)),
        # discs (flatten < 1): 0 when the capture has no normal buffer or its normals never agree
        "discs": int((gaussians.log_scales[:, 2] < gaussians.log_scales[:, 0]).sum()),
    }
    return gaussians, summary


def _voxelise(points: np.ndarray, colours: np.ndarray, lo: np.ndarray, voxel: float):
    """Mean position and colour per occupied voxel, its sample count, and each sample's voxel index."""
    keys = np.floor((points - lo) / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    pos = np.zeros((len(counts), 3))
    col = np.zeros((len(counts), colours.shape[1]))
    np.add.at(pos, inverse, points)
    np.add.at(col, inverse, colours)
    return pos / counts[:, None], col / counts[:, None], counts, inverse


def gaussians_from_points(means: np.ndarray, diffuse: np.ndarray, config: InitConfig,
                          normals: np.ndarray | None = None) -> tuple[Gaussians, np.ndarray]:
    """One isotropic Gaussian per point (the reference defaults): scale = sqrt(mean squared distance to the
    3 nearest neighbours) x ``scale_factor``, opacity / roughness / F0 from ``config``, normal 0, identity
    rotation, diffuse = ``diffuse`` (clamped >= 0). ``means``, ``diffuse``: [N, 3]. With ``config.flatten`` < 1 and
    ``normals`` [N, 3] (the mean of each voxel's buffer normals), a Gaussian whose mean normal is at least 0.9 long
    is a disc in its plane instead: its local z axis along the normal, that axis ``flatten`` x the scale.
    Returns (Gaussians, scale [N])."""
    dist, _ = cKDTree(means).query(means, k=4)  # first neighbour is the point itself
    scale = np.sqrt(np.mean(dist[:, 1:] ** 2, axis=1)) * config.scale_factor
    scale = np.maximum(scale, 1e-7)
    n = len(means)
    f32 = dict(dtype=torch.float32)
    logit = float(np.log(config.opacity / (1 - config.opacity)))
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    log_scales = np.repeat(np.log(scale)[:, None], 3, axis=1)
    if normals is not None and config.flatten < 1.0:
        length = np.linalg.norm(normals, axis=1)
        flat = length >= 0.9
        quats[flat] = quats_z_to(normals[flat] / length[flat, None])
        log_scales[flat, 2] += np.log(config.flatten)
    gaussians = Gaussians(
        means=torch.tensor(means, **f32),
        quats=torch.tensor(quats, **f32),
        log_scales=torch.tensor(log_scales, **f32),
        opacity_logits=torch.full((n,), logit, **f32),
        diffuse=torch.tensor(np.maximum(diffuse, 0.0), **f32),
        normals=torch.zeros((n, 3), **f32),
        roughness=torch.full((n,), config.roughness, **f32),
        f0=torch.full((n, 3), config.f0, **f32),
    )
    return gaussians, scale
