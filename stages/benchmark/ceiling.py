"""What a synthetic scene's test views allow at best: two ceilings on the score of any reconstruction.

1. **Noise** (``noise_*``): the test views rendered again by the scene's own renderer with another sampler seed (same
   spp, same denoising), scored against the ground truth as ``evaluate`` scores a render (tonemapped final at the
   view's peak). Two independent renders of equal noise variance differ by twice that variance, so an exact,
   noise-free render would score about 10 log10(2) = 3.01 dB above this (``noise_free_*``, an estimate under that
   assumption): the ground truth's own Monte Carlo noise caps every method there.
2. **Flat surfaces** (``flat_*``, with ``--flat OBJ,...``): the test views rendered with the same sampler seed as
   the ground truth (the noise cancels) but the named objects' textures replaced by their mean colour: what a
   reconstruction that is exact everywhere except those surfaces' texture scores. For surfaces no training view
   sees directly, whose texture only reflections carry (the wall behind the cameras), this says whether the
   texture matters to the score or only the colour does; ``--flat unseen`` takes every textured object no
   training pixel hits first (``unseen_objects``).

Measured (the zoo's captures, 128 x 96, 256 spp, `--flat unseen`): zoo_corridor noise 30.0 dB (a noise-free render
~33), its unseen start wall and door flat 47.2; zoo_spheres noise 37.2, its unseen front wall flat 29.8 (README).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from models.capture import Capture
from models.metrics import hdr
from models.metrics.image import psnr
from models.metrics.scoring import ground_truth
from models.synth.spec import SynthSpec
from models.synth.textures import make_texture

NOISE_TO_NOISE_DB = float(10 * np.log10(2))  # two independent renders differ by twice one render's noise variance


def flat_spec(spec: SynthSpec, names: list[str]) -> SynthSpec:
    """``spec`` with the named objects' textures replaced by their mean colour (an object without a texture keeps its
    colour). Raises ValueError naming an object the scene does not have."""
    objects = []
    for name in names:
        spec.object(name)  # raises with the scene's object names
    for obj in spec.objects:
        m = obj.material
        if obj.name in names and m.texture is not None:
            mean = make_texture(spec.textures[m.texture]).reshape(-1, 3).mean(0)
            obj = dataclasses.replace(obj, material=dataclasses.replace(m, texture=None,
                                                                        base_color=tuple(float(c) for c in mean)))
        objects.append(obj)
    return dataclasses.replace(spec, objects=tuple(objects))


def unseen_objects(spec: SynthSpec, cameras) -> list[str]:
    """The textured objects of ``spec`` that no pixel centre of ``cameras`` (the training views') hits first: what
    only reflections show the training views (Mitsuba's own ray casts on the scene's geometry)."""
    from models.synth.mitsuba_scene import first_hits

    dirs = [cam.ray_directions().reshape(-1, 3) for cam in cameras]
    origins = [np.broadcast_to(cam.origin, d.shape) for cam, d in zip(cameras, dirs)]
    _, names = first_hits(spec, np.concatenate(origins), np.concatenate(dirs))
    hits = set(names)
    return [o.name for o in spec.objects if o.material.texture is not None and o.name not in hits]


def score_views(truth: Capture, rendered: Capture) -> dict[str, float]:
    """Tonemapped final PSNR per test view of ``rendered`` against ``truth`` (mu-law at the truth view's peak, as
    ``evaluate``'s ``psnr_final_tonemapped``). Raises ValueError naming a view the truth lacks or whose size differs
    (a capture of another scene or resolution)."""
    views = {v.name: v for v in truth.split("test")}
    out = {}
    for v in rendered.split("test"):
        if v.name not in views:
            raise ValueError(f"rendered view {v.name!r} is not a test view of the ground truth")
        gt = ground_truth(views[v.name].buffers)["final"]
        pred = ground_truth(v.buffers)["final"]
        if gt.shape != pred.shape:
            raise ValueError(f"test view {v.name!r}: the ground truth is {gt.shape[1]} x {gt.shape[0]}, the scene "
                             f"renders {pred.shape[1]} x {pred.shape[0]} (a capture of another scene or resolution?)")
        top = hdr.peak(gt)
        out[v.name] = float(psnr(hdr.mu_law(pred, top), hdr.mu_law(gt, top)))
    return out


def run_ceiling(spec: SynthSpec, truth: Capture, flat: list[str] | None = None, seed_offset: int = 1,
                render=None) -> dict:
    """Both ceilings (module docstring) of the scene ``spec`` whose rendered ground truth is ``truth``.
    ``render(spec) -> Capture`` renders the test views (default: ``models.synth.render.render_spec``)."""
    if render is None:
        from models.synth.render import render_spec

        def render(s):
            return render_spec(s, progress=False, splits=("test",))
    if not truth.split("test"):
        raise ValueError("the ground truth has no test views")
    result: dict = {"spp": spec.spp, "seed": spec.seed, "noise_seed": spec.seed + seed_offset}
    noise = score_views(truth, render(dataclasses.replace(spec, seed=spec.seed + seed_offset)))
    result["noise_views"] = noise
    result["noise"] = float(np.mean(list(noise.values())))
    result["noise_free_estimate"] = result["noise"] + float(NOISE_TO_NOISE_DB)
    if flat:
        views = score_views(truth, render(flat_spec(spec, flat)))
        result.update(flat=list(flat), flat_views=views, flat_mean=float(np.mean(list(views.values()))))
    return result


def format_table(result: dict) -> str:
    names = sorted(result["noise_views"])
    rows = [("another sampler seed (noise)", result["noise_views"], result["noise"])]
    if "flat" in result:
        rows.append((f"flat: {', '.join(result['flat'])}", result["flat_views"], result["flat_mean"]))
    width = max(len(r[0]) for r in rows)
    lines = [f"{'ceiling (final, tonemapped dB)':{width}}  " + "  ".join(f"{n:>8}" for n in names) + "      mean"]
    for label, views, mean in rows:
        lines.append(f"{label:{width}}  " + "  ".join(f"{views[n]:8.2f}" for n in names) + f"  {mean:8.2f}")
    lines.append(f"a noise-free exact render: about {result['noise_free_estimate']:.2f} dB (noise + "
                 f"{NOISE_TO_NOISE_DB:.2f}: two independent renders differ by twice one's noise variance)")
    return "\n".join(lines)
