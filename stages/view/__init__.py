"""``view`` stage: edit a trained scene in the browser (viser), rendered by our path tracer.

``session.py`` the edit state (scene, edit spec being built, selection; no viser), ``progressive.py`` 1-spp
accumulation + denoising of one camera, ``camera.py`` browser camera <-> our Camera, ``app.py`` the viser GUI
and one render thread per browser tab, ``benchmark.py`` FPS and time to first frame after an edit.
"""

from .camera import camera_from_viser, resize_camera, viewport_size, viser_from_camera
from .progressive import SHOWN_LAYERS, Frame, ProgressiveView, ViewSettings
from .session import ViewerSession, gizmo_ops, named_selections

__all__ = ["Frame", "ProgressiveView", "SHOWN_LAYERS", "ViewSettings", "ViewerSession", "camera_from_viser",
           "gizmo_ops", "named_selections", "resize_camera", "viewport_size", "viser_from_camera"]
