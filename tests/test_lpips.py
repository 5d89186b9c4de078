"""LPIPS (models/metrics/lpips.py) from local weight files: our forward against a plain float64 re-computation,
its basic properties, strict loading with errors naming the file and key, the real lin weights of the lpips wheel
(when unpacked at /tmp/lp), and the evaluate stage / report with evaluate.lpips set.

Weights here are random (He-scaled convolutions, non-negative lins like the real ones) written in torchvision's
and the lpips package's key layouts; nothing is downloaded."""

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from models.capture import write_capture
from models.capture.exr import write_exr_channels
from models.metrics import evaluate_renders
from models.metrics.lpips import MIN_SIZE, load_lpips, lpips_distance, lpips_images, lpips_layers
from models.metrics.scoring import LPIPS_OFF
from stages.evaluate.__main__ import main as evaluate_main
from tests.test_init import plane_capture

# torchvision AlexNet features: index -> (out, in, kernel)
CONVS = {0: (64, 3, 11), 3: (192, 64, 5), 6: (384, 192, 3), 8: (256, 384, 3), 10: (256, 256, 3)}
LIN_CHANNELS = (64, 192, 384, 256, 256)
WHEEL = Path("/tmp/lp/lpips-0.1.4-py3-none-any.whl")


def random_weights(folder: Path, seed: int = 0) -> tuple[Path, Path]:
    """alexnet.pth (torchvision keys, plus classifier keys that LPIPS ignores) and alex.pth (lpips keys)."""
    g = torch.Generator().manual_seed(seed)
    tv = {}
    for i, (co, ci, k) in CONVS.items():
        tv[f"features.{i}.weight"] = torch.randn(co, ci, k, k, generator=g) * (2 / (ci * k * k)) ** 0.5
        tv[f"features.{i}.bias"] = 0.1 * torch.randn(co, generator=g)
    tv["classifier.1.weight"] = torch.randn(8, 9216, generator=g)
    lin = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for i, c in enumerate(LIN_CHANNELS)}
    folder.mkdir(parents=True, exist_ok=True)
    torch.save(tv, folder / "alexnet.pth")
    torch.save(lin, folder / "alex.pth")
    return folder / "alexnet.pth", folder / "alex.pth"


def reference_lpips(a: torch.Tensor, b: torch.Tensor, tv: dict, lin: dict) -> float:
    """LPIPS v0.1 of [1, 3, H, W] images in [-1, 1], in float64, straight from the two state dicts."""
    shift = torch.tensor([-0.030, -0.088, -0.188], dtype=torch.float64).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450], dtype=torch.float64).view(1, 3, 1, 1)

    def conv(x, i, **kw):
        return F.relu(F.conv2d(x, tv[f"features.{i}.weight"].double(), tv[f"features.{i}.bias"].double(), **kw))

    def features(x):
        x = (x.double() - shift) / scale
        r1 = conv(x, 0, stride=4, padding=2)
        r2 = conv(F.max_pool2d(r1, 3, 2), 3, padding=2)
        r3 = conv(F.max_pool2d(r2, 3, 2), 6, padding=1)
        r4 = conv(r3, 8, padding=1)
        r5 = conv(r4, 10, padding=1)
        return [r1, r2, r3, r4, r5]

    total = 0.0
    for k, (fa, fb) in enumerate(zip(features(a), features(b))):
        na = fa / (torch.sqrt((fa ** 2).sum(1, keepdim=True)) + 1e-10)
        nb = fb / (torch.sqrt((fb ** 2).sum(1, keepdim=True)) + 1e-10)
        w = lin[f"lin{k}.model.1.weight"].double()[0, :, 0, 0]
        total += float(((na - nb) ** 2 * w[None, :, None, None]).sum(1).mean())
    return total


def images(seed=1, h=48, w=56, noise=0.1):
    """A smooth [h, w, 3] image in [0, 1] and a noisy copy."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    clean = np.stack([0.5 + 0.4 * np.sin(6 * x), 0.5 + 0.4 * np.cos(5 * y), 0.3 + 0.5 * x * y], -1)
    return clean, np.clip(clean + noise * rng.normal(size=clean.shape), 0, 1)


def nchw(img):
    return torch.from_numpy(img).permute(2, 0, 1)[None] * 2 - 1


# ---------------------------------------------------------------- (a) against a plain re-computation
def test_forward_matches_plain_float64_recomputation(tmp_path):
    backbone, lin = random_weights(tmp_path)
    weights = load_lpips(backbone, lin)
    tv, lw = torch.load(backbone, weights_only=True), torch.load(lin, weights_only=True)
    for seed, (h, w) in ((1, (48, 56)), (2, (MIN_SIZE, MIN_SIZE)), (3, (67, 45))):
        clean, noisy = images(seed, h, w)
        want = reference_lpips(nchw(clean), nchw(noisy), tv, lw)
        assert want > 0
        ours64 = float(lpips_distance(nchw(clean), nchw(noisy), weights.to(dtype=torch.float64))[0])
        assert ours64 == pytest.approx(want, rel=1e-12)
        # the float32 path evaluate uses ([0, 1] images); worst relative error seen 4.6e-7 (6 weight seeds x 4 sizes)
        assert lpips_images(clean, noisy, weights) == pytest.approx(want, rel=1e-5)
    layers = lpips_layers(nchw(clean), nchw(noisy), weights)
    assert layers.shape == (1, 5) and (layers > 0).all()


# ---------------------------------------------------------------- (b) properties
def test_zero_on_itself_symmetric_and_grows_with_noise(tmp_path):
    weights = load_lpips(*random_weights(tmp_path))
    clean, _ = images()
    assert lpips_images(clean, clean, weights) == 0.0
    rng = np.random.default_rng(5)
    n = rng.normal(size=clean.shape)
    scores = []
    for level in (0.01, 0.03, 0.1, 0.3):
        noisy = np.clip(clean + level * n, 0, 1)
        d = lpips_images(clean, noisy, weights)
        assert d == lpips_images(noisy, clean, weights)
        scores.append(d)
    assert all(a < b for a, b in zip(scores, scores[1:])), scores
    with pytest.raises(ValueError, match=f"at least {MIN_SIZE} x {MIN_SIZE} pixels, got 40 x 30"):
        lpips_images(clean[:30, :40], clean[:30, :40], weights)


# ---------------------------------------------------------------- (c) the real lin weights
def test_real_lin_weights_of_the_lpips_wheel_load(tmp_path):
    if not WHEEL.is_file():
        pytest.skip(f"needs the lpips wheel at {WHEEL} (pip download --no-deps lpips -d /tmp/lp)")
    real = tmp_path / "alex.pth"
    with zipfile.ZipFile(WHEEL) as z:
        real.write_bytes(z.read("lpips/weights/v0.1/alex.pth"))
    backbone, _ = random_weights(tmp_path / "random")
    weights = load_lpips(backbone, real)  # strict: every lin key and shape is there
    stored = torch.load(real, map_location="cpu", weights_only=True)  # saved from CUDA
    for i, w in enumerate(weights.lins):
        assert torch.equal(w, stored[f"lin{i}.model.1.weight"]) and (w >= 0).all()
    assert weights.lin_sha256 == hashlib.sha256(real.read_bytes()).hexdigest()[:12]
    clean, noisy = images()
    assert lpips_images(clean, noisy, weights) > 0


# ---------------------------------------------------------------- (d) bad files
def _resave(path, edit):
    sd = torch.load(path, weights_only=True)
    edit(sd)
    torch.save(sd, path)


@pytest.mark.parametrize("which, edit, error, words", [
    ("backbone", lambda sd: sd.pop("features.6.bias"), ValueError, ["missing key 'features.6.bias'"]),
    ("backbone", lambda sd: sd.update({"features.3.weight": torch.zeros(192, 64, 3, 3)}), ValueError,
     ["'features.3.weight' has shape (192, 64, 3, 3), expected (192, 64, 5, 5)"]),
    ("lin", lambda sd: sd.pop("lin4.model.1.weight"), ValueError, ["missing key 'lin4.model.1.weight'"]),
    ("lin", lambda sd: sd.update({"lin2.model.1.weight": torch.zeros(1, 100, 1, 1)}), ValueError,
     ["'lin2.model.1.weight' has shape (1, 100, 1, 1), expected (1, 384, 1, 1)"]),
    ("lin", None, FileNotFoundError, ["LPIPS weights file not found"]),
    ("backbone", "text", ValueError, ["not a torch state dict"]),
])
def test_bad_weight_files_name_the_file_and_key(tmp_path, which, edit, error, words):
    files = dict(zip(("backbone", "lin"), random_weights(tmp_path)))
    if edit is None:
        files[which].unlink()
    elif edit == "text":
        files[which].write_text("not a checkpoint\n")
    else:
        _resave(files[which], edit)
    with pytest.raises(error) as e:
        load_lpips(**files)
    for w in [str(files[which]), *words]:
        assert w in str(e.value), (w, str(e.value))


# ---------------------------------------------------------------- (e) evaluate and the report
def _scene(tmp_path):
    """plane capture large enough for AlexNet (48 x 40), written, and a render of its test view with noise."""
    cap = plane_capture(w=48, h=40)
    for v in cap.views:
        v.buffers["specular"] = 0.2 * v.buffers["diffuse"]
    test = cap.split("test")[0]
    d, s = test.buffers["diffuse"], test.buffers["specular"]
    noisy = np.clip(d + np.random.default_rng(0).normal(0, 0.05, d.shape), 0, None).astype(np.float32)
    channels = {c: (noisy + s)[..., i] for i, c in enumerate("RGB")}
    for layer, arr in (("diffuse", noisy), ("specular", s)):
        channels.update({f"{layer}.{c}": arr[..., i] for i, c in enumerate("RGB")})
    (tmp_path / "renders/test").mkdir(parents=True)
    write_exr_channels(tmp_path / "renders/test" / f"{test.name}.exr", channels)
    (tmp_path / "renders/stage.json").write_text("{}")
    return cap, write_capture(cap, tmp_path / "cap"), test.name


def test_evaluate_writes_lpips_and_which_weights(tmp_path, capsys):
    cap, cap_dir, view = _scene(tmp_path)
    backbone, lin = random_weights(tmp_path / "weights")
    out = tmp_path / "metrics.json"
    option = {"lpips": {"backbone": str(backbone), "lin": str(lin)}}
    rc = evaluate_main(["--capture", str(cap_dir), "--renders", str(tmp_path / "renders"), "--out", str(out),
                        "--config-json", json.dumps(option)])
    assert rc == 0, capsys.readouterr().err
    m = json.loads(out.read_text())
    row = m["views"][view]
    assert row["lpips_diffuse"] > 0 and row["lpips_final"] > 0
    assert row["lpips_specular"] == 0.0  # the render's specular layer is exact
    assert m["mean"]["lpips_final"] == row["lpips_final"]
    sha = {p: hashlib.sha256(p.read_bytes()).hexdigest()[:12] for p in (backbone, lin)}
    assert m["lpips"] == (f"AlexNet v0.1, backbone {backbone} (sha256 {sha[backbone]}), lin {lin} "
                          f"(sha256 {sha[lin]}), on clamped sRGB")
    assert "lpips_<layer>" in m["definitions"]
    # as evaluate_renders gives it, on the clamped sRGB images
    assert evaluate_renders(cap, tmp_path / "renders/test", lpips=load_lpips(backbone, lin))["views"][view] == row

    # the report: an LPIPS column (mean and per view) and the provenance line; the batch report's row
    from stages.report.batch import batch_report
    from stages.report.scene import metrics_tables

    html = metrics_tables(m)
    assert "LPIPS sRGB (lower is better)" in html and f"{row['lpips_final']:.4f}" in html
    assert f"sha256 {sha[lin]}" in html
    scene = tmp_path / "results" / "plane"
    scene.mkdir(parents=True)
    (scene / "metrics.json").write_text(out.read_text())
    batch = batch_report([scene], tmp_path / "results" / "batch.html")
    assert "LPIPS, sRGB (lower is better)" in batch and f"{row['lpips_final']:.4f}" in batch


def test_evaluate_without_lpips_says_how_to_turn_it_on(tmp_path, capsys):
    cap, cap_dir, view = _scene(tmp_path)
    m = evaluate_renders(cap, tmp_path / "renders/test")
    assert not any(k.startswith("lpips_") for k in m["mean"]) and m["lpips"] == LPIPS_OFF
    assert "evaluate.lpips" in LPIPS_OFF and "backbone" in LPIPS_OFF
    from stages.report.scene import metrics_tables

    assert "LPIPS sRGB" not in metrics_tables(m) and "evaluate.lpips" in metrics_tables(m)


@pytest.mark.parametrize("option, words", [
    ({"backbone": "MISSING", "lin": "x"}, ["LPIPS weights file not found: MISSING"]),
    ({"backbone": "x"}, ["evaluate.lpips must be {backbone: <path>, lin: <path>}"]),
    ("small", ["at least 31 x 31 pixels; test view 'v3' is 40 x 30", "evaluate.lpips"]),
])
def test_evaluate_stage_bad_lpips_option(tmp_path, capsys, option, words):
    _, cap_dir, _ = _scene(tmp_path)
    if option == "small":  # the weights are fine, the views too small (plane_capture's default 40 x 30)
        cap_dir = write_capture(plane_capture(), tmp_path / "small")
        option = dict(zip(("backbone", "lin"), map(str, random_weights(tmp_path / "weights"))))
    out = tmp_path / "metrics.json"
    rc = evaluate_main(["--capture", str(cap_dir), "--renders", str(tmp_path / "renders"), "--out", str(out),
                        "--config-json", json.dumps({"lpips": option})])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and err[-1].startswith("error: ")
    for w in words:
        assert w in err[-1]
    assert not out.exists()


def test_config_schema_takes_evaluate_lpips():
    from stages.config import ConfigError, load_config

    cfg = load_config("demo", overrides={"evaluate": {"lpips": {"backbone": "a.pth", "lin": "b.pth"}}})
    assert cfg["evaluate"]["lpips"] == {"backbone": "a.pth", "lin": "b.pth"}
    with pytest.raises(ConfigError, match="lin"):
        load_config("demo", overrides={"evaluate": {"lpips": {"backbone": "a.pth"}}})
