"""evaluate: per-layer metrics against ground truth, and region scores from world boxes."""

import numpy as np

from models.capture.exr import write_exr_channels
from models.metrics import evaluate_renders, psnr, ssim
from tests.test_init import plane_capture


def test_metrics_basics():
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (16, 16, 3))
    assert ssim(x, x) == 1.0 and psnr(x, x) > 150
    assert abs(psnr(x, x + 0.1) - 20.0) < 1e-9  # MSE 0.01
    assert ssim(x, 1 - x) < 0.1


def test_regions_score_only_their_pixels(tmp_path):
    cap = plane_capture()
    for v in cap.views:
        v.buffers["specular"] = 0.2 * v.buffers["diffuse"]
    test = cap.split("test")[0]
    diffuse, specular = test.buffers["diffuse"].copy(), test.buffers["specular"].copy()
    box = {"min": [0.0, 0.0, -0.1], "max": [10.0, 10.0, 0.1]}  # the quadrant x > 0, y > 0 of the plane
    points = test.camera.origin + test.camera.ray_directions() * test.buffers["depth"]
    inside = (points[..., 0] > 0) & (points[..., 1] > 0)
    diffuse[inside] += 0.1  # wrong only inside the region
    channels = {}
    for layer, arr, names in (("rgb", diffuse + specular, "RGB"), ("diffuse", diffuse, None), ("specular", specular, None)):
        for i, c in enumerate("RGB"):
            channels[c if layer == "rgb" else f"{layer}.{c}"] = arr[..., i]
    write_exr_channels(tmp_path / f"{test.name}.exr", channels)
    m = evaluate_renders(cap, tmp_path, regions={"quadrant": box})["views"][test.name]
    assert m["quadrant_pixels"] == inside.sum() > 0
    assert abs(m["quadrant_psnr_diffuse"] - 20.0) < 0.05  # only the wrong pixels, error 0.1 (clamped at 1)
    assert m["psnr_diffuse"] > m["quadrant_psnr_diffuse"] + 1  # the whole image dilutes the error
    assert m["quadrant_psnr_specular"] > 150
