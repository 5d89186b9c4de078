"""Reader for COLMAP folders, including the paper's real-scene layout with network priors.

```
<root>/sparse/0/ (or sparse/)   COLMAP model: cameras, images, points3D (.bin or .txt);
                                undistorted PINHOLE / SIMPLE_PINHOLE cameras only
<root>/images/<name>            the photos (8-bit sRGB, decoded to linear)
<root>/priors/<buf>/<buf>_<stem>.png   optional network predictions per frame, <buf> one of
        render, diffuse, specular   8-bit, the paper's filmic encoding (inverted on load)
        roughness, metalness        [0, 1]; F0 = 0.04 (1 - metalness) + metalness
        normal                      camera space, 2v - 1; world = R_c2w (-n) as the reference does
                                    (R_c2w: COLMAP/OpenCV camera-to-world rotation)
        depth                       relative z-depth; per image, scale and shift are fitted by RANSAC
                                    to the z of the SfM points the image observes, then turned into
                                    distance along the ray (the capture's depth)
```

The final radiance (``rgb``) is the ``render`` prior when present, else the photo. Priors at
another resolution than the COLMAP camera rescale the camera's intrinsics (same aspect ratio
required). Views are ordered by image name; the test split holds every ``test_every``-th of them (the
reference's LLFF hold, 8; it counts image ids, which follow the names in its released scenes). Cameras stay in COLMAP's world frame (no normalisation here).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np
import OpenImageIO as oiio

from .camera import Camera
from .depth_align import fit_scale_shift
from .errors import CaptureError
from .layers import LAYERS
from .paper_layout import inverse_filmic
from .color import srgb_to_linear
from .points import colmap_model_dir
from .types import Capture, CaptureMeta, View, check_buffer

PRIOR_BUFFERS = ("render", "diffuse", "specular", "roughness", "metalness", "depth", "normal")
# capture layer -> the prior buffers it is made from
LAYER_PRIORS = {"rgb": ("render",), "diffuse": ("diffuse",), "specular": ("specular",),
                "roughness": ("roughness",), "f0": ("metalness",), "depth": ("depth",), "normal": ("normal",)}
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
# OpenCV camera axes (x right, y down, z forward) <-> OpenGL (x right, y up, z backward)
CV_TO_GL = np.diag([1.0, -1.0, -1.0])


def c2w_from_colmap(cam_from_world: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world [4, 4] from COLMAP's world-to-camera ``[R | t]`` [3, 4] (OpenCV axes)."""
    r, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    c2w = np.eye(4)
    c2w[:3, :3] = r.T @ CV_TO_GL
    c2w[:3, 3] = -r.T @ t
    return c2w


def colmap_from_c2w(c2w: np.ndarray) -> np.ndarray:
    """COLMAP world-to-camera ``[R | t]`` [3, 4] from an OpenGL camera-to-world [4, 4]."""
    r = (np.asarray(c2w)[:3, :3] @ CV_TO_GL).T
    return np.hstack([r, (-r @ np.asarray(c2w)[:3, 3])[:, None]])


def camera_from_colmap(cam, cam_from_world: np.ndarray, where: str) -> Camera:
    """Our Camera from a pycolmap camera (undistorted pinhole models only) and its ``[R | t]`` [3, 4]."""
    model = cam.model_name
    if model not in PINHOLE_MODELS:
        raise CaptureError(f"{where}: camera {cam.camera_id} has model {model}; only undistorted "
                           f"{' / '.join(PINHOLE_MODELS)} are read (undistort first: python -m stages.poses)")
    p = [float(x) for x in cam.params]
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if model == "SIMPLE_PINHOLE" else p[:4]
    camera = Camera(int(cam.width), int(cam.height), fx, fy, cx, cy, c2w_from_colmap(cam_from_world))
    camera.check(where)
    return camera


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from the file header. Raises CaptureError naming the file if unreadable."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise CaptureError(f"{path}: cannot read image ({oiio.geterror().strip() or 'unknown format'})")
    spec = inp.spec()
    inp.close()
    return spec.width, spec.height


def load_reconstruction(model_dir: str | Path):
    import pycolmap

    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises ValueError/RuntimeError carrying COLMAP's message
        raise CaptureError(f"{model_dir}: cannot read COLMAP model ({e})") from None


def read_colmap_capture(path: str | Path, layers: Iterable[str] | None = None, test_every: int = 8,
                        seed: int = 0) -> Capture:
    """Capture of a COLMAP folder (see the module docstring). ``layers``: only these (default: all present)."""
    path = Path(path)
    model_dir = colmap_model_dir(path)
    if model_dir is None:
        raise CaptureError(f"{path}: no COLMAP model (expected sparse/0/ or sparse/ holding cameras.bin or cameras.txt)")
    rec = load_reconstruction(model_dir)
    wanted = set(LAYERS if layers is None else layers)
    ids = sorted(rec.reg_image_ids(), key=lambda i: rec.images[i].name)  # name order: ids follow thread timing
    if not ids:
        raise CaptureError(f"{model_dir}: the COLMAP model has no registered images")
    views, fits = [], {}
    for k, image_id in enumerate(ids):
        image = rec.images[image_id]
        where = f"{model_dir} image {image.name!r}"
        camera = camera_from_colmap(rec.cameras[image.camera_id], image.cam_from_world().matrix(), where)
        stem = Path(image.name).stem
        priors = {b: f for b in PRIOR_BUFFERS if (f := path / "priors" / b / f"{b}_{stem}.png").is_file()}
        photo = path / "images" / image.name
        needed = {b for layer in wanted for b in LAYER_PRIORS.get(layer, ())} & set(priors)
        if "rgb" in wanted and "render" not in priors and not photo.is_file():
            raise CaptureError(f"{where}: neither the photo {photo} nor {path / 'priors/render'}/render_{stem}.png exists")
        raw = {b: _read_pixels(priors[b]) for b in sorted(needed)}
        if "rgb" in wanted and "render" not in raw:
            raw["photo"] = _read_pixels(photo)
        camera = _fit_camera(camera, raw, priors, photo, where)
        buffers = _buffers(raw, wanted)
        if "depth" in raw:
            if "depth" in wanted:
                buffers["depth"], fit = _aligned_depth(raw["depth"][0][:, :, 0], camera, image, rec, priors["depth"], seed)
                fits[stem] = fit
        if "normal" in raw:
            n = -(raw["normal"][0][:, :, :3] * 2.0 - 1.0 if raw["normal"][1] else raw["normal"][0][:, :, :3])
            n = n @ (camera.rotation @ CV_TO_GL).T  # OpenCV camera axes -> world
            norm = np.linalg.norm(n, axis=-1, keepdims=True)
            buffers["normal"] = np.where(norm > 1e-8, n / np.maximum(norm, 1e-8), 0.0).astype(np.float32)
        for layer, arr in buffers.items():
            check_buffer(where, layer, arr, camera.height, camera.width)
        split = "test" if test_every > 0 and k % test_every == 0 else "train"
        views.append(View(name=stem, camera=camera, split=split, buffers=buffers))
    names = [v.name for v in views]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise CaptureError(f"{model_dir}: images in different folders share the file stem(s) {dup}")
    meta = CaptureMeta(source="colmap", color_space="linear", units="colmap (arbitrary scale)",
                       extra={"layout": "colmap" + ("+priors" if (path / "priors").is_dir() else ""),
                              "model": str(model_dir), "test_every": test_every,
                              "depth_fits": fits})
    capture = Capture(views=views, meta=meta)
    capture.meta.extent = capture.camera_extent() if len(views) > 1 else None
    return capture


def _read_pixels(file: Path) -> tuple[np.ndarray, bool]:
    """Pixels [H, W, C] float64 (integer formats scaled to [0, 1]) and whether the file is integer."""
    inp = oiio.ImageInput.open(str(file))
    if inp is None:
        raise CaptureError(f"{file}: cannot read image ({oiio.geterror().strip() or 'unknown format'})")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        if pixels is None:
            raise CaptureError(f"{file}: cannot decode pixels ({inp.geterror().strip()})")
    finally:
        inp.close()
    integer = spec.format.basetype in (oiio.UINT8, oiio.UINT16, oiio.INT8, oiio.INT16, oiio.UINT32, oiio.INT32)
    return np.asarray(pixels, dtype=np.float64).reshape(spec.height, spec.width, spec.nchannels), integer


def _fit_camera(camera: Camera, raw: dict, priors: dict, photo: Path, where: str) -> Camera:
    """The camera rescaled to the buffers' resolution (all buffers of a view must agree)."""
    sizes = {name: (px.shape[1], px.shape[0]) for name, (px, _) in raw.items()}
    if len(set(sizes.values())) > 1:
        listed = ", ".join(f"{priors.get(n, photo).name} {w}x{h}" for n, (w, h) in sizes.items())
        raise CaptureError(f"{where}: buffers disagree in size: {listed}")
    if not sizes:
        return camera
    w, h = next(iter(sizes.values()))
    if (w, h) == (camera.width, camera.height):
        return camera
    sx, sy = w / camera.width, h / camera.height
    if abs(camera.height * sx - h) > 1.0:  # more than a pixel of rounding
        raise CaptureError(f"{where}: buffers are {w}x{h} but the COLMAP camera is {camera.width}x{camera.height} "
                           "(different aspect ratio)")
    return Camera(w, h, camera.fl_x * sx, camera.fl_y * sy, camera.cx * sx, camera.cy * sy, camera.c2w)


def _buffers(raw: dict, wanted: set) -> dict[str, np.ndarray]:
    out = {}
    for layer, src in (("rgb", "render"), ("diffuse", "diffuse"), ("specular", "specular")):
        if layer in wanted and src in raw:
            px, integer = raw[src]
            out[layer] = (inverse_filmic(px[:, :, :3]) if integer else px[:, :, :3]).astype(np.float32)
    if "rgb" in wanted and "rgb" not in out and "photo" in raw:
        px, integer = raw["photo"]
        px = np.repeat(px[:, :, :1], 3, axis=2) if px.shape[2] < 3 else px[:, :, :3]
        out["rgb"] = (srgb_to_linear(px) if integer else px).astype(np.float32)
    if "roughness" in wanted and "roughness" in raw:
        out["roughness"] = raw["roughness"][0][:, :, :1].astype(np.float32)
    if "f0" in wanted and "metalness" in raw:
        metal = raw["metalness"][0][:, :, :1]
        out["f0"] = np.repeat(0.04 * (1.0 - metal) + metal, 3, axis=2).astype(np.float32)
    return out


def _aligned_depth(rel: np.ndarray, camera: Camera, image, rec, file: Path, seed: int) -> tuple[np.ndarray, dict]:
    """Distance along the ray [H, W, 1] from relative z-depth ``rel`` [H, W] aligned to the image's SfM points."""
    ids = [p.point3D_id for p in image.get_observation_points2D()]
    xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    cam_from_world = image.cam_from_world().matrix()
    pc = xyz @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]  # OpenCV camera space
    front = pc[:, 2] > 1e-9
    pc = pc[front]
    u = camera.fl_x * pc[:, 0] / pc[:, 2] + camera.cx
    v = camera.fl_y * pc[:, 1] / pc[:, 2] + camera.cy
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    col, row = np.floor(u[inside]).astype(int), np.floor(v[inside]).astype(int)
    fit = fit_scale_shift(rel[row, col], pc[inside, 2], seed=seed, where=str(file))
    z = fit.scale * rel + fit.shift
    xs = (np.arange(camera.width) + 0.5 - camera.cx) / camera.fl_x
    ys = (np.arange(camera.height) + 0.5 - camera.cy) / camera.fl_y
    ray_len = np.sqrt(1.0 + xs[None, :] ** 2 + ys[:, None] ** 2)
    dist = np.where(z > 0, z * ray_len, 0.0)  # behind the camera: invalid (0)
    return dist[:, :, None].astype(np.float32), {"scale": fit.scale, "shift": fit.shift,
                                                 "inliers": fit.inliers, "samples": fit.samples}
