"""Synthetic captures: Mitsuba 3 (``llvm_ad_rgb``) split path tracer rendering synthetic captures with
exact buffers (RGB, diffuse, specular, emission, depth, normal, roughness, F0, mask).

Scenes are YAML (``configs/scenes/<name>.yaml``, section ``synth:``), parsed into typed specs
(``spec.py``), editable (``edits.py``), built into Mitsuba scene dicts in code
(``mitsuba_scene.py``) with numpy procedural textures (``textures.py``); the integrator is
``integrator.py`` (its docstring documents the layer routing and the principled diffuse lobe).
"""

from .edits import apply_edits, apply_scene_edit
from .render import render_capture, render_spec, scene_views
from .spec import SynthSpec, parse_spec

__all__ = ["SynthSpec", "apply_edits", "apply_scene_edit", "parse_spec", "render_capture", "render_spec", "scene_views"]
