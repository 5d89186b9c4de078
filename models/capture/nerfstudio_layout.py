"""nerfstudio's ``transforms.json`` keys beyond the capture format's core (ARCHITECTURE.md).

The capture format is nerfstudio-style, so a dataset written by nerfstudio (``ns-process-data``) or a tool
following it reads as a capture (``read_capture``). What such a folder adds, and how it is read:

```
transforms.json  camera_model       PINHOLE / SIMPLE_PINHOLE (or absent), or OPENCV / SIMPLE_RADIAL / RADIAL
                                    with zero distortion (k1..k4, p1, p2 absent or 0): a pinhole camera. Fisheye
                                    / equirectangular models and non-zero distortion are refused, naming the
                                    file (undistort the images to PINHOLE first).
                 train_filenames    the splits, paths as in the frames' file_path. Listed frames are train /
                 test_filenames     test (a val list also goes to test: the capture has no validation split).
                 val_filenames      Without train_filenames the frames not listed are train; with it, frames
                                    listed nowhere are left out (as nerfstudio does; counted in meta.extra).
                 ply_file_path      initial points: PLY x, y, z + 8-bit sRGB red, green, blue in the frame of
                                    transform_matrix (nerfstudio's sparse_pc.ply)
                 applied_transform  [3, 4] COLMAP world -> transforms.json world, for colmap/sparse/0 (absent:
                                    nerfstudio's legacy value, used only if the COLMAP cameras then line up)
colmap/sparse/0/                    ns-process-data's COLMAP model: the points when there is no ply_file_path
images/*.png|jpg                    8-bit images are sRGB unless the file says linear: decoded to linear on read
                                    (``exr.read_image_channels``); EXR / float images are linear
```
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .errors import CaptureError

# nerfstudio camera models that are a pinhole camera once their distortion coefficients are zero
PINHOLE_WHEN_UNDISTORTED = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL")
SPLIT_LISTS = {"train_filenames": "train", "val_filenames": "test", "test_filenames": "test"}
# what nerfstudio assumes for colmap/sparse/0 when transforms.json has no applied_transform
LEGACY_APPLIED_TRANSFORM = ((0.0, 1.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -1.0, 0.0))
COLMAP_MODEL = Path("colmap") / "sparse" / "0"


def read_transforms(tf_path: Path) -> dict:
    try:
        tf = json.loads(Path(tf_path).read_text())
    except json.JSONDecodeError as e:
        raise CaptureError(f"{tf_path}: invalid JSON ({e})") from None
    if not isinstance(tf, dict):
        raise CaptureError(f"{tf_path}: expected a JSON object, got {type(tf).__name__}")
    return tf


def check_camera_model(tf: dict, frame: dict, where: str) -> str:
    """The frame's nerfstudio ``camera_model`` (default PINHOLE); CaptureError unless it is a pinhole model."""
    model = frame.get("camera_model", tf.get("camera_model", "PINHOLE"))
    if model not in PINHOLE_WHEN_UNDISTORTED:
        raise CaptureError(f"{where}: camera_model {model!r} is not a pinhole camera; read are "
                           f"{', '.join(PINHOLE_WHEN_UNDISTORTED)} without distortion: undistort the images to "
                           "PINHOLE first")
    return model


def _key(file_path: str) -> str:
    return os.path.normpath(str(file_path))


def list_splits(tf: dict, tf_path: Path) -> list[str | None] | None:
    """Split of each frame from nerfstudio's ``train_filenames`` / ``val_filenames`` / ``test_filenames``
    (None: the frame is listed nowhere and left out); None when transforms.json has no such list."""
    present = [k for k in SPLIT_LISTS if k in tf]
    if not present:
        return None
    frames = tf.get("frames") or []
    index: dict[str, int] = {}
    for i, frame in enumerate(frames):
        if isinstance(frame, dict) and "file_path" in frame:
            index.setdefault(_key(frame["file_path"]), i)
    claimed: dict[int, str] = {}
    for key in present:
        names = tf[key]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise CaptureError(f"{tf_path}: {key} must be a list of paths (as in the frames' file_path)")
        unknown = [n for n in names if _key(n) not in index]
        if unknown:
            raise CaptureError(f"{tf_path}: {key} lists {len(unknown)} path(s) that no frame's file_path has: "
                               f"{unknown[:3]}{' ...' if len(unknown) > 3 else ''}")
        for name in names:
            i = index[_key(name)]
            other = claimed.get(i)
            if other is not None and SPLIT_LISTS[other] != SPLIT_LISTS[key]:
                raise CaptureError(f"{tf_path}: {frames[i]['file_path']!r} is listed in both {other} and {key}")
            claimed[i] = key
    default = None if "train_filenames" in tf else "train"
    return [SPLIT_LISTS[claimed[i]] if i in claimed else default for i in range(len(frames))]


def ply_file_points(capture_dir: str | Path) -> tuple[np.ndarray, np.ndarray, Path] | None:
    """``(xyz [N, 3] float64, 8-bit sRGB rgb [N, 3] uint8, source)`` of the PLY transforms.json names in
    ``ply_file_path`` (in the frame of ``transform_matrix``); None without transforms.json or that key."""
    from .points import read_points_ply

    capture_dir = Path(capture_dir)
    tf_path = capture_dir / "transforms.json"
    if not tf_path.is_file():
        return None
    tf = read_transforms(tf_path)
    if not tf.get("ply_file_path"):
        return None
    ply = capture_dir / str(tf["ply_file_path"])
    if not ply.is_file():
        raise CaptureError(f"{tf_path}: ply_file_path {tf['ply_file_path']!r} does not exist ({ply} not found)")
    xyz, rgb = read_points_ply(ply)
    return xyz, rgb, ply


def colmap_folder_points(capture_dir: str | Path) -> tuple[np.ndarray, np.ndarray, Path] | None:
    """As ``ply_file_points``, from ns-process-data's ``colmap/sparse/0`` beside transforms.json, moved into the
    frames' world by ``applied_transform``; None without transforms.json or that model."""
    from .points import read_colmap_points

    capture_dir = Path(capture_dir)
    tf_path, model = capture_dir / "transforms.json", capture_dir / COLMAP_MODEL
    if not tf_path.is_file() or not any((model / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
        return None
    transform = _applied_transform(read_transforms(tf_path), tf_path, model)
    xyz, rgb = read_colmap_points(model)
    return xyz @ transform[:, :3].T + transform[:, 3], rgb, model


def _applied_transform(tf: dict, tf_path: Path, model: Path) -> np.ndarray:
    """transforms.json's ``applied_transform`` [3, 4] (else nerfstudio's legacy one), checked against the camera
    centres the COLMAP model and the frames share (matched by file name)."""
    from .colmap_layout import c2w_from_colmap, load_reconstruction

    given = "applied_transform" in tf
    try:
        transform = np.asarray(tf.get("applied_transform", LEGACY_APPLIED_TRANSFORM), dtype=np.float64)
    except (TypeError, ValueError):
        transform = np.zeros(0)
    if transform.shape != (3, 4) or not np.isfinite(transform).all():
        raise CaptureError(f"{tf_path}: applied_transform must be a finite 3x4 matrix, "
                           f"got {tf.get('applied_transform')!r}")
    centres = {}
    for frame in tf.get("frames") or []:
        if isinstance(frame, dict) and "file_path" in frame and "transform_matrix" in frame:
            centres[Path(frame["file_path"]).name] = np.asarray(frame["transform_matrix"], dtype=np.float64)[:3, 3]
    rec = load_reconstruction(model)
    pairs = [(c2w_from_colmap(im.cam_from_world().matrix())[:3, 3], centres[Path(im.name).name])
             for im in rec.images.values() if Path(im.name).name in centres]
    what = "applied_transform" if given else "no applied_transform (nerfstudio's legacy one tried)"
    if not pairs:
        if given:
            return transform
        raise CaptureError(f"{tf_path}: {what} and none of the images of {model} is a frame, so its points cannot be "
                           "put in the frames' world: add applied_transform or ply_file_path")
    colmap, ours = (np.array(c) for c in zip(*pairs))
    err = float(np.abs(colmap @ transform[:, :3].T + transform[:, 3] - ours).max())
    size = float(np.abs(ours - ours.mean(0)).max()) if len(ours) > 1 else float(np.abs(ours).max())
    if err > 1e-3 * max(size, 1e-6):
        raise CaptureError(f"{tf_path}: with {what}, the cameras of {model} do not line up with the frames' "
                           f"(largest centre mismatch {err:.3g} over {len(pairs)} shared image(s)); its points "
                           "are in another world frame: add the right applied_transform or a ply_file_path")
    return transform
