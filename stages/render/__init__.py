"""``render`` stage: N spp reflection paths + denoiser, every layer as EXR + PNG, test split and a novel path."""

from .render import RenderConfig, camera_path, render_view, tonemap, write_layers

__all__ = ["RenderConfig", "camera_path", "render_view", "tonemap", "write_layers"]
