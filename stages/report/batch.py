"""Batch report across scenes, laid out like the paper's Table 1 (PSNR diffuse / specular / final per scene)
and Table 2 (training times), plus the cost columns of its supplemental (Gaussians, FPS, memory)."""

from __future__ import annotations

import os
from pathlib import Path

from models.metrics.edits import changed_region_gains, changed_region_pooled_gain

from .html import esc, fmt, hms, page, read_json

# The paper's own numbers (Table 1, "Ours (g.t. inputs)", and Table 2) on ITS scenes, for orientation only:
# different scenes, resolutions and a GPU schedule, so not comparable cell by cell.
PAPER_TABLE1 = {"Shiny Kitchen": (33.20, 24.30, 26.96), "Shiny Livingroom": (29.68, 26.46, 26.96),
                "Shiny Office": (31.74, 24.48, 27.54)}
PAPER_TABLE2 = {"Shiny Kitchen": "0:23:16", "Shiny Livingroom": "0:20:48", "Shiny Office": "0:24:13"}


def _grouped_table(scenes: list[str], rows: list[tuple[str, list]]) -> str:
    head1 = "<tr><th class=\"l\" rowspan=\"2\">method</th>" + "".join(
        f"<th colspan=\"3\">{esc(s)}</th>" for s in scenes) + "</tr>"
    head2 = "<tr>" + "<th>Diffuse</th><th>Spec.</th><th>Final</th>" * len(scenes) + "</tr>"
    body = "".join(f"<tr><td class=\"l\">{esc(label)}</td>" + "".join(f"<td>{fmt(v)}</td>" for v in values) + "</tr>"
                   for label, values in rows)
    return f"<table>{head1}{head2}{body}</table>"


def _presets_cell(presets: list[str] | None) -> str:
    """A scene's presets; "–" when not known (a batch report made by hand without --presets-json)."""
    return "–" if presets is None else esc(", ".join(presets) or "none")


def _photos_path_table(metrics: dict[str, dict]) -> str:
    """Photos runs scored against a rendered truth (metrics.json photos_path) beside the same room trained on
    exact buffers when the batch has it: the headline scores and what limits the photos run."""
    photos = [n for n in metrics if metrics[n].get("photos_path")]
    if not photos:
        return ""
    rows = []
    for n in photos:
        m, rec = metrics[n], metrics[n]["photos_path"]
        poses, net = rec.get("poses", {}), (rec.get("network") or {}).get("mean") or {}
        truth = rec.get("truth_scene")
        exact = metrics.get(truth, {}).get("mean", {}) if truth else {}
        cells = [esc(n), esc(truth or "–"),
                 *(f"{fmt(m.get('mean', {}).get(f'psnr_{layer}_tonemapped'))} / "
                   f"{fmt(exact.get(f'psnr_{layer}_tonemapped'))}" for layer in ("final", "specular", "diffuse")),
                 f"{poses.get('registered')}/{poses.get('photos')}",
                 f"{fmt(poses.get('rotation_deg_mean'), 3)} deg, {fmt(100 * poses.get('position_frac_mean', float('nan')), 3)}%",
                 fmt(net.get("diffuse_psnr_tonemapped")), fmt(net.get("specular_psnr_tonemapped")),
                 fmt(net.get("normal_angle_deg"), 1), fmt(net.get("depth_relative_error_median"), 3)]
        left = ' class="l"'
        rows.append("<tr>" + "".join(f"<td{left if i < 2 else ''}>{c}</td>" for i, c in enumerate(cells)) + "</tr>")
    head = ("<tr><th class=\"l\">photos run</th><th class=\"l\">same room, exact buffers</th><th>final (photos / "
            "exact)</th><th>specular</th><th>diffuse</th><th>registered</th><th>pose error (rot., pos. % extent)"
            "</th><th>net diffuse</th><th>net specular</th><th>net normal (deg)</th><th>net depth (rel.)</th></tr>")
    return ("<h2>Photos path: photos only vs exact buffers</h2><p class=\"note\">Tonemapped PSNR (dB) of the test "
            "views; a photos run's test views are the exact room's, moved into its posed frame. What limits it: "
            "pose errors after a similarity alignment of the train cameras; the network's buffers of the train "
            "views against the exact ones (PSNR tonemapped, mean normal angle, median relative depth error); the "
            "rest is the reconstruction.</p><table>" + head + "".join(rows) + "</table>")


def _seen_table(metrics: dict[str, dict]) -> str:
    """Per scene, where the test views' error is: on pixels a training camera sees directly or not
    (metrics.json seen_fraction, <seen|unseen>_psnr_final_tonemapped, unseen_error_share_final), and the final
    score with the true diffuse / specular layer in place of ours (which layer limits it), the normals' angle
    error on metal / mirror pixels, and the diffuse / specular error on pixels where that layer of the truth is dark
    (dark_error_share_<layer>, dark_fraction_<layer>)."""
    keys = {"seen_fraction", "psnr_final_tonemapped_true_diffuse"}
    names = [n for n in metrics if keys & set(metrics[n].get("mean", {}))]
    if not names:
        return ""
    def pct(m: dict, key: str, digits: int) -> str:
        return fmt(100 * m[key], digits) if key in m else "–"

    rows = []
    for n in names:
        m = metrics[n]["mean"]
        rows.append(f"<tr><td class=\"l\">{esc(n)}</td><td>{pct(m, 'seen_fraction', 1)}</td>"
                    f"<td>{fmt(m.get('psnr_final_tonemapped'))}</td><td>{fmt(m.get('seen_psnr_final_tonemapped'))}</td>"
                    f"<td>{fmt(m.get('unseen_psnr_final_tonemapped'))}</td>"
                    f"<td>{pct(m, 'unseen_error_share_final', 0)}</td>"
                    f"<td>{fmt(m.get('psnr_final_tonemapped_true_diffuse'))}</td>"
                    f"<td>{fmt(m.get('psnr_final_tonemapped_true_specular'))}</td>"
                    f"<td>{fmt(m.get('shiny_normal_angle_deg'), 1)} ({fmt(m.get('shiny_normal_angle_deg_p90'), 1)})"
                    f"</td><td>{pct(m, 'dark_error_share_diffuse', 0)} ({pct(m, 'dark_fraction_diffuse', 0)})</td>"
                    f"<td>{pct(m, 'dark_error_share_specular', 0)} ({pct(m, 'dark_fraction_specular', 0)})</td></tr>")
    return ("<h2>Where the error is: what the training cameras saw</h2><p class=\"note\">Test-view pixels whose "
            "ground-truth surface a training camera sees directly (its depth buffer has that surface there) vs the "
            "rest, which a model learns only through reflections or not at all. Final, tonemapped PSNR (dB), means "
            "over the test views; a low 'seen' column is the reconstruction's own error. The next two columns: "
            "the final score with the ground truth's diffuse / specular layer in place of ours (the layer whose "
            "truth lifts it most is the one that limits the scene). Normals on metal / mirror pixels (ground-truth "
            "F0 > 0.3): the angle to the true normal in degrees, each view's median (90th percentile) averaged over "
            "the test views: "
            "a reflection turns by twice it. Light where there is none: the share of the diffuse / specular "
            "layer's tonemapped error on pixels where that layer of the truth is dark (the diffuse of metal, the "
            "specular of matte surfaces; their share of the pixels in brackets).</p><table><tr>"
            "<th class=\"l\">scene</th>"
            "<th>seen pixels (%)</th><th>final</th><th>final, seen</th><th>final, unseen</th>"
            "<th>unseen share of the error (%)</th><th>final with true diffuse</th><th>final with true specular</th>"
            "<th>shiny normals (deg)</th><th>diffuse error on dark pixels (%)</th>"
            "<th>specular error on dark pixels (%)</th></tr>" + "".join(rows) + "</table>")


EDIT_GAIN_DB = 3.0  # the gain over doing nothing an edit is counted at (the scene zoo's bar, issue #23)


def _edits_table(scene_dirs: list[Path]) -> str:
    """Every scene's edits (<scene>/edits/<name>/metrics.json, the edit stage's): on the pixels the edit changed,
    the unedited render's and ours against the edited truth, tonemapped (the headline), the gain, and the linear
    gain beside it; a line counting the edits that gain at least EDIT_GAIN_DB. Empty without edits."""
    rows, counted, tonemapped_ok, linear_ok, pooled_ok = [], 0, 0, 0, 0
    for d in scene_dirs:
        for f in sorted((d / "edits").glob("*/metrics.json")) if (d / "edits").is_dir() else []:
            ch = read_json(f).get("changed_region", {})
            gain, linear = changed_region_gains(ch)
            counted += 1
            tonemapped_ok += gain is not None and gain >= EDIT_GAIN_DB
            linear_ok += linear is not None and linear >= EDIT_GAIN_DB
            pooled = changed_region_pooled_gain(ch)
            pooled_ok += pooled is not None and pooled >= EDIT_GAIN_DB
            changed = fmt(100 * ch["changed_fraction"], 1) if "changed_fraction" in ch else "–"
            mark = "" if gain is None or gain < EDIT_GAIN_DB else " class=\"good\""
            rows.append(f"<tr><td class=\"l\">{esc(d.name)}</td><td class=\"l\">{esc(f.parent.name)}</td>"
                        f"<td>{changed}</td><td>{fmt(ch.get('unedited_psnr_final_tonemapped'))}</td>"
                        f"<td>{fmt(ch.get('edited_psnr_final_tonemapped'))}</td>"
                        f"<td{mark}>{'–' if gain is None else f'{gain:+.2f}'}</td>"
                        f"<td>{'–' if pooled is None else f'{pooled:+.2f}'}</td>"
                        f"<td>{'–' if linear is None else f'{linear:+.2f}'}</td></tr>")
    if not rows:
        return ""
    return ("<h2>Edits: the changed pixels against the edited truth</h2><p class=\"note\">Each edit applied to the "
            "trained model, scored on the pixels where the edited ground truth differs from the unedited one: the "
            "unedited render (doing nothing) and ours, final PSNR tonemapped (as Table 1), the gain, and the gain "
            "linear at the edited truth's peak (ruled by the brightest changed pixels: a window, a lamp, a "
            "highlight). The gain is the mean of the views' (each view weighing the same, however few of its "
            "pixels changed); pooled: one PSNR over every view's changed pixels together, each pixel weighing the "
            f"same. {tonemapped_ok} of {counted} edits gain at least {EDIT_GAIN_DB:g} dB tonemapped "
            f"({pooled_ok} pooled, {linear_ok} linear).</p><table><tr><th class=\"l\">scene</th>"
            "<th class=\"l\">edit</th><th>changed pixels (%)</th><th>unedited</th><th>ours</th><th>gain</th>"
            "<th>gain, pooled</th><th>gain, linear</th></tr>"
            + "".join(rows) + "</table>")


def batch_report(scene_dirs: list[Path], out: Path, title: str = "batch report", command: str | None = None,
                 presets: dict[str, list[str]] | None = None) -> str:
    """HTML of the batch report; ``out`` is where it will be written (links to scene reports are relative);
    ``command``: the command that ran the workflow; ``presets``: scene name -> the presets it ran with."""
    presets = presets or {}
    scene_dirs = [Path(d) for d in scene_dirs]
    metrics = {d.name: read_json(d / "metrics.json", missing={})
               for d in scene_dirs}
    names = list(metrics)
    def row(key: str) -> list:
        return [metrics[n].get("mean", {}).get(key.format(layer)) for n in names
                for layer in ("diffuse", "specular", "final")]

    saturated = [n for n in names if metrics[n].get("saturated")]
    lpips = [n for n in names if any(k.startswith("lpips_") for k in metrics[n].get("mean", {}))]
    lpips_note = (("LPIPS (" + "; ".join(f"{esc(n)}: {esc(metrics[n].get('lpips', '–'))}" for n in lpips) + ").")
                  if lpips else "LPIPS is not computed: it needs local weight files (<code>evaluate.lpips</code>, "
                  "see a scene report).")
    parts = [f"<h1>{esc(title)}</h1>",
             (f"<p class=\"note\">Run with <code>{esc(command)}</code>.</p>" if command else ""),
             "<h2>Table 1: disentanglement (PSNR, dB, test views)</h2>",
             _grouped_table(names, [("Ours (g.t. inputs), tonemapped", row("psnr_{}_tonemapped")),
                                    ("Ours (g.t. inputs), linear", row("psnr_{}")),
                                    ("Ours (g.t. inputs), sRGB (clamped)", row("psnr_{}_srgb"))]
                            + ([("LPIPS, sRGB (lower is better)", [fmt(v, 4) for v in row("lpips_{}")])]
                               if lpips else [])),
             "<p class=\"note\">Tonemapped (headline): mu-law (mu = 5000) of radiance / the view's peak (the "
             "ground-truth final image's maximum, the same for every layer: <code>peak</code> in each metrics.json), no "
             "clamp; linear: no clamp, PSNR at that peak; sRGB: clamp to [0, 1] + sRGB curve, as the PNGs (blind above 1). Ground-truth final = "
             "diffuse + specular + emission, diffuse = diffuse + emission, where a capture has emission. Our scenes "
             "are rendered by the <code>synth</code> stage with exact buffers (the paper's \"g.t. inputs\" setting). "
             + lpips_note
             + (f" Photos runs ({esc(', '.join(n for n in names if metrics[n].get('photos_path')))}) are NOT g.t. "
                "inputs: COLMAP poses and network buffers from 8-bit photos (see the photos-path table below)."
                if any(metrics[n].get("photos_path") for n in names) else "")
             + (f" <b>Saturated scores</b> (see the scene reports): {esc(', '.join(saturated))}." if saturated else "")
             + "</p>",
             "<h3>For orientation: the paper's Table 1 (its scenes, GPU schedule)</h3>",
             _grouped_table(list(PAPER_TABLE1), [("Ours (g.t. inputs), paper", [v for t in PAPER_TABLE1.values()
                                                                                   for v in t])])]
    rows = []
    for d in scene_dirs:
        m = metrics[d.name]
        rel = os.path.relpath(d / "report.html", Path(out).parent)
        link = f"<a href=\"{esc(rel)}\">{esc(d.name)}</a>" if (d / "report.html").is_file() else esc(d.name)
        res = m.get("fps_resolution")
        rows.append(f"<tr><td class=\"l\">{link}</td><td>{hms(m.get('train_time_s'))}</td>"
                    f"<td>{fmt(m.get('gaussians'))}</td><td>{fmt(m.get('fps_1spp'))}"
                    f"{' @ %dx%d' % tuple(res) if res else ''}</td><td>{fmt(m.get('fps_primary'))}</td>"
                    f"<td>{fmt(m.get('train_peak_rss_mib'), 0)}</td><td>{fmt(m.get('render_spp'))}</td>"
                    f"<td class=\"l\">{_presets_cell(presets.get(d.name))}</td></tr>")
    parts += ["<h2>Table 2: training time and cost</h2>",
              "<table><tr><th class=\"l\">scene</th><th>training (h:mm:ss)</th><th>Gaussians</th>"
              "<th>FPS 1 spp</th><th>FPS primary</th><th>peak RSS (MiB)</th><th>render spp</th>"
              "<th class=\"l\">presets</th></tr>"
              + "".join(rows) + "</table>",
              "<p class=\"note\">Paper, Table 2 (its scenes, one desktop GPU): "
              + ", ".join(f"{esc(k)} {v}" for k, v in PAPER_TABLE2.items()) + ".</p>"]
    parts.append(_seen_table(metrics))
    parts.append(_edits_table(scene_dirs))
    parts.append(_photos_path_table(metrics))
    decisions = "".join(
        f"<li><b>{esc(n)}</b>: {esc('; '.join(metrics[n].get('decisions', [])) or 'none recorded')}</li>"
        for n in names)
    parts.append(f"<h2>What each scene required</h2><ul>{decisions}</ul>")
    return page(title, "\n".join(parts))
