"""nerfstudio datasets (transforms.json + PNG images, ns-process-data layout) read as captures (#21, data in):
8-bit images sRGB-decoded to linear, split lists honoured, ply_file_path / colmap/sparse/0 points, OPENCV cameras."""

import json
import struct
import zlib

import numpy as np
import pytest

from models.capture import CaptureError, read_capture, read_sfm_points
from models.capture.colmap_layout import colmap_from_c2w
from models.initialisation import InitConfig, initialise
from models.synth.cameras import look_at


def srgb_encode(linear):
    """IEC 61966-2-1 encoding, written out here independently of models/capture/color.py."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def srgb_decode(encoded):
    return np.where(encoded <= 0.04045, encoded / 12.92, ((encoded + 0.055) / 1.055) ** 2.4)


def write_png(path, rgb8, gamma=None):
    """An 8-bit RGB PNG in plain Python (zlib + struct); ``gamma``: a gAMA chunk (1.0: the file says linear)."""
    h, w, _ = rgb8.shape

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    raw = b"".join(b"\x00" + rgb8[y].astype(np.uint8).tobytes() for y in range(h))
    chunks = [chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))]
    if gamma is not None:
        chunks.append(chunk(b"gAMA", struct.pack(">I", round(100000 / gamma))))
    chunks += [chunk(b"IDAT", zlib.compress(raw)), chunk(b"IEND", b"")]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"".join(chunks))


W, H, N = 8, 6, 5
POINTS = np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5], [0.3, 0.2, -0.4], [-0.2, 0.1, 0.3]])
COLOURS = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 128, 128], [10, 200, 90], [250, 250, 250]])


def write_dataset(root, **top):
    """A nerfstudio-style dataset: PNGs sRGB-encoded from known linear images, an OPENCV camera with zero
    distortion, split lists (frame 4 listed nowhere), ply_file_path. Returns the linear truth per frame."""
    rng = np.random.default_rng(21)
    truth, frames = [], []
    for i in range(N):
        linear = rng.uniform(0.0, 0.8, size=(H, W, 3))  # <= 0.8: one 8-bit step is < 1/255 in linear terms
        write_png(root / "images" / f"frame_{i:05d}.png", np.round(srgb_encode(linear) * 255))
        truth.append(linear)
        eye = [3 * np.cos(i), 0.5, 3 * np.sin(i)]
        frames.append({"file_path": f"images/frame_{i:05d}.png", "transform_matrix": look_at(eye, (0.0, 0.0, 0.0)).tolist(),
                       "colmap_im_id": i + 1})
    tf = {"w": W, "h": H, "fl_x": 7.0, "fl_y": 7.5, "cx": 4.0, "cy": 3.0,
          "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "camera_model": "OPENCV", "frames": frames,
          "train_filenames": [f"images/frame_{i:05d}.png" for i in (0, 1, 2)],
          "test_filenames": ["./images/frame_00003.png"],  # nerfstudio compares resolved paths
          "ply_file_path": "sparse_pc.ply", "applied_transform": [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]]}
    tf.update(top)
    (root / "transforms.json").write_text(json.dumps(tf, indent=2))
    # the ASCII PLY nerfstudio's create_ply_from_colmap writes
    lines = ["ply", "format ascii 1.0", f"element vertex {len(POINTS)}", "property float x", "property float y",
             "property float z", "property uint8 red", "property uint8 green", "property uint8 blue", "end_header"]
    lines += [f"{x:8f} {y:8f} {z:8f} {r} {g} {b}" for (x, y, z), (r, g, b) in zip(POINTS, COLOURS)]
    (root / "sparse_pc.ply").write_text("\n".join(lines) + "\n")
    return truth


def test_nerfstudio_dataset_reads_linear_with_splits_and_points(tmp_path):
    truth = write_dataset(tmp_path)
    capture = read_capture(tmp_path)

    # splits: the lists, not "every frame is train"; the frame listed nowhere is left out (as nerfstudio does)
    assert [v.name for v in capture.split("train")] == ["frame_00000", "frame_00001", "frame_00002"]
    assert [v.name for v in capture.split("test")] == ["frame_00003"]
    assert capture.meta.extra["splits"] == {"from": ["train_filenames", "test_filenames"], "left_out": 1}

    # colours: linear, matching the linear truth within one 8-bit step; the old reading (raw / 255) does not
    for view in capture.views:
        i = int(view.name.split("_")[1])
        rgb = view.buffers["rgb"]
        assert rgb.dtype == np.float32 and rgb.shape == (H, W, 3)
        assert np.abs(rgb - truth[i]).max() <= 1 / 255
        stored = np.round(srgb_encode(truth[i]) * 255) / 255
        assert np.allclose(rgb, srgb_decode(stored), atol=1e-6)  # exactly the decoded bytes
        assert np.abs(stored - truth[i]).max() > 0.1  # reading the bytes as linear would be far off
    assert abs(np.mean([v.buffers["rgb"].mean() for v in capture.views]) - np.mean(truth[:4])) < 1e-3
    assert "decoded to linear" in capture.meta.extra["rgb"]

    # OPENCV with zero distortion: a pinhole camera with the file's intrinsics
    cam = capture.views[0].camera
    assert (cam.width, cam.height, cam.fl_x, cam.fl_y, cam.cx, cam.cy) == (W, H, 7.0, 7.5, 4.0, 3.0)

    # ply_file_path: the capture's initial points (colours sRGB-decoded like the images)
    xyz, rgb, source = read_sfm_points(tmp_path)
    assert source == tmp_path / "sparse_pc.ply"
    assert np.allclose(xyz, POINTS, atol=1e-6)
    assert np.allclose(rgb, srgb_decode(COLOURS / 255.0))
    gaussians, summary = initialise(read_capture(tmp_path, layers=["depth", "diffuse"]), tmp_path, InitConfig())
    assert summary["source"] == "sfm" and summary["gaussians"] == len(POINTS)
    assert "sparse_pc.ply" in summary["decision"]


def test_png_that_says_linear_stays_linear(tmp_path):
    write_dataset(tmp_path)
    linear8 = np.arange(W * H * 3).reshape(H, W, 3) % 256
    write_png(tmp_path / "images" / "frame_00001.png", linear8, gamma=1.0)
    view = {v.name: v for v in read_capture(tmp_path).views}["frame_00001"]
    assert np.allclose(view.buffers["rgb"], linear8 / 255.0, atol=1e-6)


def test_no_lists_every_frame_train_and_val_goes_to_test(tmp_path):
    write_dataset(tmp_path, train_filenames=None)
    tf = json.loads((tmp_path / "transforms.json").read_text())
    del tf["train_filenames"]
    tf["val_filenames"] = ["images/frame_00004.png"]
    (tmp_path / "transforms.json").write_text(json.dumps(tf))
    capture = read_capture(tmp_path)  # without train_filenames the frames not listed are train
    assert [v.name for v in capture.split("test")] == ["frame_00003", "frame_00004"]
    assert len(capture.split("train")) == 3
    for key in ("test_filenames", "val_filenames"):
        del tf[key]
    (tmp_path / "transforms.json").write_text(json.dumps(tf))
    assert len(read_capture(tmp_path).split("train")) == N


@pytest.mark.parametrize("change, message", [
    ({"k1": 0.1}, r"transforms.json frame 0: distortion k1=0.1 is not supported \(camera_model OPENCV, "
                  r"image 'images/frame_00000.png'\); undistort"),
    ({"camera_model": "OPENCV_FISHEYE"}, r"transforms.json frame 0: camera_model 'OPENCV_FISHEYE' is not a pinhole"),
    ({"test_filenames": ["images/nope.png"]}, r"transforms.json: test_filenames lists 1 path\(s\) that no frame"),
    ({"test_filenames": ["images/frame_00000.png"]}, r"'images/frame_00000.png' is listed in both train_filenames "
                                                     r"and test_filenames"),
])
def test_errors_name_the_file(tmp_path, change, message):
    write_dataset(tmp_path, **change)
    with pytest.raises(CaptureError, match=message):
        read_capture(tmp_path)


def test_missing_ply_file_named(tmp_path):
    write_dataset(tmp_path, ply_file_path="points/missing.ply")
    with pytest.raises(CaptureError, match=r"transforms.json: ply_file_path 'points/missing.ply' does not exist"):
        read_sfm_points(tmp_path)


def _write_colmap_model(model, frames, applied):
    """ns-process-data's colmap/sparse/0 (text model) whose world is ``applied``^-1 of the frames' world."""
    model.mkdir(parents=True)
    a = np.vstack([np.asarray(applied, float), [0, 0, 0, 1]])
    (model / "cameras.txt").write_text(f"1 PINHOLE {W} {H} 7.0 7.5 4.0 3.0\n")
    lines = []
    for i, frame in enumerate(frames):
        c2w = np.linalg.inv(a) @ np.asarray(frame["transform_matrix"])  # frames' world -> COLMAP world
        rt = colmap_from_c2w(c2w)
        import pycolmap

        q = pycolmap.Rotation3d(rt[:, :3]).quat  # xyzw
        t = rt[:, 3]
        name = frame["file_path"].split("/")[-1]
        lines += [f"{i + 1} {q[3]} {q[0]} {q[1]} {q[2]} {t[0]} {t[1]} {t[2]} 1 {name}", ""]
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    pts = (np.linalg.inv(a) @ np.c_[POINTS, np.ones(len(POINTS))].T).T[:, :3]
    (model / "points3D.txt").write_text("".join(
        f"{k + 1} {x} {y} {z} {r} {g} {b} 0.5\n" for k, ((x, y, z), (r, g, b)) in enumerate(zip(pts, COLOURS))))


def test_colmap_sparse_0_points_moved_by_applied_transform(tmp_path):
    write_dataset(tmp_path, ply_file_path=None)
    tf = json.loads((tmp_path / "transforms.json").read_text())
    del tf["ply_file_path"]
    (tmp_path / "transforms.json").write_text(json.dumps(tf))
    _write_colmap_model(tmp_path / "colmap" / "sparse" / "0", tf["frames"], tf["applied_transform"])
    xyz, rgb, source = read_sfm_points(tmp_path)
    assert source == tmp_path / "colmap" / "sparse" / "0"
    order = np.argsort(xyz[:, 0] * 100 + xyz[:, 1] * 10 + xyz[:, 2])
    expect = np.argsort(POINTS[:, 0] * 100 + POINTS[:, 1] * 10 + POINTS[:, 2])
    assert np.allclose(xyz[order], POINTS[expect], atol=1e-5)
    # no applied_transform: nerfstudio's legacy one is tried, and refused when the cameras do not line up
    del tf["applied_transform"]
    (tmp_path / "transforms.json").write_text(json.dumps(tf))
    with pytest.raises(CaptureError, match=r"cameras of .*colmap/sparse/0 do not line up with the frames'"):
        read_sfm_points(tmp_path)


def test_buffer_network_reader_honours_split_lists(tmp_path):
    from models.buffernet._capture_reader import CaptureReader

    write_dataset(tmp_path)
    assert len(CaptureReader(tmp_path)) == 4  # frame 4 is listed nowhere
    assert len(CaptureReader(tmp_path, split="train")) == 3 and len(CaptureReader(tmp_path, split="test")) == 1


def test_jpeg_views_decoded(tmp_path):
    import OpenImageIO as oiio

    write_dataset(tmp_path)
    tf = json.loads((tmp_path / "transforms.json").read_text())
    rgb8 = (np.arange(W * H * 3).reshape(H, W, 3) * 5 % 256).astype(np.uint8)
    path = tmp_path / "images" / "frame_00002.jpg"
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(W, H, 3, oiio.UINT8))
    out.write_image(rgb8)
    out.close()
    stored = np.asarray(oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8), dtype=np.float64) / 255.0  # after JPEG loss
    tf["frames"][2]["file_path"] = tf["train_filenames"][2] = "images/frame_00002.jpg"
    (tmp_path / "transforms.json").write_text(json.dumps(tf))
    view = {v.name: v for v in read_capture(tmp_path).views}["frame_00002"]
    assert np.allclose(view.buffers["rgb"], srgb_decode(stored), atol=1e-6)
