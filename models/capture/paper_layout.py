"""Reader for the paper's released synthetic layout.

``transforms_{train,test}.json`` (NeRF/OpenGL camera-to-world, ``camera_angle_x``);
per frame one file per buffer, named by replacing ``render`` in ``file_path`` with
``diffuse``, ``specular``, ``roughness``, ``normal`` (world), ``depth`` (distance
along the ray), ``f0``; ``.exr``, else ``.tiff``, else ``.png``. 8-bit PNG colour
buffers are tonemapped with the filmic curve ``(x(6.2x+0.5))/(x(6.2x+1.7)+0.06)``
raised to 1.3: inverted here on load.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Iterable

import numpy as np
import OpenImageIO as oiio

from .camera import Camera
from .errors import CaptureError
from .layers import COLOUR, LAYERS
from .types import Capture, CaptureMeta, View, check_buffer

EXTENSIONS = (".exr", ".tiff", ".tif", ".png")
# capture layer -> the word replacing "render" in the file name
BUFFER_WORDS = {"rgb": "render", "diffuse": "diffuse", "specular": "specular", "roughness": "roughness",
                "normal": "normal", "depth": "depth", "f0": "f0"}
# 8-bit values are decoded at most to this tonemapped level (255 maps to infinite radiance).
MAX_TONEMAPPED = 1.0 - 1.0 / 512.0


def filmic(x: np.ndarray) -> np.ndarray:
    """The paper's 8-bit encoding of linear radiance: filmic curve, then ^1.3."""
    x = np.maximum(x, 0.0)
    return ((x * (6.2 * x + 0.5)) / (x * (6.2 * x + 1.7) + 0.06)) ** 1.3


def inverse_filmic(y: np.ndarray) -> np.ndarray:
    """Linear radiance from the paper's 8-bit encoding (inverse of ``filmic``; 1.0 is clamped)."""
    f = np.clip(np.asarray(y, dtype=np.float64), 0.0, 1.0) ** (1.0 / 1.3)
    f = np.minimum(f, MAX_TONEMAPPED)
    # f (6.2x^2 + 1.7x + 0.06) = 6.2x^2 + 0.5x  ->  a x^2 + b x + c = 0
    a = 6.2 * (1.0 - f)
    b = 0.5 - 1.7 * f
    c = -0.06 * f
    return (-b + np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)


def read_paper_capture(path: str | Path, layers: Iterable[str] | None = None) -> Capture:
    path = Path(path)
    wanted = list(LAYERS) if layers is None else list(layers)
    views = []
    for split in ("train", "test"):
        tf_path = path / f"transforms_{split}.json"
        if not tf_path.is_file():
            continue
        try:
            tf = json.loads(tf_path.read_text())
        except json.JSONDecodeError as e:
            raise CaptureError(f"{tf_path}: invalid JSON ({e})") from None
        if "camera_angle_x" not in tf:
            raise CaptureError(f"{tf_path}: 'camera_angle_x' missing")
        for i, frame in enumerate(tf.get("frames", [])):
            where = f"{tf_path} frame {i}"
            base = path / frame["file_path"]
            rgb_file = _find(base, where, required=True)
            buffers = {}
            for layer, word in BUFFER_WORDS.items():
                if layer not in wanted:
                    continue
                file = rgb_file if layer == "rgb" else _find(_rename(base, word), where, required=False)
                if file is not None:
                    buffers[layer] = _read_buffer(file, layer)
            h, w = buffers["rgb"].shape[:2] if "rgb" in buffers else _size(rgb_file)
            fl = 0.5 * w / math.tan(0.5 * float(tf["camera_angle_x"]))
            c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
            camera = Camera(w, h, fl, fl, w / 2.0, h / 2.0, c2w)
            camera.check(where)
            for layer, arr in buffers.items():
                check_buffer(str(file), layer, arr, h, w)
            name = f"{split}_{Path(frame['file_path']).stem}"
            views.append(View(name=name, camera=camera, split=split, buffers=buffers))
    if not views:
        raise CaptureError(f"{path}: no frames in transforms_train.json / transforms_test.json")
    return Capture(views=views, meta=CaptureMeta(source="paper", extra={"layout": "paper-synthetic"}))


def _rename(base: Path, word: str) -> Path:
    if "render" not in base.name:
        return base.with_name(f"{word}_{base.name}")
    return base.with_name(base.name.replace("render", word))


def _find(base: Path, where: str, required: bool) -> Path | None:
    candidates = [base] if base.suffix.lower() in EXTENSIONS else [base.with_suffix(e) for e in EXTENSIONS]
    for c in candidates:
        if c.is_file():
            return c
    if required:
        raise CaptureError(f"{where}: image {base} is missing (tried {', '.join(c.suffix for c in candidates)})")
    return None


def _size(file: Path) -> tuple[int, int]:
    inp = oiio.ImageInput.open(str(file))
    if inp is None:
        raise CaptureError(f"{file}: cannot read image ({oiio.geterror().strip()})")
    spec = inp.spec()
    inp.close()
    return spec.height, spec.width


def _read_buffer(file: Path, layer: str) -> np.ndarray:
    inp = oiio.ImageInput.open(str(file))
    if inp is None:
        raise CaptureError(f"{file}: cannot read image ({oiio.geterror().strip()})")
    spec = inp.spec()
    eight_bit = spec.format in (oiio.UINT8, oiio.UINT16)
    pixels = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT), dtype=np.float64)
    inp.close()
    pixels = pixels.reshape(spec.height, spec.width, spec.nchannels)
    want = LAYERS[layer]
    if spec.nchannels < want:
        raise CaptureError(f"{file}: layer {layer!r} needs {want} channel(s), file has {spec.nchannels}")
    pixels = pixels[:, :, :want]
    if eight_bit:
        if layer in COLOUR:
            pixels = inverse_filmic(pixels)
        elif layer == "normal":
            pixels = pixels * 2.0 - 1.0
            pixels /= np.maximum(np.linalg.norm(pixels, axis=-1, keepdims=True), 1e-12)
        elif layer == "depth":
            raise CaptureError(f"{file}: depth stored as integer image cannot be decoded; need EXR or float TIFF")
    return pixels.astype(np.float32)
