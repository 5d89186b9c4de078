"""Viewer (stages/view): the browser camera <-> our Camera, gizmo ops, the session's edit spec replaying through the
edit stage to the same image, and the viewer end to end in headless Chromium (CDP over websockets): the streamed
image shows up in the page and changes where an edit applied through the viewer's API is, and only there
(plus its reflection in the mirror ball)."""

from __future__ import annotations

import base64
import json
import math
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from models.capture import Camera, Capture, View, read_view_buffers, write_capture
from models.editing import apply_edit, parse_edits
from models.gaussians import Gaussians, read_ply, write_ply
from models.metrics.image import psnr
from models.rendering import render_view
from stages.view import ViewerSession, ViewSettings, camera_from_viser, gizmo_ops, resize_camera, viser_from_camera

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")

BALL = {"sphere": {"centre": [-0.45, 0.3, 0.0], "radius": 0.33},
        "exclude": [{"box": {"min": [-2, -0.1, -2], "max": [2, 0.02, 2]}}]}  # minus the floor
BOX = {"box": {"min": [0.25, 0.0, -0.1], "max": [0.65, 0.4, 0.3]}}
EDITS = {"recolour_box": {"select": BOX, "ops": [{"op": "set_diffuse", "value": [0.9, 0.05, 0.05]}]},
         "move_ball": {"select": BALL, "ops": [{"op": "translate", "offset": [0.0, 0.0, 0.3]}]}}


def tiny_scene() -> Gaussians:
    """1150 Gaussians: a checker floor, a back wall, a mirror ball (left, F0 0.9, roughness 0) and a diffuse
    green box (right)."""
    rng = np.random.default_rng(0)
    parts = []

    def add(means, scale, normals, diffuse, rough, f0):
        n = len(means)
        parts.append({"means": means, "quats": np.tile([1.0, 0, 0, 0], (n, 1)),
                      "log_scales": np.log(np.broadcast_to(scale, (n, 3))), "opacity_logits": np.full(n, 5.0),
                      "diffuse": np.broadcast_to(diffuse, (n, 3)), "normals": np.broadcast_to(normals, (n, 3)),
                      "roughness": np.full(n, rough), "f0": np.broadcast_to(f0, (n, 3))})

    g = np.linspace(-1.2, 1.2, 20)
    xx, zz = np.meshgrid(g, g)
    checker = ((np.floor(xx.ravel() * 2.5) + np.floor(zz.ravel() * 2.5)) % 2)[:, None]
    add(np.stack([xx.ravel(), np.zeros(xx.size), zz.ravel()], 1), [0.08, 0.01, 0.08], [0, 1, 0],
        0.25 + 0.4 * checker * np.ones(3), 0.3, [0.04] * 3)
    xw, yy = np.meshgrid(g, np.linspace(0.0, 1.2, 10))
    add(np.stack([xw.ravel(), yy.ravel(), np.full(xw.size, -1.2)], 1), [0.08, 0.08, 0.01], [0, 0, 1],
        [0.3, 0.35, 0.6], 1.0, [0.04] * 3)
    d = rng.normal(size=(250, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    add(np.array([-0.45, 0.3, 0.0]) + 0.25 * d, 0.06, d, [0.05] * 3, 0.0, [0.9] * 3)
    u = rng.uniform(-1, 1, size=(300, 3))
    k = rng.integers(0, 3, 300)
    side = np.sign(u[np.arange(300), k])
    u[np.arange(300), k] = side
    add(np.array([0.45, 0.2, 0.1]) + 0.18 * u, 0.05, np.eye(3)[k] * side[:, None], [0.1, 0.6, 0.15], 1.0, [0.04] * 3)
    return Gaussians(**{k: torch.tensor(np.concatenate([p[k] for p in parts]), dtype=torch.float32) for k in parts[0]})


def tiny_camera(w: int = 160, h: int = 120) -> Camera:
    eye, target = np.array([0.0, 0.9, 2.0]), np.array([0.0, 0.25, 0.0])
    f = (target - eye) / np.linalg.norm(target - eye)
    r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = r, np.cross(r, f), -f, eye
    fl = h / 2 / math.tan(math.radians(25))
    return Camera(w, h, fl, fl, w / 2, h / 2, c2w)


def project_rect(camera: Camera, points: np.ndarray, pad: int) -> tuple[int, int, int, int]:
    """Pixel bounds (x0, y0, x1, y1), exclusive, of ``points`` [N, 3] seen by ``camera``, padded."""
    p = (points - camera.origin) @ camera.rotation  # camera space (OpenGL: -z forward)
    u = camera.fl_x * p[:, 0] / -p[:, 2] + camera.cx
    v = -camera.fl_y * p[:, 1] / -p[:, 2] + camera.cy
    return (max(int(u.min()) - pad, 0), max(int(v.min()) - pad, 0),
            min(int(u.max()) + 1 + pad, camera.width), min(int(v.max()) + 1 + pad, camera.height))


def rect_mask(shape, rect) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    m[rect[1]:rect[3], rect[0]:rect[2]] = True
    return m


# ----------------------------------------------------------------------------------------------- no browser


def test_browser_camera_round_trip_renders_the_same_image():
    """Camera -> viser state -> Camera is the identity (4:3 canvas, its own pixel count) and renders the same
    image as render_view for that camera; a wider canvas keeps the vertical field of view."""
    cam = tiny_camera()
    v = viser_from_camera(cam, look_distance=2.0)
    back = camera_from_viser(v["position"], v["wxyz"], v["fov"], v["aspect"], cam.width * cam.height)
    assert (back.width, back.height) == (cam.width, cam.height)
    np.testing.assert_allclose(back.c2w, cam.c2w, atol=1e-12)
    for k in ("fl_x", "fl_y", "cx", "cy"):
        assert getattr(back, k) == pytest.approx(getattr(cam, k), rel=1e-12)
    # OpenCV orientation: the camera looks along its +Z
    r_cv = camera_from_viser(v["position"], v["wxyz"], v["fov"], 4 / 3, 100).rotation @ np.diag([1, -1, -1])
    np.testing.assert_allclose(r_cv[:, 2], (v["look_at"] - v["position"]) / 2.0, atol=1e-12)
    # a capture view at the viewer's pixel budget keeps pose and field of view; at its own size it is itself
    small = resize_camera(cam, 96 * 72)
    assert (small.width, small.height) == (96, 72) and small.fl_y == pytest.approx(cam.fl_y * 0.6, rel=1e-12)
    same = resize_camera(cam, cam.width * cam.height)
    assert (same.fl_x, same.fl_y, same.cx, same.cy) == (cam.fl_x, cam.fl_y, cam.cx, cam.cy)
    wide = camera_from_viser(v["position"], v["wxyz"], v["fov"], 2.0, cam.width * cam.height)
    assert wide.width / wide.height == pytest.approx(2.0, rel=0.02)
    assert 2 * math.atan(wide.height / 2 / wide.fl_y) == pytest.approx(v["fov"], rel=1e-12)
    # same rays -> same image (through the session's accumulation; primary only: deterministic)
    s = ViewerSession(tiny_scene(), settings=ViewSettings(max_path_length=1))
    s.set_camera(back)
    frame = s.step()
    assert frame is not None and s.step() is None  # primary only: one frame, then idle
    ref = render_view(s.tracer.trace, cam, s.original, s.view.config(), torch.Generator().manual_seed(0),
                      s.model.path)
    np.testing.assert_array_equal(s.view.layers()["final"], ref["final"])
    s.close()


def test_gizmo_ops_reproduce_the_rigid_motion():
    """A gizmo moved from p0 to p1 and turned by q: the ops map x -> p1 + R (x - p0) on the selection only."""
    g = tiny_scene()
    s = ViewerSession(g)
    s.select_mapping(BALL, "ball")
    mask = s.selection_mask().clone()
    p0 = s.selection_centre()
    q = np.array([math.cos(0.3), 0.0, math.sin(0.3), 0.0])  # 34.4 deg about +y
    p1 = p0 + np.array([0.1, 0.2, -0.3])
    ops = gizmo_ops(p0, p1, q)
    assert [o["op"] for o in ops] == ["rotate", "translate"]
    s.set_pending(ops)
    assert s.ops == [] and len(s.pending) == 2  # previewed only
    s.commit_pending()
    out = s.scene()[0].means.double().numpy()
    c, sn = math.cos(0.6), math.sin(0.6)
    r = np.array([[c, 0, sn], [0, 1, 0], [-sn, 0, c]])
    want = p1 + (g.means.double().numpy()[mask.numpy()] - p0) @ r.T
    np.testing.assert_allclose(out[mask.numpy()], want, atol=2e-5)  # float32 means; ops rounded to 1e-6
    np.testing.assert_array_equal(out[~mask.numpy()], g.means.double().numpy()[~mask.numpy()])
    # the edit's selection follows the moved Gaussians
    np.testing.assert_array_equal(s.selection_mask().numpy(), mask.numpy())
    s.close()


def test_saved_spec_replays_through_the_edit_stage(tmp_path):
    """Edits made in a session (move, duplicate and roughen the ball, recolour the box: two selections), saved as
    YAML, replay through the edit stage's library (apply_edit + render_view at equal spp and seed) and its CLI
    (python -m stages.edit apply --edit-file) to the viewer's accumulated, denoised image."""
    from models.trained import read_settings

    write_ply(tmp_path / "tiny.ply", tiny_scene())
    g = read_ply(tmp_path / "tiny.ply")  # as the CLI will read it, with the settings it reads (a bare PLY: the
    # legacy ones, models/trained.py; `python -m stages.view` passes them too)
    s = ViewerSession(g, {"ball": BALL, "box": BOX}, EDITS, model=read_settings(tmp_path / "tiny.ply"),
                      settings=ViewSettings(max_path_length=3, max_spp=6, denoise_after=4, seed=3))
    cam = tiny_camera(96, 72)
    s.set_camera(cam)
    s.select("ball")
    s.apply({"op": "translate", "offset": [0.0, 0.0, 0.3]})
    s.apply({"op": "duplicate", "offset": [0.0, 0.0, -0.6]})  # the copy is left out of the edit's selection
    s.apply({"op": "set_roughness", "value": 0.2})  # -> the moved ball only
    s.select("box")
    s.apply({"op": "set_diffuse", "value": [0.9, 0.05, 0.05]}, coalesce=True)
    s.apply({"op": "set_diffuse", "value": [0.8, 0.1, 0.05]}, coalesce=True)  # a slider drag: replaces the last
    ops = s.ops
    assert [o["op"] for o in ops] == ["translate", "duplicate", "set_roughness", "set_diffuse"]
    assert "select" not in ops[0] and ops[3]["select"] == BOX
    g_view = s.scene()[0]
    assert len(g_view) == len(g) + 250
    assert int((g_view.roughness == 0.2).sum()) == 250  # the moved original, not the copy
    frames = 0
    while (f := s.step()) is not None:
        frames += 1
        last = f
    assert frames == 6 and last.spp == 6 and last.denoised
    viewer = s.view.layers()
    # layer switches only re-display; a G-buffer layer needs no samples; path length restarts the accumulation
    s.view.configure(layer="depth")
    f = s.step()
    assert f is not None and f.layer == "depth" and f.render_s == 0 and s.step() is None
    s.view.configure(max_path_length=2)
    assert s.step().render_s > 0 and s.view.frames == 1 and s.step() is None
    s.view.configure(layer="final")
    assert s.step().spp == 2
    s.view.configure(max_path_length=3)
    while s.step() is not None:
        pass
    np.testing.assert_array_equal(s.view.layers()["final"], viewer["final"])  # the same accumulation again
    path = s.save_spec(tmp_path / "edit.yaml", view={"seed": 3})
    spec = parse_edits(yaml.safe_load(path.read_text())["edits"])["viewer_edit"]
    replayed, _ = apply_edit(g, spec)
    for k, v in g_view.params().items():
        assert torch.equal(getattr(replayed, k), v), k
    cfg = s.view.config()
    assert (cfg.spp, cfg.seed, cfg.max_path_length, cfg.denoise) == (6, 3, 3, True)
    s.tracer.update(replayed, rebuild=True)
    ref = render_view(s.tracer.trace, cam, replayed, cfg, torch.Generator().manual_seed(cfg.seed), s.model.path)
    assert psnr(viewer["final"], ref["final"]) > 40
    np.testing.assert_array_equal(viewer["final"], ref["final"])  # in fact bit for bit

    # the edit stage's CLI on a one-view capture with that camera; the viewer's live preview does not follow the
    # light (no relight: models/editing/relight.py), so the stage replays it bit for bit with relight off
    doc = yaml.safe_load(path.read_text())
    doc["edits"]["viewer_edit"]["relight"] = False
    path.write_text(yaml.safe_dump(doc))
    view = View("v0", cam, "test", {"rgb": np.zeros((72, 96, 3), np.float32)})
    write_capture(Capture(views=[view]), tmp_path / "cap")
    # the render settings the viewer records with the edit (one primary per pixel: its frames are not antialiased)
    assert s.view.record()["render"] == {"spp": 6, "seed": 3, "max_path_length": 3, "antialias": 1, "denoise": True}
    render = json.dumps({"spp": 6, "seed": 3, "max_path_length": 3, "antialias": 1, "denoise": True,
                         "path_views": 0})
    proc = subprocess.run([sys.executable, "-m", "stages.edit", "apply", "--edit-file", str(path), "--edit",
                           "viewer_edit", "--model", str(tmp_path / "tiny.ply"), "--capture", str(tmp_path / "cap"),
                           "--out", str(tmp_path / "out"), "--config-json", render],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    exr = read_view_buffers(tmp_path / "out" / "renders" / "test" / "v0.exr", 72, 96, ["rgb"])
    assert psnr(exr["rgb"], viewer["final"]) > 40
    # the stage renders the model as written: the PLY's colour encoding (f_dc) rounds a set colour by ~1 ulp
    np.testing.assert_allclose(exr["rgb"], viewer["final"], rtol=1e-5, atol=1e-6)
    s.close()


# ----------------------------------------------------------------------------------------------- browser


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class Chromium:
    """Headless Chromium driven over the Chrome DevTools protocol (websockets, synchronous client)."""

    def __init__(self, profile: Path, width: int, height: int):
        from websockets.sync.client import connect

        port = _free_port()
        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--enable-unsafe-swiftshader", "--use-angle=swiftshader", f"--user-data-dir={profile}",
             f"--remote-debugging-port={port}", f"--window-size={width},{height}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 30
        while True:
            try:
                tabs = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=2))
                page = next(t for t in tabs if t["type"] == "page")
                break
            except (OSError, StopIteration, ValueError):
                if time.monotonic() > deadline or self.proc.poll() is not None:
                    self.close()
                    raise RuntimeError("chromium did not open its DevTools port") from None
                time.sleep(0.1)
        self.ws = connect(page["webSocketDebuggerUrl"], max_size=2 ** 28, open_timeout=10)
        self._id = 0
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                  mobile=False)

    def call(self, method: str, **params) -> dict:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")

    def canvas_screenshot(self) -> np.ndarray:
        """The 3D canvas only: everything drawn over it (control panel, notifications) hidden first."""
        import imageio.v3 as iio

        rect = self.evaluate("""(() => {
            const all = [...document.querySelectorAll('canvas')];
            if (!all.length) return null;
            const c = all.reduce((a, b) => (b.width * b.height > a.width * a.height ? b : a));  // the WebGL one
            const keep = new Set();
            for (let e = c; e; e = e.parentElement) keep.add(e);
            for (const e of document.body.querySelectorAll('*'))
                if (!keep.has(e) && !c.contains(e)) e.style.visibility = 'hidden';
            const r = c.getBoundingClientRect();
            return [r.x, r.y, r.width, r.height];
        })()""")
        assert rect is not None, "the page has no canvas"
        x, y, w, h = rect
        shot = self.call("Page.captureScreenshot", format="png",
                         clip={"x": x, "y": y, "width": w, "height": h, "scale": 1})
        return iio.imread(base64.b64decode(shot["data"]))[..., :3]

    def close(self) -> None:
        if getattr(self, "ws", None) is not None:
            self.ws.close()
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def _at_render_size(shot: np.ndarray, w: int, h: int) -> np.ndarray:
    """Screenshot [kH, kW, 3] uint8 -> [h, w, 3] float in [0, 1] by area averaging."""
    k = shot.shape[1] // w
    assert shot.shape[:2] == (h * k, w * k), (shot.shape, w, h)
    return shot.reshape(h, k, w, k, 3).astype(np.float64).mean(axis=(1, 3)) / 255


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (Debian: apt-get install chromium) for the browser test")
def test_viewer_in_headless_chromium(tmp_path):
    """The viewer served headless, opened in Chromium: the page shows the streamed render from the capture-like
    starting camera (the browser's camera converts back to it); an edit applied through the viewer's API
    (recolour the green box red) changes the screenshot inside the box's projection, in the mirror ball and the
    glossy floor (its reflections), and leaves the rest of the image unchanged; the page's Undo button, a
    rectangle-drawn box selection, a gizmo move and saving go through the same session."""
    from stages.view.app import ViewerApp

    w, h, k = 160, 120, 4
    settings = ViewSettings(max_path_length=3, max_spp=4, denoise_after=0)
    s = ViewerSession(tiny_scene(), {"ball": BALL, "box": BOX}, EDITS, settings=settings)
    cam = tiny_camera(w, h)
    app = ViewerApp(s, port=_free_port(), pixels=w * h, initial_camera=cam, save_dir=tmp_path, image_format="png",
                    overlays=False)
    browser = None
    try:
        browser = Chromium(tmp_path / "profile", w * k, h * k)
        browser.call("Page.navigate", url=app.url)
        # the page starts at viser's default view and then applies the server's initial camera: wait for it
        deadline = time.monotonic() + 60
        while True:
            before = app.wait_for_frame(min_spp=4, timeout=60)
            if np.allclose(before.camera.c2w, cam.c2w, atol=1e-4) or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        loop = app.clients()[0]
        # the browser's camera is the starting camera (what the capture view would render)
        bcam = before.camera
        assert (bcam.width, bcam.height) == (w, h)
        np.testing.assert_allclose(bcam.c2w, cam.c2w, atol=1e-4)
        assert bcam.fl_x == pytest.approx(cam.fl_x, rel=1e-3) and bcam.fl_y == pytest.approx(cam.fl_y, rel=1e-3)
        s.tracer.update(s.original)
        ref = render_view(s.tracer.trace, cam, s.original, loop.view.config(), torch.Generator().manual_seed(0),
                      s.model.path)
        assert psnr(loop.view.layers()["diffuse"], ref["diffuse"]) > 40

        def shot_matching(frame, timeout=30.0):
            """Screenshot once the page shows ``frame`` (the streamed PNG, upscaled by the browser) and stays
            unchanged (the last frame of an accumulation, not one on the way)."""
            want = frame.rgb.astype(np.float64) / 255
            deadline = time.monotonic() + timeout
            prev = None
            while True:
                img = _at_render_size(browser.canvas_screenshot(), w, h)
                err = np.abs(img - want).max(axis=-1)
                if (np.mean(err < 0.1) > 0.97 and prev is not None and np.array_equal(img, prev)) \
                        or time.monotonic() > deadline:
                    return img, err
                prev = img
                time.sleep(0.3)

        shot_a, err_a = shot_matching(before)
        assert np.mean(err_a < 0.1) > 0.97, f"the page does not show the streamed frame (median {np.median(err_a):.3f})"

        # an edit through the viewer's own API
        app.select("box")
        app.apply({"op": "set_diffuse", "value": [0.9, 0.05, 0.05]})
        after = app.wait_for_frame(min_spp=4, timeout=60)
        assert after.version == s.version and after.version != before.version
        shot_b, err_b = shot_matching(after)
        assert np.mean(err_b < 0.1) > 0.97

        g = s.scene()[0].means.detach().numpy()
        box_rect = project_rect(cam, g[s.selection_mask().numpy()], pad=1)
        ball_rect = project_rect(cam, g[np.linalg.norm(g - BALL["sphere"]["centre"], axis=1) < 0.33], pad=1)
        box, ball = rect_mask((h, w), box_rect), rect_mask((h, w), ball_rect)
        # near the box: its rectangle, and below it its blurry reflection in the glossy floor
        tall = box_rect[3] - box_rect[1]
        near = rect_mask((h, w), (box_rect[0] - 4, box_rect[1] - 4, box_rect[2] + 4, box_rect[3] + tall))
        far = ~near & ~rect_mask((h, w), (ball_rect[0] - 4, ball_rect[1] - 4, ball_rect[2] + 4, ball_rect[3] + 4))
        red = shot_b[..., 0] - shot_a[..., 0]
        green = shot_b[..., 1] - shot_a[..., 1]
        # the box turned red: most of its projected rectangle (it is not a full rectangle) changed strongly
        assert np.mean((red > 0.2) & (green < -0.1) & box) / box.mean() > 0.4
        # its reflection in the mirror ball turned red too (consistent reflections)
        assert (red[ball] > 0.1).sum() >= 5
        # nothing else moved
        diff = np.abs(shot_b - shot_a).max(axis=-1)
        assert diff[far].mean() < 0.005 and np.quantile(diff[far], 0.99) < 0.02, (diff[far].mean(), diff[far].max())

        # the page's own Undo button (clicked in the page) reaches the session; the same frame comes back
        browser.evaluate("[...document.querySelectorAll('button')].find(b => b.textContent.trim() == 'Undo').click()")
        deadline = time.monotonic() + 20
        while s.ops and time.monotonic() < deadline:
            time.sleep(0.1)
        assert s.ops == [] and len(s.scene()[0]) == len(s.original)
        shot_c, _ = shot_matching(app.wait_for_frame(min_spp=4, timeout=60))
        assert np.abs(shot_c - shot_a).max() < 0.02  # same scene, camera and seed: the same image

        # shift + drag over the box selects a world box around it; the gizmo moves it (preview, then commit)
        n = app.box_from_rect(loop.client.client_id, (box_rect[0] / w, box_rect[1] / h),
                              (box_rect[2] / w, box_rect[3] / h))
        mask = s.selection_mask().numpy()
        in_box = np.zeros(len(mask), bool)
        in_box[-300:] = True  # the box's Gaussians come last in tiny_scene()
        assert mask[in_box].mean() > 0.9 and n < 2 * 300, (mask[in_box].mean(), n)
        pivot = s.selection_centre()
        app.preview_transform(pivot + [0.0, 0.3, 0.0], (1.0, 0.0, 0.0, 0.0))
        assert s.ops == [] and [o["op"] for o in s.pending] == ["translate"]
        s.commit_pending()
        moved = s.scene()[0].means.numpy()
        np.testing.assert_allclose(moved[mask] - s.original.means.numpy()[mask], np.tile([0, 0.3, 0], (n, 1)),
                                   atol=1e-6)
        app.wait_for_frame(timeout=60)
        saved = yaml.safe_load(app.save().read_text())
        assert saved["edits"]["viewer_edit"]["ops"] == [{"op": "translate", "offset": [0.0, 0.3, 0.0]}]
        assert saved["viewer"]["render"]["seed"] == 0 and len(saved["viewer"]["camera"]["transform_matrix"]) == 4
    finally:
        if browser is not None:
            browser.close()
        app.stop()
        s.close()
