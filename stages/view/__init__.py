"""``view`` stage: edit a trained scene in the browser (viser), rendered by our path tracer.

``session.py`` the edit state (scene, edit spec being built, selection; no viser), ``progressive.py`` 1-spp
accumulation + denoising of one camera, ``camera.py`` browser camera <-> our Camera, ``app.py`` the viser GUI
and one render thread per browser tab (``client.py``), ``controls.py`` what each GUI control accepts (every value a
browser sends is checked there first), ``benchmark.py`` FPS and time to first frame after an edit.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from models.lazy import lazy_getattr

# name -> submodule, imported on first use (PEP 562): `python -m stages.view --help` answers without torch / Warp
_EXPORTS = {"camera_from_viser": "camera", "resize_camera": "camera", "viewport_size": "camera",
            "viser_from_camera": "camera", "SHOWN_LAYERS": "progressive", "Frame": "progressive",
            "ProgressiveView": "progressive", "ViewSettings": "progressive", "ViewerSession": "session",
            "gizmo_ops": "session", "named_selections": "session"}
__all__ = sorted(_EXPORTS)

if TYPE_CHECKING:
    from .camera import camera_from_viser, resize_camera, viewport_size, viser_from_camera
    from .progressive import SHOWN_LAYERS, Frame, ProgressiveView, ViewSettings
    from .session import ViewerSession, gizmo_ops, named_selections


__getattr__ = lazy_getattr(__name__, _EXPORTS, globals())
