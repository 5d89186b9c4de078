"""Deterministic quadrature over directions, used by the tests to check the BRDF and the
samplers independently of Monte Carlo.

Spherical coordinates in the local frame n = +z, with the view direction in the x-z
plane at azimuth pi, wo = (-sin theta_o, 0, cos theta_o), so that the mirror direction
lies at (theta_o, phi = 0) and the point wi = -wo at (pi - theta_o, phi = 0).
The integrands are sharply peaked (width ~ alpha, down to 1e-4) there; the grid is a
tensor product of Gauss-Legendre panels whose breakpoints refine geometrically (ratio 2,
down to `smallest`, 1e-7 rad by default) toward those points and include every place the integrand has a kink
or a jump (the horizon theta = pi/2, and theta = pi - theta_o where the half vector
crosses the horizon). Accuracy is estimated by comparing two orders (`order`).
"""

from __future__ import annotations

import math

import numpy as np
import torch


def view_dir(theta_o: float) -> np.ndarray:
    """wo in the local frame (n = +z) at polar angle theta_o (radians), azimuth pi. [3]."""
    return np.array([-math.sin(theta_o), 0.0, math.cos(theta_o)])


def refined_breaks(lo: float, hi: float, centers, smallest: float = 1e-7, extra=()) -> np.ndarray:
    """Sorted breakpoints in [lo, hi]: lo, hi, `extra`, and center +- smallest * 2^k."""
    pts = [lo, hi, *extra]
    steps = smallest * 2.0 ** np.arange(0, 64)
    steps = steps[steps < (hi - lo)]
    for c in centers:
        pts.append(c)
        pts.extend(c + steps)
        pts.extend(c - steps)
    b = np.unique(np.clip(np.asarray(pts, dtype=np.float64), lo, hi))
    return b[np.concatenate([[True], np.diff(b) > 1e-15])]


def gauss_panels(breaks: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Composite Gauss-Legendre nodes and weights on consecutive panels of `breaks`."""
    x, w = np.polynomial.legendre.leggauss(order)
    a, b = breaks[:-1, None], breaks[1:, None]
    half = 0.5 * (b - a)
    return (a + half * (x + 1.0)).ravel(), (half * w).ravel()


def sphere_grid(theta_o: float, order: int = 8, theta_max: float = math.pi,
                smallest: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """Directions and solid-angle weights covering theta in [0, theta_max], phi in [-pi, pi].
    Returns dirs [M, 3], weights [M] (sin theta included)."""
    tb = refined_breaks(0.0, theta_max, [theta_o, math.pi - theta_o, 0.0], smallest,
                        extra=(min(math.pi / 2, theta_max),))
    pb = refined_breaks(-math.pi, math.pi, [0.0], smallest)
    th, wt = gauss_panels(tb, order)
    ph, wp = gauss_panels(pb, order)
    T, P = np.meshgrid(th, ph, indexing="ij")
    W = np.outer(wt, wp) * np.sin(T)
    dirs = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1)
    return dirs.reshape(-1, 3), W.ravel()


def integrate(fn, dirs: np.ndarray, weights: np.ndarray, chunk: int = 1 << 18) -> np.ndarray:
    """sum_k fn(dirs_k) w_k with fn: torch float64 [M, 3] -> [M] or [M, C]."""
    total = 0.0
    for s in range(0, len(weights), chunk):
        d = torch.from_numpy(dirs[s:s + chunk])
        v = fn(d).detach().numpy()
        w = weights[s:s + chunk]
        total = total + (np.tensordot(w, v, axes=(0, 0)))
    return np.asarray(total)


def directional_albedo(eval_fn, roughness: float, theta_o: float, order: int = 8) -> np.ndarray:
    """E(wo) = int_{hemisphere} eval_fn(n, wo, wi, roughness, f0 = 1) dwi, by quadrature.
    eval_fn: like `brdf.eval_specular`. Returns [3]."""
    alpha = max(roughness, 0.01) ** 2
    dirs, w = sphere_grid(theta_o, order, theta_max=math.pi / 2, smallest=1e-3 * alpha)
    wo = torch.from_numpy(view_dir(theta_o))

    def fn(wi):
        m = wi.shape[0]
        n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(m, 3)
        return eval_fn(n, wo.expand(m, 3), wi, torch.full((m,), roughness, dtype=torch.float64),
                       torch.ones(m, 3, dtype=torch.float64))

    return integrate(fn, dirs, w)


def pdf_mass(pdf_fn, roughness: float, theta_o: float, order: int = 8,
             theta_range=(0.0, math.pi), phi_range=(-math.pi, math.pi),
             smallest: float = 1e-7) -> float:
    """int pdf_fn(n, wo, wi, roughness) dwi over a (theta, phi) box (default: the sphere)."""
    t0, t1 = theta_range
    p0, p1 = phi_range
    tb = refined_breaks(0.0, math.pi, [theta_o, math.pi - theta_o, 0.0], smallest,
                        extra=(math.pi / 2, t0, t1))
    pb = refined_breaks(-math.pi, math.pi, [0.0], smallest, extra=(p0, p1))
    tb = tb[(tb >= t0) & (tb <= t1)]
    pb = pb[(pb >= p0) & (pb <= p1)]
    th, wt = gauss_panels(tb, order)
    ph, wp = gauss_panels(pb, order)
    T, P = np.meshgrid(th, ph, indexing="ij")
    W = (np.outer(wt, wp) * np.sin(T)).ravel()
    dirs = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1).reshape(-1, 3)
    wo = torch.from_numpy(view_dir(theta_o))

    def fn(wi):
        m = wi.shape[0]
        n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(m, 3)
        return pdf_fn(n, wo.expand(m, 3), wi, torch.full((m,), roughness, dtype=torch.float64))

    return float(integrate(fn, dirs, W))


def binned_mass(pdf_fn, roughness: float, theta_o: float, theta_edges, phi_edges,
                order: int = 6) -> np.ndarray:
    """int pdf_fn dwi over each (theta, phi) bin of a grid whose edges cover the sphere
    (theta_edges from 0 to pi, phi_edges from -pi to pi, radians). Returns [T - 1, P - 1]."""
    te, pe = np.asarray(theta_edges, float), np.asarray(phi_edges, float)
    alpha = max(roughness, 0.01) ** 2
    tb = refined_breaks(0.0, math.pi, [theta_o, math.pi - theta_o, 0.0], 1e-3 * alpha,
                        extra=(math.pi / 2, *te))
    pb = refined_breaks(-math.pi, math.pi, [0.0], 1e-3 * alpha, extra=tuple(pe))
    th, wt = gauss_panels(tb, order)
    ph, wp = gauss_panels(pb, order)
    wo = torch.from_numpy(view_dir(theta_o))
    T, P = np.meshgrid(th, ph, indexing="ij")
    dirs = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1).reshape(-1, 3)
    m = dirs.shape[0]
    p = pdf_fn(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(m, 3), wo.expand(m, 3),
               torch.from_numpy(dirs), torch.full((m,), roughness, dtype=torch.float64)).numpy()
    w = p * (np.outer(wt, wp) * np.sin(T)).ravel()
    out, _, _ = np.histogram2d(T.ravel(), P.ravel(), bins=[te, pe], weights=w)
    return out


def to_theta_phi(wi: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Polar and azimuth angles (radians) of directions in the local frame. [M, 3] -> [M], [M]."""
    d = wi.detach().double().numpy()
    return np.arccos(np.clip(d[:, 2], -1.0, 1.0)), np.arctan2(d[:, 1], d[:, 0])
