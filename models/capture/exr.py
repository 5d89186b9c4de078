"""Multi-channel float32 EXR through OpenImageIO: named channels in, named channels out; other images of a view
(PNG / JPEG) decoded to linear (``read_image_channels``)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from .color import srgb_to_linear
from .errors import CaptureError


def read_exr_channels(path: str | Path) -> dict[str, np.ndarray]:
    """Every channel of every part of an EXR as float32 ``[H, W]`` arrays keyed by name."""
    path = Path(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise CaptureError(f"{path}: cannot read image ({oiio.geterror().strip() or 'unknown OpenImageIO error'})")
    channels: dict[str, np.ndarray] = {}
    try:
        sub = 0
        while inp.seek_subimage(sub, 0):
            spec = inp.spec()
            pixels = inp.read_image(sub, 0, 0, spec.nchannels, oiio.FLOAT)
            if pixels is None:
                raise CaptureError(f"{path}: failed to read pixels of part {sub} ({inp.geterror().strip()})")
            pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
            for i, name in enumerate(spec.channelnames):
                if name in channels and channels[name].shape != pixels.shape[:2]:
                    raise CaptureError(f"{path}: channel {name!r} appears in two parts with different sizes")
                channels.setdefault(name, pixels[:, :, i].copy())
            sub += 1
    finally:
        inp.close()
    return channels


def read_image_channels(path: str | Path) -> dict[str, np.ndarray]:
    """Channels of a view's image as linear float32 ``[H, W]`` arrays keyed by name: an EXR (or any float image)
    as stored; an integer image (8/16-bit PNG, JPEG, TIFF) is sRGB-encoded unless its header says linear
    (``oiio:ColorSpace``, e.g. a PNG gAMA of 1.0), so its R, G, B are decoded with ``color.srgb_to_linear``
    (other channels, alpha, stay as stored, scaled to [0, 1])."""
    if not srgb_encoded(path):
        return read_exr_channels(path)
    channels = read_exr_channels(path)
    for name in ("R", "G", "B"):
        if name in channels:
            channels[name] = srgb_to_linear(channels[name]).astype(np.float32)
    return channels


def srgb_encoded(path: str | Path) -> bool:
    """True for an integer-valued image (PNG, JPEG, integer TIFF) whose header does not say it is linear: 8-bit
    images are sRGB unless the file says otherwise. Float images (EXR, float TIFF) are linear."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise CaptureError(f"{path}: cannot read image ({oiio.geterror().strip() or 'unknown OpenImageIO error'})")
    try:
        spec = inp.spec()
    finally:
        inp.close()
    if spec.format.basetype not in (oiio.UINT8, oiio.INT8, oiio.UINT16, oiio.INT16, oiio.UINT32, oiio.INT32):
        return False
    space = spec.get_string_attribute("oiio:ColorSpace").lower()
    return not (space.startswith("lin") or "linear" in space)


def write_exr_channels(path: str | Path, channels: dict[str, np.ndarray]) -> None:
    """Write float32 ``[H, W]`` channels (in dict order) to one EXR, lossless (zip)."""
    path = Path(path)
    names = list(channels)
    if not names:
        raise ValueError(f"{path}: no channels to write")
    stack = np.stack([np.asarray(channels[n], dtype=np.float32) for n in names], axis=-1)
    height, width, nch = stack.shape
    spec = oiio.ImageSpec(width, height, nch, oiio.FLOAT)
    spec.channelnames = tuple(names)
    spec.attribute("compression", "zip")
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.exr")
    out = oiio.ImageOutput.create(str(tmp))
    if out is None or not out.open(str(tmp), spec):
        raise OSError(f"{path}: cannot open for writing ({oiio.geterror().strip()})")
    ok = out.write_image(np.ascontiguousarray(stack))
    out.close()
    if not ok:
        tmp.unlink(missing_ok=True)
        raise OSError(f"{path}: write failed ({out.geterror().strip()})")
    os.replace(tmp, path)
