"""Every layer the project names, declared once: the capture format's buffers with their EXR channel names, and
the named groups of them that the tracer, the buffer network, reconstruction, rendering and scoring use.

A view's buffers are a dict ``layer -> float32 [H, W, C]``. The EXR channel names are the contract other tools
write too (ARCHITECTURE.md, "The capture format"); readers ignore channels they do not know.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Layer:
    name: str
    channels: tuple[str, ...]  # EXR channel names, in order
    doc: str


REGISTRY: dict[str, Layer] = {layer.name: layer for layer in (
    Layer("rgb", ("R", "G", "B"), "final radiance: diffuse + specular (+ emission when present)"),
    Layer("diffuse", ("diffuse.R", "diffuse.G", "diffuse.B"), "first-vertex diffuse lobe (GI included, x albedo)"),
    Layer("specular", ("specular.R", "specular.G", "specular.B"), "first-vertex specular lobe"),
    Layer("depth", ("depth.Z",), "distance along the ray, not z-depth"),
    Layer("normal", ("normal.X", "normal.Y", "normal.Z"), "world-space unit normal"),
    Layer("roughness", ("roughness.Y",), "perceptual GGX roughness (alpha = roughness^2)"),
    Layer("f0", ("f0.R", "f0.G", "f0.B"), "base reflectance"),
    Layer("mask", ("mask.Y",), "1 = valid pixel"),
    Layer("emission", ("emission.R", "emission.G", "emission.B"), "light sources seen directly"),
)}

# layer -> EXR channel names; layer -> channel count
LAYER_CHANNELS: dict[str, tuple[str, ...]] = {name: layer.channels for name, layer in REGISTRY.items()}
LAYERS: dict[str, int] = {name: len(layer.channels) for name, layer in REGISTRY.items()}

# ---- named groups (orders are meaningful where noted)
RADIANCE = ("diffuse", "specular")  # the two lobes of the first vertex: rgb = their sum (+ emission), paper Eq. 2
COLOUR = ("rgb", *RADIANCE)  # HDR colour layers of a capture (decoded / tonemapped as colour)
GBUFFER = ("depth", "normal", "roughness", "f0")  # geometry and material of the first vertex
SUPERVISED = (*RADIANCE, *GBUFFER)  # what reconstruction has losses for (loss terms sum in this order)
TRACED = ("diffuse", "depth", "normal", "roughness", "f0")  # per-ray layers the tracer blends, in kernel packing order
PREDICTED = ("diffuse", "specular", "normal", "depth", "roughness", "f0")  # buffer-network outputs, in prompt order
SCORED = ("diffuse", "specular", "final")  # what renders are scored on; "final" is a render's rgb


def channels(names) -> dict[str, int]:
    """``{layer: channel count}`` of ``names`` (registry order kept as given)."""
    return {name: LAYERS[name] for name in names}


def diffuse_radiance(buffers: dict):
    """The view-independent radiance a Gaussian scene carries for a view's pixels (``[H, W, 3]`` or ``[R, 3]``):
    the ``diffuse`` layer plus ``emission`` (light sources seen directly) where the view has that layer, else
    ``diffuse`` itself (the same object). Reconstruction fits the Gaussians' diffuse radiance to it, scoring
    compares their rendered diffuse layer with it, and the final image is it + ``specular`` (= ``rgb``)."""
    if "emission" not in buffers:
        return buffers["diffuse"]
    return buffers["diffuse"] + buffers["emission"]


def layer_prefix(channel: str) -> str:
    """The layer a channel name claims to belong to ('' for the bare R,G,B of ``rgb``)."""
    return channel.rsplit(".", 1)[0] if "." in channel else ""


for _group in (RADIANCE, COLOUR, GBUFFER, SUPERVISED, TRACED, PREDICTED):
    assert set(_group) <= set(REGISTRY), _group
