"""The photos path scored against a rendered truth (models/poses/truth.py, `python -m stages.poses align`,
rules synth_photos / photos_truth): a known similarity is recovered exactly, views move with their buffers,
the network's buffer errors are measured in the posed frame, and the workflow plans it."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from models.capture import Camera, Capture, View, read_capture, write_capture
from models.poses import PosesError
from models.poses.truth import Similarity, buffer_errors, moved_view, photos_truth

ROOT = Path(__file__).resolve().parents[1]


def rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def views(rng, split, count, prefix, size=(8, 6)):
    out = []
    for i in range(count):
        c2w = np.eye(4)
        c2w[:3, :3] = rotation(rng)
        c2w[:3, 3] = rng.normal(size=3) * 2
        w, h = size
        normal = rng.normal(size=(h, w, 3))
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        out.append(View(f"{prefix}_{i:03d}", Camera(w, h, 7.0, 7.0, w / 2, h / 2, c2w), split, {
            "rgb": rng.uniform(0, 2, (h, w, 3)).astype(np.float32),
            "diffuse": rng.uniform(0, 1, (h, w, 3)).astype(np.float32),
            "specular": rng.uniform(0, 1, (h, w, 3)).astype(np.float32),
            "depth": rng.uniform(1, 3, (h, w, 1)).astype(np.float32),
            "normal": normal.astype(np.float32),
            "roughness": rng.uniform(0, 1, (h, w, 1)).astype(np.float32),
        }))
    return out


@pytest.fixture
def scene():
    rng = np.random.default_rng(0)
    reference = Capture(views(rng, "train", 6, "train"))  # what the photos were rendered from
    truth = Capture(views(rng, "test", 2, "test"))  # the exact room's test views
    sim = Similarity(0.37, rotation(rng), np.array([0.5, -1.0, 2.0]))
    posed = Capture([moved_view(v, sim) for v in reference.views if v.name != "train_004"])  # one not registered
    return reference, truth, posed, sim


def test_known_similarity_is_recovered_and_views_move_with_their_buffers(scene):
    reference, truth, posed, sim = scene
    moved, record = photos_truth(truth, reference, posed, truth_scene="room")
    assert record["similarity"]["scale"] == pytest.approx(0.37, rel=1e-9)
    assert np.allclose(record["similarity"]["rotation"], sim.rotation, atol=1e-9)
    poses = record["poses"]
    assert (poses["registered"], poses["photos"], poses["unregistered"]) == (5, 6, ["train_004"])
    assert poses["rotation_deg_max"] < 1e-5 and poses["position_frac_max"] < 1e-9
    assert record["truth_scene"] == "room" and record["truth_views"] == ["test_000", "test_001"]
    assert [v.split for v in moved.views] == ["test", "test"]
    for before, after in zip(truth.views, moved.views):
        # a world point seen by the camera keeps its camera-space coordinates, scaled
        x = np.array([0.3, -0.2, 1.5])
        cam_before = np.linalg.inv(before.camera.c2w) @ np.append(x, 1)
        cam_after = np.linalg.inv(after.camera.c2w) @ np.append(sim.apply_points(x), 1)
        assert np.allclose(cam_after[:3], 0.37 * cam_before[:3], atol=1e-9)
        assert np.allclose(after.buffers["depth"], 0.37 * before.buffers["depth"], rtol=1e-6)
        assert np.allclose(after.buffers["normal"], before.buffers["normal"] @ sim.rotation.T, atol=1e-6)
        assert np.array_equal(after.buffers["rgb"], before.buffers["rgb"])  # radiance does not change
    assert moved.meta.extra["photos_path"] is record


def test_network_errors_are_measured_in_the_posed_frame(scene):
    reference, truth, posed, sim = scene
    predicted = Capture([moved_view(v, sim) for v in reference.views])  # perfect buffers, posed frame
    exact = buffer_errors(predicted, reference, sim)
    assert exact["views"] == 6
    assert exact["mean"]["normal_angle_deg"] < 0.05 and exact["mean"]["depth_relative_error_median"] < 1e-6
    assert exact["mean"]["roughness_mae"] == 0.0
    assert exact["mean"]["normal_angle_deg_facing_camera"] > 60  # random normals: ~90 deg from any direction
    # a network whose normals are the TRUE frame's (not rotated) and whose depth is unscaled is wrong by that
    wrong = Capture([View(v.name, p.camera, "train", {**p.buffers, "normal": v.buffers["normal"],
                                                       "depth": v.buffers["depth"]})
                     for v, p in zip(reference.views, predicted.views)])
    errors = buffer_errors(wrong, reference, sim)["mean"]
    assert errors["normal_angle_deg"] > 20
    assert errors["depth_relative_error_median"] == pytest.approx(1 / 0.37 - 1, rel=1e-5)
    noisy = Capture([View(p.name, p.camera, "train", {**p.buffers, "diffuse": p.buffers["diffuse"] * 1.2})
                     for p in predicted.views])
    assert 10 < buffer_errors(noisy, reference, sim)["mean"]["diffuse_psnr_tonemapped"] < 60


def test_too_few_registered_photos_is_an_error_naming_them(scene):
    reference, truth, posed, _ = scene
    with pytest.raises(PosesError, match="only 2 posed views share a name"):
        photos_truth(truth, reference, Capture(posed.views[:2]))
    with pytest.raises(PosesError, match="no 'test' views"):
        photos_truth(reference, reference, posed)


def test_align_cli_writes_the_truth_capture(scene, tmp_path):
    reference, truth, posed, _ = scene
    for name, cap in (("truth", truth), ("reference", reference), ("posed", posed)):
        write_capture(cap, tmp_path / name)
    proc = subprocess.run([sys.executable, "-m", "stages.poses", "align", "--truth", str(tmp_path / "truth"),
                           "--reference", str(tmp_path / "reference"), "--posed", str(tmp_path / "posed"),
                           "--predicted", str(tmp_path / "posed"), "--truth-scene", "room",
                           "--out", str(tmp_path / "eval")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "5/6 photos registered" in proc.stdout
    out = read_capture(tmp_path / "eval")
    assert [v.name for v in out.views] == ["test_000", "test_001"]
    record = out.meta.extra["photos_path"]
    assert record["truth_scene"] == "room" and record["network"]["views"] == 5
    assert (tmp_path / "eval" / "stage.json").is_file()
    bad = subprocess.run([sys.executable, "-m", "stages.poses", "align", "--truth", str(tmp_path / "nowhere"),
                          "--reference", str(tmp_path / "reference"), "--posed", str(tmp_path / "posed"),
                          "--out", str(tmp_path / "eval2")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert bad.returncode == 1 and "nowhere" in bad.stderr and not (tmp_path / "eval2").exists()


def test_synth_photos_are_clipped_srgb_8bit(tmp_path):
    import imageio.v3 as iio

    from stages.synth.__main__ import write_photos

    rgb = np.array([[[0.0, 0.5, 2.0]]], dtype=np.float32)
    cap = Capture([View("train_000", Camera(1, 1, 1.0, 1.0, 0.5, 0.5, np.eye(4)), "train", {"rgb": rgb})])
    write_photos(cap, tmp_path)
    png = iio.imread(tmp_path / "train_000.png")
    assert png.dtype == np.uint8 and png.tolist() == [[[0, 188, 255]]]


def test_workflow_plans_the_photos_path_of_a_zoo_room(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"), "--cores", "1",
                           "--directory", str(tmp_path), "-n", "-p", "--config", "scene=zoo_lamps_photos"],
                          capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr
    jobs = dict(l.split() for l in proc.stdout.split("Job stats:")[1].split("total")[0].splitlines()[3:] if l.strip())
    # photos rendered from the scene's synth section, the truth room rendered by synth, the network trained
    assert {k: jobs.get(k) for k in ("synth_photos", "synth", "poses", "buffers", "photos_truth")} == \
        {"synth_photos": "1", "synth": "1", "poses": "1", "buffers": "1", "photos_truth": "1"}
    text = proc.stdout
    assert "--splits train" in text and "--photos results/zoo_lamps_photos/photos" in text
    assert "--images results/zoo_lamps_photos/photos" in text
    assert "--truth results/zoo_lamps/capture" in text and "--truth-scene zoo_lamps" in text
    render = [l for l in text.splitlines() if "-m stages.render " in l]
    assert render and all("--capture results/zoo_lamps_photos/capture_eval" in l for l in render)
