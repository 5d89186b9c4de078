"""HTML reports: rendered by headless Chromium with every picture decoded; tables carry the measured numbers."""

import html
import json
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from models.metrics import pareto_front
from stages.report.figures import error_map
from tests.conftest import ROOT, snakemake


def chromium_dom(html_path):
    """The DOM after load, as headless Chromium (Debian package `chromium`, installed by `.ci/setup test`) builds it;
    the calling test skips without it."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("needs Chromium (Debian: apt-get install chromium; `bash .ci/setup test` does) for the DOM check")
    proc = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom", html_path.as_uri()],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def loaded_images(dom):
    m = re.search(r'data-images-loaded="(\d+)/(\d+)"', dom)
    assert m, "the report's load check did not run"
    return int(m.group(1)), int(m.group(2))


def test_scene_report_renders_its_images(tiny_demo):
    _, results, _, _ = tiny_demo
    report = results / "demo" / "report.html"
    dom = chromium_dom(report)
    ok, total = loaded_images(dom)
    # 2 test views x (3 colour layers + 4 G-buffer layers) x (truth, ours, error) + the training curves
    assert total >= 2 * 7 * 3 + 1 and ok == total
    metrics = json.loads((results / "demo" / "metrics.json").read_text())
    assert f"{metrics['mean']['psnr_final']:.2f}" in dom
    assert f"{metrics['gaussians']:,}" in dom or str(metrics["gaussians"]) in dom
    for decision in metrics["decisions"]:  # what the scene required / switched off
        assert html.escape(decision) in dom or decision in dom
    assert "LPIPS" in dom and "training curves" in dom


def test_batch_report_tables(tiny_demo, tmp_path):
    _, results, _, _ = tiny_demo
    other = tmp_path / "results" / "demo_copy"
    shutil.copytree(results / "demo", other, ignore=shutil.ignore_patterns("capture", "renders", "checkpoints"))
    out = tmp_path / "results" / "batch.html"
    proc = subprocess.run([sys.executable, "-m", "stages.report", "batch", str(results / "demo"), str(other),
                           "--out", str(out)], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr
    dom = chromium_dom(out)
    assert "Table 1" in dom and "Table 2" in dom and "demo_copy" in dom
    metrics = json.loads((results / "demo" / "metrics.json").read_text())["mean"]
    for layer in ("diffuse", "specular", "final"):
        assert dom.count(f"{metrics[f'psnr_{layer}']:.2f}") >= 2  # both columns of the two scenes
    assert 'href="demo_copy/report.html"' in dom  # relative link to the scene's own report
    # where the error is: the share of test pixels a training camera saw, and the final score on each part
    assert "Where the error is" in dom and f"{100 * metrics['seen_fraction']:.1f}" in dom
    assert f"{metrics['seen_psnr_final_tonemapped']:.2f}" in dom
    assert f"{metrics['psnr_final_tonemapped_true_specular']:.2f}" in dom  # which layer limits it
    assert f"{metrics['shiny_normal_angle_deg']:.1f} ({metrics['shiny_normal_angle_deg_p90']:.1f})" in dom
    # light where the truth has none: the share of the diffuse / specular error on the truth's dark pixels
    assert "specular error on dark pixels" in dom
    share, dark = (100 * metrics[f"dark_{k}_specular"] for k in ("error_share", "fraction"))
    assert f"{share:.0f} ({dark:.0f})" in dom


def test_batch_report_names_missing_scene(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "stages.report", "batch", str(tmp_path / "nowhere"), "--out",
                           str(tmp_path / "b.html")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 1
    assert f"no metrics.json in {tmp_path / 'nowhere'}" in proc.stderr


def test_named_batch_plans_batch_report(tmp_path):
    proc = snakemake(tmp_path, "-n", "--config", "batch=synthetic")
    assert proc.returncode == 0, proc.stderr
    assert "batch_report" in proc.stdout and "results/batch_synthetic.html" in proc.stdout
    for scene in ("demo", "mirror_book", "chromeballs"):
        assert f"results/{scene}/report.html" in proc.stdout
    bad = snakemake(tmp_path, "-n", "--config", "batch=nope")
    assert bad.returncode != 0
    line = next(x for x in (bad.stdout + bad.stderr).splitlines() if x.startswith("error: unknown batch 'nope'"))
    assert line.startswith("error: unknown batch 'nope'; known batches: ") and "synthetic" in line.split(": ")[-1]


def test_pareto_front_keeps_undominated_points():
    pts = [{"t": 1, "q": 20}, {"t": 2, "q": 19}, {"t": 2, "q": 25}, {"t": 4, "q": 25}, {"t": 8, "q": 30},
           {"t": 0.5, "q": 10}]
    front = pareto_front(pts, "t", "q")
    assert [(p["t"], p["q"]) for p in front] == [(0.5, 10), (1, 20), (2, 25), (8, 30)]


def test_error_map_scale():
    a = np.zeros((2, 2, 3), np.float32)
    b = a.copy()
    b[0, 0] = 0.25
    m = error_map(b, a, vmax=0.25)
    assert m.dtype == np.uint8 and m.shape == (2, 2, 3)
    assert m[1, 1].sum() < 20  # exact: black end of magma
    assert m[0, 0, 0] > 240 and m[0, 0, 1] > 200  # vmax: the bright (yellow) end


def test_batch_report_states_command_and_each_scenes_presets(tmp_path):
    """What Snakemake passes (rule batch_report): the command line and each scene's presets, shown per scene."""
    folders = []
    for name in ("a", "b", "c"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.json").write_text(json.dumps({"mean": {"psnr_final": 20.0}}))
        folders.append(str(tmp_path / name))
    out = tmp_path / "batch.html"
    proc = subprocess.run([sys.executable, "-m", "stages.report", "batch", *folders, "--out", str(out),
                           "--command", "snakemake --cores 2 --config batch=x preset=ci",
                           "--presets-json", json.dumps({"a": ["fast", "ci"], "b": []})],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr
    html = out.read_text()
    assert "Run with <code>snakemake --cores 2 --config batch=x preset=ci</code>" in html
    rows = {name: re.search(rf">{name}</td>.*?</tr>", html).group(0) for name in ("a", "b", "c")}
    assert rows["a"].endswith('<td class="l">fast, ci</td></tr>')
    assert rows["b"].endswith('<td class="l">none</td></tr>')
    assert rows["c"].endswith('<td class="l">–</td></tr>')  # not given: unknown, not "none"


def test_scene_report_header_without_command_gives_the_command_for_its_presets():
    from stages.report.scene import run_line

    assert run_line("demo", ["fast", "ci"], None) == ("Made with the presets fast, ci: <code>snakemake --cores 2 "
                                                      "--config scene=demo preset=fast,ci</code>.")
    assert run_line("demo", [], "snakemake -c2 --config scene=demo") == \
        "Run with <code>snakemake -c2 --config scene=demo</code> (presets: none)."


def test_batch_report_sets_a_photos_run_beside_its_exact_room(tmp_path):
    """A photos run scored against a rendered truth (metrics.json photos_path) gets a row beside the same room on
    exact buffers, with what limits it: pose errors and the network's buffer errors."""
    exact = {"mean": {"psnr_final_tonemapped": 25.0, "psnr_specular_tonemapped": 21.0, "psnr_diffuse_tonemapped": 24.0}}
    photos = {"mean": {"psnr_final_tonemapped": 18.5, "psnr_specular_tonemapped": 12.0, "psnr_diffuse_tonemapped": 17.0},
              "photos_path": {"truth_scene": "room", "similarity": {"scale": 0.4},
                              "poses": {"registered": 19, "photos": 20, "rotation_deg_mean": 0.125,
                                        "position_frac_mean": 0.0031},
                              "network": {"mean": {"diffuse_psnr_tonemapped": 14.5, "normal_angle_deg": 31.0,
                                                   "depth_relative_error_median": 0.25}}}}
    for name, m in (("room", exact), ("room_photos", photos)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.json").write_text(json.dumps(m))
    out = tmp_path / "batch.html"
    proc = subprocess.run([sys.executable, "-m", "stages.report", "batch", str(tmp_path / "room"),
                           str(tmp_path / "room_photos"), "--out", str(out)],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr
    html = out.read_text()
    row = re.search(r"<tr><td class=\"l\">room_photos</td>.*?</tr>", html.split("Photos path")[1]).group(0)
    cells = re.findall(r"<td[^>]*>(.*?)</td>", row)
    assert cells[:5] == ["room_photos", "room", "18.50 / 25.00", "12.00 / 21.00", "17.00 / 24.00"]
    assert cells[5] == "19/20" and cells[6] == "0.125 deg, 0.310%"
    assert cells[7:] == ["14.50", "–", "31.0", "0.250"]
    assert "Photos runs (room_photos) are NOT g.t. inputs" in html


def test_batch_report_lists_every_edit_with_its_gain_tonemapped_and_linear(tmp_path):
    """Each scene's edits (edits/<name>/metrics.json): the changed pixels' PSNR unedited and ours (tonemapped), the
    gain, the gain pooled over the views' changed pixels and the linear gain beside it, and the count of edits
    gaining >= 3 dB under each; an edit scored before the tonemapped (or pooled) keys existed shows a dash, not a
    number."""
    edits = {"room": {"move": {"changed_fraction": 0.05, "unedited_psnr_final_tonemapped": 20.0,
                               "edited_psnr_final_tonemapped": 24.5, "unedited_psnr_final": 30.0,
                               "edited_psnr_final": 31.0, "pooled_unedited_psnr_final_tonemapped": 21.0,
                               "pooled_edited_psnr_final_tonemapped": 23.5},
                      "paint": {"changed_fraction": 0.1, "unedited_psnr_final_tonemapped": 18.0,
                                "edited_psnr_final_tonemapped": 19.0, "unedited_psnr_final": 20.0,
                                "edited_psnr_final": 26.0}},
             "old": {"shift": {"changed_fraction": 0.2, "unedited_psnr_final": 10.0, "edited_psnr_final": 12.0}}}
    folders = []
    for scene, named in edits.items():
        (tmp_path / scene).mkdir()
        (tmp_path / scene / "metrics.json").write_text(json.dumps({"mean": {"psnr_final_tonemapped": 25.0}}))
        for name, changed in named.items():
            (tmp_path / scene / "edits" / name).mkdir(parents=True)
            (tmp_path / scene / "edits" / name / "metrics.json").write_text(json.dumps({"changed_region": changed}))
        folders.append(str(tmp_path / scene))
    out = tmp_path / "batch.html"
    proc = subprocess.run([sys.executable, "-m", "stages.report", "batch", *folders, "--out", str(out)],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr
    html = out.read_text().split("<h2>Edits")[1]
    cells = {m.group(1): re.findall(r"<td[^>]*>(.*?)</td>", m.group(0))
             for m in re.finditer(r"<tr><td class=\"l\">\w+</td><td class=\"l\">(\w+)</td>.*?</tr>", html)}
    assert cells["move"] == ["room", "move", "5.0", "20.00", "24.50", "+4.50", "+2.50", "+1.00"]
    assert cells["paint"] == ["room", "paint", "10.0", "18.00", "19.00", "+1.00", "–", "+6.00"]
    assert cells["shift"] == ["old", "shift", "20.0", "–", "–", "–", "–", "+2.00"]
    assert "1 of 3 edits gain at least 3 dB tonemapped (0 pooled, 1 linear)" in html
    assert '<td class="good">+4.50</td>' in html
    # an edit's metrics.json cut short (a run stopped while writing it): an error naming that file
    broken = tmp_path / "room" / "edits" / "move" / "metrics.json"
    broken.write_text('{"changed_region": {"changed_fr')
    proc = subprocess.run([sys.executable, "-m", "stages.report", "batch", *folders, "--out", str(out)],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 1 and f"error: {broken}: not JSON" in proc.stderr, proc.stderr
