"""InteriorVerse (Zhu et al. 2022, jingsenzhu/IndoorInverseRendering) reader: one EXR per modality and view.

Layout (``interiorverse/README.md`` of the authors' repository)::

    <root>/{train,val,test}.txt          scene folder names, one per line
    <root>/<scene>/<III>_im.exr          HDR radiance
                   <III>_mask.exr        1 = valid pixel
                   <III>_albedo.exr      base colour
                   <III>_material.exr    R roughness, G metallic (GGX), B unused
                   <III>_depth.exr       millimetres, inf = invalid
                   <III>_normal.exr      camera space, OpenGL (x right, y up, z toward the eye)

``<root>`` is ``dataset_85`` or ``dataset_120``: the horizontal FOV in degrees (inferred from the folder
name, or pass ``hfov``). The depth is planar: the authors' own loader turns it into view-space points as
``depth * (x tan(fov_x/2), y tan(fov_y/2), -1)`` (``lightnet/utils`` ``depth_to_vpos``), so only the
unit changes here (mm -> m). Normals are renormalised and oriented toward the camera (other loaders report
unreliable orientations); pixels whose roughness and metallic are both exactly 0 are treated as missing
material, as the authors' loader does (``mgnet/dataLoader``).

``f0 = 0.04 (1 - metallic) + metallic * albedo``. The albedo is a reflectance, not shaded radiance, so
there is no diffuse / specular split: samples carry normal, depth, roughness and f0 only.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from models.capture.exr import read_exr_channels

from ._sample import BufferSample, DatasetError, finalize, orient_normals, pinhole_directions

SPLITS = ("train", "val", "test")
MODALITIES = ("im", "mask", "albedo", "material", "depth", "normal")


def read_exr(path: Path, channels: int) -> np.ndarray:
    """The first ``channels`` channels of an EXR (R, G, B order when present). # [H, W, C] float32"""
    if not path.is_file():
        raise DatasetError(f"{path}: missing InteriorVerse file")
    try:
        named = read_exr_channels(path)
    except ValueError as e:  # CaptureError
        raise DatasetError(str(e)) from None
    order = [c for c in ("R", "G", "B", "Y") if c in named] + [c for c in named if c not in ("R", "G", "B", "Y", "A")]
    if len(order) < channels:
        raise DatasetError(f"{path}: has channels {sorted(named)}, need {channels}")
    return np.stack([named[c] for c in order[:channels]], axis=-1).astype(np.float32)


class InteriorVerseReader:
    """Views of the scenes listed in ``<root>/<split>.txt`` as ``BufferSample`` (normal, depth, roughness,
    f0). ``hfov``: horizontal field of view in degrees (default: from a root named ``*_85`` / ``*_120``)."""

    def __init__(self, root: str | Path, split: str = "train", *, hfov: float | None = None):
        self.root = Path(root)
        if split not in SPLITS:
            raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
        list_path = self.root / f"{split}.txt"
        if not list_path.is_file():
            raise DatasetError(f"{list_path}: InteriorVerse split list not found")
        if hfov is None:
            m = re.search(r"_(\d+)$", self.root.resolve().name)
            if not m:
                raise ValueError(f"{self.root}: cannot infer the horizontal FOV from the folder name "
                                 f"(expected dataset_85 / dataset_120); pass hfov=")
            hfov = float(m.group(1))
        if not 0 < hfov < 180:
            raise ValueError(f"hfov must be in (0, 180) degrees, got {hfov}")
        self.hfov = float(hfov)
        scenes = [s.strip() for s in list_path.read_text().splitlines() if s.strip()]
        if not scenes:
            raise DatasetError(f"{list_path}: lists no scenes")
        self.views: list[tuple[str, str]] = []  # (scene, view id)
        for scene in scenes:
            folder = self.root / scene
            if not folder.is_dir():
                raise DatasetError(f"{folder}: scene listed in {list_path.name} is missing")
            ids = sorted(p.name[: -len("_im.exr")] for p in folder.glob("*_im.exr"))
            if not ids:
                raise DatasetError(f"{folder}: no <index>_im.exr views")
            self.views += [(scene, i) for i in ids]

    def __len__(self) -> int:
        return len(self.views)

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def paths(self, index: int) -> dict[str, Path]:
        scene, view = self.views[index]
        return {m: self.root / scene / f"{view}_{m}.exr" for m in MODALITIES}

    def __getitem__(self, index: int) -> BufferSample:
        if not -len(self) <= index < len(self):
            raise IndexError(f"view index {index} out of range ({len(self)} views)")
        index %= len(self)
        scene, view = self.views[index]
        paths = self.paths(index)
        data = {m: read_exr(p, 1 if m in ("mask", "depth") else 3) for m, p in paths.items()}
        h, w = data["im"].shape[:2]
        for m, arr in data.items():
            if arr.shape[:2] != (h, w):
                raise DatasetError(
                    f"{paths[m]}: {arr.shape[1]}x{arr.shape[0]}, expected {w}x{h} (as {paths['im'].name})")
        fl = 0.5 * w / math.tan(math.radians(self.hfov) / 2)
        dirs = pinhole_directions(h, w, fl, fl)
        normal, normal_ok = orient_normals(data["normal"], dirs)
        depth_mm = data["depth"][..., 0]
        rough, metal = data["material"][..., 0], data["material"][..., 1]
        albedo = data["albedo"]
        f0 = 0.04 * (1 - metal[..., None]) + metal[..., None] * albedo
        material_ok = ~((rough == 0) & (metal == 0))
        buffers = {"normal": normal, "depth": depth_mm / 1000.0, "roughness": np.clip(rough, 0, 1),
                   "f0": np.clip(f0, 0, 1)}
        masks = {
            "normal": normal_ok,
            "depth": np.isfinite(depth_mm) & (depth_mm > 0),
            "roughness": material_ok,
            "f0": material_ok & np.isfinite(albedo).all(-1),
        }
        base = data["mask"][..., 0] > 0.5
        return finalize(f"interiorverse/{self.root.name}/{scene}/{view}", data["im"], buffers, masks, base)
