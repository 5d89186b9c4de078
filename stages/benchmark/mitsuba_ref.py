"""Mitsuba 3 rendering the same Gaussians with the same rays: the speed reference of the tracer benchmark.

Mitsuba's ``ellipsoids`` shape (Embree on the CPU, OptiX on CUDA) with the loop of its ``volprim_rf_basic``
integrator (one closest-shell query per primitive, the ray moved past it each time), evaluating OUR kernel
exp(-r^(2p) / (2p)), opacity, alpha_min / alpha_max and transmittance threshold on the diffuse colours. Each
Gaussian's shell is its cutoff ellipsoid (local radius s = (2p ln(opacity / alpha_min))^(1/(2p)), the support
our BVH bounds), so both see the same Gaussians. Mitsuba composites in shell-ENTRY order (ours: by the
max-response point t*) and, like every ``ellipsoids`` integrator, skips shells that contain the ray origin
(backface culling): its image differs from ours there, its cost is what is compared.
"""

from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from models.gaussians import Gaussians
from models.tracer import TracerConfig
from models.tracer._torch_impl import cutoff_radius


def variant(device: str) -> str:
    return "cuda_ad_rgb" if str(device).startswith("cuda") else "llvm_ad_rgb"


class MitsubaEllipsoids:
    """The Gaussians as a Mitsuba ``ellipsoids`` scene; ``render(origins, dirs)`` composites them."""

    def __init__(self, gaussians: Gaussians, config: TracerConfig, device: str = "cpu"):
        mi.set_variant(variant(device))
        self.config = config
        g = gaussians.to(device="cpu", dtype=torch.float64)
        opacity = g.opacities()
        s = cutoff_radius(opacity, config.kernel_p, config.alpha_min)
        keep = s > 0  # masked Gaussians (opacity <= alpha_min) have no shell
        q = torch.nn.functional.normalize(g.quats[keep], dim=1)
        data = torch.cat([g.means[keep], torch.exp(g.log_scales[keep]) * s[keep, None], q[:, 1:], q[:, :1]], dim=1)  # xyzw
        f32 = lambda t: mi.TensorXf(np.ascontiguousarray(t.numpy(), dtype=np.float32))  # noqa: E731
        self.count = int(keep.sum())
        self.scene = mi.load_dict({"type": "scene", "gaussians": {
            "type": "ellipsoids", "data": f32(data.reshape(-1)), "extent": 1.0,
            "opacities": f32(opacity[keep, None]), "cutoff": f32(s[keep, None]),
            "diffuse": f32(g.diffuse[keep])}})
        self.shape = self.scene.shapes()[0]

    def render(self, origins: torch.Tensor, dirs: torch.Tensor) -> tuple[np.ndarray, np.ndarray, float, float]:
        """(diffuse [R, 3], transmittance [R], wall s, CPU s) of the rays, timed from the query to the result."""
        o = origins.detach().cpu().double().numpy().astype(np.float32)
        d = dirs.detach().cpu().double().numpy().astype(np.float32)
        ray = mi.Ray3f(mi.Point3f(*(mi.Float(o[:, i]) for i in range(3))),
                       mi.Vector3f(*(mi.Float(d[:, i]) for i in range(3))))
        dr.eval(ray)
        dr.sync_thread()
        c0, w0 = time.process_time(), time.perf_counter()
        cfg = self.config
        colour, trans = _composite(self.scene, self.shape, ray, cfg.kernel_p, cfg.alpha_min, cfg.alpha_max,
                                   cfg.transmittance_threshold)
        dr.eval(colour, trans)
        dr.sync_thread()
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        return np.array(colour).T.astype(np.float32), np.array(trans).astype(np.float32), wall, cpu


@dr.syntax
def _composite(scene, shape, ray, p: int, alpha_min: float, alpha_max: float, threshold: float):
    """volprim_rf_basic's loop with our kernel: the nearest shell, its alpha at the max-response point, the ray
    moved past the shell entry; until T < threshold or no shell is left."""
    ray = mi.Ray3f(ray)
    active = mi.Bool(True)
    trans = mi.Float(1.0)
    colour = mi.Color3f(0.0)
    while active:
        si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=False, active=active)
        active &= si.is_valid()
        data = shape.eval_attribute_x("ellipsoid", si, active)
        centre = mi.Point3f(data[0], data[1], data[2])
        cutoff = shape.eval_attribute_1("cutoff", si, active)
        scale = mi.Vector3f(data[3], data[4], data[5]) / cutoff
        rot = dr.quat_to_matrix(mi.Matrix3f, mi.Quaternion4f(data[6], data[7], data[8], data[9]))
        o_l = (rot.T @ (ray.o - centre)) / scale
        d_l = (rot.T @ ray.d) / scale
        q = dr.cross(d_l, dr.cross(o_l, d_l)) / dr.dot(d_l, d_l)
        opacity = shape.eval_attribute_1("opacities", si, active)
        alpha = dr.minimum(opacity * dr.exp(-dr.power(dr.dot(q, q), p) / (2 * p)), alpha_max)
        alpha = dr.select(active & (alpha > alpha_min), alpha, 0.0)
        colour += (trans * alpha) * shape.eval_attribute_3("diffuse", si, active)
        trans *= 1.0 - alpha
        ray.o = dr.select(active, si.p + ray.d * 1e-4, ray.o)
        active &= trans >= threshold
    return colour, trans
