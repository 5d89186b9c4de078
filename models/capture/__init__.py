"""The capture format (ARCHITECTURE.md): transforms.json + one multi-channel float32 EXR per view.

A contract other tools write too: readers ignore channels they do not know and
also accept the paper's released synthetic layout (``transforms_{train,test}.json``).
"""

from .camera import Camera
from .errors import CaptureError
from .io import read_capture, read_view_buffers, write_capture
from .layers import LAYER_CHANNELS, LAYERS
from .types import SPLITS, Capture, CaptureMeta, View

__all__ = [
    "Camera", "Capture", "CaptureError", "CaptureMeta", "LAYERS", "LAYER_CHANNELS", "SPLITS", "View",
    "read_capture", "read_view_buffers", "write_capture",
]
