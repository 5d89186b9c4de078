"""Buffers <-> 3-channel images in [-1, 1], the space the VAE encodes (one prompt per buffer).

Capture conventions (what callers pass in and get back):

- ``diffuse``, ``specular``: ``[H, W, 3]`` linear radiance, in the input image's linear units.
- ``normal``: ``[H, W, 3]`` unit vectors in CAMERA space, OpenGL camera (x right, y up, z towards
  the viewer); encoded as the vector itself (the usual ``(n + 1) / 2`` normal colour, mapped to
  [-1, 1]); decoded with renormalisation (a zero vector decodes to ``(0, 0, 1)``, facing the camera).
- ``depth``: ``[H, W]`` planar z-depth on encode. The network predicts affine-invariant depth:
  per image, the 2nd / 98th percentiles of the valid depths map to 0 / 1 (clipped outside), then
  ``2 d - 1`` replicated over 3 channels. Decoded as ``[H, W]`` relative depth in [0, 1] (the channel
  mean), i.e. depth "up to scale and shift" (near 0, far 1): align it to metric depth with
  ``models.capture.depth_align.fit_scale_shift``.
- ``roughness``, ``metalness``: ``[H, W]`` in [0, 1], ``2 r - 1`` replicated over 3 channels; decoded as
  the channel mean.
- ``f0``: ``[H, W, 3]`` base reflectance in [0, 1], ``2 f - 1``.

Radiance (the input RGB and the diffuse / specular targets) is HDR: it is multiplied by a per-image
``exposure`` (``input_exposure``: the 95th percentile of the input's luminance maps to 1.0), then
mapped by the fixed invertible curve ``radiance_to_unit`` (Reinhard + gamma: the network's encoding, not a
display tonemap) into [-1, 1]. ``input_exposure`` + ``encode_rgb``
are what both training and inference call, so exposure handling is identical in both; scaling the input
by any k > 0 gives the same encoded image. Decoded values are clipped to their valid range.

Diffuse from the image: the image IS diffuse + specular (paper Eq. 2: a path's first vertex is evaluated with
f_d or f_s), so ``split_radiance`` forms the diffuse as the image minus the predicted specular (the default of
``BufferNetPipeline.predict``, ``radiance="complement"``). The diffuse prompt's own output has to carry every
texture of the image through the VAE, which the small CPU-trained VAE cannot do well; the specular is dark
and smooth, which it can.

Invalid pixels: ``encode_target(..., mask=)`` writes 0 (mid grey) where ``mask`` is False; the caller
masks those pixels out of the loss (the mask is not part of the encoding).
"""

from __future__ import annotations

import numpy as np
import torch

from models.capture.layers import PREDICTED as BUFFERS  # the network's buffers, in prompt order

# One prompt per buffer, RGB<->X style (REFERENCE.md, "Buffer network recipes"). Changing a prompt changes
# what a trained model outputs for that buffer: prompts are part of the model.
PROMPTS: dict[str, str] = {
    "diffuse": "Diffuse radiance (albedo times diffuse lighting)",
    "specular": "Specular radiance (glossy reflections)",
    "normal": "Camera-space Normal",
    "depth": "Depth",
    "roughness": "Roughness",
    "f0": "Base reflectance F0 (specular color at normal incidence)",
    "metalness": "Metallicness",  # optional buffer, not in BUFFERS
}

RADIANCE = ("diffuse", "specular")
RADIANCE_MODES = ("complement", "heads")  # how BufferNetPipeline.predict forms the diffuse (split_radiance)
SCALAR = ("depth", "roughness", "metalness")  # [H, W] buffers, replicated over 3 channels

EXPOSURE_PERCENTILE = 95.0  # luminance percentile of the input that the exposure maps to EXPOSURE_TARGET
EXPOSURE_TARGET = 1.0
TONEMAP_GAMMA = 2.2  # applied after Reinhard, so mid tones spread over the range like the sRGB images SD saw
TONEMAP_MAX = 0.999  # largest Reinhard value decoded (x = 0.999 / 0.001 = 999 exposed units): keeps the inverse finite
DEPTH_PERCENTILES = (2.0, 98.0)  # valid depths at these percentiles map to relative depth 0 and 1
LUMINANCE = (0.2126, 0.7152, 0.0722)  # Rec. 709 / linear sRGB


def check_buffer(buffer: str) -> None:
    """ValueError naming ``buffer`` and listing the valid names when it has no prompt."""
    if buffer not in PROMPTS:
        raise ValueError(f"unknown buffer {buffer!r}; valid buffers: {', '.join(PROMPTS)}")


def check_rgb(rgb: np.ndarray, where: str = "rgb_linear") -> np.ndarray:
    """``rgb`` as float32 ``[H, W, 3]``; ValueError naming its shape otherwise."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ValueError(f"{where} must be an [H, W, 3] linear RGB image, got shape {rgb.shape}")
    return rgb.astype(np.float32, copy=False)


def radiance_to_unit(x: torch.Tensor) -> torch.Tensor:
    """Exposed linear radiance ``x >= 0`` -> [-1, 1): ``2 (x / (1 + x))^(1/2.2) - 1``. NaN/negative -> 0."""
    x = torch.nan_to_num(x, nan=0.0, posinf=1e6).clamp_min(0.0)
    return 2.0 * (x / (1.0 + x)).pow(1.0 / TONEMAP_GAMMA) - 1.0


def radiance_from_unit(y: torch.Tensor) -> torch.Tensor:
    """Inverse of ``radiance_to_unit``; ``y`` is clipped to [-1, 2 TONEMAP_MAX^(1/2.2) - 1] first (output in
    [0, 999])."""
    r = ((y + 1.0) / 2.0).clamp(0.0, 1.0).pow(TONEMAP_GAMMA).clamp(0.0, TONEMAP_MAX)
    return r / (1.0 - r)


def input_exposure(rgb_linear: np.ndarray) -> float:
    """Per-image exposure: ``EXPOSURE_TARGET / percentile_95(luminance)`` over finite pixels (negative values
    count as 0). A black (or all non-finite) image gets exposure 1."""
    rgb = check_rgb(rgb_linear)
    lum = np.clip(rgb, 0.0, None) @ np.asarray(LUMINANCE, dtype=np.float32)
    lum = lum[np.isfinite(lum)]
    if lum.size == 0:
        return 1.0
    level = float(np.percentile(lum, EXPOSURE_PERCENTILE))
    return EXPOSURE_TARGET / level if level > 1e-8 else 1.0


def encode_rgb(rgb_linear: np.ndarray, exposure: float) -> torch.Tensor:
    """Linear RGB ``[H, W, 3]`` -> ``[3, H, W]`` float32 in [-1, 1): ``radiance_to_unit(exposure * rgb)``."""
    rgb = torch.from_numpy(np.ascontiguousarray(check_rgb(rgb_linear)))
    return radiance_to_unit(rgb * float(exposure)).permute(2, 0, 1).contiguous()


def _hw(array: np.ndarray, buffer: str, channels: int) -> np.ndarray:
    a = np.asarray(array, dtype=np.float32)
    if channels == 1 and a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    ok = a.ndim == 2 if channels == 1 else (a.ndim == 3 and a.shape[2] == 3)
    if not ok:
        want = "[H, W]" if channels == 1 else "[H, W, 3]"
        raise ValueError(f"{buffer} must be {want}, got shape {a.shape}")
    return a


def normalise_depth(depth: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Planar depth ``[H, W]`` -> affine-invariant depth in [0, 1]: percentiles DEPTH_PERCENTILES of the valid
    (finite, > 0, and ``valid``) pixels map to 0 / 1, clipped. Invalid pixels get 0; a constant or empty depth
    gives 0 everywhere."""
    ok = np.isfinite(depth) & (depth > 0)
    if valid is not None:
        ok &= valid
    out = np.zeros_like(depth, dtype=np.float32)
    if not ok.any():
        return out
    lo, hi = np.percentile(depth[ok], DEPTH_PERCENTILES)
    if hi - lo <= 1e-12 * max(abs(hi), 1.0):
        return out
    out[ok] = np.clip((depth[ok] - lo) / (hi - lo), 0.0, 1.0)
    return out


def encode_target(buffer: str, array: np.ndarray, exposure: float, mask: np.ndarray | None = None) -> torch.Tensor:
    """A buffer in capture conventions (module docstring) -> ``[3, H, W]`` float32 in [-1, 1]. ``exposure`` is
    the INPUT image's (``input_exposure``), used by diffuse / specular only. ``mask`` ``[H, W]`` bool: False
    pixels are written as 0 (the caller masks them out of the loss)."""
    check_buffer(buffer)
    if buffer in SCALAR:
        a = _hw(array, buffer, 1)
        if buffer == "depth":
            a = normalise_depth(a, None if mask is None else np.asarray(mask, dtype=bool))
        a = np.repeat(np.clip(np.nan_to_num(a), 0.0, 1.0)[..., None], 3, axis=2)
        t = torch.from_numpy(a) * 2.0 - 1.0
    else:
        a = _hw(array, buffer, 3)
        if buffer in RADIANCE:
            t = radiance_to_unit(torch.from_numpy(a) * float(exposure))
        elif buffer == "normal":
            t = torch.from_numpy(np.nan_to_num(a)).clamp(-1.0, 1.0)
        else:  # f0
            t = torch.from_numpy(np.clip(np.nan_to_num(a), 0.0, 1.0)) * 2.0 - 1.0
    t = t.permute(2, 0, 1).contiguous().float()
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != t.shape[1:]:
            raise ValueError(f"{buffer}: mask shape {m.shape} does not match the buffer's {tuple(t.shape[1:])}")
        t = t * torch.from_numpy(m)[None].to(t.dtype)
    return t


def split_radiance(rgb_linear: np.ndarray, specular: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(diffuse, specular) ``[H, W, 3]`` that sum to ``max(rgb, 0)`` exactly: the specular clipped per channel to
    ``[0, max(rgb, 0)]`` (no pixel reflects more than it shows), the diffuse the rest of the image."""
    rgb = np.clip(np.nan_to_num(check_rgb(rgb_linear)), 0.0, None)
    spec = np.asarray(specular, dtype=np.float32)
    if spec.shape != rgb.shape:
        raise ValueError(f"specular shape {spec.shape} does not match the image's {rgb.shape}")
    spec = np.clip(np.nan_to_num(spec), 0.0, rgb)
    return rgb - spec, spec


def decode_output(buffer: str, tensor: torch.Tensor, exposure: float) -> np.ndarray:
    """``[3, H, W]`` network output in [-1, 1] -> the buffer in capture conventions (module docstring),
    clipped to its valid range. ``exposure``: the input's, to bring diffuse / specular back to its units."""
    check_buffer(buffer)
    t = torch.as_tensor(tensor).detach().float().cpu()
    if t.ndim != 3 or t.shape[0] != 3:
        raise ValueError(f"{buffer}: expected a [3, H, W] tensor, got shape {tuple(t.shape)}")
    t = torch.nan_to_num(t).clamp(-1.0, 1.0)
    if buffer in SCALAR:
        return ((t.mean(dim=0) + 1.0) / 2.0).clamp(0.0, 1.0).numpy()
    if buffer in RADIANCE:
        out = radiance_from_unit(t) / float(exposure)
    elif buffer == "normal":
        norm = t.norm(dim=0, keepdim=True)
        facing = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand_as(t)
        out = torch.where(norm > 1e-6, t / norm.clamp_min(1e-6), facing)
    else:  # f0
        out = ((t + 1.0) / 2.0).clamp(0.0, 1.0)
    return out.permute(1, 2, 0).contiguous().numpy()
