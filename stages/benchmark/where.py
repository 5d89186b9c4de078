"""Where a synthetic scene's test-view error lies, by what each pixel sees: the object its camera ray meets first
and, where that object is a mirror-like conductor, the objects its mirror reflections meet next.

On a synthetic scene the truth is known: Mitsuba casts every test pixel's ray into the scene's own geometry and
names the object it hits; at a conductor of roughness below ``MIRROR_ROUGHNESS`` the ray is reflected about the
true normal and cast again, up to ``bounces`` times. Each pixel gets a path label ("metal_left>ceiling",
"ball_mid>metal_right>strip_b") and the table gives, per label, its share of the view's pixels and of its
tonemapped squared error (the headline's mu-law at the view's peak, as ``evaluate``), the PSNR on those pixels,
and the mean true and rendered luminance of the layer scored: a reflection that is too dark, a light that is
too dim, a wall seen only in a ball. The sessions before this one wrote such scripts by hand each time (README,
"Fifty-sixth session": zoo_corridor's strip light seen only in chrome balls, one pixel spanning 0.4 m of ceiling).
"""

from __future__ import annotations

import numpy as np

MIRROR_ROUGHNESS = 0.3  # the capture's own "mirror-like" (F0 > 0.3 with roughness below this): reflect there


def mirror_objects(spec) -> set[str]:
    """Names of the objects whose rays the walk reflects: conductors (and metallic principled materials) smoother
    than ``MIRROR_ROUGHNESS``."""
    out = set()
    for obj in spec.objects:
        m = obj.material
        if m.roughness < MIRROR_ROUGHNESS and (m.type == "conductor" or (m.type == "principled" and m.metallic >= 0.5)):
            out.add(obj.name)
    return out


def path_labels(spec, origins: np.ndarray, dirs: np.ndarray, bounces: int = 3, scene=None) -> list[str]:
    """Each ray's path label: the first object it meets ("none" past the scene), then, while that object is in
    ``mirror_objects``, the one its mirror reflection about the true normal meets, up to ``bounces`` reflections.
    ``scene``: the spec's Mitsuba scene when the caller already built it."""
    from models.synth.mitsuba_scene import load_scene, surface_hits

    if scene is None:
        scene, _ = load_scene(spec)
    mirrors = mirror_objects(spec)
    o = np.asarray(origins, np.float64)
    d = np.asarray(dirs, np.float64)
    t, names, n = surface_hits(spec, o, d, scene=scene)
    labels = np.array(names, dtype=object)
    live = np.nonzero(np.isin(labels, list(mirrors)) & np.isfinite(t))[0]
    for _ in range(bounces):
        if not len(live):
            break
        p = o[live] + d[live] * t[live, None]
        r = d[live] - 2.0 * (d[live] * n[live]).sum(1, keepdims=True) * n[live]
        t2, names2, n2 = surface_hits(spec, p, r, eps=1e-3, scene=scene)
        names2 = np.array(names2, dtype=object)
        labels[live] = labels[live] + ">" + names2
        o, d, t, n = o.copy(), d.copy(), t.copy(), n.copy()
        o[live], d[live], t[live], n[live] = p, r, t2, n2
        live = live[np.isin(names2, list(mirrors)) & np.isfinite(t2)]
    return list(labels)


def error_by_label(err: np.ndarray, labels, truth: np.ndarray, ours: np.ndarray) -> list[dict]:
    """Per label (largest error share first): pixels, share of the pixels and of ``err``'s sum [N] (squared
    error per pixel), PSNR over those pixels (a unit peak: ``err`` is in tonemapped units), and the mean of
    ``truth`` / ``ours`` [N] (a luminance)."""
    labels = np.asarray(labels, dtype=object)
    total = max(float(err.sum()), 1e-30)
    rows = []
    for name in sorted(set(labels.tolist())):
        k = labels == name
        mse = float(err[k].mean())
        rows.append({"path": name, "pixels": int(k.sum()), "pixel_share": float(k.mean()),
                     "error_share": float(err[k].sum() / total),
                     "psnr": float(-10.0 * np.log10(max(mse, 1e-30))),
                     "truth_mean": float(truth[k].mean()), "ours_mean": float(ours[k].mean())})
    return sorted(rows, key=lambda r: -r["error_share"])


def camera_rays(view) -> tuple[np.ndarray, np.ndarray]:
    """(origins [H*W, 3], unit directions [H*W, 3]) of a capture view's pixel centres."""
    d = np.asarray(view.camera.ray_directions(), np.float64).reshape(-1, 3)
    return np.tile(np.asarray(view.camera.origin, np.float64), (len(d), 1)), d


def run_where(spec, capture, renders_dir, metrics: dict, layer: str = "final", bounces: int = 3) -> dict:
    """``error_by_label`` of every test view of ``capture`` rendered in ``renders_dir`` (``<view>.exr``), the
    ``layer`` ('final', 'diffuse' or 'specular') scored as ``evaluate`` does (mu-law at the view's peak from ``metrics``)."""
    from models.capture.exr import read_exr_channels
    from models.metrics.hdr import mu_law
    from models.synth.mitsuba_scene import load_scene

    lum = np.array([0.2126, 0.7152, 0.0722])
    out = {"layer": layer, "bounces": bounces, "views": {}}
    scene, _ = load_scene(spec)
    for view in capture.split("test"):
        path = renders_dir / f"{view.name}.exr"
        if not path.exists():
            raise ValueError(f"{path}: no render of test view {view.name!r} (run the render stage first)")
        r = read_exr_channels(path)
        prefix = "" if layer == "final" else f"{layer}."
        ours = np.stack([r[f"{prefix}{c}"] for c in "RGB"], -1).reshape(-1, 3)
        b = view.buffers
        emission = b.get("emission", 0.0)  # evaluate's truths: final = diffuse + specular + emission, diffuse + emission
        truth = {"final": b["diffuse"] + b["specular"] + emission, "diffuse": b["diffuse"] + emission,
                 "specular": b["specular"]}[layer].reshape(-1, 3)
        row = metrics.get("views", {}).get(view.name, {})
        peak = float(row.get("peak", truth.max()))
        err = ((mu_law(ours, peak) - mu_law(truth, peak)) ** 2).mean(-1)
        labels = path_labels(spec, *camera_rays(view), bounces=bounces, scene=scene)
        out["views"][view.name] = {"psnr": float(-10.0 * np.log10(max(float(err.mean()), 1e-30))),
                                   "rows": error_by_label(err, labels, truth @ lum, ours @ lum)}
    return out


def format_table(result: dict, top: int = 8) -> str:
    """Per view, the ``top`` paths by error share."""
    lines = [f"where the {result['layer']} layer's tonemapped error lies, by path (up to {result['bounces']} mirror "
             "reflections; truth / ours: mean luminance)"]
    for name, v in result["views"].items():
        lines.append(f"{name}: PSNR {v['psnr']:.2f}")
        lines.append(f"  {'path':<56} {'pixels':>7} {'error':>7} {'PSNR':>6} {'truth':>8} {'ours':>8}")
        for r in v["rows"][:top]:
            lines.append(f"  {r['path'][-56:]:<56} {r['pixel_share']:>6.1%} {r['error_share']:>6.1%} {r['psnr']:>6.2f} "
                         f"{r['truth_mean']:>8.4f} {r['ours_mean']:>8.4f}")
    return "\n".join(lines)
