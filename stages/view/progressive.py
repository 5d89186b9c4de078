"""Progressive rendering for the viewer: 1 reflection sample per pixel per frame, accumulated while camera,
scene and settings stay the same, Open Image Denoise once enough samples are in.

A frame is ``models.rendering.render_view`` at spp=1 with a generator seeded once per accumulation, so N frames
draw exactly the random numbers of ``render_view`` at spp=N with that seed (same order, same sums): the
accumulated image equals the render stage's image at equal spp and seed (the replay test checks it). The
primary segment is deterministic and is traced once per accumulation (``PrimaryCache``), not every frame.
"""

from __future__ import annotations

import numbers
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from models.capture import Camera
from models.capture.layers import GBUFFER, SCORED
from models.gaussians import Gaussians
from models.pathtrace.paths import PathConfig
from models.rendering import RenderConfig, denoise, render_view, to_png

from .camera import z_depth

SHOWN_LAYERS = (*SCORED, *GBUFFER)  # final, diffuse, specular, depth, normal, roughness, f0
SAMPLED_LAYERS = ("final", "specular")  # the layers more samples improve
FAR_DEPTH = 160.0  # z-depth sent where no surface was hit (viser's depth encoding ends at 167.77)


@dataclass
class ViewSettings:
    layer: str = "final"  # one of SHOWN_LAYERS
    max_path_length: int = 3  # path segments (1 = no reflections), as RenderConfig
    max_spp: int = 64  # accumulation stops here (the view then idles until something changes)
    denoise_after: int = 4  # denoise the specular layer once this many samples are in (0 = never)
    seed: int = 0  # generator seed of every accumulation (equal seed + spp = equal image)

    def __post_init__(self) -> None:
        if not isinstance(self.layer, str) or self.layer not in SHOWN_LAYERS:
            raise ValueError(f"layer must be one of {SHOWN_LAYERS}, got {self.layer!r}")
        for name, least in (("max_path_length", 1), ("max_spp", 1), ("denoise_after", 0), ("seed", None)):
            v = getattr(self, name)
            if not isinstance(v, numbers.Integral) or isinstance(v, bool) or (least is not None and v < least):
                raise ValueError(f"{name} must be an int{f' >= {least}' if least is not None else ''}, got {v!r}")


@dataclass
class Frame:
    """One displayable frame."""

    rgb: np.ndarray  # [H, W, 3] uint8, the shown layer as the render stage's PNGs
    depth: np.ndarray  # [H, W] float32 depth along the optical axis (FAR_DEPTH where nothing was hit)
    layer: str
    spp: int  # reflection samples accumulated (0: primary only)
    denoised: bool
    version: int  # scene version rendered
    render_s: float  # seconds spent tracing for this frame (0 when only the display changed)
    camera: Camera


class FrameAborted(Exception):
    """Raised inside a frame (between two traces) when what it renders changed meanwhile."""


class PrimaryCache:
    """A trace function remembering the first trace after ``arm()`` (render_view traces the camera rays first):
    while the same rays meet the same Gaussians it returns that output instead of tracing again. The tracer is
    deterministic, so this changes no value. Raises FrameAborted before any trace once ``abort`` is set."""

    def __init__(self, trace_fn, abort: threading.Event):
        self.trace_fn = trace_fn
        self.abort = abort
        self._key = None
        self._out = None
        self._armed = False
        self.hits = 0

    def reset(self) -> None:
        self._key = self._out = None

    def arm(self) -> None:
        self._armed = True

    def __call__(self, origins: torch.Tensor, dirs: torch.Tensor, gaussians: Gaussians):
        if self.abort.is_set():
            raise FrameAborted
        if self._armed:
            self._armed = False
            k = self._key
            if (k is not None and k[0] is gaussians and k[1].shape == origins.shape and torch.equal(k[1], origins)
                    and torch.equal(k[2], dirs)):
                self.hits += 1
                return self._out
            self._out = self.trace_fn(origins, dirs, gaussians)
            self._key = (gaussians, origins.clone(), dirs.clone())
            return self._out
        return self.trace_fn(origins, dirs, gaussians)


class ProgressiveView:
    """Accumulates 1-spp frames of one camera. ``step()`` renders at most one frame and returns what to show
    (None when nothing changed). Several views may share a tracer through ``render_lock``."""

    def __init__(self, tracer, settings: ViewSettings | None = None, render_lock: threading.Lock | None = None,
                 batch_rays: int = 65536, path: PathConfig | None = None):
        self.tracer = tracer
        self.path = path or PathConfig()  # the model's path settings (max_path_length: settings.max_path_length)
        self.settings = settings or ViewSettings()
        self.render_lock = render_lock or threading.Lock()
        self.batch_rays = batch_rays
        self.camera: Camera | None = None
        self._abort = threading.Event()
        self._trace = PrimaryCache(tracer.trace, self._abort)
        self._key = None
        self._shown = None
        self._reset()

    # ------------------------------------------------------------------ state
    def _reset(self) -> None:
        self.frames = 0  # render_view calls in this accumulation
        self._base: dict[str, np.ndarray] = {}
        self._spec_sum: np.ndarray | None = None
        self._bounce_sums: dict[str, np.ndarray] = {}
        self._denoised: tuple | None = None
        self._generator = torch.Generator().manual_seed(self.settings.seed)

    @property
    def spp(self) -> int:
        return self.frames if self.settings.max_path_length > 1 else 0

    def set_camera(self, camera: Camera) -> None:
        self.camera = camera

    def abort(self) -> None:
        """Stop the frame being rendered at its next trace (its scene, camera or settings changed: the next
        ``step`` starts over). A frame that starts after this call is not affected."""
        self._abort.set()

    def configure(self, **changes) -> None:
        """Change settings (ViewSettings fields); path length and seed restart the accumulation, layer and
        denoising only the display."""
        s = ViewSettings(**{**vars(self.settings), **changes})
        self.settings = s

    @staticmethod
    def _camera_key(c: Camera):
        return (c.width, c.height, c.fl_x, c.fl_y, c.cx, c.cy, c.c2w.tobytes())

    def config(self) -> RenderConfig:
        """The render stage's config this view's accumulation equals (at spp = the accumulated samples)."""
        s = self.settings
        n = self.camera.width * self.camera.height if self.camera is not None else 0
        # one ray batch per frame: render_view draws random numbers batch by batch, so spp=N in one call
        # equals N calls at spp=1 only with a single batch
        return RenderConfig(spp=max(self.spp, 1) if s.max_path_length > 1 else 0, max_path_length=s.max_path_length,
                            antialias=1, denoise=s.denoise_after > 0 and self.spp >= s.denoise_after, seed=s.seed,
                            batch_rays=max(self.batch_rays, n), path_views=0, video=False)

    def record(self) -> dict:
        """This view's camera and accumulation as saved with an edit spec (replayable by the render stage)."""
        c, cfg = self.camera, self.config()
        return {"camera": {"width": c.width, "height": c.height, "fl_x": c.fl_x, "fl_y": c.fl_y, "cx": c.cx,
                           "cy": c.cy, "transform_matrix": c.c2w.tolist()},
                "render": {"spp": cfg.spp, "seed": cfg.seed, "max_path_length": cfg.max_path_length,
                           "antialias": cfg.antialias, "denoise": cfg.denoise}}

    def needs_frame(self) -> bool:
        s = self.settings
        if self.camera is None:
            return False
        if self.frames == 0:
            return True
        return s.max_path_length > 1 and self.frames < s.max_spp and s.layer in SAMPLED_LAYERS

    # ------------------------------------------------------------------ rendering
    def step(self, gaussians: Gaussians, version: int) -> Frame | None:
        """Render one more frame if useful; return the frame to show, or None when it would not change."""
        if self.camera is None:
            return None
        s = self.settings
        cam = self.camera
        key = (self._camera_key(cam), version, s.max_path_length, s.seed)
        render_s = 0.0
        with self.render_lock:
            self._abort.clear()
            if key != self._key:
                self._key = key
                self._reset()
            if self.needs_frame():
                t0 = time.perf_counter()
                cfg = RenderConfig(spp=1 if s.max_path_length > 1 else 0, max_path_length=s.max_path_length,
                                   antialias=1, denoise=False, seed=s.seed,
                                   batch_rays=max(self.batch_rays, cam.width * cam.height))
                self._trace.arm()
                try:
                    img = render_view(self._trace, cam, gaussians, cfg, self._generator, self.path)
                except FrameAborted:
                    self._key = None  # the generator moved: this accumulation cannot go on
                    return None
                self._accumulate(img)
                render_s = time.perf_counter() - t0
        shown = (key, self.frames, s.layer, s.denoise_after)
        if shown == self._shown:
            return None
        self._shown = shown
        layers = self.layers()
        rgb = to_png(s.layer, layers[s.layer])
        hit = (1.0 - layers["transmittance"][..., 0]) > 0.5
        depth = np.where(hit, z_depth(cam, layers["depth"][..., 0]), FAR_DEPTH).astype(np.float32)
        return Frame(rgb=rgb, depth=depth, layer=s.layer, spp=self.spp, denoised=self._is_denoised(),
                     version=version, render_s=render_s, camera=cam)

    def _accumulate(self, img: dict[str, np.ndarray]) -> None:
        self.frames += 1
        if self.frames == 1:
            self._base = {k: img[k] for k in ("diffuse", "depth", "normal", "roughness", "f0", "transmittance")}
        if self.settings.max_path_length > 1:
            # the same float32 additions, in the same order, as render_view's spec += out.specular
            noisy = img["specular_noisy"]
            self._spec_sum = noisy.copy() if self._spec_sum is None else self._spec_sum + noisy
            for k, v in img.items():
                if k.startswith("bounce"):
                    self._bounce_sums[k] = v.copy() if k not in self._bounce_sums else self._bounce_sums[k] + v

    def _is_denoised(self) -> bool:
        s = self.settings
        return s.max_path_length > 1 and s.denoise_after > 0 and self.spp >= s.denoise_after

    def layers(self) -> dict[str, np.ndarray]:
        """The accumulated image as render_view's dict (final, diffuse, specular, specular_noisy, depth, normal,
        roughness, f0, transmittance, bounce<i>), float32 [H, W, C]."""
        if self.frames == 0:
            raise RuntimeError("no frame rendered yet")
        out = dict(self._base)
        n = max(self.spp, 1)
        h, w = out["diffuse"].shape[:2]
        noisy = self._spec_sum / np.float32(n) if self._spec_sum is not None else np.zeros((h, w, 3), np.float32)
        out["specular_noisy"] = noisy
        for k, v in self._bounce_sums.items():
            out[k] = v / np.float32(n)
        out["specular"] = noisy
        if self._is_denoised():
            if self._denoised is None or self._denoised[0] != self.frames:
                self._denoised = (self.frames, np.maximum(denoise(noisy, albedo=out["f0"], normal=out["normal"]), 0))
            out["specular"] = self._denoised[1]
        out["final"] = out["diffuse"] + out["specular"]
        return out
