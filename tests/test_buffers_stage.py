"""buffers stage: predictions land in the capture format (world normals, aligned ray depth, ranges)."""

from __future__ import annotations

import numpy as np
import pytest

from models.buffernet.build import build_pipeline
from models.capture import Camera, Capture, read_capture, write_capture
from models.capture.depth_align import align_to_points
from models.capture.points import write_points_ply
from models.capture.types import CaptureMeta, View
from stages.buffers.__main__ import main as buffers_main
from models.buffernet.fill import BuffersConfig, fill_buffers, to_capture_buffers
from models.synth.cameras import look_at


def floor_capture(n=3, h=12, w=16):
    """Cameras above the plane y = 0; exact distance and normal buffers of the floor."""
    views = []
    for i in range(n):
        cam = Camera(w, h, 14.0, 14.0, w / 2, h / 2, look_at((0.3 * i, 2.0, 1.5), (0.1 * i, 0, -0.5)))
        d = cam.ray_directions()
        t = -cam.origin[1] / d[..., 1]
        rgb = np.full((h, w, 3), 0.4, np.float32) + 0.1 * np.sin(np.arange(w))[None, :, None].astype(np.float32)
        views.append(View(f"v{i}", cam, "train" if i < n - 1 else "test", {
            "rgb": rgb, "depth": t[..., None].astype(np.float32),
            "normal": np.broadcast_to(np.array([0, 1, 0], np.float32), (h, w, 3)).copy()}))
    return Capture(views, CaptureMeta())


def test_align_to_points_recovers_distance():
    cap = floor_capture()
    v = cap.views[0]
    cam = v.camera
    dist = v.buffers["depth"][..., 0]
    z = dist / np.linalg.norm(cam.camera_directions(), axis=-1)
    rel = (z - 1.0) / 3.0  # an affine relative depth, as the network predicts
    pts = cam.origin + cam.ray_directions()[::2, ::2].reshape(-1, 3) * dist[::2, ::2].reshape(-1, 1)
    out, fit = align_to_points(rel, cam, pts)
    assert fit.scale == pytest.approx(3.0, rel=1e-6) and fit.shift == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(out[..., 0], dist, rtol=1e-5)


def test_network_normals_go_to_world_space():
    cap = floor_capture()
    v = cap.views[1]
    world = v.buffers["normal"]
    cam_space = world.astype(np.float64) @ v.camera.rotation  # world -> camera
    out, _ = to_capture_buffers(v, {"normal": cam_space.astype(np.float32), "roughness": np.full(world.shape[:2], 0.3)},
                                None, 0)
    np.testing.assert_allclose(out["normal"], world, atol=1e-6)
    assert out["roughness"].shape == world.shape[:2] + (1,) and out["roughness"].dtype == np.float32


def test_fill_buffers_and_cli(tmp_path):
    cap = floor_capture()
    src = tmp_path / "capture"
    write_capture(Capture([View(v.name, v.camera, v.split, {"rgb": v.buffers["rgb"]}) for v in cap.views],
                          cap.meta), src)
    # SfM points: the floor
    xs, zs = np.meshgrid(np.linspace(-2, 2, 30), np.linspace(-3, 1, 30))
    write_points_ply(src / "points3D.ply", np.stack([xs.ravel(), np.zeros(xs.size), zs.ravel()], 1),
                     np.full((xs.size, 3), 128, np.uint8))
    model = tmp_path / "net"
    build_pipeline("tiny").save_pretrained(model)
    out = tmp_path / "capture_net"
    cfg = '{"predict": ["diffuse", "specular", "normal", "depth", "roughness", "f0"]}'
    assert buffers_main(["--config-json", cfg, "--capture", str(src), "--model", str(model), "--out", str(out),
                         "--no-progress"]) == 0
    got = read_capture(out)
    assert set(got.layers) >= {"rgb", "diffuse", "specular", "normal", "depth", "roughness", "f0"}
    for v in got.views:
        n = v.buffers["normal"]
        np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-4)
        assert (v.buffers["roughness"] >= 0).all() and (v.buffers["roughness"] <= 1).all()
        assert (v.buffers["f0"] >= 0).all() and (v.buffers["f0"] <= 1).all()
        assert (v.buffers["depth"] >= 0).all()
        # radiance: complement (the default): the diffuse is the image minus the specular
        np.testing.assert_allclose(v.buffers["diffuse"] + v.buffers["specular"], np.clip(v.buffers["rgb"], 0, None),
                                   atol=1e-5)
    assert (out / "points3D.ply").is_file() and (out / "stage.json").is_file()
    assert got.meta.extra["buffers"]["points"].startswith("sfm")

    # replace mode on a capture with truth: train views predicted, test views keep their buffers
    pipe = build_pipeline("tiny")
    result, info = fill_buffers(cap, src, pipe, BuffersConfig(predict=["normal", "depth"], replace=True,
                                                              points="truth", truth_points=40), progress=False)
    assert set(info["views"]) == {"v0", "v1"}
    test = result.views[2]
    assert test.buffers["depth"] is cap.views[2].buffers["depth"]


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown buffer.*albedo"):
        BuffersConfig.from_dict({"predict": ["albedo"]})
    with pytest.raises(ValueError, match="buffers.radiance must be one of complement, heads, got 'sum'"):
        BuffersConfig.from_dict({"predict": ["diffuse"], "radiance": "sum"})
    with pytest.raises(ValueError, match="unknown buffers option"):
        BuffersConfig.from_dict({"predict": [], "bogus": 1})
    cap = floor_capture()
    src = tmp_path / "c"
    write_capture(cap, src)
    with pytest.raises(ValueError, match="needs SfM points"):
        fill_buffers(cap, src, build_pipeline("tiny"), BuffersConfig(predict=["depth"], replace=True), progress=False)
    assert buffers_main(["--config-json", '{"predict": ["normal"]}', "--capture", str(src), "--model",
                         str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 1
