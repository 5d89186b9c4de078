"""The capture format (ARCHITECTURE.md): transforms.json + one multi-channel float32 EXR per view.

A contract other tools write too: readers ignore channels they do not know and
also accept the paper's released synthetic layout (``transforms_{train,test}.json``) and COLMAP
folders (``sparse/`` + ``images/``, with the paper's real-scene ``priors/``: ``colmap_layout.py``).
nerfstudio datasets (PNG / JPEG views decoded from sRGB, split lists, ``ply_file_path``): ``nerfstudio_layout.py``.
SfM points of a capture: ``points.py``.
"""

from .camera import Camera
from .colmap_layout import read_colmap_capture
from .errors import CaptureError
from .io import read_capture, read_view_buffers, write_capture
from .layers import LAYER_CHANNELS, LAYERS
from .points import POINTS_FILE, read_sfm_points, write_points_ply
from .types import SPLITS, Capture, CaptureMeta, View

__all__ = [
    "Camera", "Capture", "CaptureError", "CaptureMeta", "LAYERS", "LAYER_CHANNELS", "SPLITS", "View",
    "POINTS_FILE", "read_capture", "read_colmap_capture", "read_sfm_points", "read_view_buffers", "write_capture",
    "write_points_ply",
]
