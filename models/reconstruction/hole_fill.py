"""Whether a trained model renders with the hole fill (``PathConfig.hole_fill``; Trainer._decide_hole_fill).

A closed room leaves no ray a way out: every pixel of every view ends on a surface. A model of one still lets
rays through where its surfaces hold too few Gaussians, and that happens exactly where the test views look and
the training views did not (a wall behind every camera, seen only in a mirror: 12-22 % of zoo_mirror_only's
test pixels keep a transmittance above 0.05, and showed the black behind it, a test view 6-15 % darker than the
truth). The fill divides what such a ray blended by its opacity. Where the training views themselves look past
the scene (an object on a black background: the ray ends on nothing, and black is the truth there), it would
turn every half-covered silhouette pixel into a solid one, so it is used only where the training views are
opaque: at most ``MAX_OPEN_SHARE`` of their pixels keep a transmittance above ``OPEN_TRANSMITTANCE`` in the
trained model. A window or a sky is no exception: the model learns it as Gaussians like any other surface.
"""

from __future__ import annotations

import torch

from models.gaussians import Gaussians
from models.pathtrace.paths import TraceFn

OPEN_TRANSMITTANCE = 0.5  # a training pixel whose ray keeps this much transmittance looks past the scene
MAX_OPEN_SHARE = 0.01  # a scene whose training views have at most this share of such pixels is closed
MAX_RAYS = 65536  # training pixels traced for the decision (an even stride over all of them)

HOLE_FILL_MODES = ("auto", "on", "off")


@torch.no_grad()
def open_share(trace_fn: TraceFn, origins: torch.Tensor, dirs: torch.Tensor, gaussians: Gaussians) -> float:
    """Share of the rays ``origins``, ``dirs`` ([R, 3] each) that keep a transmittance above
    ``OPEN_TRANSMITTANCE`` through ``gaussians`` (0 for no rays)."""
    if len(origins) == 0:
        return 0.0
    out = trace_fn(origins, dirs, gaussians)
    return float((out.transmittance.reshape(-1) > OPEN_TRANSMITTANCE).float().mean())


def strided(count: int, max_rays: int = MAX_RAYS) -> torch.Tensor:
    """[<= max_rays] int64: every k-th of ``count`` rows, k the smallest stride that keeps to ``max_rays``."""
    step = max(1, -(-count // max_rays))
    return torch.arange(0, count, step, dtype=torch.long)


def decide(mode: str, share: float | None) -> tuple[bool, str]:
    """(hole fill on, why) for the config's ``mode`` and the training views' measured open ``share`` (None:
    not measured, only with mode on / off)."""
    if mode not in HOLE_FILL_MODES:
        raise ValueError(f"hole_fill must be one of {HOLE_FILL_MODES}, got {mode!r}")
    if mode != "auto":
        return mode == "on", f"hole fill {mode} (reconstruct.hole_fill)"
    measured = (f"{share:.2%} of the training pixels keep a transmittance above {OPEN_TRANSMITTANCE} "
                f"(at most {MAX_OPEN_SHARE:.0%}: a closed scene)")
    if share <= MAX_OPEN_SHARE:
        return True, f"hole fill on in the renders: {measured}"
    return False, f"hole fill off (the training views look past the scene): {measured}"
