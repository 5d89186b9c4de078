"""The browser viewer: viser GUI + one render thread per connected browser, over a ViewerSession.

Each browser tab gets its own ProgressiveView (its camera follows the tab's camera; accumulation restarts
when camera, scene or path length change) and a thread that renders 1-spp frames into it and streams
them as the scene's background image (JPEG, with depth so the gizmo and selection overlay composite).
Every GUI control calls a ViewerSession method; scripts and tests call the same methods through
``ViewerApp`` (``select``, ``apply``, ``apply_named_edit``, ``save``...) while the server runs.

What a tab sends is checked before viser stores it: every control (and the gizmo) has an entry in one table
(``_control_table``, kinds in controls.py); a value it refuses never reaches viser, the control keeps its last good
value and the panel and a notification on that tab say why. An exception in a tab's frame or in a callback is
logged and shown there; the server and the other tabs go on.
"""

from __future__ import annotations

import contextlib
import inspect
import logging
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
from .controls import BUTTON, CHECKBOX, ControlTable, Refused, choice, number, pose, text, vector
from .progressive import SHOWN_LAYERS, Frame, ViewSettings
from .session import ViewerSession, gizmo_ops

log = logging.getLogger("stages.view")

BOX = "(box)"  # the selection dropdown's entry for a drawn box (parenthesised: never a selection's name)
NONE = "(none)"
GIZMO = "Gizmo"  # the transform gizmo's entry in the control table (a scene node, not a GUI element)
RECT = "Rectangle"  # shift + drag on the image: corners (x0, y0, x1, y1) as fractions of the canvas


def gui_to_linear(rgb) -> list[float]:
    """GUI colour (0..255 sRGB) -> linear [0, 1] (diffuse and F0 are stored linear)."""
    return srgb_to_linear(np.asarray(rgb, dtype=np.float64) / 255.0).round(4).tolist()


def _gated(gate, handlers):
    """An incoming-message handler calling ``handlers`` (viser's own) only for messages ``gate`` passes."""
    async def gated(client_id, message) -> None:
        if not gate(client_id, message):
            return
        for h in handlers:
            out = h(client_id, message)
            if inspect.isawaitable(out):
                await out
    return gated


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
        # viser runs callbacks on a thread pool: one at a time here (with the panel refresh), as in a desktop GUI
        self._gui_lock = threading.RLock()
        with contextlib.redirect_stdout(sys.stderr):  # viser's banner: stdout stays for the caller's URL line
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction(up)
        self.server.scene.world_axes.visible = False
        means = session.original.means.detach().float().cpu().numpy()
        lo, hi = np.percentile(means, 2, axis=0), np.percentile(means, 98, axis=0)
        self.extent = float(np.linalg.norm(hi - lo)) or 1.0
        # how far from the origin a box, an offset or the gizmo may go (farther is a typo or a fuzzer, not an edit)
        self.reach = 100 * self.extent + float(np.abs(np.stack([lo, hi])).max())
        if initial_camera is not None:
            v = viser_from_camera(initial_camera, look_distance=0.3 * self.extent)
            ic = self.server.initial_camera
            ic.position, ic.look_at, ic.up, ic.fov = v["position"], v["look_at"], v["up_direction"], v["fov"]
        self._pivot = np.zeros(3)
        self._denoise_after = max(session.settings.denoise_after, 0) or 4  # what the Denoise checkbox turns on
        self.controls = self._control_table()
        self._handles: dict[str, object] = {}  # control name (its label) -> viser GUI handle
        self._build_gui()
        self._install_gate()
        session.on_change(self._session_changed)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._refresh()

    # ------------------------------------------------------------------ server
    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def _connect(self, client) -> None:
        try:
            loop = ClientLoop(self, client)
        except Exception as e:  # this tab gets no frames; the others and the server go on
            log.exception("starting the render thread of client %s", client.client_id)
            self._error(f"render thread failed to start: {type(e).__name__}: {e}", client)
            return
        with self._loops_lock:
            self._loops[client.client_id] = loop

    def _disconnect(self, client) -> None:
        with self._loops_lock:
            loop = self._loops.pop(client.client_id, None)
        if loop is not None:
            try:
                loop.stop()
            except Exception:
                log.exception("stopping the render thread of client %s", client.client_id)

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
        try:
            corners = [*screen_min, *screen_max]
        except TypeError:  # not two points: validate names it
            corners = [screen_min, screen_max]
        rect = self.controls.validate(RECT, corners)
        loop = self._loops.get(client_id)
        if loop is None or loop.view.frames == 0:
            raise ValueError("no frame shown in that browser tab yet")
        layers = loop.view.layers()
        hit = (1.0 - layers["transmittance"][..., 0]) > 0.5
        box = box_from_pixels(loop.view.camera, layers["depth"][..., 0], hit, rect)
        if box is None:
            raise ValueError("the rectangle shows no surface")
        lo, hi = box
        size = self.controls["Box size"]
        self._set_gui(self.g_select, BOX)
        for h in (self.g_box_centre, self.g_box_size, self.g_box_hint):
            h.visible = True
        self._set_gui(self.g_box_centre, tuple(float(v) for v in (lo + hi) / 2))
        self._set_gui(self.g_box_size, tuple(float(v) for v in np.clip(hi - lo, size.lo, size.hi)))
        return self._select_box_from_gui()

    def save(self, path: Path | None = None) -> Path:
        """Write the edit spec YAML (default: <save_dir>/<edit name>.yaml) with the first tab's camera and
        accumulation for the record."""
        path = Path(path) if path is not None else self.save_dir / f"{self.session.name}.yaml"
        loops = self.clients()
        view = loops[0].view.record() if loops and loops[0].last_frame is not None else None
        return self.session.save_spec(path, view)

    # ------------------------------------------------------------------ GUI
    def _control_table(self) -> ControlTable:
        """What every control accepts, by label: the GUI is built from it and every value a browser sends is
        checked against it (``_gate_gui``) before viser stores it."""
        s, st, reach = self.session, self.session.settings, self.reach
        named = list(s.named_edits)
        return ControlTable({
            "Selection": choice([NONE] + [n for n in s.selections if n not in (BOX, NONE)] + [BOX]),
            "Box centre": vector(3, -reach, reach),
            "Box size": vector(3, 1e-3, reach),
            "Show selection": CHECKBOX,
            "Apply transform": BUTTON,
            "Cancel transform": BUTTON,
            "Duplicate offset": vector(3, -reach, reach),
            "Duplicate": BUTTON,
            "Delete": BUTTON,
            "Roughness": number(0.0, 1.0),
            "F0": number(0.0, 1.0),
            "F0 tint": vector(3, 0, 255, integer=True),  # sRGB 0..255
            "Diffuse colour": vector(3, 0, 255, integer=True),
            "Undo": BUTTON,
            "Reset": BUTTON,
            "Named edit": choice(named or [NONE]),
            "Apply named edit": BUTTON,
            "Edit name": text(max(64, len(s.name))),  # the edit-name rule itself is checked on saving
            "Save edit spec": BUTTON,
            "Layer": choice(SHOWN_LAYERS),
            "Max path length": number(1, max(6, st.max_path_length), integer=True),
            "Max spp": number(1, max(4096, st.max_spp), integer=True),
            "Denoise": CHECKBOX,
            GIZMO: pose(reach),
            RECT: vector(4, -1.0, 2.0),  # a drag may end a little outside the canvas (box_from_pixels clips)
        })

    def _add(self, handle):
        """Register a GUI input under its label (its control-table entry)."""
        name = handle.label
        if name not in self.controls or name in self._handles:
            raise RuntimeError(f"GUI control {name!r}: not in the control table, or twice")
        self._handles[name] = handle
        return handle

    def _build_gui(self) -> None:
        gui, s, c, add = self.server.gui, self.session, self.controls, self._add
        gui.configure_theme(control_width="medium", show_share_button=False)
        with gui.add_folder("Selection"):
            self.g_select = add(gui.add_dropdown("Selection", c["Selection"].options, initial_value=NONE,
                                                 hint="named selections of the scene config's edits:, or a box"))
            self.g_box_centre = add(gui.add_vector3("Box centre", (0.0, 0.0, 0.0), step=0.01, visible=False))
            self.g_box_size = add(gui.add_vector3("Box size", (0.2 * self.extent,) * 3, min=(c["Box size"].lo,) * 3,
                                                  step=0.01, visible=False))
            self.g_box_hint = gui.add_markdown("Shift + drag on the image draws the box around what it shows.",
                                               visible=False)
            self.g_show_sel = add(gui.add_checkbox("Show selection", True, hint="selected Gaussian centres as points"))
            self.g_sel_info = gui.add_markdown("Nothing selected.")
        with gui.add_folder("Transform"):
            gui.add_markdown("Drag the gizmo (move / rotate) to preview; Apply commits it.")
            self.g_apply_tf = add(gui.add_button("Apply transform", disabled=True))
            self.g_cancel_tf = add(gui.add_button("Cancel transform", disabled=True))
            self.g_dup_offset = add(gui.add_vector3("Duplicate offset", (round(0.1 * self.extent, 2), 0.0, 0.0),
                                                    step=0.01))
            self.g_dup = add(gui.add_button("Duplicate"))
            self.g_delete = add(gui.add_button("Delete", color="red"))
        with gui.add_folder("Material"):
            r, f0 = c["Roughness"], c["F0"]
            self.g_rough = add(gui.add_slider("Roughness", r.lo, r.hi, 0.01, 0.5))
            self.g_f0 = add(gui.add_slider("F0", f0.lo, f0.hi, 0.01, 0.04, hint="base reflectance (times the F0 tint)"))
            self.g_f0_tint = add(gui.add_rgb("F0 tint", (255, 255, 255)))
            self.g_diffuse = add(gui.add_rgb("Diffuse colour", (128, 128, 128), hint="sRGB picker, stored linear"))
        with gui.add_folder("Edit"):
            self.g_ops = gui.add_markdown("No edit yet.")
            self.g_undo = add(gui.add_button("Undo"))
            self.g_reset = add(gui.add_button("Reset"))
            named = bool(s.named_edits)
            self.g_named = add(gui.add_dropdown("Named edit", c["Named edit"].options, disabled=not named))
            self.g_named_apply = add(gui.add_button("Apply named edit", disabled=not named))
            self.g_name = add(gui.add_text("Edit name", s.name))
            self.g_save = add(gui.add_button("Save edit spec",
                                             hint=f"writes {self.save_dir}/<name>.yaml and downloads it"))
            self.g_error = gui.add_markdown("")
        with gui.add_folder("Render"):
            st = s.settings
            self.g_layer = add(gui.add_dropdown("Layer", c["Layer"].options, initial_value=st.layer))
            p, spp = c["Max path length"], c["Max spp"]
            self.g_path = add(gui.add_slider("Max path length", int(p.lo), int(p.hi), 1, st.max_path_length))
            self.g_max_spp = add(gui.add_number("Max spp", st.max_spp, min=int(spp.lo), max=int(spp.hi), step=1))
            self.g_denoise = add(gui.add_checkbox("Denoise", st.denoise_after > 0,
                                                  hint=f"Open Image Denoise from {self._denoise_after} spp on"))
            self.g_status = gui.add_markdown("Waiting for a browser.")
        self.gizmo = self.server.scene.add_transform_controls("/edit/gizmo", scale=0.08 * self.extent,
                                                              depth_test=False, visible=False)
        self.box_node = None
        self.sel_points = None
        missing = set(self.controls) - set(self._handles) - {GIZMO, RECT}
        if missing:
            raise RuntimeError(f"control table entries without a GUI control: {sorted(missing)}")
        for name, h in self._handles.items():  # every initial value is one the table accepts
            self.controls.validate(name, h.value if self.controls[name].kind != "button" else True)
        self._wire()

    # ------------------------------------------------------------------ checking what browsers send
    def _install_gate(self) -> None:
        """Put the control table in front of viser: every GUI value and gizmo pose a tab sends is checked (and
        normalised: int / float / tuple) before viser's own handler stores it and re-broadcasts it to the other
        tabs (and, kept in its persistent buffer, to every later one). Written against viser 1.1.1 (pinned in
        pyproject.toml): the server's incoming-message handler lists are internal."""
        import viser
        from viser import _messages

        ws = self.server._websock_server
        self._names = {h._impl.uuid: name for name, h in self._handles.items()}
        for cls, gate in ((_messages.GuiUpdateMessage, self._gate_gui),
                          (_messages.TransformControlsUpdateMessage, self._gate_gizmo)):
            inner = list(getattr(ws, "_incoming_handlers", {}).get(cls, ()))
            if not inner:
                raise RuntimeError(f"viser {viser.__version__} has no {cls.__name__} handler to guard (the viewer "
                                   "is written against viser 1.1.1)")
            for h in inner:
                ws.unregister_handler(cls, h)
            ws.register_handler(cls, _gated(gate, inner))

    def _gate_gui(self, client_id: int, message) -> bool:
        """True: pass ``message`` (a GuiUpdateMessage, its value normalised) on to viser; False: refused (the
        sender's control snaps back, the panel says why). Runs on viser's event loop: never raises."""
        name = self._names.get(message.uuid)
        if name is None:
            return True  # not one of ours (viser's own elements)
        handle = self._handles[name]
        try:
            updates = message.updates
            if not isinstance(updates, dict) or list(updates) != ["value"]:
                raise Refused(name, updates, "sets more than the control's value")
            value = updates["value"]
            if handle.disabled or not handle.visible:
                raise Refused(name, value, "was sent to a disabled or hidden control")
            message.updates = {"value": self.controls.validate(name, value)}
            return True
        except Refused as e:
            self._refuse(client_id, e, handle)
        except Exception:
            log.exception("checking the value of %s sent by client %s", name, client_id)
        return False

    def _gate_gizmo(self, client_id: int, message) -> bool:
        """As ``_gate_gui`` for the gizmo's pose (TransformControlsUpdateMessage)."""
        if message.name != self.gizmo.name:
            return True
        try:
            message.wxyz, message.position = self.controls.validate(GIZMO, (message.wxyz, message.position))
            return True
        except Refused as e:
            self._refuse(client_id, e, None)
        except Exception:
            log.exception("checking the gizmo pose sent by client %s", client_id)
        return False

    def _refuse(self, client_id: int, refused: Refused, handle) -> None:
        """Tell the sender (panel + notification) and put its control back to the value the server holds (viser
        skips assigning an unchanged value, so the update is queued directly)."""
        try:
            if handle is None:  # the gizmo
                message = refused.message(has_kept=False) + ", kept its pose"
                self._resend_gizmo()
            elif self.controls[refused.name].kind == "button":
                message = refused.message(has_kept=False)
            else:
                message = refused.message(handle.value)
                handle._queue_update("value", handle.value)
            log.warning("refused from client %s: %s", client_id, message)
            self._error(message, self.server.get_clients().get(client_id), title="Refused")
        except Exception:
            log.exception("reporting a refused value to client %s", client_id)

    def _resend_gizmo(self) -> None:
        from viser import _messages

        g = self.gizmo
        g._impl.api._queue_scene_message(_messages.SetPositionMessage(g.name, tuple(float(v) for v in g.position)))
        g._impl.api._queue_scene_message(_messages.SetOrientationMessage(g.name, tuple(float(v) for v in g.wxyz)))

    def _guard(self, fn, programmatic: bool = False):
        """A GUI callback: ignore programmatic value changes (no client; ``programmatic``: run them too), show
        errors in the panel and to the tab that caused them; an unexpected exception is logged, never raised
        into viser."""
        def cb(event):
            client = getattr(event, "client", None)
            if (client is None and not programmatic) or self._syncing:
                return
            try:
                with self._gui_lock:
                    self.g_error.content = ""
                    fn(event)
            except (EditSpecError, ValueError) as e:
                self._error(str(e), client)
            except Exception as e:
                log.exception("GUI callback")
                self._error(f"{type(e).__name__}: {e} (a bug: see the server log)", client)
        return cb

    def _error(self, message: str, client=None, title: str = "Error") -> None:
        """Show ``message`` in the panel (every tab) and, given the tab it concerns, as a notification there."""
        self.g_error.content = f"**{title}:** `{message.replace('`', chr(39))}`"
        if client is not None:
            try:
                client.add_notification(title, message, auto_close_seconds=8.0, color="red")
            except Exception:  # the tab went away meanwhile
                log.debug("notification to client %s failed", getattr(client, "client_id", "?"), exc_info=True)

    def _wire(self) -> None:
        s, guard = self.session, self._guard

        @self.g_select.on_update
        @guard
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
            h.on_update(guard(lambda _e: self._select_box_from_gui()))

        @self.server.scene.on_rect_select(modifier="shift")
        @guard
        def _(event):
            self.box_from_rect(event.client_id, event.screen_min, event.screen_max)

        self.g_show_sel.on_update(guard(lambda _e: self._refresh(), programmatic=True))

        @self.gizmo.on_update
        @guard
        def _(_event):
            if s.selection is not None:
                self.preview_transform(self.gizmo.position, self.gizmo.wxyz)

        self.g_apply_tf.on_click(guard(lambda _e: s.commit_pending()))
        self.g_cancel_tf.on_click(guard(lambda _e: s.clear_pending()))
        self.g_dup.on_click(guard(
            lambda _e: s.apply({"op": "duplicate", "offset": list(self.g_dup_offset.value)})))
        self.g_delete.on_click(guard(lambda _e: s.apply({"op": "delete"})))
        self.g_rough.on_update(guard(
            lambda _e: s.apply({"op": "set_roughness", "value": round(float(self.g_rough.value), 4)}, coalesce=True)))

        def set_f0(_e):
            tint = np.asarray(gui_to_linear(self.g_f0_tint.value))
            s.apply({"op": "set_f0", "value": (np.clip(tint * float(self.g_f0.value), 0, 1)).round(4).tolist()},
                    coalesce=True)

        self.g_f0.on_update(guard(set_f0))
        self.g_f0_tint.on_update(guard(set_f0))
        self.g_diffuse.on_update(guard(
            lambda _e: s.apply({"op": "set_diffuse", "value": gui_to_linear(self.g_diffuse.value)}, coalesce=True)))
        self.g_undo.on_click(guard(lambda _e: s.undo()))
        self.g_reset.on_click(guard(lambda _e: s.reset()))
        self.g_named_apply.on_click(guard(lambda _e: s.apply_named_edit(self.g_named.value)))

        @self.g_save.on_click
        @guard
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
            old = s.settings  # replaced whole (render threads read it), never edited in place
            new = ViewSettings(layer=self.g_layer.value, max_path_length=int(self.g_path.value),
                               max_spp=int(self.g_max_spp.value),
                               denoise_after=self._denoise_after if self.g_denoise.value else 0, seed=old.seed)
            s.settings = new
            for loop in self.clients():
                loop.changed(force=new.max_path_length != old.max_path_length)

        for h in (self.g_layer, self.g_path, self.g_max_spp, self.g_denoise):
            h.on_update(guard(settings, programmatic=True))

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
        with self._gui_lock, self.server.atomic():
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
                self._set_gui(self.g_diffuse, tuple(min(max(int(round(v * 255)), 0), 255)
                                                    for v in linear_to_srgb(np.nan_to_num(stats["diffuse"]))))
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
        pts = s.selected_means() if self.overlays and self.g_show_sel.value else np.zeros((0, 3), np.float32)
        if len(pts):
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
