"""Procedural RGB textures in numpy (fixed seed per texture): rich, non-repeating detail for SfM matching."""

from __future__ import annotations

import numpy as np

from .spec import TextureSpec


def _value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Tileable bilinear value noise in [0, 1]. # [size, size]"""
    grid = rng.random((cells, cells))
    t = np.arange(size) * cells / size
    i0 = np.floor(t).astype(int)
    f = t - i0
    f = f * f * (3 - 2 * f)  # smoothstep
    i1 = (i0 + 1) % cells
    rows0, rows1 = grid[i0], grid[i1]  # [size, cells]
    top = rows0[:, i0] * (1 - f)[None, :] + rows0[:, i1] * f[None, :]
    bot = rows1[:, i0] * (1 - f)[None, :] + rows1[:, i1] * f[None, :]
    return top * (1 - f)[:, None] + bot * f[:, None]


def _palette(t: np.ndarray, colors: np.ndarray) -> np.ndarray:
    """Map t in [0, 1] piecewise-linearly through ``colors`` [K, 3]. # [..., 3]"""
    k = len(colors) - 1
    x = np.clip(t, 0, 1) * k
    i = np.minimum(np.floor(x).astype(int), k - 1)
    f = (x - i)[..., None]
    return colors[i] * (1 - f) + colors[i + 1] * f


def make_texture(spec: TextureSpec) -> np.ndarray:
    """Linear RGB texels in [0, 1]. # [size, size, 3] float32"""
    rng = np.random.default_rng(spec.seed)
    n = spec.size
    colors = np.asarray(spec.colors, dtype=np.float64)
    if spec.type == "noise":
        t = np.zeros((n, n))
        amp, total = 1.0, 0.0
        for o in range(spec.octaves):
            cells = max(2, int(round(spec.scale * 2**o)))
            t += amp * _value_noise(rng, n, min(cells, n))
            total += amp
            amp *= 0.5
        t /= total
        t = (t - t.min()) / max(t.max() - t.min(), 1e-9)
        img = _palette(t, colors)
    elif spec.type == "checker":
        checks = max(1, int(round(spec.scale)))
        cell = (np.arange(n) * checks // n)
        cy, cx = np.meshgrid(cell, cell, indexing="ij")
        pick = rng.random((checks, checks))  # a random palette position per check
        img = _palette(pick[cy, cx], colors)
    else:  # guarded by spec parsing
        raise ValueError(f"texture {spec.name!r}: unknown type {spec.type!r}")
    # Sparse bright / dark dots plus per-texel variation: corners and blobs for feature matching.
    detail = spec.detail
    if detail > 0:
        img = img * (1 - detail + detail * _value_noise(rng, n, max(2, n // 4))[..., None] * 2 * rng.random(3) ** 0.2)
        n_dots = n * n // 2048
        ys, xs = rng.integers(0, n, n_dots), rng.integers(0, n, n_dots)
        r = max(1, n // 128)
        dot_col = rng.random((n_dots, 3))
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                img[(ys + dy) % n, (xs + dx) % n] = dot_col
    return np.clip(img, 0.0, 1.0).astype(np.float32)
