"""The ``poses`` stage: photos -> COLMAP model -> a capture in our format (normalised), with SfM points.

Output (``--out``, written atomically)::

    <capture>/transforms.json, images/*.exr, capture.yaml   the capture format (ARCHITECTURE.md); rgb is the
                                                            photos sRGB-decoded to linear (+ the real-scene
                                                            priors' buffers when the input folder has priors/)
    <capture>/points3D.ply                                  SfM points, capture frame, 8-bit sRGB colours
    <capture>/sparse/                                       the undistorted COLMAP model, capture frame

``capture.yaml`` records the normalisation (centre, scale), the chosen model, registered / dropped photos
and step timings. An input folder that already has a COLMAP model beside ``images/`` (the paper's
released real scenes) skips SfM: its model is read, normalised and written the same way.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path

import numpy as np

from models.capture import Capture, read_colmap_capture, write_capture, write_points_ply
from models.capture.colmap_layout import load_reconstruction
from models.capture.points import colmap_model_dir

from .config import PosesConfig
from .normalise import normalisation_of, normalise_capture
from .photos import check_photos, has_poses, photos_dir
from .sfm import run_sfm

log = logging.getLogger("models.poses")


def run_poses(images: str | Path, work: str | Path, out: str | Path, config: PosesConfig = PosesConfig(),
              threads: int = 2, progress: bool = True) -> Capture:
    """Pose the photos in ``images`` (or read the COLMAP model already there) and write the capture to ``out``.
    ``work`` keeps COLMAP's database and models. Returns the (normalised) capture."""
    images, work, out = Path(images), Path(work), Path(out)
    t0 = time.perf_counter()
    if has_poses(images):
        source = images
        info: dict = {"sfm": f"skipped: {colmap_model_dir(images)} already holds a COLMAP model"}
        log.info("poses: %s", info["sfm"])
    else:
        names, (w, h) = check_photos(images, config.min_images)
        log.info("poses: %d photos of %dx%d in %s", len(names), w, h, photos_dir(images))
        result = run_sfm(photos_dir(images), names, work, config, threads=threads, progress=progress)
        source = result.undistorted
        info = {"sfm": "pycolmap incremental mapping", "photos": len(names), "photo_size": [w, h],
                "matcher": config.matcher, "camera_model": config.camera_model, "models": result.model_sizes,
                "model_index": result.model_index, "verified_pairs": result.verified_pairs,
                "registered": len(result.registered), "unregistered": result.unregistered,
                "seconds": result.seconds, "work": str(work)}

    log.info("poses: reading %s", source)
    capture = read_colmap_capture(source, test_every=config.test_every, seed=config.seed)
    rec = load_reconstruction(colmap_model_dir(source))
    if config.normalise:
        import pycolmap

        norm = normalisation_of(capture, config.target_radius)
        normalise_capture(capture, norm)
        rec.transform(pycolmap.Sim3d(norm.scale, pycolmap.Rotation3d(), -norm.scale * norm.centre))
        log.info("poses: normalised, centre %s, scale %.6g", np.round(norm.centre, 4).tolist(), norm.scale)
    capture.meta.units = "normalised" if config.normalise else "colmap (arbitrary scale)"
    capture.meta.extra.update({"input": str(images), "poses": info, "model": "sparse/ (this folder)",
                               "rgb": "photos: 8-bit sRGB decoded to linear (not HDR)"})
    info["seconds_total"] = round(time.perf_counter() - t0, 3)
    _write(capture, rec, out)
    log.info("poses: wrote %d views (%d train, %d test) and %d SfM points to %s", len(capture.views),
             len(capture.split("train")), len(capture.split("test")), rec.num_points3D(), out)
    return capture


def _write(capture: Capture, rec, out: Path) -> None:
    """Capture + points3D.ply + sparse/ into a build folder, then renamed into place."""
    build = out.with_name(f".{out.name}.build{os.getpid()}")
    if build.exists():
        shutil.rmtree(build)
    write_capture(capture, build)
    (build / "sparse").mkdir()
    rec.write(str(build / "sparse"))
    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    write_points_ply(build / "points3D.ply", xyz, rgb)
    if out.exists():
        old = out.with_name(f".{out.name}.old{os.getpid()}")
        os.replace(out, old)
        os.replace(build, out)
        shutil.rmtree(old)
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        os.replace(build, out)
