"""Dense init on an analytic capture: a textured plane seen by four cameras with exact depth."""

import numpy as np
import pytest
import torch

from models.capture import Camera, Capture, CaptureError, View, write_capture
from models.gaussians import read_ply
from models.initialisation import InitConfig, dense_init
from stages.init.__main__ import main as init_main
from tests.test_capture import look_at


def colour_at(p):
    return np.stack([0.5 + 0.4 * np.sin(3 * p[..., 0]), 0.5 + 0.4 * np.cos(2 * p[..., 1]), np.full(p.shape[:-1], 0.3)], -1)


def plane_capture(w=40, h=30):
    views = []
    for i, eye in enumerate([[0.3, 0.2, 2.0], [-0.5, 0.4, 2.5], [0.6, -0.5, 1.8], [0.0, 0.0, 3.0]]):
        cam = Camera(w, h, 30.0, 30.0, w / 2, h / 2, look_at(eye, [0, 0, 0]))
        d = cam.ray_directions()
        t = -cam.origin[2] / d[..., 2]  # ray-plane z = 0, distance along the unit ray
        p = cam.origin + d * t[..., None]
        buffers = {
            "depth": t[..., None].astype(np.float32),
            "diffuse": colour_at(p).astype(np.float32),
            "mask": np.ones((h, w, 1), np.float32),
        }
        views.append(View(f"v{i}", cam, "train" if i < 3 else "test", buffers))
    return Capture(views)


def test_dense_init_plane():
    cap = plane_capture()
    g, summary = dense_init(cap, InitConfig(resolution=40, voxel_fraction=1 / 40))
    means = g.means.numpy()
    assert summary["views"] == 3 and summary["gaussians"] == len(g) > 50
    assert np.abs(means[:, 2]).max() < 1e-5  # every Gaussian on the plane
    # each voxel's colour is the mean of its samples: close to the texture at the voxel mean
    assert np.abs(g.diffuse.numpy() - colour_at(means)).max() < 0.05
    # isotropic 3-NN scale of the order of the voxel size
    scale = g.log_scales.exp().numpy()
    assert np.allclose(scale[:, 0], scale[:, 1]) and np.allclose(scale[:, 0], scale[:, 2])
    assert 0.2 * summary["voxel"] < np.median(scale) < 3 * summary["voxel"]
    assert torch.allclose(g.opacities(), torch.tensor(0.1))
    assert torch.all(g.roughness == 0.1) and torch.all(g.f0 == 0.04) and torch.all(g.normals == 0)


def test_flatten_makes_discs_in_the_plane_the_normal_buffer_gives():
    """``flatten`` < 1: a voxel whose samples agree on a normal starts as a disc in that plane (local z along the
    normal, thickness flatten x width); without a normal buffer, or at flatten 1, the reference's spheres."""
    from models.gaussians.activations import quats_to_rotmats

    cap = plane_capture()
    tilt = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])  # a normal buffer tilted off the plane's
    for v in cap.views:
        v.buffers["normal"] = np.broadcast_to(tilt, v.buffers["depth"].shape[:2] + (3,)).astype(np.float32).copy()
    sphere, _ = dense_init(cap, InitConfig(resolution=40, voxel_fraction=1 / 40, flatten=1.0))
    assert InitConfig().flatten == 0.3  # discs by default (the README's zoo rows)
    disc, summary = dense_init(cap, InitConfig(resolution=40, voxel_fraction=1 / 40, flatten=0.25))
    assert summary["discs"] == len(disc)
    assert torch.equal(sphere.means, disc.means) and torch.equal(sphere.log_scales[:, 0], disc.log_scales[:, 0])
    assert torch.equal(sphere.quats, torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand_as(sphere.quats))
    ratio = (disc.log_scales[:, 2] - disc.log_scales[:, 0]).exp()
    assert torch.allclose(ratio, torch.tensor(0.25), atol=1e-6)
    z_axis = quats_to_rotmats(disc.quats)[:, :, 2]
    assert torch.allclose(z_axis, torch.tensor(tilt, dtype=torch.float32).expand_as(z_axis), atol=1e-6)
    for v in cap.views:  # normals that disagree (a corner, an edge): the voxel stays a sphere
        v.buffers["normal"][:, ::2] *= -1
    mixed, _ = dense_init(cap, InitConfig(resolution=40, voxel_fraction=1 / 40, flatten=0.25))
    round_ = (mixed.log_scales[:, 2] == mixed.log_scales[:, 0])
    assert 0 < int(round_.sum()) < len(mixed)


def test_min_samples_and_mask():
    cap = plane_capture()
    for v in cap.views:
        v.buffers["mask"][:, : v.camera.width // 2] = 0  # left half invalid
    g1, s1 = dense_init(cap, InitConfig(resolution=40, voxel_fraction=1 / 40, min_samples=1))
    g3, s3 = dense_init(cap, InitConfig(resolution=40, voxel_fraction=1 / 40, min_samples=3))
    assert s1["samples"] < 3 * 40 * 30 * 0.55
    assert len(g3) < len(g1)


def test_errors_name_problem():
    cap = plane_capture()
    del cap.views[0].buffers["depth"]
    with pytest.raises(CaptureError, match="view 'v0': dense init needs the 'depth' buffer"):
        dense_init(cap)
    with pytest.raises(ValueError, match=r"unknown init option\(s\) \['voxel'\]"):
        InitConfig.from_dict({"voxel": 0.1})


def test_cli_writes_ply(tmp_path, caplog):
    write_capture(plane_capture(), tmp_path / "cap")
    rc = init_main(["--capture", str(tmp_path / "cap"), "--out", str(tmp_path / "init"),
                    "--config-json", '{"resolution": 40, "voxel_fraction": 0.025}'])
    assert rc == 0
    g = read_ply(tmp_path / "init/points.ply")
    assert len(g) > 50 and (tmp_path / "init/stage.json").is_file()
    assert init_main(["--capture", str(tmp_path / "nope"), "--out", str(tmp_path / "x")]) == 1
    # flatten < 1 on a capture without normals: spheres, and the log says why (info: the default asks for discs)
    with caplog.at_level("INFO"):
        assert init_main(["--capture", str(tmp_path / "cap"), "--out", str(tmp_path / "init_s"),
                          "--config-json", '{"resolution": 40, "voxel_fraction": 0.025, "flatten": 0.5}']) == 0
    assert "none made: the capture has no normal buffer" in caplog.text
    # flatten < 1: the stage reads the normal buffer too (it read only depth / diffuse / emission / mask)
    cap = plane_capture()
    for v in cap.views:
        v.buffers["normal"] = np.broadcast_to(np.float32([0, 0, 1]), v.buffers["depth"].shape[:2] + (3,)).copy()
    write_capture(cap, tmp_path / "cap_n")
    assert init_main(["--capture", str(tmp_path / "cap_n"), "--out", str(tmp_path / "init_n"),
                      "--config-json", '{"resolution": 40, "voxel_fraction": 0.025, "flatten": 0.5}']) == 0
    g = read_ply(tmp_path / "init_n/points.ply")
    assert torch.allclose((g.log_scales[:, 2] - g.log_scales[:, 0]).exp(), torch.tensor(0.5), atol=1e-5)


def test_coarse_levels_fill_surfaces_seen_from_far_and_still_drop_lone_samples():
    """Where a pixel's footprint is wider than the voxel (the plane's far, grazing parts) samples are alone in
    their voxels: the reference recipe (coarse_levels 0) leaves holes up to 1.2 m across the seen plane (the
    zoo's distant walls: 0.8 m); the coarse levels cover it up to the coarsest voxel's scale, and a lone stray
    sample (a depth outlier 1 m off the plane) is still dropped at every level."""
    from scipy.spatial import cKDTree

    cap = plane_capture()
    v = cap.views[0]
    v.buffers["depth"][10, 12] *= 0.5  # one stray sample, far in front of the plane
    stray = v.camera.origin + v.camera.ray_directions()[10, 12] * v.buffers["depth"][10, 12]
    cfg = dict(resolution=40, voxel_fraction=1 / 100)
    every, _ = dense_init(cap, InitConfig(**cfg, coarse_levels=0, min_samples=1))  # a Gaussian at each sample
    seen = every.means.numpy()[np.abs(every.means.numpy()[:, 2]) < 1e-4]
    g_ref, s_ref = dense_init(cap, InitConfig(**cfg, coarse_levels=0))
    gap_ref = cKDTree(g_ref.means.numpy()).query(seen)[0]
    g, s = dense_init(cap, InitConfig(**cfg))
    means = g.means.numpy()
    gap = cKDTree(means).query(seen)[0]
    coarsest = 8 * s["voxel"]
    assert s_ref["coarse"] == [] and gap_ref.max() > 4 * coarsest  # the recipe's holes
    assert gap.max() < 1.25 * coarsest, (gap.max(), coarsest)
    assert np.percentile(gap, 99) < 0.25 * np.percentile(gap_ref, 99)
    assert len(g) == s["gaussians"] == len(g_ref) + sum(s["coarse"]) and len(s["coarse"]) == 3
    # where the recipe's Gaussians cover the plane the levels add nothing (holes only)
    near = cKDTree(g_ref.means.numpy()).query(means[len(g_ref):])[0]
    assert near.min() > 1.5 * 2 * s["voxel"]
    assert np.abs(means[:, 2]).max() < 1e-5  # every Gaussian on the plane: the stray sample made none
    assert cKDTree(means).query(stray)[0] > 0.5
