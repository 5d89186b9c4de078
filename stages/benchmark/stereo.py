"""How close mirror stereo puts what the mirrors show to where it truly is, per object of a synthetic scene.

Mirror stereo (models/reconstruction/mirror_stereo.py) places Gaussians along reflected rays at the depth its
plane sweep chooses. On a synthetic scene the truth is known: Mitsuba casts each match's reflected ray (from its
mirror point, along its reflected direction) into the scene's own geometry and names the object it hits first and
how far. The table gives, per object and per kind of match (matched by its own texture, or a flat pixel completed
from its matched neighbours; every match, or only those placed after the mirrors' vote), how many lie within 5 cm
and 15 cm of the true surface, and how many more than 15 cm in front of it (``near``: floaters in the room, which a
view looking at that space directly sees as haze) or behind it (``deep``: hidden behind the surface).

The sweep runs on the capture's init (what the trainer's warm-up starts from) in place of the warmed-up model the
trainer gives it at the end of the warm-up: the open mirror pixels (reflections that leave the scene) come out
nearly the same. At 128 x 96 a pixel of disparity is ~15-40 cm at the virtual distances of a room seen in a mirror
(5-7 m, baselines 1-2.5 m), so 15 cm is about what a match at the right surface reaches.

Measured (probe_mirror_21, the wall mirror's matches): with the share of other views counted over mirror PLANES
(51 in 20 views: a chrome cube's faces), 41 % of the own-texture matches lay within 15 cm, the ceiling's all ~3 m
too near; counted over views, 54 % (README, "Fifty-fourth session").
"""

from __future__ import annotations

import numpy as np

KINDS = (("own", "all"), ("own", "placed"), ("completed", "all"), ("completed", "placed"))


def true_hits(spec, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """``models.synth.mitsuba_scene.first_hits`` from 1 cm along each reflected ray: past the mirror itself (a mirror
    point from a depth buffer can lie a fraction of a mm behind it)."""
    from models.synth.mitsuba_scene import first_hits

    return first_hits(spec, origins, dirs, eps=1e-2)


def accuracy_table(t: np.ndarray, t_true: np.ndarray, names: list[str], own: np.ndarray, placed: np.ndarray,
                   near_cm: float = 5.0, far_cm: float = 15.0) -> dict:
    """Per kind of match (``KINDS``) and object: count, median signed error (m, estimate minus truth), and the
    fractions within ``near_cm`` / ``far_cm`` of the truth, more than ``far_cm`` in front of it (near) and behind
    it (deep). ``t``, ``t_true`` [N]: chosen and true distances along each match's reflected ray; ``own``,
    ``placed`` [N] bool. Objects: the names of ``names``, and "all"."""
    err = np.asarray(t, np.float64) - np.asarray(t_true, np.float64)
    names = np.asarray(names, dtype=object)
    a, b = near_cm / 100, far_cm / 100
    out: dict = {}
    for kind, subset in KINDS:
        sel = (own if kind == "own" else ~own) & (placed if subset == "placed" else np.ones(len(err), bool))
        rows = {}
        for name in ["all"] + sorted(set(names[sel])):
            m = sel & ((names == name) if name != "all" else True)
            e = err[m]
            if not len(e):
                continue
            finite = np.isfinite(e)
            rows[name] = {"n": int(m.sum()), "median_error_m": float(np.median(e[finite])) if finite.any() else None,
                          f"within_{near_cm:g}cm": float(np.mean(np.abs(e) <= a)),
                          f"within_{far_cm:g}cm": float(np.mean(np.abs(e) <= b)),
                          "near": float(np.mean(e < -b)), "deep": float(np.mean(e > b))}
        out[f"{kind}/{subset}"] = rows
    return out


def format_table(result: dict, near_cm: float = 5.0, far_cm: float = 15.0) -> str:
    lines = []
    for key, rows in result["accuracy"].items():
        lines.append(f"{key}: matches vs the true surface along their reflected ray")
        lines.append(f"  {'object':16s} {'n':>6s} {'median m':>9s} {f'<{near_cm:g}cm':>7s} {f'<{far_cm:g}cm':>7s} "
                     f"{'near':>6s} {'deep':>6s}")
        for name, r in rows.items():
            med = "–" if r["median_error_m"] is None else f"{r['median_error_m']:+.3f}"
            lines.append(f"  {name:16s} {r['n']:6d} {med:>9s} {r[f'within_{near_cm:g}cm']:7.2f} "
                         f"{r[f'within_{far_cm:g}cm']:7.2f} {r['near']:6.2f} {r['deep']:6.2f}")
    s = result["stereo"]
    lines.append(f"mirror stereo: {s['planes']} mirror planes in {s['planar_views']} views, {s['kept']} matches "
                 f"({s['completed']} completed), {s['inconsistent']} dropped by the vote, {s['added']} placed")
    return "\n".join(lines)


def run_stereo_benchmark(spec, capture, init, config, trace=None) -> dict:
    """Mirror stereo on ``capture`` with ``init`` (Gaussians) as the scene, as the trainer calls it with
    ``config`` (ReconstructConfig), checked against ``spec``'s geometry (module docstring). ``trace``: the
    open-reflection test (default: the config's tracer)."""
    import torch

    from models.reconstruction import Trainer
    from models.reconstruction.mirror_stereo import mirror_stereo_gaussians
    from models.tracer import Tracer

    trainer = Trainer(capture, init, config, Tracer(config.tracer))
    with torch.no_grad():
        scene = trainer.gaussians()
        _, stats = mirror_stereo_gaussians(trainer.rays, trace or trainer.backend.trace, scene,
                                           config.mirror_stereo_count, opacity=config.mirror_stereo_opacity,
                                           seed=config.seed, min_share=config.mirror_stereo_min_share,
                                           plane_slack=config.stereo_plane_slack)
    summary = {k: stats.get(k, 0) for k in ("planes", "planar_views", "pixels", "ignored", "kept", "completed",
                                            "inconsistent", "added", "edge")}
    m = stats.get("matches")
    if m is None or not len(m["t"]):
        return {"stereo": summary, "accuracy": {}}
    t_true, names = true_hits(spec, m["start"], m["dirs"])
    return {"stereo": summary, "accuracy": accuracy_table(m["t"], t_true, names, m["own"], m["placed"])}
