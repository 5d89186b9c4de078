"""Buffer-network dataset readers on tiny files written in the real layouts (Hypersim HDF5, InteriorVerse
EXR, the project's capture format), and the crop / resize / flip of BufferDataset."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

h5py = pytest.importorskip("h5py")

from models.buffernet.datasets import (  # noqa: E402
    BUFFER_CHANNELS, BufferDataset, BufferSample, CaptureReader, DatasetError, HypersimReader, InteriorVerseReader,
    resize_sample,
)
from models.capture import Camera, Capture, View, write_capture  # noqa: E402
from models.capture.exr import write_exr_channels  # noqa: E402
from models.synth.cameras import look_at  # noqa: E402

H, W = 6, 8  # 4:3 like Hypersim's 1024x768


def pixel_rays(h, w, fl):
    """Independent pinhole model: camera-space (OpenGL) ray through each pixel centre, z = -1."""
    x = (np.arange(w) + 0.5 - w / 2) / fl
    y = -(np.arange(h) + 0.5 - h / 2) / fl
    xx, yy = np.meshgrid(x, y)
    return np.stack([xx, yy, -np.ones_like(xx)], -1)


# ---------------------------------------------------------------------------------------------- Hypersim


def write_h5(path, array):
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        f.create_dataset("dataset", data=array)


def hypersim_scene(root, scene="ai_001_001", cam="cam_00", frame="0000", d=2.5):
    """A fronto-parallel wall at planar depth ``d``; pixel (0, 0) background, (0, 1) NaN colour,
    (1, 0) zero normal; normals of the right half point away from the camera."""
    rng = np.random.default_rng(0)
    refl = rng.uniform(0.1, 0.9, (H, W, 3)).astype(np.float16)
    illum = rng.uniform(0.0, 4.0, (H, W, 3)).astype(np.float16)
    resid = rng.uniform(0.0, 0.5, (H, W, 3)).astype(np.float16)
    color = (refl.astype(np.float32) * illum + resid).astype(np.float16)
    color[0, 1] = np.nan
    fl = 886.81 * W / 1024  # the documented focal at 1024x768, scaled to this width
    distance = d * np.linalg.norm(pixel_rays(H, W, fl), axis=-1)  # Euclidean distance to the centre
    normal = np.zeros((H, W, 3), np.float16)
    normal[..., 2] = 1.0
    normal[:, W // 2:, 2] = -1.0  # inward (issue #26 of ml-hypersim)
    normal[1, 0] = 0.0
    entity = np.full((H, W), 7, np.int32)
    entity[0, 0] = -1
    final = root / scene / "images" / f"scene_{cam}_final_hdf5"
    geometry = root / scene / "images" / f"scene_{cam}_geometry_hdf5"
    for name, arr in (("color", color), ("diffuse_illumination", illum), ("diffuse_reflectance", refl),
                      ("residual", resid)):
        write_h5(final / f"frame.{frame}.{name}.hdf5", arr)
    for name, arr in (("depth_meters", distance.astype(np.float16)), ("normal_bump_cam", normal),
                      ("normal_cam", normal), ("render_entity_id", entity)):
        write_h5(geometry / f"frame.{frame}.{name}.hdf5", arr)
    return dict(refl=refl, illum=illum, resid=resid, color=color)


def test_hypersim_reader(tmp_path):
    truth = hypersim_scene(tmp_path, d=2.5)
    hypersim_scene(tmp_path, scene="ai_001_002", d=1.0)
    reader = HypersimReader(tmp_path, scenes=["ai_001_001"])
    assert len(reader) == 1 and len(HypersimReader(tmp_path)) == 2
    s = reader[0]
    s.check()
    assert s.name == "hypersim/ai_001_001/cam_00/frame.0000"
    assert set(s.buffers) == {"diffuse", "specular", "normal", "depth"}  # no roughness / f0 in Hypersim
    m = s.masks["diffuse"]
    refl, illum = truth["refl"].astype(np.float32), truth["illum"].astype(np.float32)
    np.testing.assert_allclose(s.buffers["diffuse"][m], (refl * illum)[m], rtol=1e-6)
    np.testing.assert_allclose(s.buffers["specular"][m], truth["resid"].astype(np.float32)[m])
    # distance -> planar: the fronto-parallel wall has constant z (float16 storage: ~1e-3 relative)
    np.testing.assert_allclose(s.buffers["depth"][s.masks["depth"]], 2.5, rtol=2e-3)
    # every normal faces the camera: (0, 0, 1) for the wall, whatever its stored orientation
    n = s.buffers["normal"][s.masks["normal"]]
    np.testing.assert_allclose(n, np.broadcast_to([0, 0, 1], n.shape), atol=1e-6)
    # invalid pixels: background (entity -1) everywhere, NaN colour everywhere, zero normal for normals only
    for key in s.buffers:
        assert not s.masks[key][0, 0] and not s.masks[key][0, 1]
    assert np.all(s.rgb[0, 1] == 0) and np.isfinite(s.rgb).all()
    assert not s.masks["normal"][1, 0] and s.masks["depth"][1, 0] and s.masks["diffuse"][1, 0]
    assert s.masks["depth"].sum() == H * W - 2


def test_hypersim_errors_name_the_file(tmp_path):
    with pytest.raises(DatasetError, match="no Hypersim scene folders"):
        HypersimReader(tmp_path)
    hypersim_scene(tmp_path)
    with pytest.raises(DatasetError, match="ai_009_009"):
        HypersimReader(tmp_path, scenes=["ai_009_009"])
    missing = tmp_path / "ai_001_001/images/scene_cam_00_final_hdf5/frame.0000.residual.hdf5"
    missing.unlink()
    with pytest.raises(DatasetError, match=r"frame\.0000\.residual\.hdf5: missing"):
        HypersimReader(tmp_path)[0]
    with h5py.File(missing, "w") as f:
        f.create_dataset("data", data=np.zeros((H, W, 3)))
    with pytest.raises(DatasetError, match="no 'dataset' key"):
        HypersimReader(tmp_path)[0]


# ------------------------------------------------------------------------------------------ InteriorVerse


def write_exr(path, array, names=("R", "G", "B")):
    path.parent.mkdir(parents=True, exist_ok=True)
    array = np.asarray(array, np.float32)
    array = array[..., None] if array.ndim == 2 else array
    write_exr_channels(path, {n: array[..., i] for i, n in enumerate(names)})


def interiorverse_root(tmp_path, hfov=85):
    root = tmp_path / f"dataset_{hfov}"
    rng = np.random.default_rng(1)
    fl = 0.5 * W / math.tan(math.radians(hfov) / 2)
    for scene in ("SCENE_A", "SCENE_B"):
        for view in ("000", "001"):
            base = root / scene / view
            write_exr(base.with_name(f"{view}_im.exr"), rng.uniform(0, 3, (H, W, 3)))
            mask = np.ones((H, W))
            mask[0, 0] = 0
            write_exr(base.with_name(f"{view}_mask.exr"), mask, names=("Y",))
            write_exr(base.with_name(f"{view}_albedo.exr"), rng.uniform(0, 1, (H, W, 3)))
            material = np.stack([rng.uniform(0.05, 1, (H, W)), rng.choice([0.0, 1.0], (H, W)), np.zeros((H, W))], -1)
            material[2, 2, :2] = 0.0  # roughness = metallic = 0: no material there
            write_exr(base.with_name(f"{view}_material.exr"), material)
            depth = np.full((H, W), 1800.0)  # mm, planar
            depth[3, 3] = np.inf
            write_exr(base.with_name(f"{view}_depth.exr"), np.repeat(depth[..., None], 3, -1))
            normal = np.zeros((H, W, 3))
            normal[..., 1] = 1.0  # a floor seen from a level camera: up
            normal[:, :2] = -normal[:, :2]  # left columns stored facing away (must flip)
            normal[4, 4] = 0.0
            write_exr(base.with_name(f"{view}_normal.exr"), normal)
    (root / "train.txt").write_text("SCENE_A\nSCENE_B\n")
    (root / "val.txt").write_text("SCENE_B\n")
    (root / "test.txt").write_text("SCENE_MISSING\n")
    return root, fl


def test_interiorverse_reader(tmp_path):
    root, fl = interiorverse_root(tmp_path)
    reader = InteriorVerseReader(root)
    assert reader.hfov == 85 and len(reader) == 4 and len(InteriorVerseReader(root, "val")) == 2
    s = reader[1]
    s.check()
    assert s.name == "interiorverse/dataset_85/SCENE_A/001"
    assert set(s.buffers) == {"normal", "depth", "roughness", "f0"}  # albedo is not shaded diffuse
    from models.capture.exr import read_exr_channels

    mat = read_exr_channels(root / "SCENE_A/001_material.exr")
    alb = read_exr_channels(root / "SCENE_A/001_albedo.exr")
    metal = mat["G"]
    f0 = np.stack([0.04 * (1 - metal) + metal * alb[c] for c in "RGB"], -1)
    ok = s.masks["f0"]
    np.testing.assert_allclose(s.buffers["f0"][ok], f0[ok], rtol=1e-6)
    np.testing.assert_allclose(s.buffers["roughness"][ok], mat["R"][ok])
    assert not s.masks["f0"][2, 2] and not s.masks["roughness"][2, 2] and s.masks["depth"][2, 2]
    np.testing.assert_allclose(s.buffers["depth"][s.masks["depth"]], 1.8)  # mm -> m, already planar
    assert not s.masks["depth"][3, 3] and s.buffers["depth"][3, 3] == 0  # inf = invalid
    assert not any(s.masks[k][0, 0] for k in s.buffers)  # _mask = 0
    n = s.buffers["normal"]
    to_camera = -pixel_rays(H, W, fl)
    assert ((n * to_camera).sum(-1)[s.masks["normal"]] >= 0).all()
    assert not s.masks["normal"][4, 4]
    # stored +y or -y alike: +y where the ray goes down (bottom rows), -y where it goes up
    expected_y = np.where(pixel_rays(H, W, fl)[..., 1] < 0, 1.0, -1.0)
    ok = s.masks["normal"]
    np.testing.assert_allclose(n[..., 1][ok], expected_y[ok])


def test_interiorverse_errors(tmp_path):
    root, _ = interiorverse_root(tmp_path)
    with pytest.raises(DatasetError, match="SCENE_MISSING: scene listed in test.txt is missing"):
        InteriorVerseReader(root, "test")
    (root / "SCENE_A/000_depth.exr").unlink()
    with pytest.raises(DatasetError, match="000_depth.exr: missing"):
        InteriorVerseReader(root)[0]
    renamed = root.rename(tmp_path / "iv")
    with pytest.raises(ValueError, match="pass hfov"):
        InteriorVerseReader(renamed)
    assert InteriorVerseReader(renamed, hfov=120).hfov == 120
    with pytest.raises(DatasetError, match="split list not found"):
        InteriorVerseReader(tmp_path, hfov=85)


# ------------------------------------------------------------------------------------------ captures


def floor_view(name, c2w, split, h=6, w=8, fl=7.0):
    """The world floor y = 0 (normal +y) seen by ``c2w``: exact distance-along-ray depth."""
    cam = Camera(width=w, height=h, fl_x=fl, fl_y=fl, cx=w / 2, cy=h / 2, c2w=c2w)
    d = cam.ray_directions()
    t = -cam.origin[1] / d[..., 1]  # distance to the floor along the unit ray
    rng = np.random.default_rng(2)
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    diffuse, specular = rng.uniform(0, 1, (h, w, 3)), rng.uniform(0, 0.2, (h, w, 3))
    emission = np.zeros((h, w, 3))
    emission[0, 0] = 5.0
    mask = np.ones((h, w, 1))
    mask[5, 7] = 0.25
    buffers = {
        "rgb": f32(diffuse + specular + emission), "diffuse": f32(diffuse), "specular": f32(specular),
        "emission": f32(emission), "depth": f32(t[..., None]), "normal": f32(np.broadcast_to([0, 1, 0], (h, w, 3))),
        "roughness": f32(rng.uniform(0, 1, (h, w, 1))), "f0": f32(rng.uniform(0, 1, (h, w, 3))), "mask": f32(mask),
    }
    return View(name=name, camera=cam, split=split, buffers=buffers), t


def test_capture_reader_camera_space(tmp_path):
    down, _ = floor_view("down", look_at([0, 2, 0], [0, 0, 0]), "train")
    oblique_c2w = look_at([1.0, 1.5, 2.0], [0.0, 0.0, 0.0])
    oblique, t = floor_view("oblique", oblique_c2w, "test")
    write_capture(Capture(views=[down, oblique]), tmp_path / "scene_0000")
    reader = CaptureReader(tmp_path / "scene_0000")
    assert len(reader) == 2 and len(CaptureReader(tmp_path / "scene_0000", split="test")) == 1
    s = reader[0]
    s.check()
    assert s.name == "capture/scene_0000/down"
    assert set(s.buffers) == set(BUFFER_CHANNELS)
    # a floor (world +y) seen by a camera looking down: camera-space normal toward the camera (+z)
    np.testing.assert_allclose(s.buffers["normal"][s.masks["normal"]], [[0, 0, 1]] * int(s.masks["normal"].sum()),
                               atol=1e-6)
    np.testing.assert_allclose(s.buffers["depth"][s.masks["depth"]], 2.0, rtol=1e-6)  # planar, not distance
    np.testing.assert_allclose(s.buffers["diffuse"][0, 0], down.buffers["diffuse"][0, 0] + 5.0)  # + emission
    ok = s.masks["diffuse"]
    np.testing.assert_allclose(s.rgb[ok], (s.buffers["diffuse"] + s.buffers["specular"])[ok], atol=1e-6)
    assert not any(s.masks[k][5, 7] for k in s.buffers)  # mask 0.25 < 0.5
    # oblique view: planar depth = -z of the floor point in camera space; the normal is R^T (0, 1, 0)
    s = reader[1]
    cam = oblique.camera
    points = cam.origin + t[..., None] * cam.ray_directions()
    z_cam = ((points - cam.origin) @ cam.rotation)[..., 2]
    np.testing.assert_allclose(s.buffers["depth"], -z_cam * s.masks["depth"], rtol=1e-5, atol=1e-6)
    n_cam = cam.rotation.T @ np.array([0.0, 1.0, 0.0])
    np.testing.assert_allclose(s.buffers["normal"][2, 3], n_cam, atol=1e-6)
    assert n_cam @ -cam.camera_directions()[2, 3] > 0


def test_capture_reader_errors(tmp_path):
    with pytest.raises(DatasetError, match="not a capture"):
        CaptureReader(tmp_path)
    view, _ = floor_view("v", look_at([0, 2, 0], [0, 0, 0]), "train")
    write_capture(Capture(views=[view]), tmp_path / "c")
    with pytest.raises(DatasetError, match="no views in split 'test'"):
        CaptureReader(tmp_path / "c", split="test")
    (tmp_path / "c/images/v.exr").unlink()
    with pytest.raises(DatasetError, match=r"v\.exr"):
        CaptureReader(tmp_path / "c")


# ------------------------------------------------------------------------------------------ BufferDataset


def ramp_sample(h=8, w=8, name="ramp"):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    rgb = np.stack([xx, yy, xx + yy], -1)
    normal = np.stack([xx - w / 2 + 0.5, yy - h / 2 + 0.5, np.full_like(xx, 4.0)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    buffers = {"diffuse": rgb * 0.5, "normal": normal.astype(np.float32), "depth": 1 + xx + 10 * yy,
               "roughness": xx / w}
    masks = {k: np.ones((h, w), bool) for k in buffers}
    masks["diffuse"][1, 2] = False
    return BufferSample(rgb=rgb, buffers=buffers, masks=masks, name=name)


def test_resize_area_masks_and_flip():
    s = ramp_sample()
    out = resize_sample(s, (0, 0, 8, 8), 4)
    blocks = lambda a: a.reshape(4, 2, 4, 2, *a.shape[2:]).mean((1, 3))  # noqa: E731
    np.testing.assert_allclose(out["rgb"].permute(1, 2, 0).numpy(), blocks(s.rgb), rtol=1e-6)
    m = out["masks"]["diffuse"]
    assert not m[0, 1] and m.sum() == 15  # the block holding pixel (1, 2) is invalid (masks AND-ed)
    np.testing.assert_allclose(out["buffers"]["diffuse"].permute(1, 2, 0).numpy()[m.numpy()],
                               blocks(s.buffers["diffuse"])[m.numpy()], rtol=1e-6)
    assert out["buffers"]["diffuse"][:, 0, 1].abs().sum() == 0
    assert torch.allclose(out["buffers"]["normal"].norm(dim=0), torch.ones(4, 4), atol=1e-6)
    assert set(out["buffers"]["depth"].flatten().tolist()) <= set(s.buffers["depth"].flatten().tolist())  # nearest
    flipped = resize_sample(s, (0, 0, 8, 8), 4, flip=True)
    assert torch.equal(flipped["rgb"], out["rgb"].flip(-1))
    assert torch.equal(flipped["masks"]["diffuse"], out["masks"]["diffuse"].flip(-1))
    nf, n = flipped["buffers"]["normal"], out["buffers"]["normal"].flip(-1)
    assert torch.equal(nf[0], -n[0]) and torch.equal(nf[1:], n[1:])  # flip negates normal x


def test_buffer_dataset_batches(tmp_path):
    hypersim_scene(tmp_path)
    readers = [[ramp_sample(), ramp_sample(8, 12, "wide")], HypersimReader(tmp_path)]
    ds = BufferDataset(readers, size=4)
    assert len(ds) == 3
    torch.manual_seed(0)
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=3)))
    assert batch["rgb"].shape == (3, 3, 4, 4) and batch["rgb"].dtype == torch.float32
    for key, c in BUFFER_CHANNELS.items():
        assert batch["buffers"][key].shape == (3, c, 4, 4) and batch["masks"][key].dtype == torch.bool
    order = list(BUFFER_CHANNELS)
    assert batch["present"][2].tolist() == [k in ("diffuse", "specular", "normal", "depth") for k in order]
    assert batch["present"][0].tolist() == [k in ("diffuse", "normal", "depth", "roughness") for k in order]
    assert not batch["masks"]["f0"].any()  # no source has f0 here
    assert batch["name"] == ["ramp", "wide", "hypersim/ai_001_001/cam_00/frame.0000"]
    fixed = BufferDataset(readers, size=6, augment=False)[1]  # centred 8x8 of the 8x12 sample
    assert fixed["rgb"][0].min() >= 2 and fixed["rgb"][0].max() <= 9  # x in [2, 10) only
