"""Ground truth of an edit on a synthetic scene: its test views re-rendered with the edited scene spec."""

from __future__ import annotations

from pathlib import Path

from models.capture import Capture
from stages.synth.render import render_capture

from .spec import EditSpec, EditSpecError


def render_truth(synth: dict, spec: EditSpec, out_dir: Path, progress: bool = True) -> Capture:
    """Render the test views of ``synth`` with ``spec.ground_truth`` applied into the capture ``out_dir``.
    Only the test split is rendered, each view with the sampler seed it has in the full capture, so the
    pixels the edit does not reach are the capture's own, noise included."""
    if not spec.ground_truth:
        raise EditSpecError(f"edit {spec.name!r}: has no ground_truth (a list of synth edits) to render")
    try:
        return render_capture(synth, Path(out_dir), edits=list(spec.ground_truth), progress=progress,
                              scene_name=f"edit:{spec.name}", splits=("test",))
    except EditSpecError:
        raise
    except ValueError as e:
        raise EditSpecError(f"edit {spec.name!r} ground_truth: {e}") from None
