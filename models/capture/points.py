"""SfM points of a capture: where they live and how they are read.

Contract (beside the capture format of ARCHITECTURE.md):

```
<capture>/points3D.ply   SfM points in the capture's world frame (the frame of transforms.json):
                         vertex x, y, z (float) and red, green, blue (uchar, sRGB as COLMAP stores them)
<capture>/sparse/        optional COLMAP model (cameras/images/points3D .bin or .txt, also sparse/0/),
                         in the same world frame; read when points3D.ply is absent
```

A nerfstudio folder (``nerfstudio_layout.py``) names its points in transforms.json (``ply_file_path``, read
first: the file says so) or has ns-process-data's ``colmap/sparse/0`` (read last, moved by ``applied_transform``).

``python -m stages.poses`` writes both; the paper's real-scene layout has ``sparse/``.
Readers return linear-RGB colours (sRGB decoded), the colour space of the capture's buffers.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from .color import srgb_to_linear
from .errors import CaptureError

POINTS_FILE = "points3D.ply"


def write_points_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Write points ``xyz`` [N, 3] with 8-bit sRGB colours ``rgb`` [N, 3] (binary PLY, atomically)."""
    path = Path(path)
    xyz = np.asarray(xyz, dtype=np.float32)
    rgb = np.asarray(rgb)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape:
        raise ValueError(f"{path}: need xyz [N, 3] and rgb [N, 3], got {xyz.shape} and {rgb.shape}")
    vertex = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = xyz.T
    vertex["red"], vertex["green"], vertex["blue"] = np.clip(rgb, 0, 255).astype(np.uint8).T
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(tmp))
    os.replace(tmp, path)


def read_points_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] float64 and 8-bit sRGB colours [N, 3] uint8 of a PLY with x,y,z,red,green,blue."""
    path = Path(path)
    try:
        vertex = PlyData.read(str(path))["vertex"]
    except Exception as e:  # plyfile raises several types for malformed files
        raise CaptureError(f"{path}: cannot read PLY points ({e})") from None
    names = vertex.data.dtype.names
    missing = [n for n in ("x", "y", "z", "red", "green", "blue") if n not in names]
    if missing:
        raise CaptureError(f"{path}: vertex properties {missing} missing (have {list(names)})")
    xyz = np.stack([vertex[n] for n in ("x", "y", "z")], axis=1).astype(np.float64)
    rgb = np.stack([vertex[n] for n in ("red", "green", "blue")], axis=1).astype(np.uint8)
    if not np.isfinite(xyz).all():
        raise CaptureError(f"{path}: {int((~np.isfinite(xyz)).any(axis=1).sum())} point(s) with NaN/Inf coordinates")
    return xyz, rgb


def colmap_model_dir(root: str | Path) -> Path | None:
    """The COLMAP model folder under ``root/sparse`` (``sparse/0`` first, then ``sparse``), or None."""
    root = Path(root)
    for cand in (root / "sparse" / "0", root / "sparse"):
        if any((cand / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
            return cand
    return None


def read_colmap_points(model_dir: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] float64 and sRGB colours [N, 3] uint8 of a COLMAP model folder."""
    import pycolmap

    model_dir = Path(model_dir)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises ValueError/RuntimeError with COLMAP's message
        raise CaptureError(f"{model_dir}: cannot read COLMAP model ({e})") from None
    if rec.num_points3D() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    pts = list(rec.points3D.values())
    return (np.array([p.xyz for p in pts], dtype=np.float64),
            np.array([p.color for p in pts], dtype=np.uint8))


def read_sfm_points(capture_dir: str | Path) -> tuple[np.ndarray, np.ndarray, Path] | None:
    """SfM points of a capture folder: ``(xyz [N, 3], linear rgb [N, 3] float64, source file)`` from
    transforms.json's ``ply_file_path``, else ``points3D.ply``, else the ``sparse/`` COLMAP model, else
    nerfstudio's ``colmap/sparse/0``; None when it has none of them."""
    found = find_sfm_points(capture_dir)
    if found is None:
        return None
    xyz, rgb, source = found
    return xyz, srgb_to_linear(rgb / 255.0), source


def find_sfm_points(capture_dir: str | Path) -> tuple[np.ndarray, np.ndarray, Path] | None:
    """As ``read_sfm_points`` with the colours as stored: 8-bit sRGB ``[N, 3]`` uint8."""
    from .nerfstudio_layout import colmap_folder_points, ply_file_points

    capture_dir = Path(capture_dir)
    found = ply_file_points(capture_dir)
    if found is not None:
        return found
    ply = capture_dir / POINTS_FILE
    if ply.is_file():
        xyz, rgb = read_points_ply(ply)
        return xyz, rgb, ply
    model = colmap_model_dir(capture_dir)
    if model is not None:
        xyz, rgb = read_colmap_points(model)
        return xyz, rgb, model
    return colmap_folder_points(capture_dir)
