"""Reader of the project's own capture format (``models/capture``) for buffer-network training.

The capture stores world-space normals and distance-along-the-ray depth (ARCHITECTURE.md, "The capture
format"); samples carry camera-space normals (OpenGL, toward the camera) and planar z-depth. Lights seen
directly (the ``emission`` layer) are added to ``diffuse`` by default, so that ``rgb ~= diffuse + specular``
as for a photo, where a lamp's radiance has to come out of some buffer (the diffuse layer is the Gaussians'
radiance). ``mask`` (the fraction of a pixel's samples that hit geometry) > ``mask_threshold`` is valid.

Native captures (``transforms.json``) are read one view at a time; other layouts that ``read_capture``
accepts (the paper's synthetic data, COLMAP folders) are read whole at construction.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from models.capture import Camera, CaptureError, read_capture, read_view_buffers
from models.capture.io import _camera, _resolve_image
from models.capture.nerfstudio_layout import list_splits
from models.capture.layers import REGISTRY
from models.capture.types import SPLITS

from ._sample import BufferSample, DatasetError, distance_to_planar, finalize, orient_normals

LAYERS = tuple(REGISTRY)  # every capture layer (models/capture/layers.py)


def view_sample(name: str, camera: Camera, layers: dict[str, np.ndarray], *, mask_threshold: float = 0.5,
                emission_in_diffuse: bool = True) -> BufferSample:
    """A capture view's buffers (``layer -> [H, W, C]``, capture conventions) as a ``BufferSample``."""
    if "rgb" not in layers:
        raise DatasetError(f"{name}: the view has no R,G,B channels")
    h, w = camera.height, camera.width
    dirs = camera.camera_directions()  # [H, W, 3], z = -1
    base = layers["mask"][..., 0] > mask_threshold if "mask" in layers else np.ones((h, w), bool)
    buffers, masks = {}, {}
    if "diffuse" in layers:
        diffuse = layers["diffuse"]
        if emission_in_diffuse and "emission" in layers:
            diffuse = diffuse + layers["emission"]
        buffers["diffuse"], masks["diffuse"] = diffuse, np.ones((h, w), bool)
    if "specular" in layers:
        buffers["specular"], masks["specular"] = layers["specular"], np.ones((h, w), bool)
    if "normal" in layers:
        world = layers["normal"].astype(np.float64)
        cam = world @ camera.rotation  # R^T n per pixel: world -> camera
        buffers["normal"], masks["normal"] = orient_normals(cam, dirs)
    if "depth" in layers:
        distance = layers["depth"][..., 0].astype(np.float64)
        buffers["depth"] = distance_to_planar(distance, dirs)
        masks["depth"] = distance > 0
    if "roughness" in layers:
        buffers["roughness"] = np.clip(layers["roughness"][..., 0], 0, 1)
        masks["roughness"] = np.ones((h, w), bool)
    if "f0" in layers:
        buffers["f0"], masks["f0"] = np.clip(layers["f0"], 0, 1), np.ones((h, w), bool)
    return finalize(name, layers["rgb"], buffers, masks, base)


class CaptureReader:
    """Views of a capture folder (optionally one ``split``) as ``BufferSample``."""

    def __init__(self, capture_dir: str | Path, split: str | None = None, *, mask_threshold: float = 0.5,
                 emission_in_diffuse: bool = True):
        self.root = Path(capture_dir)
        if split is not None and split not in SPLITS:
            raise ValueError(f"split must be None or one of {', '.join(SPLITS)}, got {split!r}")
        self.mask_threshold = mask_threshold
        self.emission_in_diffuse = emission_in_diffuse
        # entries: (view name, camera, image path or None, in-memory layers or None)
        self._views: list[tuple[str, Camera, Path | None, dict | None]] = []
        tf_path = self.root / "transforms.json"
        try:
            if tf_path.is_file():
                self._index_native(tf_path, split)
            else:
                capture = read_capture(self.root, layers=list(LAYERS))
                views = capture.views if split is None else capture.split(split)
                self._views = [(v.name, v.camera, None, v.buffers) for v in views]
        except CaptureError as e:
            raise DatasetError(str(e)) from None
        if not self._views:
            raise DatasetError(f"{self.root}: capture has no views" + (f" in split {split!r}" if split else ""))
        label = self.root.name if self.root.name != "capture" else f"{self.root.parent.name}/capture"
        self.label = f"capture/{label}"

    def _index_native(self, tf_path: Path, split: str | None) -> None:
        try:
            tf = json.loads(tf_path.read_text())
        except json.JSONDecodeError as e:
            raise DatasetError(f"{tf_path}: invalid JSON ({e})") from None
        frames = tf.get("frames")
        if not isinstance(frames, list) or not frames:
            raise DatasetError(f"{tf_path}: 'frames' must be a non-empty list")
        listed = list_splits(tf, tf_path)  # nerfstudio's *_filenames lists; None: listed nowhere, left out
        for i, frame in enumerate(frames):
            where = f"{tf_path} frame {i}"
            if "file_path" not in frame or "transform_matrix" not in frame:
                raise DatasetError(f"{where}: needs 'file_path' and 'transform_matrix'")
            view_split = frame.get("split", "train") if listed is None else listed[i]
            if view_split is None or (split is not None and view_split != split):
                continue
            camera = _camera(tf, frame, where)
            camera.check(where)
            image = _resolve_image(self.root, frame["file_path"], where)
            self._views.append((Path(frame["file_path"]).stem, camera, image, None))

    def __len__(self) -> int:
        return len(self._views)

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def __getitem__(self, index: int) -> BufferSample:
        if not -len(self) <= index < len(self):
            raise IndexError(f"view index {index} out of range ({len(self)} views)")
        name, camera, image, layers = self._views[index]
        if layers is None:
            try:
                layers = read_view_buffers(image, camera.height, camera.width, LAYERS)
            except CaptureError as e:
                raise DatasetError(str(e)) from None
        return view_sample(f"{self.label}/{name}", camera, layers, mask_threshold=self.mask_threshold,
                           emission_in_diffuse=self.emission_in_diffuse)
