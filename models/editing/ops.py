"""Edit operations on the selected Gaussians. Each returns a new Gaussians (the input is not modified).

Stored conventions are kept (models/gaussians/scene.py, the trainer's clamp): roughness is the
perceptual value in [0, 1], F0 in [0, 1], diffuse linear RGB >= 0, quaternions wxyz (raw, so a
rotation keeps their norm), log-scales. Rigid ops move means, quaternions and normals together;
a uniform scale multiplies the offsets from the pivot and adds log(s) to every log-scale.
"""

from __future__ import annotations

import math

import torch

from models.gaussians import Gaussians
from models.gaussians.activations import quat_multiply
from models.pathtrace.paths import PathConfig, TraceFn

from .albedo import albedo_radiance
from .spec import Op

NEEDS_TRACER = frozenset({"set_albedo"})  # ops that trace the scene (apply_op passes them trace_fn and path)


def axis_angle_quat(axis, angle_deg: float, dtype=torch.float64) -> torch.Tensor:
    """Unit quaternion (wxyz) of a rotation by ``angle_deg`` about the unit ``axis``. [4]"""
    half = math.radians(angle_deg) / 2
    ax = torch.as_tensor(axis, dtype=dtype)
    ax = ax / ax.norm()
    return torch.cat([torch.tensor([math.cos(half)], dtype=dtype), math.sin(half) * ax])


def rotation_matrix(axis, angle_deg: float, dtype=torch.float64) -> torch.Tensor:
    """Rodrigues: [3, 3] rotation by ``angle_deg`` about ``axis`` (right-handed)."""
    ax = torch.as_tensor(axis, dtype=dtype)
    x, y, z = (ax / ax.norm()).tolist()
    k = torch.tensor([[0, -z, y], [z, 0, -x], [-y, x, 0]], dtype=dtype)
    t = math.radians(angle_deg)
    return torch.eye(3, dtype=dtype) + math.sin(t) * k + (1 - math.cos(t)) * (k @ k)


def selection_centre(g: Gaussians, mask: torch.Tensor) -> torch.Tensor:
    """Centre of the axis-aligned bounds of the selected means (the default pivot). [3]"""
    p = g.means.detach()[mask]
    return 0.5 * (p.amin(dim=0) + p.amax(dim=0))


def _with(g: Gaussians, **changes: torch.Tensor) -> Gaussians:
    params = {k: v.detach().clone() for k, v in g.params().items()}
    params.update(changes)
    return Gaussians(**params)


def _masked(g: Gaussians, mask: torch.Tensor, name: str, new_rows: torch.Tensor) -> torch.Tensor:
    out = getattr(g, name).detach().clone()
    out[mask] = new_rows.to(out.dtype)
    return out


def translate(g: Gaussians, mask: torch.Tensor, offset) -> Gaussians:
    return _with(g, means=_masked(g, mask, "means", g.means.detach()[mask] + g.means.new_tensor(offset)))


def rotate(g: Gaussians, mask: torch.Tensor, axis, angle: float, pivot=None) -> Gaussians:
    """Rigid rotation about ``pivot`` (default: the selection centre): means, quaternions and normals."""
    pivot = selection_centre(g, mask) if pivot is None else g.means.new_tensor(pivot)
    r = rotation_matrix(axis, angle)
    q = axis_angle_quat(axis, angle)
    f64 = torch.float64
    p = g.means.detach()[mask].to(f64) - pivot.to(f64)
    return _with(
        g,
        means=_masked(g, mask, "means", p @ r.T + pivot.to(f64)),
        quats=_masked(g, mask, "quats", quat_multiply(q.expand(int(mask.sum()), 4), g.quats.detach()[mask].to(f64))),
        normals=_masked(g, mask, "normals", g.normals.detach()[mask].to(f64) @ r.T),
    )


def scale(g: Gaussians, mask: torch.Tensor, factor: float, pivot=None) -> Gaussians:
    """Uniform scale about ``pivot`` (default: the selection centre); orientations and normals unchanged."""
    pivot = selection_centre(g, mask) if pivot is None else g.means.new_tensor(pivot)
    p = g.means.detach()[mask]
    return _with(
        g,
        means=_masked(g, mask, "means", pivot + factor * (p - pivot)),
        log_scales=_masked(g, mask, "log_scales", g.log_scales.detach()[mask] + math.log(factor)),
    )


def duplicate(g: Gaussians, mask: torch.Tensor, offset) -> Gaussians:
    """Append copies of the selected Gaussians moved by ``offset`` (originals keep their indices)."""
    params = {k: v.detach() for k, v in g.params().items()}
    copies = {k: v[mask].clone() for k, v in params.items()}
    copies["means"] = copies["means"] + g.means.new_tensor(offset)
    return Gaussians(**{k: torch.cat([params[k], copies[k]]) for k in params})


def delete(g: Gaussians, mask: torch.Tensor) -> Gaussians:
    return Gaussians(**{k: v.detach()[~mask].clone() for k, v in g.params().items()})


def set_roughness(g: Gaussians, mask: torch.Tensor, value: float) -> Gaussians:
    return _with(g, roughness=_masked(g, mask, "roughness", g.roughness.new_full((int(mask.sum()),), value)))


def shift_roughness(g: Gaussians, mask: torch.Tensor, delta: float) -> Gaussians:
    return _with(g, roughness=_masked(g, mask, "roughness", (g.roughness.detach()[mask] + delta).clamp(0, 1)))


def multiply_roughness(g: Gaussians, mask: torch.Tensor, factor: float) -> Gaussians:
    return _with(g, roughness=_masked(g, mask, "roughness", (g.roughness.detach()[mask] * factor).clamp(0, 1)))


def set_f0(g: Gaussians, mask: torch.Tensor, value) -> Gaussians:
    rgb = g.f0.new_tensor(value if isinstance(value, tuple) else (value,) * 3)
    return _with(g, f0=_masked(g, mask, "f0", rgb.expand(int(mask.sum()), 3)))


def set_diffuse(g: Gaussians, mask: torch.Tensor, value) -> Gaussians:
    return _with(g, diffuse=_masked(g, mask, "diffuse", g.diffuse.new_tensor(value).expand(int(mask.sum()), 3)))


def set_albedo(g: Gaussians, mask: torch.Tensor, value, samples: int, trace_fn: TraceFn | None = None,
               path: PathConfig | None = None) -> Gaussians:
    """Lambertian of albedo ``value``: diffuse radiance := albedo x the cosine-weighted mean of the radiance the
    other Gaussians send to each selected one (albedo.py)."""
    rgb = albedo_radiance(g, mask, value, samples, trace_fn, path)
    return _with(g, diffuse=_masked(g, mask, "diffuse", rgb))


def rgb_to_hsv(rgb: torch.Tensor) -> torch.Tensor:
    """[N, 3] RGB >= 0 -> [N, 3] (hue in [0, 6), saturation in [0, 1], value = max channel)."""
    v, imax = rgb.max(dim=-1)
    c = v - rgb.min(dim=-1).values
    safe = c.clamp_min(1e-12)
    r, g, b = rgb.unbind(-1)
    h = torch.where(imax == 0, ((g - b) / safe) % 6, torch.where(imax == 1, (b - r) / safe + 2, (r - g) / safe + 4))
    h = torch.where(c > 0, h, torch.zeros_like(h))
    s = torch.where(v > 0, c / v.clamp_min(1e-12), torch.zeros_like(v))
    return torch.stack([h, s, v], dim=-1)


def hsv_to_rgb(hsv: torch.Tensor) -> torch.Tensor:
    """Inverse of rgb_to_hsv. [N, 3] -> [N, 3]"""
    h, s, v = hsv.unbind(-1)
    k = (torch.tensor([5.0, 3.0, 1.0], dtype=hsv.dtype, device=hsv.device) + h[:, None]) % 6
    return v[:, None] - (v * s)[:, None] * torch.clamp(torch.minimum(k, 4 - k), 0, 1)


def shift_diffuse_hsv(g: Gaussians, mask: torch.Tensor, hue: float, saturation: float, value: float) -> Gaussians:
    """Hue rotated by ``hue`` degrees, saturation (clamped to [0, 1]) and value multiplied."""
    hsv = rgb_to_hsv(g.diffuse.detach()[mask].double())
    h = (hsv[:, 0] + hue / 60.0) % 6
    s = (hsv[:, 1] * saturation).clamp(0, 1)
    rgb = hsv_to_rgb(torch.stack([h, s, hsv[:, 2] * value], dim=-1)).clamp_min(0)
    return _with(g, diffuse=_masked(g, mask, "diffuse", rgb))


_FUNCS = {
    "translate": translate, "rotate": rotate, "scale": scale, "duplicate": duplicate, "delete": delete,
    "set_roughness": set_roughness, "shift_roughness": shift_roughness, "multiply_roughness": multiply_roughness,
    "set_f0": set_f0, "set_diffuse": set_diffuse, "shift_diffuse_hsv": shift_diffuse_hsv, "set_albedo": set_albedo,
}


def apply_op(g: Gaussians, op: Op, mask: torch.Tensor, trace_fn: TraceFn | None = None,
             path: PathConfig | None = None) -> Gaussians:
    """Apply one parsed op to the Gaussians of ``mask`` [N] bool. ``trace_fn`` (Tracer.trace) and ``path`` (the
    model's path settings) reach the ops of NEEDS_TRACER only; those raise ValueError without a trace_fn."""
    if op.kind in NEEDS_TRACER:
        return _FUNCS[op.kind](g, mask, **op.params, trace_fn=trace_fn, path=path)
    return _FUNCS[op.kind](g, mask, **op.params)
