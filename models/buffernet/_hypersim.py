"""Hypersim (Roberts et al. 2021, apple/ml-hypersim) reader: HDF5 images, key ``"dataset"``.

Layout (the dataset README)::

    <root>/<scene>/images/scene_<cam>_final_hdf5/frame.IIII.{color,diffuse_illumination,
                                                               diffuse_reflectance,residual}.hdf5
    <root>/<scene>/images/scene_<cam>_geometry_hdf5/frame.IIII.{depth_meters,normal_cam,
                                                                  normal_bump_cam,render_entity_id}.hdf5

Facts used (README and maintainers' answers in the ml-hypersim issues):

* ``color == diffuse_reflectance * diffuse_illumination + residual``: ``diffuse`` is the product,
  ``specular`` is the non-diffuse ``residual`` (view-dependent effects: specular reflections, but also
  light sources seen directly and transmission; render noise can make it slightly negative).
* ``depth_meters`` is the Euclidean distance to the optical centre, not planar depth (issue #9).
* Camera space is x right, y up, z away from the viewing direction (OpenGL); ``normal_cam`` /
  ``normal_bump_cam`` are in it, but may be zero, non-unit or point inward (issue #26): renormalised,
  oriented toward the camera, zero normals masked.
* Intrinsics: 60 degrees horizontal FOV (focal 886.81 px at 1024x768, scaled with the resolution). A few
  scenes use tilt-shift lenses; pass the contributed ``metadata_camera_parameters.csv``
  (``M_cam_from_uv_*`` columns: camera-space ray = M @ [u, v, 1] with u, v in [-1, 1] at pixel centres,
  v up) to use each scene's exact rays.
* ``render_entity_id == -1``: no geometry (background); such pixels are invalid for every buffer.

No roughness or F0 (absent from ``buffers``).
"""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import numpy as np

from ._sample import BufferSample, DatasetError, distance_to_planar, finalize, orient_normals

FINAL = ("color", "diffuse_illumination", "diffuse_reflectance", "residual")
NORMAL_FILES = ("normal_bump_cam", "normal_cam")
_FRAME = re.compile(r"^frame\.(\d+)\.color\.hdf5$")
# Default M_cam_from_uv: 60 degree horizontal FOV, 4:3 image (tan 30 deg, tan 30 deg * 3/4, -1).
DEFAULT_M_CAM_FROM_UV = np.diag([math.tan(math.radians(30)), math.tan(math.radians(30)) * 0.75, -1.0])


def read_hdf5(path: Path) -> np.ndarray:
    """The ``"dataset"`` array of a Hypersim HDF5 file, as float32 (ids as int64)."""
    import h5py

    if not path.is_file():
        raise DatasetError(f"{path}: missing Hypersim file")
    try:
        with h5py.File(path, "r") as f:
            if "dataset" not in f:
                raise DatasetError(f"{path}: no 'dataset' key (keys: {', '.join(f.keys()) or 'none'})")
            arr = f["dataset"][()]
    except OSError as e:
        raise DatasetError(f"{path}: cannot read HDF5 ({e})") from None
    return arr.astype(np.int64 if np.issubdtype(arr.dtype, np.integer) else np.float32)


def hypersim_directions(height: int, width: int, m_cam_from_uv: np.ndarray = DEFAULT_M_CAM_FROM_UV) -> np.ndarray:
    """Camera-space (OpenGL) ray directions through pixel centres, from Hypersim's M_cam_from_uv. # [H, W, 3]"""
    u = np.linspace(-1 + 1 / width, 1 - 1 / width, width)
    v = np.linspace(1 - 1 / height, -1 + 1 / height, height)  # row 0 is the top: v = +1
    uu, vv = np.meshgrid(u, v)
    uv1 = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
    return uv1 @ np.asarray(m_cam_from_uv, dtype=np.float64).T


def read_camera_parameters(csv_path: str | Path) -> dict[str, np.ndarray]:
    """scene name -> M_cam_from_uv [3, 3] from ml-hypersim's ``metadata_camera_parameters.csv``."""
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        raise DatasetError(f"{csv_path}: camera parameters CSV not found")
    out = {}
    with csv_path.open(newline="") as f:
        for row in csv.DictReader(f):
            try:
                m = [[float(row[f"M_cam_from_uv_{i}{j}"]) for j in range(3)] for i in range(3)]
            except (KeyError, ValueError) as e:
                raise DatasetError(
                    f"{csv_path}: row {row.get('scene_name')!r} lacks a valid M_cam_from_uv ({e})") from None
            out[row["scene_name"]] = np.asarray(m)
    return out


class HypersimReader:
    """Frames of Hypersim scenes as ``BufferSample`` (diffuse, specular, normal, depth).

    ``scenes``: scene names (``ai_VVV_NNN``) under ``root``; default every folder with an ``images/``.
    ``normal_file``: ``"normal_bump_cam"`` (with bump mapping, default) or ``"normal_cam"``.
    ``camera_parameters``: optional path of ``metadata_camera_parameters.csv`` for per-scene rays.
    """

    def __init__(self, root: str | Path, scenes: list[str] | None = None, *, normal_file: str = "normal_bump_cam",
                 camera_parameters: str | Path | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: Hypersim root folder not found")
        if normal_file not in NORMAL_FILES:
            raise ValueError(f"normal_file must be one of {', '.join(NORMAL_FILES)}, got {normal_file!r}")
        self.normal_file = normal_file
        self.m_cam_from_uv = read_camera_parameters(camera_parameters) if camera_parameters else {}
        if scenes is None:
            scenes = sorted(p.name for p in self.root.iterdir() if (p / "images").is_dir())
            if not scenes:
                raise DatasetError(f"{self.root}: no Hypersim scene folders (<scene>/images/) found")
        self.frames: list[tuple[str, str, str]] = []  # (scene, cam, frame id)
        for scene in scenes:
            images = self.root / scene / "images"
            if not images.is_dir():
                raise DatasetError(f"{images}: missing (scene {scene!r} not in the Hypersim layout)")
            found = []
            for final in sorted(images.glob("scene_*_final_hdf5")):
                cam = final.name[len("scene_"):-len("_final_hdf5")]
                for f in sorted(final.iterdir()):
                    m = _FRAME.match(f.name)
                    if m:
                        found.append((scene, cam, m.group(1)))
            if not found:
                raise DatasetError(f"{images}: no scene_<cam>_final_hdf5/frame.IIII.color.hdf5 files")
            self.frames += found

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def paths(self, index: int) -> dict[str, Path]:
        """Every file of frame ``index``, keyed by modality."""
        scene, cam, frame = self.frames[index]
        images = self.root / scene / "images"
        final, geometry = images / f"scene_{cam}_final_hdf5", images / f"scene_{cam}_geometry_hdf5"
        out = {k: final / f"frame.{frame}.{k}.hdf5" for k in FINAL}
        for k in ("depth_meters", self.normal_file, "render_entity_id"):
            out[k] = geometry / f"frame.{frame}.{k}.hdf5"
        return out

    def __getitem__(self, index: int) -> BufferSample:
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame index {index} out of range ({len(self)} frames)")
        index %= len(self)
        scene, cam, frame = self.frames[index]
        paths = self.paths(index)
        data = {k: read_hdf5(p) for k, p in paths.items()}
        rgb = data["color"]
        h, w = rgb.shape[:2]
        for k, arr in data.items():
            want = (h, w) if k in ("depth_meters", "render_entity_id") else (h, w, 3)
            if arr.shape != want:
                raise DatasetError(f"{paths[k]}: shape {arr.shape}, expected {want} (as {paths['color'].name})")
        dirs = hypersim_directions(h, w, self.m_cam_from_uv.get(scene, DEFAULT_M_CAM_FROM_UV))
        normal, normal_ok = orient_normals(data[self.normal_file], dirs)
        distance = data["depth_meters"]
        depth = distance_to_planar(np.where(np.isfinite(distance), distance, 0.0), dirs)
        buffers = {
            "diffuse": data["diffuse_reflectance"] * data["diffuse_illumination"],
            "specular": data["residual"],
            "normal": normal,
            "depth": depth,
        }
        masks = {
            "diffuse": np.ones((h, w), bool),
            "specular": np.ones((h, w), bool),
            "normal": normal_ok,
            "depth": np.isfinite(distance) & (depth > 0),
        }
        base = data["render_entity_id"] != -1
        return finalize(f"hypersim/{scene}/{cam}/frame.{frame}", rgb, buffers, masks, base)
