"""The browser viewer: viser GUI + one render thread per connected browser, over a ViewerSession.

Each browser tab gets its own ProgressiveView (its camera follows the tab's camera; accumulation restarts
when camera, scene or path length change) and a thread that renders 1-spp frames into it and streams
them as the scene's background image (JPEG, with depth so the gizmo and selection overlay composite).
Every GUI control calls a ViewerSession method; scripts and tests call the same methods through
``ViewerApp`` (``select``, ``apply``, ``apply_named_edit``, ``save``...) while the server runs.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from pathlib import Path

import numpy as np

from models.capture import Camera
from models.capture.color import linear_to_srgb, srgb_to_linear
from models.editing import EditSpecError

from .camera import box_from_pixels, viser_from_camera
from .client import ClientLoop
from .progressive import SHOWN_LAYERS, Frame
from .session import ViewerSession, gizmo_ops

BOX = "(box)"  # the selection dropdown's entry for a drawn box (parenthesised: never a selection's name)
NONE = "(none)"


def gui_to_linear(rgb) -> list[float]:
    """GUI colour (0..255 sRGB) -> linear [0, 1] (diffuse and F0 are stored linear)."""
    return srgb_to_linear(np.asarray(rgb, dtype=np.float64) / 255.0).round(4).tolist()


class ViewerApp:
    """viser server + GUI over a ViewerSession. ``pixels``: render pixel count (the image follows the
    canvas aspect). ``initial_camera``: where new browser tabs start (e.g. a capture view)."""

    def __init__(self, session: ViewerSession, host: str = "127.0.0.1", port: int = 8080, pixels: int = 160 * 120,
                 initial_camera: Camera | None = None, save_dir: Path | None = None, image_format: str = "jpeg",
                 jpeg_quality: int = 90, up: str = "+y", overlays: bool = True):
        import viser

        self.session = session
        self.pixels = int(pixels)
        self.image_format = image_format
        self.overlays = overlays  # False: no gizmo / selection points / box drawn over the image (screenshots)
        self.jpeg_quality = jpeg_quality
        self.save_dir = Path(save_dir) if save_dir is not None else Path.cwd()
        self._loops: dict[int, ClientLoop] = {}
        self._loops_lock = threading.Lock()
        self._frame_cv = threading.Condition()
        self._syncing = False  # GUI values being set from here (their callbacks must not edit)
        with contextlib.redirect_stdout(sys.stderr):  # viser's banner: stdout stays for the caller's URL line
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction(up)
        self.server.scene.world_axes.visible = False
        means = session.original.means.detach().float().cpu().numpy()
        lo, hi = np.percentile(means, 2, axis=0), np.percentile(means, 98, axis=0)
        self.extent = float(np.linalg.norm(hi - lo)) or 1.0
        if initial_camera is not None:
            v = viser_from_camera(initial_camera, look_distance=0.3 * self.extent)
            ic = self.server.initial_camera
            ic.position, ic.look_at, ic.up, ic.fov = v["position"], v["look_at"], v["up_direction"], v["fov"]
        self._pivot = np.zeros(3)
        self._build_gui()
        session.on_change(self._session_changed)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._refresh()

    # ------------------------------------------------------------------ server
    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def _connect(self, client) -> None:
        loop = ClientLoop(self, client)
        with self._loops_lock:
            self._loops[client.client_id] = loop

    def _disconnect(self, client) -> None:
        with self._loops_lock:
            loop = self._loops.pop(client.client_id, None)
        if loop is not None:
            loop.stop()

    def stop(self) -> None:
        with self._loops_lock:
            loops = list(self._loops.values())
            self._loops.clear()
        for loop in loops:
            loop.stop()
        self.server.stop()

    def clients(self) -> list[ClientLoop]:
        with self._loops_lock:
            return list(self._loops.values())

    def _frame_shown(self, loop: ClientLoop) -> None:
        with self._frame_cv:
            self._frame_cv.notify_all()
        self._update_status(loop)

    def wait_for_frame(self, version: int | None = None, min_spp: int = 0, timeout: float = 60.0) -> Frame:
        """Block until a browser tab was sent a frame of scene ``version`` (default: the current one) with at
        least ``min_spp`` samples (or its accumulation finished); return it."""
        deadline = time.monotonic() + timeout
        with self._frame_cv:
            while True:
                want = self.session.version if version is None else version
                for loop in self.clients():
                    f = loop.last_frame
                    if f is not None and f.version == want and (f.spp >= min_spp or not loop.view.needs_frame()):
                        return f
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no frame of scene version {want} (spp >= {min_spp}) within {timeout} s")
                self._frame_cv.wait(min(left, 0.2))

    # ------------------------------------------------------------------ API (also what the GUI calls)
    def select(self, name: str) -> int:
        return self.session.select(name)

    def select_box(self, lo, hi) -> int:
        return self.session.select_box(lo, hi)

    def apply(self, op: dict, coalesce: bool = False) -> list[dict]:
        return self.session.apply(op, coalesce=coalesce)

    def apply_named_edit(self, name: str) -> list[dict]:
        return self.session.apply_named_edit(name)

    def preview_transform(self, position, wxyz) -> list[dict]:
        """What dragging the gizmo does: it started at the selection centre with the identity rotation; preview
        the ops taking it to ``position`` / ``wxyz`` (not committed: Apply transform / commit_pending)."""
        ops = gizmo_ops(self._pivot, position, wxyz)
        self.session.set_pending(ops)
        return ops

    def box_from_rect(self, client_id: int, screen_min, screen_max) -> int:
        """What a shift + drag on the image does: select the world box around what that tab's image shows in
        the rectangle (corners as fractions of the canvas, top-left origin). Returns the Gaussians caught."""
        loop = self._loops.get(client_id)
        if loop is None or loop.view.frames == 0:
            raise ValueError("no frame shown in that browser tab yet")
        layers = loop.view.layers()
        hit = (1.0 - layers["transmittance"][..., 0]) > 0.5
        box = box_from_pixels(loop.view.camera, layers["depth"][..., 0], hit, (*screen_min, *screen_max))
        if box is None:
            raise ValueError("the rectangle shows no surface")
        lo, hi = box
        self._set_gui(self.g_select, BOX)
        for h in (self.g_box_centre, self.g_box_size, self.g_box_hint):
            h.visible = True
        self._set_gui(self.g_box_centre, tuple(float(v) for v in (lo + hi) / 2))
        self._set_gui(self.g_box_size, tuple(float(v) for v in hi - lo))
        return self._select_box_from_gui()

    def save(self, path: Path | None = None) -> Path:
        """Write the edit spec YAML (default: <save_dir>/<edit name>.yaml) with the first tab's camera and
        accumulation for the record."""
        path = Path(path) if path is not None else self.save_dir / f"{self.session.name}.yaml"
        loops = self.clients()
        view = loops[0].view.record() if loops and loops[0].last_frame is not None else None
        return self.session.save_spec(path, view)

    # ------------------------------------------------------------------ GUI
    def _build_gui(self) -> None:
        gui, s = self.server.gui, self.session
        gui.configure_theme(control_width="medium", show_share_button=False)
        with gui.add_folder("Selection"):
            names = [n for n in s.selections if n not in (BOX, NONE)] + [BOX]
            self.g_select = gui.add_dropdown("Selection", [NONE] + names, initial_value=NONE,
                                             hint="named selections of the scene config's edits:, or a box")
            self.g_box_centre = gui.add_vector3("Box centre", (0.0, 0.0, 0.0), step=0.01, visible=False)
            self.g_box_size = gui.add_vector3("Box size", (0.2 * self.extent,) * 3, min=(1e-3,) * 3, step=0.01,
                                              visible=False)
            self.g_box_hint = gui.add_markdown("Shift + drag on the image draws the box around what it shows.",
                                               visible=False)
            self.g_show_sel = gui.add_checkbox("Show selection", True, hint="selected Gaussian centres as points")
            self.g_sel_info = gui.add_markdown("Nothing selected.")
        with gui.add_folder("Transform"):
            gui.add_markdown("Drag the gizmo (move / rotate) to preview; Apply commits it.")
            self.g_apply_tf = gui.add_button("Apply transform", disabled=True)
            self.g_cancel_tf = gui.add_button("Cancel transform", disabled=True)
            self.g_dup_offset = gui.add_vector3("Duplicate offset", (round(0.1 * self.extent, 2), 0.0, 0.0), step=0.01)
            self.g_dup = gui.add_button("Duplicate")
            self.g_delete = gui.add_button("Delete", color="red")
        with gui.add_folder("Material"):
            self.g_rough = gui.add_slider("Roughness", 0.0, 1.0, 0.01, 0.5)
            self.g_f0 = gui.add_slider("F0", 0.0, 1.0, 0.01, 0.04, hint="base reflectance (times the F0 tint)")
            self.g_f0_tint = gui.add_rgb("F0 tint", (255, 255, 255))
            self.g_diffuse = gui.add_rgb("Diffuse colour", (128, 128, 128), hint="sRGB picker, stored linear")
        with gui.add_folder("Edit"):
            self.g_ops = gui.add_markdown("No edit yet.")
            self.g_undo = gui.add_button("Undo")
            self.g_reset = gui.add_button("Reset")
            named = list(s.named_edits)
            self.g_named = gui.add_dropdown("Named edit", named or ["(none)"], disabled=not named)
            self.g_named_apply = gui.add_button("Apply named edit", disabled=not named)
            self.g_name = gui.add_text("Edit name", s.name)
            self.g_save = gui.add_button("Save edit spec", hint=f"writes {self.save_dir}/<name>.yaml and downloads it")
            self.g_error = gui.add_markdown("")
        with gui.add_folder("Render"):
            st = s.settings
            self.g_layer = gui.add_dropdown("Layer", list(SHOWN_LAYERS), initial_value=st.layer)
            self.g_path = gui.add_slider("Max path length", 1, 6, 1, st.max_path_length)
            self.g_max_spp = gui.add_number("Max spp", st.max_spp, min=1, max=4096, step=1)
            self.g_denoise = gui.add_checkbox("Denoise", st.denoise_after > 0,
                                              hint=f"Open Image Denoise from {max(st.denoise_after, 1)} spp on")
            self.g_status = gui.add_markdown("Waiting for a browser.")
        self.gizmo = self.server.scene.add_transform_controls("/edit/gizmo", scale=0.08 * self.extent,
                                                              depth_test=False, visible=False)
        self.box_node = None
        self.sel_points = None
        self._wire()

    def _guard(self, fn):
        """A GUI callback: ignore programmatic value changes (no client), show edit errors in the panel."""
        def cb(event):
            if getattr(event, "client", None) is None or self._syncing:
                return
            try:
                self.g_error.content = ""
                fn(event)
            except (EditSpecError, ValueError) as e:
                self._error(str(e))
        return cb

    def _error(self, message: str) -> None:
        self.g_error.content = f"**Error:** {message}"

    def _wire(self) -> None:
        s = self.session

        @self.g_select.on_update
        @self._guard
        def _(_e):
            name = self.g_select.value
            box = name == BOX
            for h in (self.g_box_centre, self.g_box_size, self.g_box_hint):
                h.visible = box
            if box:
                self._select_box_from_gui()
            elif name in s.selections:
                s.select(name)

        for h in (self.g_box_centre, self.g_box_size):
            h.on_update(self._guard(lambda _e: self._select_box_from_gui()))

        @self.server.scene.on_rect_select(modifier="shift")
        def _(event):
            try:
                self.box_from_rect(event.client_id, event.screen_min, event.screen_max)
            except (EditSpecError, ValueError) as e:
                self._error(str(e))

        self.g_show_sel.on_update(lambda _e: self._refresh())

        @self.gizmo.on_update
        def _(event):
            if event.client is None or self._syncing or s.selection is None:
                return
            try:
                self.preview_transform(self.gizmo.position, self.gizmo.wxyz)
            except (EditSpecError, ValueError) as e:
                self._error(str(e))

        self.g_apply_tf.on_click(self._guard(lambda _e: s.commit_pending()))
        self.g_cancel_tf.on_click(self._guard(lambda _e: s.clear_pending()))
        self.g_dup.on_click(self._guard(
            lambda _e: s.apply({"op": "duplicate", "offset": list(self.g_dup_offset.value)})))
        self.g_delete.on_click(self._guard(lambda _e: s.apply({"op": "delete"})))
        self.g_rough.on_update(self._guard(
            lambda _e: s.apply({"op": "set_roughness", "value": round(float(self.g_rough.value), 4)}, coalesce=True)))

        def set_f0(_e):
            tint = np.asarray(gui_to_linear(self.g_f0_tint.value))
            s.apply({"op": "set_f0", "value": (np.clip(tint * float(self.g_f0.value), 0, 1)).round(4).tolist()},
                    coalesce=True)

        self.g_f0.on_update(self._guard(set_f0))
        self.g_f0_tint.on_update(self._guard(set_f0))
        self.g_diffuse.on_update(self._guard(
            lambda _e: s.apply({"op": "set_diffuse", "value": gui_to_linear(self.g_diffuse.value)}, coalesce=True)))
        self.g_undo.on_click(self._guard(lambda _e: s.undo()))
        self.g_reset.on_click(self._guard(lambda _e: s.reset()))
        self.g_named_apply.on_click(self._guard(lambda _e: s.apply_named_edit(self.g_named.value)))

        @self.g_save.on_click
        @self._guard
        def _(event):
            name = self.g_name.value.strip()
            if name != s.name:
                from models.editing import parse_edit
                parse_edit(name, {"ops": [{"op": "delete", "select": {"all": True}}]})  # valid name?
                s.name = name
            path = self.save()
            event.client.send_file_download(path.name, path.read_bytes())
            self.g_error.content = f"Saved `{path}`."

        def settings(_e):
            st = s.settings
            restart = st.max_path_length != int(self.g_path.value)
            st.layer = self.g_layer.value
            st.max_path_length = int(self.g_path.value)
            st.max_spp = max(1, int(self.g_max_spp.value))
            st.denoise_after = 4 if self.g_denoise.value else 0
            for loop in self.clients():
                loop.changed(force=restart)

        for h in (self.g_layer, self.g_path, self.g_max_spp, self.g_denoise):
            h.on_update(settings)

    def _set_gui(self, handle, value) -> None:
        self._syncing = True
        try:
            handle.value = value
        finally:
            self._syncing = False

    def _select_box_from_gui(self) -> int:
        c, size = np.asarray(self.g_box_centre.value), np.abs(np.asarray(self.g_box_size.value))
        return self.session.select_box(c - size / 2, c + size / 2)

    # ------------------------------------------------------------------ reacting to the session
    def _session_changed(self) -> None:
        for loop in self.clients():
            loop.changed()
        self._refresh()

    def _refresh(self) -> None:
        """Selection overlay, gizmo, material sliders and the op list after a change."""
        s = self.session
        with self.server.atomic():
            stats = s.selection_stats()
            if s.selection is not None and s.selection_name != BOX and s.selection_name in s.selections \
                    and self.g_select.value != s.selection_name:
                self._set_gui(self.g_select, s.selection_name)
            if stats is None:
                self.g_sel_info.content = "Nothing selected." if s.selection is None else \
                    "The selection catches no Gaussian."
            else:
                self.g_sel_info.content = f"{stats['count']:,} of {len(s.scene()[0]):,} Gaussians selected."
            self._update_overlay()
            pending = bool(s.pending)
            self.g_apply_tf.disabled = self.g_cancel_tf.disabled = not pending
            if not pending:  # gizmo back at the selection centre, identity rotation
                centre = s.selection_centre()
                self.gizmo.visible = centre is not None and self.overlays
                if centre is not None:
                    self._pivot = centre
                    self._syncing = True
                    try:
                        self.gizmo.position = tuple(centre)
                        self.gizmo.wxyz = (1.0, 0.0, 0.0, 0.0)
                    finally:
                        self._syncing = False
            if stats is not None and not any(op["op"] in ("set_roughness", "set_f0", "set_diffuse")
                                             for op in s.ops[-1:]):
                self._set_gui(self.g_rough, round(min(max(stats["roughness"], 0.0), 1.0), 2))
                self._set_gui(self.g_f0, round(min(max(float(np.mean(stats["f0"])), 0.0), 1.0), 2))
                self._set_gui(self.g_diffuse, tuple(int(round(v * 255)) for v in linear_to_srgb(stats["diffuse"])))
            ops = s.ops
            if ops:
                lines = [f"{i + 1}. `{op['op']}` " + ", ".join(f"{k}={v}" for k, v in op.items()
                                                                 if k not in ("op", "select"))
                         + (" (own selection)" if "select" in op else "") for i, op in enumerate(ops)]
                self.g_ops.content = "\n".join(lines) + (f"\n\n+ {len(s.pending)} previewed" if pending else "")
            else:
                self.g_ops.content = "No edit yet." + (" (transform previewed)" if pending else "")

    def _update_overlay(self) -> None:
        s = self.session
        mask = s.selection_mask()
        if self.overlays and self.g_show_sel.value and bool(mask.any()):
            pts = s.scene()[0].means.detach()[mask].float().cpu().numpy()
            if len(pts) > 20000:
                pts = pts[np.random.default_rng(0).choice(len(pts), 20000, replace=False)]
            self.sel_points = self.server.scene.add_point_cloud(
                "/edit/selection", pts, colors=(255, 200, 0), point_size=0.0015 * self.extent, point_shape="circle")
        elif self.sel_points is not None:
            self.sel_points.remove()
            self.sel_points = None
        box = s.selection.get("box") if s.selection is not None and s.selection_name == BOX and self.overlays else None
        if box is not None:
            lo, hi = np.asarray(box["min"]), np.asarray(box["max"])
            self.box_node = self.server.scene.add_box("/edit/box", color=(0, 200, 255), dimensions=tuple(hi - lo),
                                                      wireframe=True, position=tuple((lo + hi) / 2))
        elif self.box_node is not None:
            self.box_node.remove()
            self.box_node = None

    def _update_status(self, loop: ClientLoop) -> None:
        self.g_status.content = loop.status()
