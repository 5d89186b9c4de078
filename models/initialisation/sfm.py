"""SfM-point initialisation, and the choice between it and dense (depth) initialisation.

When the capture has no depth buffer (photos posed by ``stages.poses`` before any
buffer prediction), one Gaussian per SfM point is created with the same defaults as
the dense recipe (isotropic scale from the 3 nearest neighbours, opacity 0.1,
roughness 0.1, F0 0.04, normal 0); its diffuse colour is the point's colour.

Where the points live (``models/capture/points.py``): ``<capture>/points3D.ply``
(x, y, z + 8-bit sRGB red, green, blue, in the capture's world frame; written by
``stages.poses``), else the COLMAP model in ``<capture>/sparse/`` (the paper's
real-scene layout). Colours are sRGB-decoded to linear like the capture's buffers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.capture import Capture, CaptureError, read_sfm_points
from models.gaussians import Gaussians

from .dense import InitConfig, dense_init, gaussians_from_points

MIN_POINTS = 4  # the 3-NN scale needs at least 4 points


def sfm_init(points: np.ndarray, colours: np.ndarray, config: InitConfig = InitConfig(),
             where: str = "SfM points") -> tuple[Gaussians, dict]:
    """One Gaussian per SfM point. ``points`` [N, 3], linear ``colours`` [N, 3]. Returns (Gaussians, summary)."""
    points = np.asarray(points, dtype=np.float64)
    colours = np.asarray(colours, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or colours.shape != points.shape:
        raise CaptureError(f"{where}: need points [N, 3] and colours [N, 3], got {points.shape} and {colours.shape}")
    if len(points) < MIN_POINTS:
        raise CaptureError(f"{where}: only {len(points)} SfM point(s); SfM init needs >= {MIN_POINTS}")
    gaussians, scale = gaussians_from_points(points, colours, config)
    return gaussians, {"source": "sfm", "points_file": where, "gaussians": int(len(points)),
                       "median_scale": float(np.median(scale))}


def has_depth(capture: Capture) -> bool:
    """Every training view has the depth and diffuse buffers dense init needs."""
    train = capture.split("train")
    return bool(train) and all("depth" in v.buffers and "diffuse" in v.buffers for v in train)


def initialise(capture: Capture, capture_dir: str | Path, config: InitConfig = InitConfig()) -> tuple[Gaussians, dict]:
    """Dense init from depth when the capture has it (or ``source: depth``), else from the SfM points of
    ``capture_dir``. The summary's ``decision`` says which and why."""
    capture_dir = Path(capture_dir)
    if not capture.split("train"):
        raise CaptureError(f"{capture_dir}: the capture has no training views (all {len(capture.views)} are "
                           "split: test); mark the views to train on \"split\": \"train\" in its transforms.json")
    if config.source != "sfm":  # depth in some training views only: a broken capture, not one without depth
        capture.require_complete("train", ("depth", "diffuse"))
    depth = has_depth(capture)
    if config.source == "depth" or (config.source == "auto" and depth):
        gaussians, summary = dense_init(capture, config)
        why = "config source: depth" if config.source == "depth" else "every training view has depth + diffuse"
        return gaussians, {"source": "depth", **summary, "decision": f"dense init from depth ({why})"}
    found = read_sfm_points(capture_dir)
    if found is None:
        missing = "has no depth buffer and " if not depth else ""
        raise CaptureError(f"{capture_dir}: {missing}no SfM points to initialise from "
                           f"(expected {capture_dir / 'points3D.ply'}, a COLMAP model in {capture_dir / 'sparse'}, "
                           "a ply_file_path in transforms.json or nerfstudio's colmap/sparse/0)")
    points, colours, source = found
    gaussians, summary = sfm_init(points, colours, config, where=str(source))
    why = "config source: sfm" if config.source == "sfm" else "the capture has no depth buffer"
    return gaussians, {**summary, "decision": f"SfM init from {source} ({why})"}
