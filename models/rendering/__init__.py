"""Rendering a trained model: N spp reflection paths + Open Image Denoise, every layer as EXR + PNG.

``render.py`` the render settings and one view's layers, ``images.py`` a rendered view on disk,
``camera_path.py`` a novel camera path, ``denoise.py`` Open Image Denoise, ``fps.py`` render speed.
"""

from .camera_path import camera_path
from .denoise import denoise
from .fps import measure_fps
from .images import to_png, write_layers
from .render import RenderConfig, render_view, render_views

__all__ = ["RenderConfig", "camera_path", "denoise", "measure_fps", "render_view", "render_views", "to_png",
           "write_layers"]
