"""Pictures for the HTML reports: images as PNG data URIs, error maps, training curves, the Pareto plot.

Everything is embedded in the HTML (data URIs) so a report is one self-contained file that can be mailed
or copied off a remote machine.
"""

from __future__ import annotations

import base64
import io

import numpy as np

from models.metrics.pareto import pareto_front
from models.rendering.images import to_png


def png_uri(image: np.ndarray) -> str:
    """uint8 [H, W, 3] (or float [0, 1]) -> ``data:image/png;base64,...``."""
    import imageio.v3 as iio

    if image.dtype != np.uint8:
        image = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    return "data:image/png;base64," + base64.b64encode(iio.imwrite("<bytes>", image, extension=".png")).decode()


def layer_uri(layer: str, arr: np.ndarray) -> str:
    """A float buffer shown the way the render stage's PNGs show it (colour layers: clamp + sRGB)."""
    return png_uri(to_png(layer, arr))


def error_map(pred: np.ndarray, target: np.ndarray, vmax: float = 0.25) -> np.ndarray:
    """uint8 [H, W, 3]: mean absolute error over channels (linear, clamped to [0, 1]) through the magma
    colour map; black = exact, bright yellow = ``vmax`` or more."""
    from matplotlib import colormaps

    err = np.abs(np.clip(pred, 0, 1) - np.clip(target, 0, 1)).mean(axis=-1)
    rgb = colormaps["magma"](np.clip(err / vmax, 0, 1))[..., :3]
    return (rgb * 255 + 0.5).astype(np.uint8)


def _figure_uri(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def training_curves(rows: list[dict], warmup: int | None = None) -> str | None:
    """Loss, PSNR (diffuse / specular on the training batch) and Gaussian count against the step, as one
    PNG data URI; None without rows."""
    if not rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    step = np.array([r["step"] for r in rows])
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.2))
    axes[0].semilogy(step, [r["loss"] for r in rows], color="k", lw=1)
    axes[0].set_title("training loss")
    for layer, colour in (("diffuse", "tab:blue"), ("specular", "tab:orange"), ("final", "tab:green")):
        # solid: tonemapped (mu-law at the training peak, the headline); dotted: linear at peak 1 (logs before
        # the tonemapped scores have only these)
        for key, style, label in ((f"psnr_{layer}_tonemapped", "-", layer), (f"psnr_{layer}", ":", f"{layer} linear")):
            values = [(s, r[key]) for s, r in zip(step, rows) if r.get(key) is not None]
            if values:
                s, v = zip(*values)
                axes[1].plot(s, v, color=colour, lw=1, ls=style, label=label)
    axes[1].set_title("training-batch PSNR (dB)")
    axes[1].legend(fontsize=8)
    axes[2].plot(step, [r["gaussians"] for r in rows], color="tab:purple", lw=1)
    axes[2].set_title("Gaussians")
    for ax in axes:
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
        if warmup:
            ax.axvline(warmup, color="grey", ls="--", lw=0.8)
    return _figure_uri(fig)


def pareto_plot(points: list[dict], x: str, ys: list[str], label: str = "name") -> str:
    """Time (``x``, log scale) against each quality column in ``ys`` (one panel each); points on the Pareto
    front (no other point both faster and better) are joined and labelled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(ys), figsize=(5 * len(ys), 4), squeeze=False)
    for ax, y in zip(axes[0], ys):
        pts = [p for p in points if p.get(x) is not None and p.get(y) is not None]
        groups = sorted({p.get("group", "") for p in pts})
        for g in groups:
            sel = [p for p in pts if p.get("group", "") == g]
            ax.scatter([p[x] for p in sel], [p[y] for p in sel], s=18, label=g or None)
        front = pareto_front(pts, x, y)
        ax.plot([p[x] for p in front], [p[y] for p in front], color="k", lw=1, ls="--")
        for p in front:
            ax.annotate(str(p[label]), (p[x], p[y]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel(x)
        ax.set_ylabel(y)
        ax.grid(alpha=0.3)
        if len(groups) > 1:
            ax.legend(fontsize=7)
    return _figure_uri(fig)
