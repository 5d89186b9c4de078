"""poses stage: synthetic photos -> COLMAP (pycolmap) -> capture; the real-scene layout reader; SfM init.

The synthetic scene is rendered once (12 views, 320x240, 24 spp: at 8-16 spp render noise alone pushed
rotation errors to 0.2-0.36 deg, at 32 spp they were < 0.1 deg) and its poses thrown away.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pycolmap
import pytest
import torch
import yaml

from models.capture import Capture, CaptureError, View, read_capture, read_colmap_capture
from models.capture.colmap_layout import CV_TO_GL, colmap_from_c2w
from models.capture.depth_align import fit_scale_shift
from models.capture.paper_layout import filmic
from models.capture.color import linear_to_srgb, srgb_to_linear
from models.capture.points import read_points_ply
from models.initialisation import InitConfig, initialise
from models.poses import PosesConfig, PosesError, check_photos, pose_errors, run_poses, umeyama
from models.synth.render import render_spec
from models.synth.spec import parse_spec
from tests.conftest import PROFILE_NOTE

ROOT = Path(__file__).resolve().parents[1]
VIEWS = 12

# A small textured corner (floor, two walls, two boxes) seen along a 150-degree arc with a height change.
SPEC = {
    "seed": 0, "resolution": [320, 240], "spp": 24, "max_depth": 2,
    "textures": {
        "tiles": {"type": "checker", "seed": 1, "scale": 9, "detail": 0.5,
                  "colors": [[0.15, 0.12, 0.1], [0.7, 0.62, 0.5], [0.35, 0.4, 0.45]]},
        "plaster": {"type": "noise", "seed": 2, "scale": 8, "octaves": 5, "detail": 0.5,
                    "colors": [[0.2, 0.3, 0.5], [0.85, 0.8, 0.7]]},
        "moss": {"type": "noise", "seed": 3, "scale": 10, "octaves": 5, "detail": 0.5,
                 "colors": [[0.1, 0.3, 0.1], [0.55, 0.75, 0.3], [0.9, 0.9, 0.6]]},
        "crate": {"type": "checker", "seed": 4, "scale": 6, "detail": 0.5,
                  "colors": [[0.1, 0.15, 0.5], [0.9, 0.5, 0.1], [0.9, 0.9, 0.9]]},
    },
    "objects": [
        {"name": "floor", "shape": "rectangle", "material": {"type": "diffuse", "texture": "tiles"},
         "transform": {"rotate": [{"axis": [1, 0, 0], "angle": -90}], "scale": [2, 2, 1]}},
        {"name": "wall", "shape": "rectangle", "material": {"type": "diffuse", "texture": "plaster"},
         "transform": {"translate": [0, 1, -2], "scale": [2, 1, 1]}},
        {"name": "wall2", "shape": "rectangle", "material": {"type": "diffuse", "texture": "moss"},
         "transform": {"translate": [-2, 1, 0], "rotate": [{"axis": [0, 1, 0], "angle": 90}], "scale": [2, 1, 1]}},
        {"name": "box_a", "shape": "cube", "material": {"type": "principled", "texture": "moss", "roughness": 0.4},
         "transform": {"translate": [0.3, 0.25, 0.1], "rotate": [{"axis": [0, 1, 0], "angle": 25}], "scale": 0.25}},
        {"name": "box_b", "shape": "cube", "material": {"type": "diffuse", "texture": "crate"},
         "transform": {"translate": [-0.5, 0.3, -0.5], "scale": [0.3, 0.3, 0.2]}},
        {"name": "light", "shape": "rectangle", "material": {"type": "diffuse", "base_color": [0, 0, 0]},
         "transform": {"translate": [0, 3, 0.5], "rotate": [{"axis": [1, 0, 0], "angle": 90}], "scale": [1.5, 1.5, 1]},
         "emitter": {"radiance": [4, 4, 4]}},
    ],
    "cameras": {
        "train": {"type": "orbit", "count": VIEWS, "fov_y": 55, "target": [-0.2, 0.4, -0.3], "radius": 2.2,
                  "height": [1.0, 1.9], "azimuth": [-40, 110]},
        "test": {"type": "orbit", "count": 0},
    },
}


def write_png(path, pixels, bits=8):
    """[H, W, C] values in [0, 1] -> integer PNG."""
    pixels = np.atleast_3d(pixels)
    h, w, c = pixels.shape
    fmt, top = (oiio.UINT8, 255) if bits == 8 else (oiio.UINT16, 65535)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, c, fmt))
    out.write_image(np.ascontiguousarray(np.round(np.clip(pixels, 0, 1) * top).astype(np.uint8 if bits == 8 else np.uint16)))
    out.close()


def write_photos(views, folder):
    folder.mkdir(parents=True, exist_ok=True)
    for v in views:
        write_png(folder / f"{v.name}.png", linear_to_srgb(v.buffers["rgb"]))
    return folder


@pytest.fixture(scope="module")
def synth():
    return render_spec(parse_spec(SPEC), progress=False)


@pytest.fixture(scope="module")
def posed(synth, tmp_path_factory):
    root = tmp_path_factory.mktemp("poses")
    photos = write_photos(synth.views, root / "photos")
    capture = run_poses(photos, root / "work", root / "capture", PosesConfig(), threads=2, progress=False)
    return capture, root


def test_recovered_cameras_match_truth(synth, posed, record_property):
    capture, root = posed
    assert len(capture.views) == VIEWS  # every photo registered
    truth = {v.name: v.camera for v in synth.views}
    est = [v.camera.c2w for v in capture.views]
    err = pose_errors(est, [truth[v.name].c2w for v in capture.views])
    timings = capture.meta.extra["poses"]["seconds"]
    record_property("pose_errors", {"rotation_deg_max": float(err["rotation_deg"].max()),
                                    "rotation_deg_mean": float(err["rotation_deg"].mean()),
                                    "position_pct_max": float(100 * err["position_frac"].max()),
                                    "seconds": timings})
    print(f"\npose errors: rotation max {err['rotation_deg'].max():.3f} deg (mean {err['rotation_deg'].mean():.3f}), "
          f"position max {100 * err['position_frac'].max():.3f}% of extent; seconds {timings}")
    assert err["rotation_deg"].max() < 0.5
    assert err["position_frac"].max() < 0.01
    # undistorted pinhole intrinsics: focal within 1% of the renderer's, image within a few pixels of 320x240
    cam, gt = capture.views[0].camera, synth.views[0].camera
    assert abs(cam.fl_x / gt.fl_x - 1) < 0.01 and abs(cam.fl_y / gt.fl_y - 1) < 0.01
    assert abs(cam.width - gt.width) <= 8 and abs(cam.height - gt.height) <= 8
    # LLFF hold: every 8th registered photo is a test view
    assert [v.split for v in capture.views] == ["test" if i % 8 == 0 else "train" for i in range(VIEWS)]


def test_true_cameras_move_onto_the_colmap_ones(synth, posed):
    """The photos path's scoring (models/poses/truth.py): the renderer's cameras, moved into the posed frame by the
    similarity of the camera centres, land on the cameras COLMAP recovered for the same photos."""
    from models.poses.truth import photos_truth

    capture, _ = posed
    moved, record = photos_truth(synth, synth, capture, split="train")
    assert record["poses"]["registered"] == VIEWS and record["poses"]["rotation_deg_max"] < 0.5
    extent = capture.camera_extent()
    by_name = {v.name: v.camera.c2w for v in capture.views}
    for view in moved.views:
        c2w = by_name[view.name]
        assert np.linalg.norm(view.camera.c2w[:3, 3] - c2w[:3, 3]) < 0.01 * extent
        cos = (np.trace(view.camera.c2w[:3, :3].T @ c2w[:3, :3]) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 0.5
    scale = record["similarity"]["scale"]
    assert np.allclose(moved.views[0].buffers["depth"], synth.views[0].buffers["depth"] * scale, rtol=1e-6)


def test_capture_on_disk_is_normalised_with_points_and_model(posed):
    capture, root = posed
    out = root / "capture"
    disk = read_capture(out)
    assert [v.name for v in disk.views] == [v.name for v in capture.views]
    assert disk.layers == ["rgb"]
    centres = np.stack([v.camera.origin for v in disk.views])
    assert np.abs(centres.mean(0)).max() < 1e-6  # centred
    assert abs(np.linalg.norm(centres, axis=1).max() - 1.0) < 1e-6  # farthest camera at target_radius 1
    meta = yaml.safe_load((out / "capture.yaml").read_text())
    norm = meta["extra"]["normalisation"]
    assert meta["source"] == "colmap" and norm["scale"] > 0 and len(norm["centre"]) == 3
    # the COLMAP model kept in the capture is in the capture's frame: same camera centres
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    by_name = {img.name.rsplit(".", 1)[0]: img for img in rec.images.values()}
    for v in disk.views:
        assert np.allclose(by_name[v.name].projection_center(), v.camera.origin, atol=1e-6)
    # and in the original COLMAP frame: x_capture = scale * (x_colmap - centre)
    orig = pycolmap.Reconstruction(str(root / "work" / "undistorted" / "sparse"))
    for img in orig.images.values():
        mapped = norm["scale"] * (img.projection_center() - np.array(norm["centre"]))
        assert np.allclose(mapped, by_name[img.name.rsplit(".", 1)[0]].projection_center(), atol=1e-6)
    xyz, rgb = read_points_ply(out / "points3D.ply")
    assert len(xyz) == rec.num_points3D() > 200
    # the points lie in front of the cameras that see them, at scene-like distances (the room is ~4 m wide,
    # the cameras ~2.2 m from the target: normalised distances of order 1)
    img = next(iter(rec.images.values()))
    pts = np.array([rec.points3D[p.point3D_id].xyz for p in img.get_observation_points2D()])
    z = (pts @ img.cam_from_world().matrix()[:, :3].T + img.cam_from_world().matrix()[:, 3])[:, 2]
    assert (z > 0).all() and 0.1 < np.median(z) < 5


def test_sfm_init_then_reconstruct_loss_falls(posed):
    from models.tracer import Tracer, TracerConfig
    from models.reconstruction import ReconstructConfig, Trainer

    capture, root = posed
    out = root / "capture"
    gaussians, summary = initialise(capture, out, InitConfig())
    assert summary["source"] == "sfm" and "no depth buffer" in summary["decision"]
    xyz, rgb = read_points_ply(out / "points3D.ply")
    assert len(gaussians) == len(xyz)
    assert np.allclose(gaussians.means.numpy(), xyz, atol=1e-6)
    assert np.allclose(gaussians.diffuse.numpy(), srgb_to_linear(rgb / 255.0), atol=1e-6)  # linear colours
    assert torch.allclose(gaussians.opacities(), torch.tensor(0.1))
    assert torch.all(gaussians.roughness == 0.1) and torch.all(gaussians.f0 == 0.04) and torch.all(gaussians.normals == 0)
    scale = gaussians.log_scales.exp()
    assert torch.allclose(scale[:, 0], scale[:, 2])  # isotropic
    # photos only (the buffers stage is not built): the photo's radiance stands in for the diffuse buffer
    for v in capture.views:
        v.buffers["diffuse"] = v.buffers["rgb"]
    cfg = ReconstructConfig.from_dict(dict(iterations=40, warmup=40, rays_per_step=1024, prune_from=10_000,
                                           far_field="off", log_every=10, checkpoint_every=1000))
    trainer = Trainer(capture, gaussians, cfg, Tracer(TracerConfig(num_threads=2)))
    losses = [trainer.train_step()["loss"] for _ in range(cfg.iterations)]
    first, last = np.mean(losses[:5]), np.mean(losses[-5:])
    assert last < 0.8 * first, (first, last)


# ----------------------------------------------------------------------------------- the real-scene layout


def build_layout(capture, root, names, *, rescale=2, points_per_view=150, outliers=0.2, model="PINHOLE",
                 priors=True, seed=0):
    """The paper's real-scene layout from a synthetic capture: COLMAP model from the known poses (camera at
    ``rescale`` x the priors' resolution), SfM points unprojected from the true depth (a fraction ``outliers``
    with a wrong depth), photos in images/, network-style priors in priors/<buf>/<buf>_<stem>.png."""
    rng = np.random.default_rng(seed)
    views = [v for v in capture.views if v.name in names]
    cam0 = views[0].camera
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, model, cam0.fl_x * rescale, cam0.width * rescale,
                                                 cam0.height * rescale)
    if model == "PINHOLE":
        cam.params = [cam0.fl_x * rescale, cam0.fl_y * rescale, cam0.cx * rescale, cam0.cy * rescale]
    rec.add_camera_with_trivial_rig(cam)
    (root / "images").mkdir(parents=True)
    rel_range = {}
    for i, v in enumerate(views, start=1):
        c = v.camera
        dist = v.buffers["depth"][..., 0]
        ok = (dist > 0) & (v.buffers["mask"][..., 0] > 0.99)
        rows, cols = np.nonzero(ok)
        pick = rng.choice(len(rows), size=min(points_per_view, len(rows)), replace=False)
        rows, cols = rows[pick], cols[pick]
        d = dist[rows, cols].astype(np.float64)
        d[: int(outliers * len(d))] *= rng.uniform(0.5, 1.5, int(outliers * len(d)))  # mismatched tracks
        xyz = c.origin + c.ray_directions()[rows, cols] * d[:, None]
        keypoints = np.stack([(cols + 0.5) * rescale, (rows + 0.5) * rescale], axis=1)
        image = pycolmap.Image(name=f"{v.name}.png", keypoints=keypoints, camera_id=1, image_id=i)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(colmap_from_c2w(c.c2w)))
        for j, x in enumerate(xyz):
            track = pycolmap.Track()
            track.add_element(i, j)
            rec.add_point3D(x, track, np.array([200, 100, 50], dtype=np.uint8))
        write_png(root / "images" / f"{v.name}.png", linear_to_srgb(v.buffers["rgb"]))
        if not priors:
            continue
        for buf, layer in (("render", "rgb"), ("diffuse", "diffuse"), ("specular", "specular")):
            (root / "priors" / buf).mkdir(parents=True, exist_ok=True)
            write_png(root / "priors" / buf / f"{buf}_{v.name}.png", filmic(v.buffers[layer]))
        for buf in ("roughness", "metalness", "normal", "depth"):
            (root / "priors" / buf).mkdir(parents=True, exist_ok=True)
        write_png(root / "priors/roughness" / f"roughness_{v.name}.png", v.buffers["roughness"])
        metal = np.clip((v.buffers["f0"].mean(-1, keepdims=True) - 0.04) / 0.96, 0, 1)
        write_png(root / "priors/metalness" / f"metalness_{v.name}.png", metal)
        r_cv = c.rotation @ CV_TO_GL  # OpenCV camera-to-world
        n_cam = -(v.buffers["normal"] @ r_cv)  # the reference's convention: world = R_cv (-n_cam)
        write_png(root / "priors/normal" / f"normal_{v.name}.png", (n_cam + 1) / 2)
        ray_len = np.linalg.norm(c.camera_directions(), axis=-1)
        z = dist / ray_len
        lo, hi = z[ok].min(), z[ok].max()
        rel_range[v.name] = (lo, hi)
        write_png(root / "priors/depth" / f"depth_{v.name}.png", np.where(ok, (z - lo) / (hi - lo) * 0.9 + 0.05, 0),
                  bits=16)
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write(str(root / "sparse" / "0"))
    return views


def test_real_layout_reader(synth, tmp_path):
    root = tmp_path / "scene"
    names = [v.name for v in synth.views[:6]]
    truth = build_layout(synth, root, names)
    cap = read_capture(root)  # no transforms.json: the COLMAP reader
    assert cap.meta.source == "colmap" and [v.name for v in cap.views] == names
    assert set(cap.layers) == {"rgb", "diffuse", "specular", "roughness", "f0", "normal", "depth"}
    assert [v.split for v in cap.views] == ["test"] + ["train"] * 5  # LLFF hold of 8
    assert [v.split for v in read_colmap_capture(root, layers=["rgb"], test_every=3).views] == ["test", "train", "train"] * 2
    for v, gt in zip(cap.views, truth):
        c, g = v.camera, gt.camera
        # the COLMAP camera is at 2x: the reader rescales it to the priors' 320x240
        assert (c.width, c.height) == (g.width, g.height)
        assert np.allclose([c.fl_x, c.fl_y, c.cx, c.cy], [g.fl_x, g.fl_y, g.cx, g.cy], rtol=1e-12)
        assert np.allclose(c.c2w, g.c2w, atol=1e-9)
        full = gt.buffers["mask"][..., 0] > 0.99
        # colour priors: the filmic 8-bit encoding inverted (within quantisation where not saturated)
        for layer in ("rgb", "diffuse", "specular"):
            enc = filmic(gt.buffers[layer])
            keep = enc < 0.98
            assert np.abs(filmic(v.buffers[layer]) - enc)[keep].max() < 0.6 / 255, layer
        # F0 = 0.04 (1 - metal) + metal, grey
        metal = np.round(np.clip((gt.buffers["f0"].mean(-1, keepdims=True) - 0.04) / 0.96, 0, 1) * 255) / 255
        assert np.allclose(v.buffers["f0"], np.repeat(0.04 * (1 - metal) + metal, 3, -1), atol=1e-6)
        # camera-space normals back in world space (8-bit quantisation: < 1 degree typical)
        cos = np.clip((v.buffers["normal"] * gt.buffers["normal"]).sum(-1), -1, 1)
        ang = np.degrees(np.arccos(cos[full & (np.linalg.norm(gt.buffers["normal"], axis=-1) > 0.99)]))
        assert np.median(ang) < 0.5 and np.percentile(ang, 99) < 1.5
        # relative depth aligned to the SfM points (20% of them wrong) by RANSAC: distance along the ray
        dist = gt.buffers["depth"][..., 0]
        rel_err = np.abs(v.buffers["depth"][..., 0] - dist)[full] / dist[full]
        assert np.median(rel_err) < 0.002 and np.percentile(rel_err, 99) < 0.01
        fit = cap.meta.extra["depth_fits"][v.name]
        assert fit["samples"] == 150 and fit["inliers"] >= 0.75 * 150
    # the released layout through the poses stage: SfM skipped, normalised (depth is a distance: x scale),
    # and init goes dense since every view has depth + diffuse
    posed = run_poses(root, tmp_path / "work", tmp_path / "capture", PosesConfig(), progress=False)
    meta = yaml.safe_load((tmp_path / "capture" / "capture.yaml").read_text())
    assert meta["extra"]["poses"]["sfm"].startswith("skipped:")
    scale = meta["extra"]["normalisation"]["scale"]
    assert np.allclose(posed.views[1].buffers["depth"], cap.views[1].buffers["depth"] * scale, rtol=1e-6)
    _, summary = initialise(read_capture(tmp_path / "capture", layers=["depth", "diffuse", "mask"]),
                            tmp_path / "capture", InitConfig(resolution=32, voxel_fraction=0.05))
    assert summary["source"] == "depth" and summary["decision"].startswith("dense init from depth")
    # without priors the photos are the radiance (sRGB decoded); SfM points feed the init fallback
    bare = tmp_path / "bare"
    build_layout(synth, bare, names[:3], priors=False)
    cap2 = read_capture(bare)
    assert cap2.layers == ["rgb"]
    gt = synth.views[0].buffers["rgb"]
    keep = linear_to_srgb(gt) < 0.99
    assert np.abs(linear_to_srgb(cap2.views[0].buffers["rgb"]) - linear_to_srgb(gt))[keep].max() < 0.6 / 255
    gaussians, summary = initialise(cap2, bare, InitConfig())
    assert summary["source"] == "sfm" and summary["points_file"].endswith("sparse/0")
    assert len(gaussians) == 3 * 150
    assert np.allclose(gaussians.diffuse.numpy(), srgb_to_linear(np.array([200, 100, 50]) / 255.0), atol=1e-6)


def test_real_layout_errors_name_the_problem(synth, tmp_path):
    names = [synth.views[0].name]
    build_layout(synth, tmp_path / "radial", names, model="SIMPLE_RADIAL", priors=False)
    with pytest.raises(CaptureError, match=r"sparse/0 image 'train_000.png': camera 1 has model SIMPLE_RADIAL; only "
                                           r"undistorted PINHOLE / SIMPLE_PINHOLE"):
        read_capture(tmp_path / "radial")
    build_layout(synth, tmp_path / "few", names, points_per_view=3, outliers=0)
    with pytest.raises(ValueError, match=r"depth_train_000.png: only 3 SfM point\(s\) project into the image; need >= 5"):
        read_capture(tmp_path / "few")
    photos_only = Capture([View(v.name, v.camera, "train", {"rgb": v.buffers["rgb"]}) for v in synth.views[:2]])
    with pytest.raises(CaptureError, match=r"nothing: has no depth buffer and no SfM points to initialise from "
                                           r"\(expected .*nothing/points3D.ply, a COLMAP model in .*nothing/sparse"):
        initialise(photos_only, tmp_path / "nothing", InitConfig())


def test_fit_scale_shift_rejects_outliers():
    rng = np.random.default_rng(1)
    d = rng.uniform(0.1, 0.9, 200)
    z = 3.0 * d + 0.7
    z[:60] = rng.uniform(0.5, 4.0, 60)  # 30% outliers
    fit = fit_scale_shift(d, z)
    # the few outliers that fall inside the inlier band (5% of the median depth) move the refit a little
    assert abs(fit.scale - 3.0) < 0.01 and abs(fit.shift - 0.7) < 0.01 and fit.inliers >= 140
    with pytest.raises(ValueError, match="the relative depth is constant"):
        fit_scale_shift(np.full(10, 0.5), np.arange(10.0), where="x.png")


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    r = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ r.T + [1.0, -2.0, 0.5]
    s, r_est, t = umeyama(src, dst)
    assert abs(s - 2.5) < 1e-12 and np.allclose(r_est, r, atol=1e-12) and np.allclose(t, [1.0, -2.0, 0.5])


# ----------------------------------------------------------------------------------- errors of the poses stage


def test_photo_errors_before_sfm(synth, tmp_path):
    few = write_photos(synth.views[:2], tmp_path / "few")
    with pytest.raises(PosesError, match=rf"needs at least 3 photos but {few} holds 2 photo\(s\)"):
        check_photos(few, 3)
    bad = write_photos(synth.views[:3], tmp_path / "bad")
    (bad / "broken.jpg").write_bytes(b"not a jpeg at all")
    with pytest.raises(PosesError, match=r"1 unreadable photo\(s\) in .*bad: .*broken.jpg: cannot read image"):
        check_photos(bad, 3)
    mixed = write_photos(synth.views[:3], tmp_path / "mixed")
    write_png(mixed / "small.png", np.zeros((120, 160, 3)))
    with pytest.raises(PosesError, match=r"mixed resolutions \(320x240: 3 photo\(s\) \(train_000.png, train_001.png, "
                                         r"train_002.png\); 160x120: 1 photo\(s\) \(small.png\)\)"):
        check_photos(mixed, 3)
    with pytest.raises(ValueError, match="poses needs vocab_tree .matcher vocab_tree needs the path of a COLMAP"):
        PosesConfig.from_dict({"matcher": "vocab_tree"})
    with pytest.raises(ValueError, match=r"unknown poses option\(s\) \['matching'\]"):
        PosesConfig.from_dict({"matching": "exhaustive"})
    missing_tree = PosesConfig.from_dict({"matcher": "vocab_tree", "vocab_tree": str(tmp_path / "tree.bin")})
    with pytest.raises(PosesError, match=rf"poses.vocab_tree: {tmp_path / 'tree.bin'} does not exist; the vocabulary "
                                         "tree is not downloaded"):
        run_poses(write_photos(synth.views[:3], tmp_path / "ok"), tmp_path / "w", tmp_path / "c", missing_tree,
                  progress=False)
    # the CLI: one line naming the problem, exit status 1
    proc = subprocess.run([sys.executable, "-m", "stages.poses", "--images", str(few), "--work", str(tmp_path / "w2"),
                           "--out", str(tmp_path / "c2")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[-1].startswith("error: needs at least 3 photos")


def test_unregistered_photos_are_named(synth, tmp_path):
    photos = write_photos(synth.views[:5], tmp_path / "photos")
    rng = np.random.default_rng(3)
    write_png(photos / "noise.png", rng.uniform(size=(240, 320, 3)))
    with pytest.raises(PosesError, match=r"1 of 6 photo\(s\) failed to register in the largest COLMAP model "
                                         r"\(model 0 holds 5; 1 model\(s\) found\): noise.png"):
        run_poses(photos, tmp_path / "work", tmp_path / "capture", PosesConfig(), progress=False)
    capture = run_poses(photos, tmp_path / "work", tmp_path / "capture", PosesConfig(allow_unregistered=True),
                        progress=False)
    assert [v.name for v in capture.views] == [v.name for v in synth.views[:5]]
    meta = yaml.safe_load((tmp_path / "capture" / "capture.yaml").read_text())
    assert meta["extra"]["poses"]["unregistered"] == ["noise.png"]


def test_no_model_is_an_error(tmp_path):
    rng = np.random.default_rng(4)
    folder = tmp_path / "noise"
    folder.mkdir()
    for i in range(3):
        write_png(folder / f"n{i}.png", rng.uniform(size=(96, 128, 3)))
    with pytest.raises(PosesError, match=r"COLMAP found no model for the 3 photos in .*noise \(\d+ verified image pairs\)"):
        run_poses(folder, tmp_path / "work", tmp_path / "capture", PosesConfig(), progress=False)


def dry_run(workdir, scene):
    return subprocess.run([sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"), "--cores", "1",
                           "--directory", str(workdir), "-n", "--config", f"scene={scene}"],
                          capture_output=True, text=True, timeout=120)


def test_workflow_says_what_to_download(tmp_path):
    proc = dry_run(tmp_path, "bear")
    assert proc.returncode != 0
    lines = [l for l in (proc.stdout + proc.stderr).splitlines() if l.strip() and not PROFILE_NOTE.match(l)]
    assert len(lines) == 1, lines
    assert lines[0].startswith("error: scene 'bear': needs at least 3 photos but data/bear does not exist; download "
                               "https://repo-sam.inria.fr/nerphys/editable-gaussian-reflections/datasets/neural_catacaustics.zip")
    assert "data/bear/" in lines[0]


def test_workflow_plans_poses_for_photos(synth, tmp_path):
    write_photos(synth.views[:3], tmp_path / "data" / "my_capture")
    proc = dry_run(tmp_path, "my_capture")
    assert proc.returncode == 0, proc.stderr
    jobs = dict(l.split() for l in proc.stdout.split("Job stats:")[1].split("total")[0].splitlines()[3:] if l.strip())
    assert jobs.get("poses") == "1" and "synth" not in jobs  # the capture comes from poses, unambiguously
    assert {"init", "reconstruct", "render", "evaluate"} <= set(jobs)
