"""Per-scene HTML report: ground truth vs ours per layer, error maps, training curves, metrics, decisions."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np

from models.capture import read_capture, read_view_buffers
from models.capture.layers import GBUFFER as GBUFFER_LAYERS
from models.capture.layers import SCORED as COLOUR_LAYERS
from models.metrics import changed_region_gains, changed_region_pooled_gain, ground_truth

from .figures import error_map, layer_uri, png_uri, training_curves
from .html import esc, figure, fmt, hms, page, read_json, table

# error-map scale per layer (mean absolute error shown as full-bright)
ERROR_SCALE = {"final": 0.25, "diffuse": 0.25, "specular": 0.25, "normal": 0.5, "roughness": 0.25, "f0": 0.25}


def _json(path: Path) -> dict:
    return read_json(path, missing={})


def _jsonl(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def metrics_tables(metrics: dict) -> str:
    mean = metrics.get("mean", {})
    # (header, key with {layer}, digits): the headline (mu-law tonemapped) first, then linear at the stated peak,
    # then the LDR scores (blind above 1) for comparison with numbers measured on clamped images
    columns = [("PSNR tonemapped (dB)", "psnr_{}_tonemapped", 2), ("SSIM tonemapped", "ssim_{}_tonemapped", 3),
               ("PSNR linear (dB)", "psnr_{}", 2), ("view peak", "peak", 3), ("SSIM linear", "ssim_{}", 3),
               ("PSNR clamped (dB)", "psnr_{}_clamped", 2), ("PSNR sRGB (dB)", "psnr_{}_srgb", 2),
               ("SSIM sRGB", "ssim_{}_srgb", 3)]
    lpips = any(k.startswith("lpips_") for k in mean)  # evaluate.lpips was set
    if lpips:
        columns.append(("LPIPS sRGB (lower is better)", "lpips_{}", 4))
    out = table(["layer", *[c[0] for c in columns]],
                [[layer, *[fmt(mean.get(key.format(layer)), digits) for _, key, digits in columns]]
                 for layer in COLOUR_LAYERS])
    truth = metrics.get("ground_truth") or {"final": "diffuse + specular"}
    out += ("<p class=\"note\">Mean over the test views. Tonemapped (headline): mu-law, mu = 5000, of radiance "
            "divided by the view's ground-truth peak (PSNR-mu of HDR imaging), nothing clamped. Linear: no clamp, "
            "PSNR at that peak (max of the ground-truth layer; column <i>peak</i>, mean over views), SSIM with data "
            "range = peak. Clamped: radiance clamped to [0, 1], peak 1; sRGB: clamp, then the sRGB curve (as the "
            "PNGs): both ignore every error above 1. SSIM: " + esc(metrics.get("definitions", {}).get("ssim", "–"))
            + ". Ground truth: " + ", ".join(f"{esc(k)} = {esc(v)}" for k, v in truth.items())
            + f". LPIPS: {esc(metrics.get('lpips', 'not computed'))}.</p>")
    saturated = metrics.get("saturated") or []
    if saturated:
        out += ("<p><b>Saturated scores</b> (they no longer measure the error):</p><ul>" + "".join(
            f"<li>{esc(s['view'])} {esc(s['layer'])}: {esc('; '.join(s['reasons']))}</li>" for s in saturated)
            + "</ul>")
    regions = sorted({k.split("_psnr_")[0] for k in mean if "_psnr_" in k})
    if regions:
        kinds = [("tonemapped", "_tonemapped"), ("linear, the view's peak", ""), ("clamped, peak 1", "_clamped")]
        out += "<h3>Regions</h3>" + table(
            ["region", "pixels (mean per view)",
             *[f"PSNR {layer} {kind}" for kind, _ in kinds for layer in COLOUR_LAYERS]],
            [[r, fmt(mean.get(f"{r}_pixels"), 0),
              *[mean.get(f"{r}_psnr_{layer}{suffix}") for _, suffix in kinds for layer in COLOUR_LAYERS]]
             for r in regions])
    views = metrics.get("views", {})
    if views:
        keys = [("PSNR {} tonemapped", "psnr_{}_tonemapped"), ("PSNR {} linear", "psnr_{}")]
        keys += [("LPIPS {}", "lpips_{}")] if lpips else []
        out += "<h3>Per view</h3>" + table(
            ["view", *[head.format(layer) for head, _ in keys for layer in COLOUR_LAYERS]],
            [[name, *[fmt(row.get(key.format(layer)), 4 if key.startswith("lpips") else 2) for _, key in keys
                      for layer in COLOUR_LAYERS]] for name, row in views.items()])
    return out


def cost_table(metrics: dict) -> str:
    res = metrics.get("fps_resolution")
    rows = [
        ["training time", hms(metrics.get("train_time_s")) + f" ({fmt(metrics.get('train_time_s'), 0)} s)"],
        ["Gaussians", fmt(metrics.get("gaussians"))],
        ["peak memory, training (MiB RSS)", fmt(metrics.get("train_peak_rss_mib"), 0)],
        ["render FPS at 1 spp, full path" + (f" ({res[0]}x{res[1]})" if res else ""), fmt(metrics.get("fps_1spp"))],
        ["render FPS, primary segment only", fmt(metrics.get("fps_primary"))],
        ["render spp (test views, denoised)", fmt(metrics.get("render_spp"))],
    ]
    if metrics.get("train_peak_cuda_mib") is not None:
        rows.append(["peak GPU memory, training (MiB)", fmt(metrics["train_peak_cuda_mib"], 0)])
    seconds = metrics.get("render_seconds_per_view") or {}
    if seconds:
        rows.append(["render time per test view (s, mean)", fmt(float(np.mean(list(seconds.values()))))])
    return table(["", "value"], rows, left=2)


def what_ran(config: dict, scene_dir: Path) -> str:
    kind = config.get("kind", "synthetic")
    items = {
        "synthetic": "<code>synth</code>: rendered by Mitsuba 3 with exact buffers (no <code>poses</code>, "
                     "no <code>buffers</code>)",
        "photos": "<code>poses</code>: COLMAP poses from the photos",
        "capture": "capture given (no <code>synth</code>, no <code>poses</code>)",
    }
    lines = [items.get(kind, esc(kind))]
    init = _json(scene_dir / "init" / "stage.json")
    if init:
        summary = init.get("summary", {})
        source = summary.get("source", "depth + diffuse buffers")
        lines.append(f"<code>init</code>: {fmt(summary.get('gaussians'))} Gaussians from {esc(source)} "
                     f"({fmt(init.get('wall_time_s'), 1)} s)")
    model = _json(scene_dir / "model" / "stage.json")
    for d in model.get("decisions", []):
        lines.append(f"<code>reconstruct</code>: {esc(d)}")
    presets = ", ".join(config.get("presets", [])) or "none"
    lines.append(f"presets: {esc(presets)}; device: {esc(config.get('device', 'cpu'))}")
    return "<ul>" + "".join(f"<li>{x}</li>" for x in lines) + "</ul>"


def view_images(capture_dir: Path, renders: Path, max_views: int = 3) -> str:
    capture = read_capture(capture_dir, layers=["diffuse", "specular", "emission", "normal", "depth", "roughness",
                                                "f0"])
    blocks = []
    for view in capture.split("test")[:max_views]:
        exr = renders / "test" / f"{view.name}.exr"
        if not exr.is_file():
            continue
        pred = read_view_buffers(exr, view.camera.height, view.camera.width)
        pred["final"] = pred.pop("rgb")
        gt = dict(view.buffers)
        if "diffuse" in gt and "specular" in gt:
            gt.update(ground_truth(view.buffers))  # diffuse (+ emission), final = + specular, as scored
        cells = ["<div></div><div><b>ground truth</b></div><div><b>ours</b></div><div><b>|error|</b></div>"]
        for layer in (*COLOUR_LAYERS, *GBUFFER_LAYERS):
            if layer not in pred or layer not in gt:
                continue
            p, t = pred[layer], gt[layer]
            if layer == "depth":
                scale = float(t[t > 0].max()) if (t > 0).any() else 1.0
                p, t = p / scale, t / scale
                err = error_map(p, t, 0.1)
            else:
                err = error_map(p * 0.5 + 0.5, t * 0.5 + 0.5, ERROR_SCALE[layer] / 2) if layer == "normal" \
                    else error_map(p, t, ERROR_SCALE[layer])
            show = "roughness" if layer == "depth" else layer  # depth already normalised by the gt scale
            cells.append(f"<div><b>{layer}</b></div>"
                         f"<div>{figure(layer_uri(show, t), f'{view.name} {layer} ground truth')}</div>"
                         f"<div>{figure(layer_uri(show, p), f'{view.name} {layer} ours')}</div>"
                         f"<div>{figure(png_uri(err), f'{view.name} {layer} error')}</div>")
        blocks.append(f"<h3>{esc(view.name)}</h3><div class=\"grid\" style=\"grid-template-columns: 6em repeat(3, "
                      f"max-content)\">{''.join(cells)}</div>")
    if not blocks:
        return "<p>No test renders.</p>"
    return ("<p class=\"note\">Error maps: mean absolute error over channels (magma; bright = 0.25 for colour, F0 "
            "and roughness, 0.5 for normals, 10% of the depth range for depth).</p>" + "".join(blocks))


def edits_section(scene_dir: Path) -> str:
    """Each edit of <scene>/edits/<name>/ (the edit stage): PSNR of the edited render against the Mitsuba
    re-render of the same edit, next to the unedited model's PSNR, and before / after / ground truth of the
    first test view."""
    root = scene_dir / "edits"
    edit_dirs = sorted(p for p in root.glob("*") if (p / "metrics.json").is_file()) if root.is_dir() else []
    if not edit_dirs:
        return ""
    rows, blocks = [], []
    for d in edit_dirs:
        m = _json(d / "metrics.json")
        ed, un, ch = m.get("edited_vs_truth", {}), m.get("unedited_vs_truth", {}), m.get("changed_region", {})
        caught = ", ".join(str(op.get("selected")) if op.get("op") != "relight" else f"relit {op.get('relit')}"
                           for op in m.get("ops", []))
        gain, _ = changed_region_gains(ch)
        rows.append([d.name, caught, ed.get("psnr_final_tonemapped"), ed.get("psnr_diffuse_tonemapped"),
                     ed.get("psnr_specular_tonemapped"), un.get("psnr_final_tonemapped"),
                     fmt(100 * ch["changed_fraction"], 1) if "changed_fraction" in ch else "–",
                     ch.get("edited_psnr_final_tonemapped"), ch.get("unedited_psnr_final_tonemapped"), gain,
                     changed_region_pooled_gain(ch), ch.get("edited_psnr_final"), ch.get("unedited_psnr_final")])
        exrs = sorted((d / "renders" / "test").glob("*.exr"))
        if not exrs:
            continue
        view = exrs[0].stem
        cells = []
        for label, path, key in (("before", scene_dir / "renders" / "test" / f"{view}.exr", "rgb"),
                                 ("after (ours)", exrs[0], "rgb"),
                                 ("ground truth", d / "truth" / "images" / f"{view}.exr", None)):
            if not path.is_file():
                continue
            from models.capture.exr import read_exr_channels

            ch_ = read_exr_channels(path)
            if key == "rgb" or not all(f"diffuse.{c}" in ch_ for c in "RGB"):
                img = np.stack([ch_[c] for c in "RGB"], -1)
            else:  # ground truth final = diffuse + specular (lights seen directly are not reconstructed)
                img = np.stack([ch_[f"diffuse.{c}"] + ch_[f"specular.{c}"] for c in "RGB"], -1)
            cells.append(figure(layer_uri("final", img), f"{d.name} {view}: {label}"))
        blocks.append("<div>" + "".join(cells) + "</div>")
    head = ["edit", "Gaussians selected", "PSNR final vs edited truth", "diffuse", "specular",
            "unedited PSNR final", "changed pixels %", "changed: PSNR final ours", "changed: unedited",
            "changed: gain", "changed: gain, pooled over the views", "changed, linear: ours",
            "changed, linear: unedited"]
    return ("<h2>Edits</h2><p class=\"note\">Each edit is applied to the trained model and, for synthetic "
            "scenes, to the Mitsuba scene (re-rendered as ground truth). \"Changed\" pixels: where the two "
            "ground truths differ; there the unedited render is the do-nothing baseline, and the gain is ours "
            "minus it. PSNR tonemapped (mu-law at the view's peak, as the scene's scores) but for the last two "
            "columns: linear at the edited truth's peak, where a window's or a lamp's error outweighs the rest.</p>"
            + table(head, rows) + "".join(blocks))


def run_line(scene: str, presets: list[str], command: str | None) -> str:
    """The header's sentence on how the results were made: the workflow's own command line when given, else the
    command that makes them; and the presets either way."""
    named = ", ".join(presets) or "none"
    if command:
        return f"Run with <code>{esc(command)}</code> (presets: {esc(named)})."
    preset = f" preset={','.join(presets)}" if presets else ""
    return f"Made with the presets {esc(named)}: <code>snakemake --cores 2 --config scene={esc(scene)}{esc(preset)}</code>."


def photos_path_section(metrics: dict) -> str:
    """What limits a photos run scored against a rendered truth (metrics.json photos_path): the poses' errors
    and the network's buffer errors on the train views; empty for other scenes."""
    record = metrics.get("photos_path")
    if not record:
        return ""
    poses = record.get("poses", {})
    rows = [["photos registered", f"{poses.get('registered')} / {poses.get('photos')}"],
            ["rotation error, mean / max (deg)",
             f"{fmt(poses.get('rotation_deg_mean'), 3)} / {fmt(poses.get('rotation_deg_max'), 3)}"],
            ["position error, mean / max (% of the camera extent)",
             f"{fmt(100 * poses.get('position_frac_mean', float('nan')), 3)} / "
             f"{fmt(100 * poses.get('position_frac_max', float('nan')), 3)}"]]
    network = (record.get("network") or {}).get("mean") or {}
    rows += [[f"network: {k.replace('_', ' ')}", fmt(v, 3)] for k, v in network.items()]
    return ("<h2>Photos path: what limits it</h2><p class=\"note\">The test views are the rendered truth moved "
            "into the posed frame (similarity of the true and posed train cameras, scale "
            f"{fmt(record.get('similarity', {}).get('scale'), 4)}). Poses: errors after that alignment. Network: "
            "its buffers of the train views against the renderer's exact ones (PSNR tonemapped for diffuse / "
            "specular, mean angle for normals, median relative error for depth, mean absolute error for roughness "
            "/ F0).</p>" + table(["", "value"], rows))


def scene_report(scene_dir: Path, config: dict | None = None, command: str | None = None) -> str:
    """The HTML of one scene's report (results/<scene>/ holds capture, model, renders, metrics.json); ``command``:
    the command that ran the workflow (default: the snakemake command for the config's scene and presets)."""
    scene_dir = Path(scene_dir)
    config = config or {}
    name = config.get("scene", scene_dir.name)
    metrics = _json(scene_dir / "metrics.json")
    model = _json(scene_dir / "model" / "stage.json")
    parts = [f"<h1>{esc(name)}</h1>",
             f"<p class=\"note\">{run_line(name, config.get('presets', []), command)} "
             f"Results folder <code>{esc(scene_dir)}</code>.</p>"]
    parts.append("<h2>Metrics (test views)</h2>" + (metrics_tables(metrics) if metrics else "<p>No metrics.json.</p>"))
    parts.append("<h2>Cost</h2>" + cost_table(metrics))
    parts.append("<h2>What the scene required</h2>" + what_ran(config, scene_dir))
    photos = photos_path_section(metrics)
    if photos:
        parts.append(photos)
    # a photos run scored against a rendered truth (photos_of) has its test views in capture_eval
    truth = scene_dir / "capture_eval" if (scene_dir / "capture_eval").is_dir() else scene_dir / "capture"
    parts.append("<h2>Ground truth vs ours</h2>" + view_images(truth, scene_dir / "renders"))
    curves = training_curves(_jsonl(scene_dir / "model" / "train_log.jsonl"),
                             warmup=(model.get("config") or {}).get("warmup"))
    if curves:
        parts.append("<h2>Training curves</h2><p class=\"note\">Dashed: end of the primary-only warm-up.</p>"
                     f"<img class=\"plot\" src=\"{curves}\" alt=\"training curves\">")
    gif = scene_dir / "renders" / "path" / "path.gif"
    if gif.is_file():
        uri = "data:image/gif;base64," + base64.b64encode(gif.read_bytes()).decode()
        parts.append(f"<h2>Novel camera path</h2>{figure(uri, 'final, novel path')}")
    parts.append(edits_section(scene_dir))
    return page(f"{name}: report", "\n".join(parts))
