"""Buffer layers of the capture format and their EXR channel names.

A view's buffers are a dict ``layer -> float32 [H, W, C]``. The EXR channel
names are the contract other tools write too (ARCHITECTURE.md, "The capture
format"); readers ignore channels they do not know.
"""

# layer -> EXR channel names, in order. ``rgb`` is the final radiance.
LAYER_CHANNELS: dict[str, tuple[str, ...]] = {
    "rgb": ("R", "G", "B"),
    "diffuse": ("diffuse.R", "diffuse.G", "diffuse.B"),
    "specular": ("specular.R", "specular.G", "specular.B"),
    "depth": ("depth.Z",),  # distance along the ray, not z-depth
    "normal": ("normal.X", "normal.Y", "normal.Z"),  # world space, unit
    "roughness": ("roughness.Y",),  # perceptual; GGX alpha = roughness^2
    "f0": ("f0.R", "f0.G", "f0.B"),  # base reflectance
    "mask": ("mask.Y",),  # 1 = valid pixel
    "emission": ("emission.R", "emission.G", "emission.B"),  # lights seen directly
}

# layer -> channel count
LAYERS: dict[str, int] = {name: len(ch) for name, ch in LAYER_CHANNELS.items()}

# channel name -> (layer, index within the layer)
CHANNEL_TO_LAYER: dict[str, tuple[str, int]] = {
    ch: (layer, i) for layer, chans in LAYER_CHANNELS.items() for i, ch in enumerate(chans)
}


def layer_prefix(channel: str) -> str:
    """The layer a channel name claims to belong to ('' for the bare R,G,B of ``rgb``)."""
    return channel.rsplit(".", 1)[0] if "." in channel else ""
