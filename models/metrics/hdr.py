"""Scoring HDR radiance without clamping errors away: the peak a linear PSNR is stated at, the mu-law tonemap of
the headline scores, and the test for a clamped score that has saturated.

Radiance is unbounded (lamps, highlights, a capture in other units): clamping to [0, 1] before scoring makes
every error above 1 vanish (radiance x 1e4 scores 200 dB). Instead:

* linear PSNR / SSIM use the ground truth's own peak (``peak``: its maximum over pixels and channels), so a
  capture and the same capture x 1e4 score the same;
* the tonemapped scores use mu-law compression of radiance divided by that peak, mu = 5000: the "PSNR-mu" of
  HDR imaging (Kalantari & Ramamoorthi 2017, "Deep High Dynamic Range Imaging of Dynamic Scenes"); it is
  logarithmic, so errors in bright and dark regions both count, and nothing is clamped (negative values, which
  radiance should not have, are mapped odd-symmetrically);
* the display tonemap of the PNGs (clamp + sRGB curve) is still scored, for comparison with LDR numbers, and
  ``saturation`` says where it (or any score) has stopped measuring anything.
"""

from __future__ import annotations

import numpy as np

MU = 5000.0  # mu-law compression (Kalantari & Ramamoorthi 2017)
SATURATED_FRACTION = 0.01  # a clamped score is flagged when more than this fraction of g.t. pixels exceed 1
SATURATED_DB = 100.0  # a PSNR above this (or not finite) is flagged: the metric no longer sees the error


def peak(target) -> float:
    """The ground truth's peak: max over pixels and channels; 1.0 if it is not positive (an all-black layer,
    e.g. the specular layer of a diffuse scene) or not finite."""
    m = float(np.max(target)) if np.size(target) else 0.0
    return m if np.isfinite(m) and m > 0 else 1.0


def mu_law(x, peak_value: float, mu: float = MU):
    """sign(x) log(1 + mu |x| / peak) / log(1 + mu) in float64: 0 -> 0, peak -> 1, no clamp. A torch tensor stays
    one (float64, on its device: the trainer's batch scores, no read-back); anything else becomes numpy."""
    if type(x).__module__.startswith("torch"):
        t = x.detach().double() / peak_value
        return t.sign() * (mu * t.abs()).log1p() / np.log1p(mu)
    x = np.asarray(x, dtype=np.float64) / peak_value
    return np.sign(x) * np.log1p(mu * np.abs(x)) / np.log1p(mu)


def over_one(target) -> float:
    """Fraction of pixels of [H, W, C] ``target`` with any channel > 1 (what a [0, 1] clamp cuts off)."""
    t = np.asarray(target)
    return float((t > 1.0).any(axis=-1).mean()) if t.size else 0.0


def saturation(scores: dict[str, float], over: float) -> list[str]:
    """Why a layer's scores have saturated (empty: they have not). ``scores``: key -> PSNR (dB) of one view and
    layer; ``over``: its ``over_one`` fraction (the clamped scores, ``*_clamped`` and ``*_srgb``, cut it off)."""
    reasons = []
    if over > SATURATED_FRACTION:
        reasons.append(f"{over:.1%} of ground-truth pixels exceed 1: the clamped scores (*_clamped, *_srgb) "
                       "ignore every error there")
    for key, value in scores.items():
        if not np.isfinite(value) or value > SATURATED_DB:
            reasons.append(f"{key} = {value:.1f} dB (> {SATURATED_DB:.0f}): render and ground truth (nearly) equal "
                           "under this metric")
    return reasons
