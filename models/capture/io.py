"""Read and write the capture format: ``transforms.json`` + one multi-channel EXR per view + ``capture.yaml``."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Iterable

import numpy as np
import yaml

from models.settings import read_yaml_mapping

from .camera import Camera
from .errors import CaptureError
from .exr import read_image_channels, srgb_encoded, write_exr_channels
from .layers import LAYER_CHANNELS, LAYERS, layer_prefix
from .nerfstudio_layout import check_camera_model, list_splits, read_transforms
from .types import SPLITS, Capture, CaptureMeta, View, check_buffer

INTRINSICS = ("w", "h", "fl_x", "fl_y", "cx", "cy")
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def write_capture(capture: Capture, out_dir: str | Path) -> Path:
    """Write ``capture`` to ``out_dir`` atomically (a temp folder renamed into place). Returns ``out_dir``."""
    capture.check()
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.with_name(f".{out_dir.name}.tmp{os.getpid()}")
    if tmp.exists():
        shutil.rmtree(tmp)
    (tmp / "images").mkdir(parents=True)

    shared = _shared_intrinsics(capture.views)
    frames = []
    for view in capture.views:
        rel = f"images/{view.name}.exr"
        channels = {
            ch: view.buffers[layer][:, :, i]
            for layer in LAYERS
            if layer in view.buffers
            for i, ch in enumerate(LAYER_CHANNELS[layer])
        }
        write_exr_channels(tmp / rel, channels)
        frame = {"file_path": rel, "transform_matrix": view.camera.c2w.tolist(), "split": view.split}
        if shared is None:
            frame.update(_intrinsics(view.camera))
        frames.append(frame)
    transforms = {**(shared or {}), "camera_model": "PINHOLE", "frames": frames}
    (tmp / "transforms.json").write_text(json.dumps(transforms, indent=1))
    meta = asdict(capture.meta)
    meta["channels"] = capture.layers
    (tmp / "capture.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))

    if out_dir.exists():
        old = out_dir.with_name(f".{out_dir.name}.old{os.getpid()}")
        os.replace(out_dir, old)
        os.replace(tmp, out_dir)
        shutil.rmtree(old)
    else:
        os.replace(tmp, out_dir)
    return out_dir


def read_capture(path: str | Path, layers: Iterable[str] | None = None, check: bool = True) -> Capture:
    """Read a capture folder. ``layers``: only load these (default: every known layer present).

    Channels the format does not know are ignored. Raises CaptureError naming the file and problem.
    """
    path = Path(path)
    tf_path = path / "transforms.json"
    if not tf_path.is_file():
        if (path / "transforms_train.json").is_file():
            from .paper_layout import read_paper_capture

            return read_paper_capture(path, layers=layers)
        from .points import colmap_model_dir

        if colmap_model_dir(path) is not None:
            from .colmap_layout import read_colmap_capture

            return read_colmap_capture(path, layers=layers)
        raise CaptureError(f"{path}: not a capture (no transforms.json, transforms_train.json or COLMAP sparse/)")
    if layers is not None:
        layers = list(layers)
        unknown = [l for l in layers if l not in LAYERS]
        if unknown:
            raise ValueError(f"unknown layer(s) {unknown} (known: {', '.join(LAYERS)})")
    tf = read_transforms(tf_path)
    frames = tf.get("frames")
    if not isinstance(frames, list) or not frames:
        raise CaptureError(f"{tf_path}: 'frames' must be a non-empty list")
    listed = list_splits(tf, tf_path)  # nerfstudio's train_filenames / test_filenames (nerfstudio_layout.py)

    views, decoded = [], 0
    for i, frame in enumerate(frames):
        where = f"{tf_path} frame {i}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise CaptureError(f"{where}: needs 'file_path' and 'transform_matrix'")
        split = frame.get("split", "train")
        if listed is not None:
            if "split" in frame and listed[i] is not None and frame["split"] != listed[i]:
                raise CaptureError(f"{where} ({frame['file_path']}): split {frame['split']!r} but the *_filenames "
                                   f"lists put it in {listed[i]!r}")
            split = listed[i]
            if split is None:  # listed in no split: left out, as nerfstudio does
                continue
        image = _resolve_image(path, frame["file_path"], where)
        camera = _camera(tf, frame, where)
        if split not in SPLITS:
            raise CaptureError(f"{where} ({frame['file_path']}): unknown split {split!r} (expected one of {', '.join(SPLITS)})")
        camera.check(f"{where} ({frame['file_path']})")
        buffers = read_view_buffers(image, camera.height, camera.width, layers, check=check)
        decoded += image.suffix.lower() != ".exr" and srgb_encoded(image)
        views.append(View(name=Path(frame["file_path"]).stem, camera=camera, split=split, buffers=buffers))

    meta = _read_meta(path / "capture.yaml")
    if decoded:
        meta.extra["rgb"] = f"{decoded} 8-bit sRGB image(s) decoded to linear (not HDR)"
    if listed is not None:
        meta.extra["splits"] = {"from": [k for k in ("train_filenames", "val_filenames", "test_filenames") if k in tf],
                                "left_out": sum(s is None for s in listed)}
    capture = Capture(views=views, meta=meta)
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        raise CaptureError(f"{tf_path}: two frames share an image name")
    return capture


def read_view_buffers(
    image: Path, height: int, width: int, layers: Iterable[str] | None = None, check: bool = True
) -> dict[str, np.ndarray]:
    """Known layers of one view's EXR as float32 ``[H, W, C]``; validates channel counts, size and finiteness.
    A PNG / JPEG view (8-bit, sRGB unless the file says linear) gives its R, G, B decoded to linear."""
    channels = read_image_channels(image)
    wanted = list(LAYERS) if layers is None else list(layers)
    buffers = {}
    for layer in LAYERS:
        expected = LAYER_CHANNELS[layer]
        present = [c for c in expected if c in channels]
        prefix = "" if layer == "rgb" else layer
        extra = [c for c in channels if prefix and layer_prefix(c) == prefix and c not in expected]
        if not present and not extra:
            continue
        if len(present) != len(expected) or extra:
            raise CaptureError(
                f"{image}: layer {layer!r} has {len(present) + len(extra)} channel(s) "
                f"{sorted(present + extra)}, expected {len(expected)}: {list(expected)}"
            )
        if layer not in wanted:
            continue
        arr = np.stack([channels[c] for c in expected], axis=-1)
        if check:
            check_buffer(str(image), layer, arr, height, width)
        buffers[layer] = arr
    return buffers


def _shared_intrinsics(views: list[View]) -> dict | None:
    first = _intrinsics(views[0].camera)
    return first if all(_intrinsics(v.camera) == first for v in views) else None


def _intrinsics(cam: Camera) -> dict:
    return {"w": cam.width, "h": cam.height, "fl_x": cam.fl_x, "fl_y": cam.fl_y, "cx": cam.cx, "cy": cam.cy}


def _camera(tf: dict, frame: dict, where: str) -> Camera:
    values = {}
    for key in INTRINSICS:
        value = frame.get(key, tf.get(key))
        if value is None:
            raise CaptureError(f"{where}: intrinsic {key!r} missing (neither in the frame nor at top level)")
        values[key] = value
    model = check_camera_model(tf, frame, where)
    for key in DISTORTION:
        if float(frame.get(key, tf.get(key, 0.0)) or 0.0) != 0.0:
            raise CaptureError(f"{where}: distortion {key}={frame.get(key, tf.get(key))} is not supported "
                               f"(camera_model {model}, image {frame.get('file_path')!r}); undistort the images to "
                               "PINHOLE first (e.g. python -m stages.poses on the photos)")
    c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
    if c2w.shape == (3, 4):
        c2w = np.vstack([c2w, [0, 0, 0, 1]])
    return Camera(
        width=int(values["w"]), height=int(values["h"]),
        fl_x=float(values["fl_x"]), fl_y=float(values["fl_y"]),
        cx=float(values["cx"]), cy=float(values["cy"]), c2w=c2w,
    )


def _resolve_image(root: Path, file_path: str, where: str) -> Path:
    image = root / file_path
    if image.suffix == "" and not image.is_file():
        image = image.with_suffix(".exr")
    if not image.is_file():
        raise CaptureError(f"{where}: image {file_path!r} is missing ({image} not found)")
    return image


def _read_meta(path: Path) -> CaptureMeta:
    if not path.is_file():
        return CaptureMeta(source="unknown")
    raw = read_yaml_mapping(path, CaptureError)
    known = {k: raw[k] for k in ("source", "color_space", "extent", "units", "extra") if k in raw}
    return CaptureMeta(**known)
