"""The render thread of one browser tab: its camera follows the tab's, it renders 1-spp frames of the session's
scene into its own ProgressiveView and streams them as the tab's background image (with depth, so the gizmo and
selection overlay composite)."""

from __future__ import annotations

import logging
import threading
import time

from models.capture import Camera

from .camera import camera_from_viser
from .progressive import Frame, ProgressiveView

log = logging.getLogger("stages.view")


class ClientLoop:
    """Render thread of one browser tab."""

    def __init__(self, app, client):
        self.app, self.client = app, client
        self.view: ProgressiveView = app.session.new_view(app.session.settings)
        self.wake = threading.Event()
        self.stopped = threading.Event()
        self.last_frame: Frame | None = None
        self.frames_sent = 0
        self.rendered = 0
        self.fps = 0.0
        self.first_frame_s: dict[int, float] = {}  # scene version -> seconds from the edit to its first frame
        self._last_render_t = None
        self._version = -1  # scene version of the frame being rendered
        self._failed = ""  # the last render failure shown (cleared by the next frame sent)
        client.camera.on_update(self._camera_moved)
        self.thread = threading.Thread(target=self._run, name=f"view-client-{client.client_id}", daemon=True)
        self.thread.start()

    def _camera_moved(self, _cam) -> None:
        cam, current = self.camera(), self.view.camera
        if cam is not None and current is not None and ProgressiveView._camera_key(cam) != \
                ProgressiveView._camera_key(current):
            self.view.abort()  # the frame in flight shows the old view: drop it
        self.wake.set()

    def changed(self, force: bool = False) -> None:
        """The session changed: drop the frame in flight if it renders an older scene (or ``force``: the path
        length changed), and render the new state."""
        if force or self.app.session.version != self._version:
            self.view.abort()
        self.wake.set()

    def camera(self) -> Camera | None:
        cam = self.client.camera
        try:
            return camera_from_viser(cam.position, cam.wxyz, cam.fov, cam.aspect, self.app.pixels)
        except (AssertionError, ValueError, TypeError, ZeroDivisionError):  # no camera message yet / zero-size
            return None  # canvas / a pose that is no camera (NaN, zero quaternion): nothing to render

    def _run(self) -> None:
        while not self.stopped.is_set():
            try:
                if not self._tick():
                    self.wake.wait(0.05)
                    self.wake.clear()
            except Exception as e:  # keep serving: log, show this tab, and go on with the next frame
                message = f"render failed: {type(e).__name__}: {e}"
                if message != self._failed:  # (once, not every second while it keeps failing)
                    log.exception("render loop of client %s", self.client.client_id)
                    self.app._error(message, self.client)
                self._failed = message
                self.wake.wait(1.0)
                self.wake.clear()

    def _tick(self) -> bool:
        cam = self.camera()
        if cam is None:
            return False
        self.view.set_camera(cam)
        self.view.configure(**vars(self.app.session.settings))
        g, version, changed_at = self.app.session.snapshot()
        self._version = version
        frame = self.view.step(g, version)
        if frame is None or self.stopped.is_set():
            return False
        self.client.scene.set_background_image(frame.rgb, format=self.app.image_format,
                                               jpeg_quality=self.app.jpeg_quality, depth=frame.depth)
        now = time.perf_counter()
        if version not in self.first_frame_s:
            self.first_frame_s[version] = now - changed_at
            for old in sorted(self.first_frame_s)[:-64]:
                del self.first_frame_s[old]
        if frame.render_s > 0:
            self.rendered += 1
            if self._last_render_t is not None and frame.spp > 1:
                dt = now - self._last_render_t
                self.fps = 1.0 / dt if self.fps == 0 else 0.7 * self.fps + 0.3 / dt
            self._last_render_t = now
        self.last_frame = frame
        self.frames_sent += 1
        self._failed = ""
        self.app._frame_shown(self)
        return True

    def stop(self) -> None:
        self.stopped.set()
        self.view.abort()
        self.wake.set()
        self.thread.join(timeout=10)

    def status(self) -> str:
        """The status line of the last frame sent: samples, denoising, fps, size, time to the first frame after
        the last change, Gaussians."""
        f, st = self.last_frame, self.app.session.settings
        ff = self.first_frame_s.get(f.version)
        spp = f"{f.spp}/{st.max_spp} spp" if st.max_path_length > 1 else "primary only"
        return (f"{spp}{' · denoised' if f.denoised else ''} · {self.fps:.1f} fps · {f.camera.width}x{f.camera.height}"
                f"\n\nfirst frame after the last change: {ff:.2f} s · {len(self.app.session.scene()[0]):,} Gaussians")
