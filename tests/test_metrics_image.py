"""Image metrics: SSIM against the 3DGS formula (transcribed with plain loops) and pytorch-msssim; HDR-safe PSNR
(linear at the ground truth's peak, mu-law tonemapped) and the saturation flag."""

import math

import numpy as np
import pytest
import torch

from models.metrics import hdr, score_layer
from models.metrics.image import gaussian_window, psnr, ssim


def ssim_3dgs_loops(x: np.ndarray, y: np.ndarray, window: int = 11, sigma: float = 1.5) -> float:
    """3DGS utils/loss_utils.py ``ssim`` written out: the 1-D Gaussian exp(-(i - w//2)^2 / (2 sigma^2)) normalised,
    its outer product as the 2-D window, conv2d with zero padding w//2 per channel, C1 = 0.01^2, C2 = 0.03^2,
    the map's mean over channels and pixels."""
    g = [math.exp(-((i - window // 2) ** 2) / (2 * sigma**2)) for i in range(window)]
    g = [v / sum(g) for v in g]
    h, w, channels = x.shape
    r = window // 2
    c1, c2 = 0.01**2, 0.03**2
    total = 0.0
    for c in range(channels):
        for i in range(h):
            for j in range(w):
                mx = my = sxx = syy = sxy = 0.0
                for a in range(window):
                    for b in range(window):
                        ii, jj = i + a - r, j + b - r
                        if 0 <= ii < h and 0 <= jj < w:  # zero padding
                            k = g[a] * g[b]
                            u, v = x[ii, jj, c], y[ii, jj, c]
                            mx += k * u
                            my += k * v
                            sxx += k * u * u
                            syy += k * v * v
                            sxy += k * u * v
                sxx, syy, sxy = sxx - mx * mx, syy - my * my, sxy - mx * my
                total += ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return total / (channels * h * w)


def test_window_is_3dgs():
    g = gaussian_window()
    assert g.shape == (11,) and abs(g.sum() - 1) < 1e-15 and g.argmax() == 5
    assert np.allclose(g[5] / g[4], math.exp(1 / (2 * 1.5**2)), rtol=1e-14)


def test_ssim_matches_3dgs_formula():
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, (14, 17, 3))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    # float64 both ways; the loops sum in a different order: worst seen 8e-16
    assert abs(ssim(y, x) - ssim_3dgs_loops(y, x)) < 1e-12
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-12)


def test_ssim_valid_matches_pytorch_msssim():
    pytorch_msssim = pytest.importorskip("pytorch_msssim", reason="pytorch-msssim is in the test extra")
    rng = np.random.default_rng(2)
    x = rng.uniform(0, 2, (40, 33, 3))
    y = x * rng.uniform(0.8, 1.2, x.shape)
    win = torch.tensor(gaussian_window(), dtype=torch.float64)[None, None]  # its own is float32
    ref = pytorch_msssim.ssim(torch.tensor(y).permute(2, 0, 1)[None], torch.tensor(x).permute(2, 0, 1)[None],
                              data_range=2.0, win=win.repeat(3, 1, 1, 1))
    assert abs(ssim(y, x, peak=2.0, padding="valid") - float(ref)) < 1e-12  # worst seen 1e-16
    assert ssim(y, x, peak=2.0) != ssim(y, x, peak=2.0, padding="valid")  # borders: 3DGS zero-pads


def test_hdr_psnr_is_scale_invariant():
    """Radiance x 1e4 with the same relative error scores as at x 1: never 200 dB."""
    rng = np.random.default_rng(3)
    gt = rng.uniform(0.1, 1, (24, 32, 3)).astype(np.float32)
    pred = gt + rng.normal(0, 0.02, gt.shape).astype(np.float32)
    at1 = score_layer(pred, gt, "final")
    at1e4 = score_layer(pred * 1e4, gt * 1e4, "final")
    for key in ("psnr_final", "psnr_final_tonemapped", "ssim_final", "ssim_final_tonemapped"):
        assert at1e4[key] == pytest.approx(at1[key], rel=1e-5), key
    assert 20 < at1e4["psnr_final"] < 60 and at1e4["peak_final"] == pytest.approx(1e4 * gt.max())
    # the clamp metrics saturate, and the flag says so
    assert at1e4["psnr_final_clamped"] > 100 and at1e4["ssim_final_srgb"] == pytest.approx(1.0)
    reasons = hdr.saturation({k: v for k, v in at1e4.items() if k.startswith("psnr_")}, at1e4["over1_final"])
    assert any("exceed 1" in r for r in reasons) and any("psnr_final_clamped" in r for r in reasons)
    assert not hdr.saturation({k: v for k, v in at1.items() if k.startswith("psnr_")}, at1["over1_final"])


def test_errors_on_bright_pixels_lose_psnr():
    """5% of pixels at radiance 10: an error there lowers the linear and tonemapped PSNR (clamping hid it)."""
    rng = np.random.default_rng(4)
    gt = rng.uniform(0.1, 0.9, (40, 40, 3))
    bright = rng.uniform(size=(40, 40)) < 0.05
    gt[bright] = 10.0
    clean = score_layer(gt + rng.normal(0, 0.005, gt.shape), gt, "final")
    pred = gt.copy()
    pred[bright] = 8.0  # 20% low on the bright pixels only
    wrong = score_layer(pred + rng.normal(0, 0.005, gt.shape), gt, "final")
    assert wrong["psnr_final"] < clean["psnr_final"] - 10
    assert wrong["psnr_final_tonemapped"] < clean["psnr_final_tonemapped"] - 10
    assert wrong["ssim_final"] < clean["ssim_final"]
    assert abs(wrong["psnr_final_clamped"] - clean["psnr_final_clamped"]) < 0.5  # the clamp cannot see it
    assert wrong["over1_final"] == pytest.approx(bright.mean())


def test_mu_law_and_peak():
    assert hdr.mu_law(np.array([0.0, 3.0, -3.0]), 3.0).tolist() == [0.0, 1.0, -1.0]
    x = np.array([0.0, 1e-4, 0.3, 3.0, -2.0, 12.0], dtype=np.float32)
    on_torch = hdr.mu_law(torch.from_numpy(x), 3.0)  # the trainer's batch scores: a float64 tensor, same values
    assert on_torch.dtype == torch.float64 and np.array_equal(on_torch.numpy(), hdr.mu_law(x, 3.0))
    assert hdr.peak(np.zeros((4, 4, 3))) == 1.0 and hdr.peak(np.full((2, 2, 3), 7.0)) == 7.0
    x = np.array([0.5])
    assert psnr(x, x + 0.1, peak=2.0) == pytest.approx(20 + 20 * math.log10(2.0))


def test_layers_are_scored_at_the_views_peak_not_their_own():
    """A view with almost no reflection: the same small absolute specular error must not score 15x worse because
    the specular layer's own maximum is tiny (evaluate scores every layer at the final image's peak)."""
    rng = np.random.default_rng(5)
    diffuse = rng.uniform(0.05, 0.3, (32, 32, 3))
    faint = rng.uniform(0, 0.02, (32, 32, 3))  # specular peaking at 0.02 in an image peaking near 0.32
    error = rng.normal(0, 0.002, faint.shape)
    final_peak = hdr.peak(diffuse + faint)
    own = score_layer(faint + error, faint, "specular")
    at_view = score_layer(faint + error, faint, "specular", reference=final_peak)
    assert at_view["peak_specular"] == pytest.approx(faint.max())  # the layer's own max is still recorded
    # at its own peak the error looks final_peak / 0.02 ~ 16x larger: ~24 dB lower linear PSNR
    assert at_view["psnr_specular"] - own["psnr_specular"] == pytest.approx(20 * np.log10(final_peak / faint.max()),
                                                                             abs=1e-6)
    assert at_view["psnr_specular_tonemapped"] > own["psnr_specular_tonemapped"] + 3
    # and a brighter reflection with the same absolute error scores the same linear PSNR at the same view peak
    brighter = score_layer(faint * 5 + error, faint * 5, "specular", reference=final_peak)
    assert brighter["psnr_specular"] == pytest.approx(at_view["psnr_specular"], rel=1e-9)
