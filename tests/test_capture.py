"""Capture format: bit-exact round trip, validation errors named, paper layout reader."""

import json
import math

import numpy as np
import OpenImageIO as oiio
import pytest

from models.capture import LAYERS, Camera, Capture, CaptureError, CaptureMeta, View, read_capture, write_capture
from models.capture.exr import read_exr_channels, write_exr_channels
from models.capture.paper_layout import filmic, inverse_filmic


def look_at(eye, target, up=(0, 1, 0)):
    """OpenGL camera-to-world looking from ``eye`` at ``target``."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
    c2w[:3, 3] = eye
    return c2w


def make_capture(rng, w=6, h=4, n=3, per_view_intrinsics=False):
    views = []
    for i in range(n):
        f = 5.0 + (i if per_view_intrinsics else 0)
        cam = Camera(w, h, f, f * 1.01, w / 2 + 0.25, h / 2 - 0.125, look_at(rng.normal(size=3) * 3, [0, 0, 0]))
        buffers = {layer: rng.normal(size=(h, w, c)).astype(np.float32) * 10 ** rng.uniform(-6, 6) for layer, c in LAYERS.items()}
        buffers["depth"] = np.abs(buffers["depth"])
        views.append(View(f"v{i:03d}", cam, "test" if i == n - 1 else "train", buffers))
    return Capture(views, CaptureMeta(source="synthetic", extent=2.5, extra={"spp": 4}))


@pytest.mark.parametrize("per_view", [False, True])
def test_round_trip_bit_exact(tmp_path, per_view):
    rng = np.random.default_rng()
    cap = make_capture(rng, per_view_intrinsics=per_view)
    write_capture(cap, tmp_path / "cap")
    back = read_capture(tmp_path / "cap")
    assert [v.name for v in back.views] == [v.name for v in cap.views]
    assert back.meta.extent == 2.5 and back.meta.extra == {"spp": 4}
    for a, b in zip(cap.views, back.views):
        assert a.split == b.split
        assert np.array_equal(a.camera.c2w, b.camera.c2w)
        assert (a.camera.fl_x, a.camera.fl_y, a.camera.cx, a.camera.cy) == (b.camera.fl_x, b.camera.fl_y, b.camera.cx, b.camera.cy)
        assert set(a.buffers) == set(b.buffers)
        for layer in a.buffers:
            assert a.buffers[layer].tobytes() == b.buffers[layer].tobytes(), layer


def test_rewrite_replaces_atomically_and_layers_filter(tmp_path):
    rng = np.random.default_rng(1)
    write_capture(make_capture(rng, n=3), tmp_path / "cap")
    write_capture(make_capture(rng, n=2), tmp_path / "cap")
    back = read_capture(tmp_path / "cap", layers=["rgb", "depth"])
    assert len(back.views) == 2 and set(back.views[0].buffers) == {"rgb", "depth"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap"]  # no temp folders left behind


def test_unknown_channels_ignored(tmp_path):
    rng = np.random.default_rng(2)
    write_capture(make_capture(rng, n=1), tmp_path / "cap")
    exr = tmp_path / "cap/images/v000.exr"
    chans = read_exr_channels(exr)
    chans["objectid.Y"] = np.zeros((4, 6), np.float32)
    chans["A"] = np.ones((4, 6), np.float32)
    write_exr_channels(exr, chans)
    back = read_capture(tmp_path / "cap")
    assert set(back.views[0].buffers) == set(LAYERS)


def _write_broken(tmp_path, mutate_frame=None, mutate_channels=None, size=(6, 4)):
    rng = np.random.default_rng(3)
    write_capture(make_capture(rng, n=2), tmp_path / "cap")
    root = tmp_path / "cap"
    tf = json.loads((root / "transforms.json").read_text())
    if mutate_frame:
        mutate_frame(tf["frames"][1])
    (root / "transforms.json").write_text(json.dumps(tf))
    if mutate_channels:
        exr = root / "images/v001.exr"
        chans = read_exr_channels(exr)
        mutate_channels(chans)
        write_exr_channels(exr, chans)
    return root


def test_error_missing_image(tmp_path):
    root = _write_broken(tmp_path)
    (root / "images/v001.exr").unlink()
    with pytest.raises(CaptureError, match=r"frame 1: image 'images/v001.exr' is missing"):
        read_capture(root)


def test_error_resolution_mismatch(tmp_path):
    root = _write_broken(tmp_path)
    chans = read_exr_channels(root / "images/v001.exr")
    write_exr_channels(root / "images/v001.exr", {k: np.zeros((5, 7), np.float32) for k in chans})
    with pytest.raises(CaptureError, match=r"v001.exr: layer 'rgb' is 7x5 but transforms.json says 6x4"):
        read_capture(root)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_error_nonfinite_pixels(tmp_path, bad):
    def poison(chans):
        chans["normal.Y"][2, 3] = bad

    root = _write_broken(tmp_path, mutate_channels=poison)
    with pytest.raises(CaptureError, match=r"v001.exr: layer 'normal' has 1 pixel\(s\) with NaN/Inf \(first at x=3, y=2"):
        read_capture(root)


def test_error_non_orthonormal_rotation(tmp_path):
    def scale(frame):
        frame["transform_matrix"][0][0] *= 1.5

    root = _write_broken(tmp_path, mutate_frame=scale)
    with pytest.raises(CaptureError, match=r"frame 1 \(images/v001.exr\): rotation of transform_matrix is not orthonormal"):
        read_capture(root)


def test_error_unknown_split(tmp_path):
    def split(frame):
        frame["split"] = "validation"

    root = _write_broken(tmp_path, mutate_frame=split)
    with pytest.raises(CaptureError, match=r"frame 1 \(images/v001.exr\): unknown split 'validation' \(expected one of train, test\)"):
        read_capture(root)


def test_error_wrong_channel_count(tmp_path):
    def drop(chans):
        del chans["normal.Z"]

    root = _write_broken(tmp_path, mutate_channels=drop)
    with pytest.raises(CaptureError, match=r"v001.exr: layer 'normal' has 2 channel\(s\) \['normal.X', 'normal.Y'\], expected 3"):
        read_capture(root)


def test_error_extra_channel_in_known_layer(tmp_path):
    def add(chans):
        chans["depth.W"] = chans["depth.Z"].copy()

    root = _write_broken(tmp_path, mutate_channels=add)
    with pytest.raises(CaptureError, match=r"layer 'depth' has 2 channel\(s\)"):
        read_capture(root)


def test_error_distortion_and_missing_intrinsic(tmp_path):
    root = _write_broken(tmp_path, mutate_frame=lambda f: f.update(k1=0.1))
    with pytest.raises(CaptureError, match=r"frame 1: distortion k1=0.1 is not supported"):
        read_capture(root)
    tf = json.loads((root / "transforms.json").read_text())
    del tf["frames"][1]["k1"]
    del tf["fl_x"]
    (root / "transforms.json").write_text(json.dumps(tf))
    with pytest.raises(CaptureError, match=r"frame 0: intrinsic 'fl_x' missing"):
        read_capture(root)


def test_in_memory_check_names_view():
    cam = Camera(4, 3, 2.0, 2.0, 2.0, 1.5, np.eye(4))
    view = View("a", cam, "train", {"rgb": np.zeros((3, 4, 2), np.float32)})
    with pytest.raises(CaptureError, match=r"view 'a': layer 'rgb' must have 3 channel\(s\), got array of shape \(3, 4, 2\)"):
        Capture([view]).check()


def test_camera_rays_convention():
    c2w = look_at([0, 0, 5], [0, 0, 0])
    cam = Camera(5, 3, 4.0, 4.0, 2.5, 1.5, c2w)
    d = cam.ray_directions()
    assert np.allclose(d[1, 2], [0, 0, -1])  # centre pixel looks at the target
    assert d[1, 4, 0] > 0 and d[0, 2, 1] > 0  # right column looks right, top row looks up
    assert np.allclose(np.linalg.norm(d, axis=-1), 1)


def test_filmic_inverse():
    x = np.concatenate([np.linspace(0, 1, 101), np.geomspace(1, 50, 50)])
    assert np.allclose(inverse_filmic(filmic(x)), x, rtol=1e-9, atol=1e-12)


def _png(path, arr8):
    spec = oiio.ImageSpec(arr8.shape[1], arr8.shape[0], arr8.shape[2], oiio.UINT8)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    out.write_image(arr8)
    out.close()


def test_paper_layout_reader(tmp_path):
    rng = np.random.default_rng(4)
    w, h = 8, 6
    radiance = rng.uniform(0, 3, size=(h, w, 3))
    frames = []
    for split in ("train", "test"):
        (tmp_path / split).mkdir()
        c2w = look_at([1, 2, 3], [0, 0, 0])
        frames = [{"file_path": f"./{split}/render_0000", "transform_matrix": c2w.tolist()}]
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
        _png(tmp_path / split / "render_0000.png", np.round(filmic(radiance) * 255).astype(np.uint8))
        write_exr_channels(tmp_path / split / "depth_0000.exr", {"Y": np.full((h, w), 2.5, np.float32)})
        normal = np.zeros((h, w, 3))
        normal[..., 2] = 1
        _png(tmp_path / split / "normal_0000.png", np.round((normal * 0.5 + 0.5) * 255).astype(np.uint8))
    cap = read_capture(tmp_path)
    assert [v.split for v in cap.views] == ["train", "test"]
    v = cap.views[0]
    assert set(v.buffers) == {"rgb", "depth", "normal"}
    assert math.isclose(v.camera.fl_x, 0.5 * w / math.tan(0.4))
    # 8-bit quantisation of the tonemapped value bounds the decoded error
    back8 = np.round(filmic(v.buffers["rgb"]) * 255)
    assert np.array_equal(back8, np.round(filmic(radiance) * 255))
    assert np.allclose(v.buffers["depth"], 2.5) and np.allclose(v.buffers["normal"][..., 2], 1, atol=1e-2)


def test_not_a_capture(tmp_path):
    with pytest.raises(CaptureError, match="not a capture"):
        read_capture(tmp_path)
