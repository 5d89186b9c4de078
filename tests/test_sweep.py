"""Speed/accuracy sweep: training-resolution resampling is exact for a pinhole camera; a quick sweep on the
CI-sized demo yields consistent points, a Pareto-derived recommendation, and the report stage draws its JSON
into a page Chromium renders."""

import json
import math

import numpy as np

from models.capture import View, read_capture
from models.capture.camera import Camera
from models.capture.resample import downsample_view
from stages.benchmark.sweep import SweepGrid, config_for_sweep, run_sweep
from stages.config import load_config
from stages.report.__main__ import main as report_main
from tests.test_report import chromium_dom, loaded_images


def test_downsample_view_keeps_rays_and_averages():
    cam = Camera(8, 6, 7.0, 7.5, 4.2, 2.9, np.eye(4))
    rng = np.random.default_rng(0)
    diffuse = rng.random((6, 8, 3)).astype(np.float32)
    depth = np.ones((6, 8, 1), np.float32)
    depth[0, 0] = 0  # one invalid pixel
    normal = np.zeros((6, 8, 3), np.float32)
    normal[..., 2] = 1
    view = View("v", cam, "train", {"diffuse": diffuse, "depth": depth, "normal": normal})
    low = downsample_view(view, 2)
    assert (low.camera.width, low.camera.height) == (4, 3)
    # a low-resolution pixel sees the centre of its 2x2 block (camera-space directions are affine in u, v)
    full = cam.camera_directions()
    block = full.reshape(3, 2, 4, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(low.camera.camera_directions(), block, atol=1e-12)
    np.testing.assert_allclose(low.buffers["diffuse"], diffuse.reshape(3, 2, 4, 2, 3).mean(axis=(1, 3)), atol=1e-6)
    assert low.buffers["mask"][0, 0, 0] == 0 and low.buffers["mask"][1:, :].min() == 1  # partly invalid block
    assert math.isclose(float(low.buffers["depth"][0, 0, 0]), 1.0)  # averaged over valid pixels only
    np.testing.assert_allclose(np.linalg.norm(low.buffers["normal"], axis=-1), 1, atol=1e-6)


def test_config_for_sweep_scales_schedule():
    cfg = config_for_sweep({"reconstruct": {"iterations": 3000, "warmup": 300, "prune_every": 250,
                                            "prune_from": 600}}, 1500)
    assert cfg["reconstruct"] == {"iterations": 1500, "warmup": 150, "prune_every": 125, "prune_from": 300,
                                  "checkpoint_every": 1500}


def test_quick_sweep_on_tiny_demo(tiny_demo, tmp_path):
    _, results, _, _ = tiny_demo
    capture = read_capture(results / "demo" / "capture")
    config = load_config("demo", presets=["ci"])
    result = run_sweep(capture, config, SweepGrid.quick(), progress=lambda m: None, work_dir=tmp_path / "work")
    names = [p["name"] for p in result["points"]]
    assert names[:4] == ["base", "train path 1", "train res 1/2", "voxel x2"]
    for p in result["points"]:
        for key in ("render_s_per_view", "psnr_diffuse", "psnr_specular", "psnr_final"):
            assert math.isfinite(p[key]) and p[key] > 0, (p["name"], key)
    by = {p["name"]: p for p in result["points"]}
    # fewer Gaussians from a coarser voxel grid; the primary segment (diffuse) is deterministic, so spp and the
    # denoiser (which acts on the specular layer only) leave diffuse PSNR unchanged
    assert by["voxel x2"]["gaussians"] < by["base"]["gaussians"]
    assert by["antialias 1"]["render_s_per_view"] > 0  # one primary per pixel against the base's 2 x 2
    assert {by[n]["psnr_diffuse"] for n in ("spp 1", "spp 1 +dn", "spp 4", "spp 4 +dn", "render path 1")} == \
        {by["base"]["psnr_diffuse"]}
    rec = {(r["group"], r["role"]): r for r in result["recommended"]}
    for group, cost in (("training", "train_s"), ("render", "render_s_per_view")):
        fast, bal, best = (rec[(group, role)] for role in ("fastest", "balanced", "quality"))
        assert fast[cost] <= bal[cost] and fast["psnr_final"] <= bal["psnr_final"] <= best["psnr_final"]
    (tmp_path / "sweep.json").write_text(json.dumps(result))
    html = tmp_path / "sweep.html"
    assert report_main(["sweep", str(tmp_path / "sweep.json"), "--out", str(html)]) == 0
    ok, total = loaded_images(chromium_dom(html))
    assert total == 2 and ok == 2  # the training and the render Pareto plots
