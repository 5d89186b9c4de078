"""Viewer GUI robustness (issue #20): every control's value as a browser tab's websocket would send it, random and
wrong (NaN, inf, 1e30, huge ints, strings, None, lists, bools...), driven into a real viser server through a real
websocket client speaking viser's wire protocol. The server refuses what is not valid (the control snaps back, the
panel says why), and a fresh tab still connects and gets a finite frame of the right size."""

from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np
import pytest

from stages.view import ViewerSession, ViewSettings, viser_from_camera
from tests.test_view import BALL, BOX, EDITS, _free_port, tiny_camera, tiny_scene

NAN, INF = math.nan, math.inf
W, H = 40, 30  # render size (a tiny scene, a tiny image: the fuzz renders many frames on 2 cores)


class Tab:
    """What a browser tab is to the viser server: a websocket speaking viser's wire protocol (msgpack to the
    server; zstd-compressed msgpack windows back). Keeps the GUI as the server describes it (uuid -> label, value,
    props), the notifications shown, and the background images received."""

    def __init__(self, url: str, timeout: float = 20.0):
        import viser
        from websockets.sync.client import connect

        self.ws = connect(url.replace("http://", "ws://"), subprotocols=[f"viser-v{viser.__version__}"],
                          max_size=2 ** 28, open_timeout=timeout)
        self.gui: dict[str, dict] = {}  # uuid -> {"kind", "label", "value", "props"}
        self.notifications: dict[str, dict] = {}  # uuid -> props (title, body...)
        self.images: list[tuple[str, bytes]] = []  # (format, encoded bytes) as received
        self.close_code: int | None = None
        self._cv = threading.Condition()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ receiving
    def _read(self) -> None:
        import msgspec
        import zstandard
        from websockets.exceptions import ConnectionClosed

        zstd = zstandard.ZstdDecompressor()
        try:
            while True:
                raw = self.ws.recv()
                n, c = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
                window = msgspec.msgpack.decode(zstd.decompress(raw[16:16 + c], max_output_size=n))
                with self._cv:
                    for m in window["messages"]:
                        self._take(m)
                    self._cv.notify_all()
        except ConnectionClosed as e:
            with self._cv:
                self.close_code = e.rcvd.code if e.rcvd is not None else 1006
                self._cv.notify_all()

    def _take(self, m: dict) -> None:
        kind = m["type"]
        if kind.startswith("Gui") and kind.endswith("Message") and "props" in m and "uuid" in m:
            self.gui[m["uuid"]] = {"kind": kind[3:-7], "label": m["props"].get("label"), "value": m.get("value"),
                                   "props": dict(m["props"])}
        elif kind == "GuiUpdateMessage" and m["uuid"] in self.gui:
            e = self.gui[m["uuid"]]
            for k, v in m["updates"].items():
                if k == "value":
                    e["value"] = v
                else:
                    e["props"][k] = v
        elif kind == "GuiRemoveMessage":
            self.gui.pop(m["uuid"], None)
        elif kind in ("NotificationShowMessage", "NotificationUpdateMessage"):
            self.notifications[m["uuid"]] = m["props"]
        elif kind == "RemoveNotificationMessage":
            self.notifications.pop(m["uuid"], None)
        elif kind == "BackgroundImageMessage" and m.get("rgb_data"):
            self.images.append((m["format"], bytes(m["rgb_data"])))

    def wait(self, predicate, timeout: float = 30.0, what: str = "a condition"):
        deadline = time.monotonic() + timeout
        with self._cv:
            while not (out := predicate()):
                left = deadline - time.monotonic()
                if left <= 0 or self.close_code is not None:
                    raise TimeoutError(f"{what} not reached within {timeout} s (websocket close code "
                                       f"{self.close_code})")
                self._cv.wait(min(left, 0.2))
            return out

    # ------------------------------------------------------------------ sending
    def send(self, kind: str, **fields) -> None:
        import msgspec

        self.ws.send(msgspec.msgpack.encode({"type": kind, **fields}))

    def send_camera(self, camera) -> None:
        v = viser_from_camera(camera, look_distance=2.0)
        self.send("ViewerCameraMessage", wxyz=[float(x) for x in v["wxyz"]],
                  position=[float(x) for x in v["position"]], fov=float(v["fov"]), near=0.01, far=1000.0,
                  image_height=camera.height * 10, image_width=camera.width * 10,
                  look_at=[float(x) for x in v["look_at"]], up_direction=[float(x) for x in v["up_direction"]])

    def uuid(self, label: str) -> str:
        with self._cv:
            hits = [u for u, e in self.gui.items() if e["label"] == label and e["kind"] != "Folder"]
        assert len(hits) == 1, f"{len(hits)} GUI elements labelled {label!r}"
        return hits[0]

    def set_value(self, label: str, value, updates: dict | None = None) -> None:
        """What the browser does when the control ``label`` is set (or, for a button, clicked): show the value
        in its own widget and send it (``updates``: send that instead)."""
        uuid = self.uuid(label)
        with self._cv:
            if self.gui[uuid]["kind"] != "Button":
                self.gui[uuid]["value"] = value
        self.send("GuiUpdateMessage", uuid=uuid, updates={"value": value} if updates is None else updates)

    def value(self, label: str):
        with self._cv:
            return self.gui[self.uuid(label)]["value"]

    def frame(self, after: int = 0, timeout: float = 60.0) -> np.ndarray:
        """The first background image received after the first ``after`` ones, decoded: [H, W, 3] uint8."""
        import imageio.v3 as iio

        self.wait(lambda: len(self.images) > after, timeout, f"background image #{after + 1}")
        fmt, data = self.images[after]
        return iio.imread(data, extension=".png" if fmt == "png" else ".jpg")

    def close(self) -> None:
        self.ws.close()
        self._thread.join(timeout=10)


# ----------------------------------------------------------------------------------------------- fixtures


@pytest.fixture
def viewer(tmp_path):
    """(app, open_tab): the viewer on the tiny scene at 40x30 pixels, and a function opening a tab (a websocket)
    that waits for the whole GUI and sends the test camera."""
    from stages.view.app import GIZMO, RECT, ViewerApp

    s = ViewerSession(tiny_scene(), {"ball": BALL, "box": BOX}, EDITS,
                      settings=ViewSettings(max_path_length=2, max_spp=2, denoise_after=0))
    app = ViewerApp(s, port=_free_port(), pixels=W * H, image_format="png", save_dir=tmp_path)
    labels = set(app.controls) - {GIZMO, RECT}
    tabs: list[Tab] = []

    def open_tab() -> Tab:
        t = Tab(app.url)
        tabs.append(t)
        t.wait(lambda: labels <= {e["label"] for e in t.gui.values()}, 20, "the whole GUI")
        t.send_camera(tiny_camera(W, H))
        return t

    try:
        yield app, open_tab
    finally:
        for t in tabs:
            t.close()
        app.stop()
        s.close()


def panel(app, tab: Tab) -> str:
    """The error line of the panel as ``tab`` shows it."""
    with tab._cv:
        return tab.gui[app.g_error._impl.uuid]["props"].get("_markdown", "")


def assert_fresh_tab_renders(app, open_tab) -> Tab:
    """A new tab connects, gets the GUI and a frame: a [H, W, 3] image, rendered from finite layers."""
    before = {loop.client.client_id for loop in app.clients()}
    t = open_tab()
    img = t.frame(timeout=60)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    deadline = time.monotonic() + 30
    while not (new := [lp for lp in app.clients() if lp.client.client_id not in before and lp.last_frame]):
        assert time.monotonic() < deadline, "the new tab's render thread sent no frame"
        time.sleep(0.05)
    frame, layers = new[0].last_frame, new[0].view.layers()
    assert frame.rgb.shape == (H, W, 3) and np.isfinite(frame.depth).all()
    for k in ("final", "diffuse", "specular", "normal", "roughness", "f0"):
        assert np.isfinite(layers[k]).all(), k
    return t


# ----------------------------------------------------------------------------------------------- the table


def test_control_table_refuses_what_is_not_a_value():
    """One check per kind of control: right type, finite, in range, one of the options; the value comes back as
    the control holds it; the refusal names the control, the value and why."""
    from stages.view.controls import BUTTON, CHECKBOX, ControlTable, Refused, choice, number, pose, text, vector

    t = ControlTable({"Max spp": number(1, 4096, integer=True), "Roughness": number(0.0, 1.0),
                      "Layer": choice(["final", "depth"]), "Name": text(8), "Box": vector(3, -10, 10),
                      "Tint": vector(3, 0, 255, integer=True), "On": CHECKBOX, "Go": BUTTON, "Gizmo": pose(100.0)})
    assert t.validate("Max spp", 12.0) == 12 and type(t.validate("Max spp", 12.0)) is int
    assert t.validate("Roughness", 1) == 1.0 and type(t.validate("Roughness", 1)) is float
    assert t.validate("Box", [1, 2, 3]) == (1.0, 2.0, 3.0) and t.validate("Tint", (0, 128.0, 255)) == (0, 128, 255)
    assert t.validate("Layer", "depth") == "depth" and t.validate("Name", "") == "" and t.validate("On", False) is False
    q, p = t.validate("Gizmo", ([2, 0, 0, 0], [1, 2, 3]))
    assert q == (1.0, 0.0, 0.0, 0.0) and p == (1.0, 2.0, 3.0)
    with pytest.raises(Refused) as e:
        t.validate("Max spp", 1e30)
    assert e.value.message(64) == "Max spp: 1e+30 is out of range 1..4096, kept 64"
    bad = {"Max spp": [math.nan, math.inf, -math.inf, 0, -3, 4097, 2 ** 64 - 1, 10 ** 400, 12.5, True, "12", None, [1]],
           "Roughness": [math.nan, -0.01, 1.01, "0.5", None, False, [0.5]],
           "Layer": ["nosuch", "", None, 5, ["final"], "Final"],
           "Name": ["123456789", "a\nb", "\x00", None, 5, ["a"]],
           "Box": [[1, 2], [1, 2, 3, 4], [math.nan, 0, 0], [11, 0, 0], "abc", None, 5, [None, 0, 0], [True, 0, 0]],
           "Tint": [[256, 0, 0], [-1, 0, 0], [1.5, 0, 0], [1e30, 0, 0]],
           "On": ["yes", 1, 0, None, [True]],
           "Go": [False, 1, "true", None],
           "Gizmo": [([0, 0, 0, 0], [0, 0, 0]), ([math.nan, 0, 0, 1], [0, 0, 0]), ([1, 0, 0, 0], [1e30, 0, 0]),
                     ([1, 0, 0], [0, 0, 0]), ([1, 0, 0, 0], [0, 0]), (None, None), "x", [1e300, 1e300, 0, 0]]}
    for name, values in bad.items():
        for v in values:
            with pytest.raises(Refused, match=f"^{name}: "):
                t.validate(name, v)
    with pytest.raises(Refused, match="not a control"):
        t.validate("nosuch", 1)


def test_browser_camera_that_is_no_camera_is_refused():
    """A camera message with a NaN pose, a zero quaternion or no field of view is no camera (ValueError: the tab's
    render thread waits for the next one); a canvas of absurd aspect gets a thin image, not a huge one."""
    from stages.view import camera_from_viser, viewport_size

    v = viser_from_camera(tiny_camera(W, H), look_distance=2.0)
    for pos, wxyz, fov in [([NAN, 0, 0], v["wxyz"], v["fov"]), (v["position"], [0, 0, 0, 0], v["fov"]),
                           (v["position"], [1, 0, INF, 0], v["fov"]), (v["position"], v["wxyz"], 0.0),
                           (v["position"], v["wxyz"], NAN), (v["position"], [1, 0, 0], v["fov"])]:
        with pytest.raises(ValueError):
            camera_from_viser(pos, wxyz, fov, 4 / 3, W * H)
    for aspect in (NAN, INF, 0.0, -1.0):
        with pytest.raises(ValueError):
            viewport_size(aspect, W * H)
    assert viewport_size(1e9, W * H) == (W * H, 1) and viewport_size(1e-9, W * H) == (1, W * H)


# ----------------------------------------------------------------------------------------------- reported cases


@pytest.mark.parametrize("label, bad, message, good", [
    ("Max spp", 1e30, "Max spp: 1e+30 is out of range 1..4096, kept 2", 3),
    ("Layer", "nosuch", "Layer: 'nosuch' is not one of diffuse, specular, final, depth, normal, roughness, f0, "
                        "kept 'final'", "diffuse"),
])
def test_reported_value_is_refused_and_the_next_frame_renders(viewer, label, bad, message, good):
    """Issue #20: one message setting Max spp to 1e30 made every later connection fail (websocket close 1011:
    viser re-sends the stored int to every new tab and msgpack cannot encode it); Layer 'nosuch' made every frame
    fail. Now the value is refused: the panel and a notification on the sending tab say so, its control snaps back,
    the server keeps the last good value, the tab's next change renders and a fresh tab renders."""
    app, open_tab = viewer
    a = open_tab()
    a.frame()
    kept = app._handles[label].value
    a.set_value(label, bad)
    a.wait(lambda: message in panel(app, a), 10, "the refusal in the panel")
    a.wait(lambda: any(n["body"] == message for n in a.notifications.values()), 10, "the refusal notification")
    a.wait(lambda: a.value(label) == kept, 10, "the control snapping back")
    assert app._handles[label].value == kept and getattr(app.session.settings, {"Max spp": "max_spp"}.get(
        label, "layer")) == kept
    n = len(a.images)
    a.set_value(label, good)  # the next (valid) change renders
    img = a.frame(after=n)
    assert img.shape == (H, W, 3) and img.std() > 5  # the scene, not a blank image
    assert app._handles[label].value == good
    b = assert_fresh_tab_renders(app, open_tab)
    assert b.value(label) == good and a.close_code is None


def test_a_failing_frame_or_callback_stays_with_its_tab(viewer, monkeypatch):
    """An exception in one tab's frame or in a GUI callback is logged and shown to that tab (notification) and
    in the panel; the server, the other tab and later changes go on."""
    app, open_tab = viewer
    a = open_tab()
    a.frame()
    b = open_tab()
    b.frame()
    loop_a = min(app.clients(), key=lambda lp: lp.client.client_id)  # tab a connected first

    def boom(*_a, **_k):
        raise RuntimeError("boom")

    monkeypatch.setattr(loop_a.view, "step", boom)
    n = len(b.images)
    b.set_value("Layer", "depth")  # both tabs re-render; a's frame fails
    b.frame(after=n)
    a.wait(lambda: any("render failed: RuntimeError: boom" in x["body"] for x in a.notifications.values()), 10,
           "a's render failure shown to a")
    assert not any("boom" in x["body"] for x in b.notifications.values())
    monkeypatch.undo()  # a renders again
    n = len(a.images)
    a.set_value("Layer", "normal")
    a.frame(after=n)
    monkeypatch.setattr(app.session, "undo", boom)
    a.set_value("Undo", True)
    a.wait(lambda: "RuntimeError: boom" in panel(app, a), 10, "the callback failure in the panel")
    a.wait(lambda: any("RuntimeError: boom" in x["body"] for x in a.notifications.values()), 10, "a notification")
    assert not any("boom" in x["body"] for x in b.notifications.values())
    n = len(b.images)
    b.set_value("Layer", "final")
    b.frame(after=n)
    assert a.close_code is None and b.close_code is None
    assert_fresh_tab_renders(app, open_tab)


# ----------------------------------------------------------------------------------------------- fuzz

NASTY = [NAN, INF, -INF, 1e30, -1e30, 1e308, -1, 0, 0.5, 1.5, 2 ** 63 - 1, -2 ** 63, 2 ** 64 - 1, True, False, None,
         "", "nosuch", "1", "x" * 5000, "\x00\n", [], [1, 2], [NAN, 0, 0], [1e30] * 3, [0, 0, 0, 0], [None] * 3,
         ["a", "b", "c"], [[1], [2], [3]], {}, {"value": 1}]


def nasty(rng) -> object:
    """A random value of a random wrong (or at least suspicious) kind."""
    k = int(rng.integers(7))
    if k == 0:
        return float(rng.choice([-1, 1]) * 10 ** rng.uniform(-5, 300))
    if k == 1:
        return int(rng.integers(-2 ** 63, 2 ** 63 - 1, dtype=np.int64))
    if k == 2:
        return "".join(rng.choice(list("abc_-./\\`*<>é\x01 "), size=int(rng.integers(0, 80))))
    if k == 3:
        return [nasty(rng) if rng.random() < 0.3 else float(rng.normal() * 10 ** rng.uniform(0, 40))
                for _ in range(int(rng.integers(0, 6)))]
    if k == 4:
        return NASTY[int(rng.integers(len(NASTY)))]
    if k == 5:
        return bool(rng.random() < 0.5)
    return None


def valid(rng, spec) -> object:
    """A random value the control takes (the fuzz also walks the paths that edit and render)."""
    if spec.kind == "number":
        return int(rng.integers(spec.lo, spec.hi + 1)) if spec.integer else float(rng.uniform(spec.lo, spec.hi))
    if spec.kind == "vector":
        if spec.integer:
            return [int(v) for v in rng.integers(spec.lo, spec.hi + 1, size=spec.size)]
        lo = max(spec.lo, -1.0)
        return [float(v) for v in rng.uniform(lo, max(lo + 0.5, 0.5), size=spec.size)]
    if spec.kind == "choice":
        return str(rng.choice(spec.options))
    if spec.kind == "text":
        return "".join(rng.choice(list("abcxyz_-0123"), size=int(rng.integers(1, 20))))
    if spec.kind == "checkbox":
        return bool(rng.random() < 0.5)
    return True  # a button: a click


@pytest.mark.filterwarnings("ignore:.*does not match annotation:UserWarning")  # viser, on the wrong-length poses
def test_fuzz_every_control_then_a_fresh_tab_renders(viewer, caplog):
    """Every GUI element the viewer creates (found as a browser finds it: in the messages the server sends), and
    the gizmo, the shift + drag rectangle and the camera, are sent random valid values and random wrong ones (NaN,
    inf, 1e30, huge ints, negative, 0, strings, None, lists, bools, dicts; and updates of more than the value),
    interleaved, through the websocket. Afterwards: the server still runs, the fuzzing tab is still connected,
    every control holds a value its spec takes (on the server and as a fresh tab receives it), the session's
    settings and scene are valid, and a fresh tab connects and gets a finite frame of the right size."""
    from stages.view.app import GIZMO, RECT

    app, open_tab = viewer
    caplog.set_level(logging.WARNING, logger="stages.view")
    a = open_tab()
    a.frame()
    rng = np.random.default_rng(20)
    with a._cv:
        elements = {e["label"]: e["kind"] for e in a.gui.values() if e["kind"] not in ("Folder", "Markdown")}
    assert set(elements) == set(app.controls) - {GIZMO, RECT}, "a GUI element without an entry in the table"
    sends = []
    for label in elements:
        spec = app.controls[label]
        values = ([("value", v) for v in NASTY] + [("value", nasty(rng)) for _ in range(10)]
                  + [("value", valid(rng, spec)) for _ in range(12)]
                  + [("updates", {"value": valid(rng, spec), "disabled": False}), ("updates", {"max": 1e30}),
                     ("updates", [])])
        sends += [(label, *v) for v in values]
    pivot = app.session.original.means.mean(0).tolist()
    for _ in range(40):  # the gizmo (only numbers survive viser's own decoding: anything else drops that tab)
        q = list(rng.normal(size=4)) if rng.random() < 0.5 else [float(rng.choice([NAN, INF, 0, 1e30, 1])) for _ in
                                                                  range(int(rng.choice([3, 4, 5])))]
        p = [v + float(rng.normal() * 0.1) for v in pivot] if rng.random() < 0.5 else \
            [float(rng.choice([NAN, -INF, 1e30, 0])) for _ in range(int(rng.choice([2, 3])))]
        sends.append((GIZMO, "pose", ([float(v) for v in q], p)))
    for _ in range(15):  # shift + drag rectangles
        corners = rng.uniform(0, 1, size=4) if rng.random() < 0.5 else rng.choice([NAN, INF, -1e30, 0.5], size=4)
        sends.append((RECT, "rect", [[float(corners[0]), float(corners[1])], [float(corners[2]), float(corners[3])]]))
    for _ in range(10):  # cameras that are no camera (NaN pose, zero quaternion, no field of view, odd canvases)
        sends.append(("camera", "camera", int(rng.integers(6))))
    order = rng.permutation(len(sends))
    cam = tiny_camera(W, H)
    t0 = time.monotonic()
    for i in order:
        label, how, v = sends[i]
        if how == "value":
            a.set_value(label, v)
        elif how == "updates":
            a.set_value(label, None, updates=v)
        elif how == "pose":
            a.send("TransformControlsUpdateMessage", name="/edit/gizmo", wxyz=v[0], position=v[1], owner="")
        elif how == "rect":
            a.send("ScenePointerMessage", event_type="rect-select", ray_origin=None, ray_direction=None, screen_pos=v,
                   modifier="shift")
        else:
            a.send_camera(cam)
            bad = {0: {"position": [NAN, 0.0, 0.0]}, 1: {"wxyz": [0.0, 0.0, 0.0, 0.0]}, 2: {"fov": 0.0},
                   3: {"fov": NAN}, 4: {"image_width": 10 ** 9, "image_height": 1},
                   5: {"image_width": 1, "image_height": 10 ** 9}}[v]
            a.send("ViewerCameraMessage", **{**_camera_fields(cam), **bad})
        time.sleep(0.002)
    a.send_camera(cam)
    # let the callbacks the fuzz queued finish: the scene version stays put for a second
    last, still = app.session.version, time.monotonic()
    while time.monotonic() - still < 1.0:
        assert time.monotonic() - t0 < 60, "the session keeps changing"
        time.sleep(0.1)
        if app.session.version != last:
            last, still = app.session.version, time.monotonic()
    assert a.close_code is None, f"the fuzzing tab was dropped (close code {a.close_code})"
    refused = [r.getMessage() for r in caplog.records if r.getMessage().startswith("refused")]
    bugs = [caplog.handler.format(r)[-1500:] for r in caplog.records if r.levelno >= logging.ERROR]
    print(f"{len(sends)} messages, {len(refused)} refused, scene version {app.session.version}, "
          f"{len(app.session.ops)} ops, {len(a.images)} frames; errors logged: {len(bugs)}")
    assert not bugs, bugs[:3]  # a refused value is no error; a failed callback or frame is
    assert len(refused) > len(sends) / 2 and app.session.version > 20  # wrong values refused, valid ones applied
    # every control holds a value its spec takes
    for label, h in app._handles.items():
        if app.controls[label].kind != "button":
            assert app.controls.validate(label, h.value) == h.value, label
    ViewSettings(**vars(app.session.settings))
    g = app.session.scene()[0]
    for k, v in g.params().items():
        assert bool(v.isfinite().all()), k
    # a fresh tab: connects, renders, and receives the values the server holds
    b = assert_fresh_tab_renders(app, open_tab)
    for label, h in app._handles.items():
        if app.controls[label].kind != "button":
            b.wait(lambda: app.controls.validate(label, b.value(label)) == app.controls.validate(label, h.value), 10,
                   f"{label} as the server holds it")
    assert a.close_code is None and b.close_code is None


def _camera_fields(camera) -> dict:
    v = viser_from_camera(camera, look_distance=2.0)
    return {"wxyz": [float(x) for x in v["wxyz"]], "position": [float(x) for x in v["position"]],
            "fov": float(v["fov"]), "near": 0.01, "far": 1000.0, "image_height": camera.height * 10,
            "image_width": camera.width * 10, "look_at": [float(x) for x in v["look_at"]],
            "up_direction": [float(x) for x in v["up_direction"]]}
