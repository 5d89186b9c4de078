"""evaluate: per-layer metrics against ground truth (emission included), HDR-safe (a capture x 1e4 scores as at x 1,
clamped scores flagged as saturated), and region scores from world boxes."""

import numpy as np
import pytest

from models.capture.exr import write_exr_channels
from models.metrics import evaluate_renders, psnr, ssim
from tests.test_init import plane_capture


def test_metrics_basics():
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (16, 16, 3))
    assert ssim(x, x) == 1.0 and psnr(x, x) > 150
    assert abs(psnr(x, x + 0.1) - 20.0) < 1e-9  # MSE 0.01
    assert ssim(x, 1 - x) < 0.1


def test_regions_score_only_their_pixels(tmp_path):
    cap = plane_capture()
    for v in cap.views:
        v.buffers["specular"] = 0.2 * v.buffers["diffuse"]
    test = cap.split("test")[0]
    diffuse, specular = test.buffers["diffuse"].copy(), test.buffers["specular"].copy()
    box = {"min": [0.0, 0.0, -0.1], "max": [10.0, 10.0, 0.1]}  # the quadrant x > 0, y > 0 of the plane
    points = test.camera.origin + test.camera.ray_directions() * test.buffers["depth"]
    inside = (points[..., 0] > 0) & (points[..., 1] > 0)
    diffuse[inside] += 0.1  # wrong only inside the region
    channels = {}
    for layer, arr, names in (("rgb", diffuse + specular, "RGB"), ("diffuse", diffuse, None), ("specular", specular, None)):
        for i, c in enumerate("RGB"):
            channels[c if layer == "rgb" else f"{layer}.{c}"] = arr[..., i]
    write_exr_channels(tmp_path / f"{test.name}.exr", channels)
    m = evaluate_renders(cap, tmp_path, regions={"quadrant": box})["views"][test.name]
    assert m["quadrant_pixels"] == inside.sum() > 0
    # only the wrong pixels, error 0.1, at the view's ground-truth peak (no clamp)
    assert abs(m["quadrant_psnr_diffuse"] - (20.0 + 20 * np.log10(m["peak"]))) < 1e-3
    # at peak 1 on [0, 1]-clamped values, whatever else the view shows: error 0.1 where the truth is below 0.9
    truth = test.buffers["diffuse"]
    expected = 10 * np.log10(1 / np.mean((np.clip(diffuse, 0, 1) - np.clip(truth, 0, 1))[inside] ** 2))
    assert m["quadrant_psnr_diffuse_clamped"] == pytest.approx(expected, abs=1e-3) and expected >= 20.0 - 1e-6
    assert 20.0 < m["quadrant_psnr_diffuse_tonemapped"] < 150 and m["quadrant_psnr_specular_tonemapped"] > 150
    assert m["peak"] == pytest.approx(float((test.buffers["diffuse"] + test.buffers["specular"]).max()))
    assert m["peak_diffuse"] == test.buffers["diffuse"].max()  # each layer's own maximum, recorded only
    assert m["psnr_diffuse"] > m["quadrant_psnr_diffuse"] + 1  # the whole image dilutes the error
    assert m["quadrant_psnr_specular"] > 150


def _write_render(folder, name, diffuse, specular, final):
    channels = {c: final[..., i] for i, c in enumerate("RGB")}
    for layer, arr in (("diffuse", diffuse), ("specular", specular)):
        channels.update({f"{layer}.{c}": arr[..., i] for i, c in enumerate("RGB")})
    folder.mkdir(parents=True, exist_ok=True)
    write_exr_channels(folder / f"{name}.exr", channels)


def _lamp_capture():
    """plane_capture with specular, and an emission layer: a bright lamp (radiance 20) in a corner of each view."""
    cap = plane_capture()
    for v in cap.views:
        v.buffers["specular"] = 0.2 * v.buffers["diffuse"]
        emission = np.zeros_like(v.buffers["diffuse"])
        emission[:6, :8] = 20.0
        v.buffers["emission"] = emission
    return cap


def test_final_and_diffuse_include_emission(tmp_path):
    """Ground truth final = diffuse + specular + emission, diffuse = diffuse + emission: a render that has the
    lamp scores high, one that misses it (black lamp) loses on diffuse and final, and specular is unaffected."""
    cap = _lamp_capture()
    test = cap.split("test")[0]
    d, s, e = (test.buffers[k] for k in ("diffuse", "specular", "emission"))
    _write_render(tmp_path / "lit", test.name, d + e, s, d + e + s)
    _write_render(tmp_path / "dark", test.name, d, s, d + s)
    lit = evaluate_renders(cap, tmp_path / "lit")
    dark = evaluate_renders(cap, tmp_path / "dark")
    assert lit["ground_truth"] == {"diffuse": "diffuse + emission", "specular": "specular",
                                   "final": "diffuse + specular + emission"}
    assert "3DGS" in lit["definitions"]["ssim"]
    for layer in ("diffuse", "final"):
        assert lit["mean"][f"psnr_{layer}"] > 100 and dark["mean"][f"psnr_{layer}"] < 30
        assert dark["mean"][f"psnr_{layer}_tonemapped"] < 30
        assert lit["mean"][f"peak_{layer}"] >= 20
    assert lit["mean"]["psnr_specular"] == dark["mean"]["psnr_specular"]
    # the lamp exceeds 1 on 4% of the pixels: the clamped scores are flagged for diffuse and final
    flagged = {(f["view"], f["layer"]) for f in dark["saturated"] if any("exceed 1" in r for r in f["reasons"])}
    assert flagged == {(test.name, "diffuse"), (test.name, "final")}


def test_no_emission_and_zero_emission_score_alike(tmp_path):
    """A capture without an emission layer scores exactly as with an all-zero one (and as diffuse + specular)."""
    cap = _lamp_capture()
    test = cap.split("test")[0]
    d, s = test.buffers["diffuse"], test.buffers["specular"]
    rng = np.random.default_rng(0)
    noisy = d + rng.normal(0, 0.02, d.shape).astype(np.float32)
    _write_render(tmp_path, test.name, noisy, s, noisy + s)
    for v in cap.views:
        v.buffers["emission"] = np.zeros_like(v.buffers["diffuse"])
    zero = evaluate_renders(cap, tmp_path)
    for v in cap.views:
        del v.buffers["emission"]
    absent = evaluate_renders(cap, tmp_path)
    assert zero["mean"] == absent["mean"] and zero["views"] == absent["views"]
    assert zero["saturated"] == absent["saturated"] and absent["ground_truth"]["final"] == "diffuse + specular"


def test_capture_x1e4_scores_as_at_x1_and_flags_the_clamped_scores(tmp_path):
    scores = {}
    for scale in (1.0, 1e4):
        cap = plane_capture()
        rng = np.random.default_rng(1)
        for v in cap.views:
            v.buffers["diffuse"] = scale * (0.5 * v.buffers["diffuse"] + 0.1)
            v.buffers["specular"] = 0.2 * v.buffers["diffuse"]
        test = cap.split("test")[0]
        d, s = test.buffers["diffuse"], test.buffers["specular"]
        noisy = d * (1 + rng.normal(0, 0.02, d.shape)).astype(np.float32)
        _write_render(tmp_path / str(scale), test.name, noisy, s, noisy + s)
        scores[scale] = evaluate_renders(cap, tmp_path / str(scale))
    one, big = scores[1.0], scores[1e4]
    for key in ("psnr_diffuse", "psnr_final", "psnr_final_tonemapped", "ssim_final", "ssim_final_tonemapped"):
        assert big["mean"][key] == pytest.approx(one["mean"][key], abs=1e-3), key
    assert 20 < big["mean"]["psnr_final"] < 60 and big["mean"]["psnr_final_clamped"] > 100
    assert big["mean"]["peak_final"] == pytest.approx(1e4 * one["mean"]["peak_final"], rel=1e-6)
    flagged = {f["layer"] for f in big["saturated"]}
    assert flagged == {"diffuse", "specular", "final"}
    assert not any(f["layer"] in ("diffuse", "final") for f in one["saturated"])


def test_seen_mask_is_what_a_training_camera_sees_directly(tmp_path):
    """A test pixel is 'seen' when its surface point projects into a training view whose depth buffer has that
    surface there; an occluder in front of every training camera makes every pixel unseen; the seen / unseen
    scores split the error where it is."""
    from models.metrics.scoring import seen_mask

    cap = plane_capture()
    for v in cap.views:
        v.buffers["specular"] = 0.2 * v.buffers["diffuse"]
    test, train = cap.split("test")[0], cap.split("train")
    seen, surface = seen_mask(test, train)
    assert surface.all()
    points = (test.camera.origin + test.camera.ray_directions() * test.buffers["depth"]).reshape(-1, 3)
    margin = np.full(len(points), -np.inf)  # how far inside a training image each point lands, best view
    for t in train:
        u, v, z = t.camera.project(points)
        inside = np.minimum.reduce([u, t.camera.width - u, v, t.camera.height - v])
        margin = np.maximum(margin, np.where(z > 0, inside, -np.inf))
    margin = margin.reshape(seen.shape)
    assert (margin > 2).any() and (margin < -2).any()  # the test view sees beyond the training views
    assert seen[margin > 2].all() and not seen[margin < -2].any()

    for t in train:  # something in front of every training camera: nothing the test view shows is seen
        t.buffers["depth"] = 0.5 * t.buffers["depth"]
    seen_hidden, _ = seen_mask(test, train)
    assert not seen_hidden.any()
    for t in train:
        t.buffers["depth"] = 2.0 * t.buffers["depth"]

    diffuse = test.buffers["diffuse"].copy()
    diffuse[~seen] += 0.1  # wrong only where no training camera looked
    _write_render(tmp_path, test.name, diffuse, test.buffers["specular"], diffuse + test.buffers["specular"])
    m = evaluate_renders(cap, tmp_path)["views"][test.name]
    assert m["seen_fraction"] == pytest.approx(seen.mean())
    assert m["seen_psnr_final_tonemapped"] > 150 and m["unseen_psnr_final_tonemapped"] < 40
    assert m["unseen_error_share_final"] == pytest.approx(1.0) and m["unseen_error_share_specular"] == 0.0
    for t in train:  # no depth in the training views: nothing to test against, no seen scores
        del t.buffers["depth"]
    assert seen_mask(test, train) is None
    assert "seen_fraction" not in evaluate_renders(cap, tmp_path)["views"][test.name]


def test_true_layer_scores_name_the_layer_that_limits_the_final_image(tmp_path):
    """psnr_final_tonemapped_true_<layer>: our final with the truth's layer in its place; a render whose specular
    alone is wrong scores perfectly with the true specular and as itself with the true diffuse."""
    cap = _lamp_capture()
    test = cap.split("test")[0]
    diffuse = test.buffers["diffuse"] + test.buffers["emission"]
    specular = test.buffers["specular"] + 0.05
    _write_render(tmp_path, test.name, diffuse, specular, diffuse + specular)
    m = evaluate_renders(cap, tmp_path)["views"][test.name]
    assert m["psnr_final_tonemapped_true_specular"] > 150
    assert m["psnr_final_tonemapped_true_diffuse"] == pytest.approx(m["psnr_final_tonemapped"])
    assert m["psnr_final_tonemapped"] < 40


def test_dark_error_share_finds_light_where_the_truth_has_none(tmp_path):
    """dark_error_share_<layer>: the share of a layer's tonemapped error on pixels where the truth's layer is dark
    (every channel below DARK x the peak: a matte surface's specular, a metal's diffuse). The test view's left half
    made matte (no specular), its bottom-right quarter metal (no diffuse); a render that leaks 1 % of the peak of
    specular onto the matte half and is 10 % off in diffuse everywhere but on the metal has all its specular error
    on the dark pixels and none of its diffuse error."""
    from models.metrics.scoring import DARK
    cap = _lamp_capture()
    test = cap.split("test")[0]
    h, w = test.buffers["diffuse"].shape[:2]
    test.buffers["specular"][:, : w // 2] = 0.0
    test.buffers["diffuse"][h // 2:, w // 2:] = 0.0
    spec, diffuse = test.buffers["specular"], test.buffers["diffuse"] + test.buffers["emission"]
    _write_render(tmp_path, test.name, diffuse, spec, diffuse + spec)
    peak = evaluate_renders(cap, tmp_path)["views"][test.name]["peak"]
    dark_s, dark_d = (spec < DARK * peak).all(-1), (diffuse < DARK * peak).all(-1)
    assert dark_s.mean() == pytest.approx(0.5) and dark_d.mean() == pytest.approx(0.25)
    leak = np.where(dark_s[..., None], spec + 0.01 * peak, spec)
    wrong = diffuse * 1.1
    _write_render(tmp_path, test.name, wrong, leak, wrong + leak)
    result = evaluate_renders(cap, tmp_path)
    m = result["views"][test.name]
    assert m["dark_fraction_specular"] == pytest.approx(0.5) and m["dark_fraction_diffuse"] == pytest.approx(0.25)
    assert m["dark_error_share_specular"] == pytest.approx(1.0)
    assert m["dark_error_share_diffuse"] == 0.0
    assert m["psnr_specular_tonemapped"] < 30 and m["psnr_diffuse_tonemapped"] < 45
    assert "dark_error_share_<layer>" in result["definitions"]


def test_normal_angles_on_all_and_on_shiny_pixels(tmp_path):
    """normal_angle_deg: median angle between our (unnormalised) rendered normals and the truth's;
    shiny_normal_angle_deg[_p90]: the same on F0 > 0.3 pixels only; absent without normals."""
    cap = plane_capture()
    test = cap.split("test")[0]
    h, w = test.buffers["depth"].shape[:2]
    test.buffers["specular"] = 0.2 * test.buffers["diffuse"]
    test.buffers["normal"] = np.broadcast_to(np.float32([0, 0, 1]), (h, w, 3)).copy()
    f0 = np.full((h, w, 3), 0.04, np.float32)
    f0[:, : w // 4] = 0.9  # a metal strip on the left quarter
    test.buffers["f0"] = f0
    tilt = np.radians(10.0)
    ours = np.broadcast_to(np.float32([0, 0, 3]), (h, w, 3)).copy()  # right direction, length 3
    ours[:, : w // 4] = 2 * np.float32([np.sin(tilt), 0, np.cos(tilt)])  # 10 degrees off on the metal
    final = test.buffers["diffuse"] + test.buffers["specular"]
    _write_render(tmp_path, test.name, test.buffers["diffuse"], test.buffers["specular"], final)
    from models.capture.exr import read_exr_channels
    channels = read_exr_channels(tmp_path / f"{test.name}.exr")
    channels.update({f"normal.{c}": ours[..., i] for i, c in enumerate("XYZ")})
    write_exr_channels(tmp_path / f"{test.name}.exr", channels)
    m = evaluate_renders(cap, tmp_path)["views"][test.name]
    assert m["normal_angle_deg"] == pytest.approx(0.0, abs=0.05)  # 3/4 of the pixels are right
    assert m["shiny_normal_angle_deg"] == pytest.approx(10.0, abs=0.05)
    assert m["shiny_normal_angle_deg_p90"] == pytest.approx(10.0, abs=0.05)
    del test.buffers["normal"]
    assert "normal_angle_deg" not in evaluate_renders(cap, tmp_path)["views"][test.name]
