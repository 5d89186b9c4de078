"""A rendered view on disk: one EXR with the capture's channel names + one PNG per layer."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.capture import LAYER_CHANNELS
from models.capture.color import linear_to_srgb
from models.capture.exr import write_exr_channels


def write_layers(out_dir: Path, name: str, img: dict[str, np.ndarray]) -> None:
    """<out_dir>/<name>.exr with capture channel names (R,G,B = final) + <out_dir>/png/<name>_<layer>.png."""
    channels = {}
    names = {"final": "rgb"}
    for layer, arr in img.items():
        key = names.get(layer, layer)
        if key in LAYER_CHANNELS:
            chans = LAYER_CHANNELS[key]
        else:
            suffix = ("R", "G", "B") if arr.shape[-1] == 3 else ("Y",)
            chans = tuple(f"{layer}.{s}" for s in suffix)
        for i, c in enumerate(chans):
            channels[c] = arr[..., i]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_exr_channels(out_dir / f"{name}.exr", channels)
    png_dir = out_dir / "png"
    png_dir.mkdir(exist_ok=True)
    import imageio.v3 as iio

    for layer, arr in img.items():
        iio.imwrite(png_dir / f"{name}_{layer}.png", to_png(layer, arr))


def to_png(layer: str, arr: np.ndarray) -> np.ndarray:
    if layer == "normal":
        v = arr * 0.5 + 0.5
    elif layer == "depth":
        finite = arr[arr > 0]
        v = arr / (finite.max() if finite.size else 1.0)
    elif layer in ("roughness", "f0", "transmittance"):
        v = arr
    else:
        v = linear_to_srgb(arr)
    v = np.clip(v, 0, 1)
    if v.shape[-1] == 1:
        v = np.repeat(v, 3, axis=-1)
    return (v * 255 + 0.5).astype(np.uint8)


