"""The speed / accuracy sweep's report (``python -m stages.report sweep <sweep.json>``): Pareto plots of time
against PSNR per layer, the table of points and the recommended settings, from the JSON the benchmark stage
writes (``python -m stages.benchmark sweep``)."""

from __future__ import annotations

from .figures import pareto_plot
from .html import esc, page, table


def sweep_report(result: dict, title: str) -> str:
    """HTML: the Pareto plots (time vs PSNR per layer), the table, the recommended settings."""
    parts = [f"<h1>{esc(title)}</h1>", "<p class=\"note\">Each training point retrains the scene with one knob "
             "changed from the base schedule; each render point re-renders the base model. Dashed: the Pareto "
             "front (no other point both faster and better). Test views scored: "
             f"{result['test_views']}; device: {esc(result['device'])}.</p>"]
    for group, cost in (("training", "train_s"), ("render", "render_s_per_view")):
        pts = [p for p in result["points"] if p["group"] == group]
        if pts:
            uri = pareto_plot(pts, cost, ["psnr_diffuse", "psnr_specular", "psnr_final"])
            parts.append(f"<h2>{group}: {cost} vs PSNR</h2><img class=\"plot\" src=\"{uri}\" alt=\"{group} pareto\">")
    parts.append("<h2>Points</h2>" + table(
        ["point", "group", "train s", "render s/view", "Gaussians", "PSNR diffuse", "PSNR specular", "PSNR final"],
        [[p["name"], p["group"], p.get("train_s"), p["render_s_per_view"], p["gaussians"], p["psnr_diffuse"],
          p["psnr_specular"], p["psnr_final"]] for p in result["points"]], left=2))
    parts.append("<h2>Recommended settings</h2>" + table(
        ["group", "role", "point", "seconds", "PSNR final"],
        [[r["group"], r["role"], r["name"], r.get("train_s", r.get("render_s_per_view")), r["psnr_final"]]
         for r in result["recommended"]], left=3))
    return page(title, "\n".join(parts))
