"""Reconstruction on the demo scene at CI size: loss falls, PSNR floor, exact resume, decisions logged."""

import dataclasses
import json
import math
import re

import numpy as np
import pytest
import torch

from models.tracer import Tracer, TracerConfig
from stages.config import load_config
from models.initialisation import InitConfig, dense_init
from models.reconstruction import ReconstructConfig, Trainer, train
from models.reconstruction.data import build_rayset
from models.gaussians import Gaussians
from models.metrics import psnr
from models.reconstruction.trainer import REFERENCE_HEIGHT
from models.reconstruction.reflection_fill import seen_by_cameras
from models.synth import render_capture

SMALL = dict(iterations=160, warmup=80, rays_per_step=768, prune_from=100, prune_every=50, log_every=10,
             reflection_fill_count=0,  # tests/test_reflection_fill.py covers it
             checkpoint_every=40)


def _scene(name: str, folder):
    """The scene at CI size: its capture and dense initialisation."""
    cfg = load_config(name, presets=["ci"])
    capture = render_capture(cfg["synth"], folder / "capture", progress=False)
    init, _ = dense_init(capture, InitConfig.from_dict(cfg["init"]))
    return capture, init


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return _scene("demo", tmp_path_factory.mktemp("demo"))


@pytest.fixture(scope="module")
def book(tmp_path_factory):
    """mirror_book: the training cameras see the back of the room only in the mirror."""
    return _scene("mirror_book", tmp_path_factory.mktemp("book"))


def tracer():
    return Tracer(TracerConfig(num_threads=2))


def view_psnr(trainer, view_rays):
    g = trainer.gaussians()
    with torch.no_grad():
        out = trainer.backend.trace(view_rays.origins, view_rays.dirs, g)
    return psnr(out.diffuse, view_rays.targets["diffuse"])


def test_training_loss_falls_and_psnr_rises(demo, tmp_path):
    capture, init = demo
    trainer = Trainer(capture, init, ReconstructConfig.from_dict(SMALL), tracer())
    test_rays = build_rayset(capture, "test")
    before = view_psnr(trainer, test_rays)
    train(trainer, tmp_path, progress=False)
    lines = [json.loads(l) for l in (tmp_path / "train_log.jsonl").read_text().splitlines()]
    assert lines[-1]["step"] == 160
    first = np.mean([l["loss_diffuse"] for l in lines[:3]])
    last = np.mean([l["loss_diffuse"] for l in lines[-3:]])
    assert last < 0.7 * first
    after = view_psnr(trainer, test_rays)
    assert after > before + 2 and after > 20, (before, after)  # held-out views, diffuse layer
    assert any("psnr_specular" in l for l in lines)  # reflections switched on after warm-up
    # paths under min_throughput are not traced in training (counted, with their tiny share of the gradient
    # weight), while the model renders every path
    reflected = [l for l in lines if "psnr_specular" in l]
    assert all(l["paths_stopped"] >= 0 and 0 <= l["stopped_weight"] < 0.05 for l in reflected)
    assert trainer.settings().path.min_throughput == 0 and trainer.config.min_throughput == 0.01
    assert any("paths stop below throughput 0.01 in training" in d for d in trainer.decisions)
    # after the last step the sphere snap (tests/test_sphere_snap.py: the demo's mirror ball) and the back-face
    # fill (tests/test_back_fill.py) say what they added: fixed prior rows, at the end
    snap = next(d for d in trainer.decisions if "round shiny objects replaced by discs" in d)
    assert "sphere snap: 1 of 1 round shiny objects" in snap, snap
    snapped = int(snap.split(" replaced by ")[-1].split(")")[0])
    line = next(d for d in trainer.decisions if "Gaussians behind thin surfaces seen from one side only" in d)
    added = int(line.split("added ")[1].split()[0]) + snapped
    assert int(trainer.fixed.sum()) == added and bool(trainer.prior[len(trainer.prior) - added:].all())
    for name, p in trainer.params.items():
        assert torch.isfinite(p).all(), name


def test_the_sphere_snap_switched_off_resumes_the_finished_run(demo, tmp_path):
    """The sphere snap acts only after the last step: a finished run's checkpoint resumes a run without it (no
    other config), which redoes only what follows the steps and writes the model without the snap."""
    capture, init = demo
    cfg = dict(SMALL, iterations=40, warmup=10, prune_from=20, prune_every=10, checkpoint_every=20)
    snapped = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    train(snapped, tmp_path / "a", progress=False)
    state = snapped.read_checkpoint(tmp_path / "a" / "checkpoints" / "last.pt")
    plain = Trainer(capture, init, ReconstructConfig.from_dict(dict(cfg, sphere_snap=False)), tracer())
    assert plain.resume_mismatch(state) is None
    plain.load_checkpoint(tmp_path / "a" / "checkpoints" / "last.pt")
    train(plain, tmp_path / "a", progress=False)
    snap = next(d for d in snapped.decisions if "round shiny objects replaced by discs" in d)
    removed, added = (int(x) for x in re.search(r"\((\d+) Gaussians replaced by (\d+)\)", snap).groups())
    assert not any("sphere snap" in d for d in plain.decisions)
    assert len(snapped.gaussians()) - len(plain.gaussians()) == added - removed


def test_resume_is_exact(demo, tmp_path):
    capture, init = demo
    cfg = dict(SMALL, iterations=40, warmup=10, prune_from=20, prune_every=10, checkpoint_every=20)
    straight = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    train(straight, tmp_path / "a", progress=False)
    half = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    train(half, tmp_path / "b", progress=False, until=20)  # interrupted
    resumed = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    resumed.load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")
    assert resumed.step == 20
    train(resumed, tmp_path / "b", progress=False)
    for name in straight.params:
        assert torch.equal(straight.params[name], resumed.params[name]), name


def test_decisions_switch_off_missing(demo):
    capture, init = demo
    # a copy: the module's demo keeps its f0 (an in-place pop once let the far-field test below pass for the
    # wrong reason: no mirror-like pixels rather than a closed room)
    capture = dataclasses.replace(capture, views=[
        dataclasses.replace(v, buffers={k: b for k, b in v.buffers.items() if k != "f0"}) for v in capture.views])
    trainer = Trainer(capture, init, ReconstructConfig.from_dict(dict(SMALL, max_path_length=1)), tracer())
    text = "\n".join(trainer.decisions)
    assert "loss f0: the capture has no f0 buffer, off" in text
    assert "reflections: max_path_length 1, primary rays only" in text
    assert "far field: off" in text
    assert "f0" not in trainer.weights


def test_warmup_past_the_end_says_reflections_never_turn_on(demo, caplog):
    import logging

    capture, init = demo
    with caplog.at_level(logging.WARNING):
        trainer = Trainer(capture, init, ReconstructConfig.from_dict(dict(SMALL, warmup=160)), tracer())
    assert not trainer.reflections
    text = "\n".join(trainer.decisions)
    assert "reflections: never on (warmup 160 >= iterations 160)" in text and "on after step" not in text
    assert "reflections: never on" in caplog.text


def test_config_errors():
    with pytest.raises(ValueError, match=r"unknown reconstruct option\(s\) \['iters'\]"):
        ReconstructConfig.from_dict({"iters": 3})
    with pytest.raises(ValueError, match=r"unknown reconstruct.loss option\(s\) \['colour'\]"):
        ReconstructConfig.from_dict({"loss": {"colour": 1.0}})


def test_far_field_only_when_reflections_escape(demo, book):
    capture, init = demo
    # demo: the orbiting cameras never see the ceiling its mirror sphere reflects; a threshold above the
    # measured escape fraction calls it closed
    closed = Trainer(capture, init, ReconstructConfig.from_dict(dict(SMALL, far_field_escape=0.9)), tracer())
    assert not closed.far_field
    assert any(d.startswith("far field: off, closed scene") for d in closed.decisions), closed.decisions
    # mirror_book: the mirror reflects the part of the room behind the training cameras, never captured
    opened = Trainer(*book, ReconstructConfig.from_dict(SMALL), tracer())
    assert opened.far_field
    assert any("mirror-like reflection rays leave the initial geometry" in d for d in opened.decisions), \
        opened.decisions
    # the same room through a network whose roughness never goes below 0.3 (the zoo photos runs): no mirror-like
    # pixel, so no fill can run; the log says so instead of calling the room closed
    rough = dataclasses.replace(book[0], views=[
        dataclasses.replace(v, buffers={**v.buffers, "roughness": np.maximum(v.buffers["roughness"], 0.35)})
        for v in book[0].views])
    blind = Trainer(rough, book[1], ReconstructConfig.from_dict(SMALL), tracer())
    assert not blind.far_field
    assert any(d.startswith("far field: off, no mirror-like training pixels") for d in blind.decisions), \
        blind.decisions


def test_far_field_margin_keeps_the_grown_shell_out_of_the_room(book):
    """``far_field_margin``: the far field's rows are marked (``Trainer.far``); after each step every one of them
    has that many standard deviations outside the captured box (the one the shell was drawn outside of), however
    large training made it. Off (0), grown far-field Gaussians reach into the room (zoo_mirror_only: through the
    wall seen only in the mirror, F0 0.04 on the test views' matte wall)."""
    import math

    from models.reconstruction.far_field import clearance_factors

    cfg = dict(SMALL, warmup=0, mirror_stereo_count=0, highlight_fill=False, close_room=False, prune_every=0)
    trainers = {m: Trainer(*book, ReconstructConfig.from_dict(dict(cfg, far_field_margin=m)), tracer())
                for m in (0.0, 2.0)}
    factors = {}
    for margin, trainer in trainers.items():
        n_scene = len(trainer.params["means"])
        trainer.train_step()  # reflections on: adds the far field (appended: the fills are off)
        assert trainer.far_field_added and trainer.far[n_scene:].all() and not trainer.far[:n_scene].any()
        with torch.no_grad():  # grown, as training grows the shell's Gaussians behind a wall seen in a mirror
            trainer.params["log_scales"][n_scene:] += math.log(20.0)
        before = trainer.params["log_scales"].detach()[n_scene:].clone()
        trainer.train_step()
        lo, hi = trainer._thickness_box
        p = {k: v.detach()[n_scene:].double() for k, v in trainer.params.items()}
        factors[margin] = clearance_factors(p["means"], p["quats"], p["log_scales"], lo, hi, 2.0,
                                            1e-4 * trainer.scene_size)
        if margin:
            shrunk = (p["log_scales"] < before.double() - 0.1).all(1)
            assert 0 < shrunk.sum() < len(shrunk) // 2  # only those that reached in
    assert (factors[0.0] < 0.9).sum() > 50  # off: grown ones reach into the room
    torch.testing.assert_close(factors[2.0], torch.ones_like(factors[2.0]), atol=1e-6, rtol=0)


def test_pruning_keeps_what_the_views_see_only_in_mirrors(book):
    """The far-field Gaussians behind mirror_book's walls are seen by no training camera directly, only in the
    mirror. Pruning by the primary rays' blending weight alone removed every one of them (and every object seen
    only in a mirror); after warm-up their weight in the traced reflections counts too."""
    trainer = Trainer(*book, ReconstructConfig.from_dict(dict(SMALL, warmup=0, mirror_stereo_count=0,
                                                              highlight_fill=False, close_room=False)), tracer())
    n_scene = len(trainer.params["means"])
    trainer.train_step()  # reflections on: adds the far field (appended: the fills are off)
    assert trainer.far_field_added
    # none of it inside the captured room (the 0.5-99.5 % box of the scene's Gaussians): floaters for new views
    room = trainer.params["means"][:n_scene].detach().double()
    lo, hi = torch.quantile(room, torch.tensor([0.005, 0.995], dtype=torch.float64), dim=0)
    shell = trainer.params["means"][n_scene:].detach().double()
    assert len(shell) > 1000 and not ((shell >= lo) & (shell <= hi)).all(1).any()
    cams = torch.tensor(np.stack([v.camera.origin for v in trainer.rays.views]))  # nor among the cameras
    assert not ((shell >= cams.min(0).values) & (shell <= cams.max(0).values)).all(1).any()
    with torch.no_grad():  # as if trained: opaque walls, the back wall's Gaussians mirror-like
        trainer.params["opacity_logits"][:n_scene] = 6.0
        on_mirror = trainer.params["means"][:, 2] < -2.3
        trainer.params["f0"][on_mirror] = 0.9
        trainer.params["roughness"][on_mirror] = 0.02
        trainer.params["normals"][on_mirror] = torch.tensor([0.0, 0.0, 1.0])
    far = torch.arange(len(trainer.params["means"])) >= n_scene
    views = list(range(len(trainer.rays.views)))
    direct = trainer.blending_weights(views)
    both = trainer.blending_weights(views, reflections=True)
    threshold = trainer.config.prune_min_weight * (trainer.rays.views[0].camera.height / REFERENCE_HEIGHT) ** 2
    seen_direct, seen_both = int((direct[far] >= threshold).sum()), int((both[far] >= threshold).sum())
    assert seen_both > 3 * seen_direct + 100  # the mirror sees far more of the far field than the holes of the walls
    assert torch.all(both[~far] >= direct[~far] - 1e-6)
    free = trainer._free_rows().cpu()  # prune_hidden tests the scene's own, not the far field
    assert not free[far].any() and free[~far].sum() > 100


def test_pruning_removes_what_every_camera_hides_of_the_initialisation(demo):
    """``prune_hidden``: a pruning step removes the initialisation's Gaussians that no training camera sees
    (``seen_by_cameras``: behind the surface every view's depth shows there, or outside every frame; probe_mirror_213:
    one had moved behind a sphere, where only the wall mirror saw it, and covered the sphere in the test views),
    whatever their blending weight; a mirror fill's, an emitter's and a prior's stay; off, nothing goes for it."""
    capture, init = demo
    for on in (True, False):
        cfg = dict(SMALL, plane_fill_count=0, sphere_fill=False, prune_views=100, prune_hidden=on)
        trainer = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
        threshold = trainer.config.prune_min_weight * (trainer.rays.views[0].camera.height / REFERENCE_HEIGHT) ** 2
        n = len(trainer.params["means"])
        centre = torch.tensor(np.stack([v.camera.origin for v in trainer.rays.views]).mean(0), dtype=torch.float32)
        with torch.no_grad():  # rows 0-3 far below the floor (behind it from every camera), tiny
            trainer.params["means"][:4] = centre + torch.tensor([0.0, -50.0, 0.0])
            trainer.params["log_scales"][:4] = -6.0
        trainer.reflected[1] = True  # a mirror fill's
        trainer.scale_cap[2] = 0.0  # an emitter's (capped)
        trainer.prior[3] = True
        trainer.blending_weights = lambda views, reflections=False: torch.full((len(trainer.params["means"]),),
                                                                               10 * threshold)
        kept = trainer.params["means"].detach()[1:4].clone()
        removed = trainer.prune()
        assert len(trainer.params["means"]) == n - removed and trainer.pruned_hidden == removed
        rows = trainer.params["means"].detach()
        if on:  # row 0 (and whatever else of the initialisation no camera sees: none here) went, the fills stay
            assert removed == 1 and torch.equal(rows[0:3], kept)
        else:
            assert removed == 0 and torch.equal(rows[1:4], kept)


def test_seen_by_cameras_is_what_a_view_shows_not_what_its_surfaces_hide(book):
    """``seen_by_cameras``: a point on a surface a view shows is seen; the same point moved well behind that
    surface, or out of every frame, is not; a large Gaussian there reaches out (its size counts); a view without
    a depth buffer sees all of its frame."""
    capture, _ = book
    views = capture.split("train")
    view = views[0]
    cam = view.camera
    h, w = cam.height, cam.width
    dirs = cam.ray_directions().reshape(h, w, 3)
    depth = np.asarray(view.buffers["depth"])[..., 0]
    r, c = h // 2, w // 2
    on = cam.origin + dirs[r, c] * depth[r, c]
    far_behind = cam.origin + dirs[r, c] * depth[r, c] * 3.0
    pts = torch.tensor(np.stack([on, far_behind, far_behind]))
    sizes = torch.tensor([0.001, 0.001, depth[r, c] * 2.0])
    seen = seen_by_cameras(pts, sizes, [view])
    assert seen.tolist() == [True, False, True]
    outside = torch.tensor(cam.origin - 5.0 * dirs[r, c])[None]  # behind the camera: in no frame
    assert not seen_by_cameras(outside, torch.tensor([0.001]), views).any()
    bare = dataclasses.replace(view, buffers={k: v for k, v in view.buffers.items() if k != "depth"})
    assert seen_by_cameras(pts, sizes, [bare]).all()


def _room(n_views=2, width=32, height=24):
    """A capture built in memory (no Mitsuba): a random room of 2000 Gaussians traced by the tracer itself."""
    from stages.benchmark.room_capture import room_capture

    return room_capture(tracer(), 2000, n_views, width, height, seed=3)


def _room_config(**kw) -> ReconstructConfig:
    return ReconstructConfig(**{**dict(iterations=100, warmup=0, rays_per_step=64, far_field="off", prune_every=0,
                                       checkpoint_every=100), **kw})


def test_ray_batches_are_the_rayset_rows():
    """RayBatcher (one packed table on the trainer's device, one gather per batch) gives RaySet.subset's rows and
    view_rays' views, bit for bit."""
    from models.reconstruction.batches import RayBatcher

    capture, _ = _room()
    rays = build_rayset(capture, "train")
    batches = RayBatcher(rays, torch.device("cpu"))
    index = torch.randint(len(rays), (100,), generator=torch.Generator().manual_seed(0))
    for a, b in ((rays.subset(index), batches.sample(index)), (rays.view_rays(1), batches.view(1))):
        for name in ("origins", "dirs", "mask", "view_of_ray"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert a.targets.keys() == b.targets.keys()
        for name in a.targets:
            assert torch.equal(a.targets[name], b.targets[name]), name


def test_jittered_rays_go_through_uniform_random_points_of_their_own_pixels():
    """With ``jitter`` a batch drawn with a generator goes through a random point of each ray's pixel (projected
    back: inside that pixel, spread over all of it, centred on it on average); without a generator, or without
    ``jitter``, through the centres (the plain table's rows, bit for bit); everything but the directions stays."""
    from models.reconstruction.batches import RayBatcher

    capture, _ = _room()
    rays = build_rayset(capture, "train")
    plain, jittered = RayBatcher(rays, torch.device("cpu")), RayBatcher(rays, torch.device("cpu"), jitter=True)
    index = torch.randint(len(rays), (4000,), generator=torch.Generator().manual_seed(0))
    centres = plain.sample(index)
    assert torch.equal(jittered.sample(index).dirs, centres.dirs)
    assert torch.equal(plain.sample(index, torch.Generator().manual_seed(1)).dirs, centres.dirs)
    batch = jittered.sample(index, torch.Generator().manual_seed(1))
    assert torch.allclose(batch.dirs.norm(dim=-1), torch.ones(len(index)), atol=1e-6)
    assert torch.equal(batch.origins, centres.origins) and torch.equal(batch.mask, centres.mask)
    for name in batch.targets:
        assert torch.equal(batch.targets[name], centres.targets[name]), name
    offsets = []
    for i, view in enumerate(rays.views):
        rows = torch.nonzero(batch.view_of_ray == i).reshape(-1)
        cam = view.camera
        pixel = index[rows] - int(torch.nonzero(rays.view_of_ray == i)[0])  # row-major pixel number in the view
        u, v, z = cam.project(cam.origin + batch.dirs[rows].double().numpy())
        assert (z > 0).all()
        offsets.append(np.stack([u - (pixel % cam.width).numpy(), v - (pixel // cam.width).numpy()], 1))
    offsets = np.concatenate(offsets)
    assert (offsets > -1e-4).all() and (offsets < 1 + 1e-4).all()  # inside the ray's own pixel
    assert np.abs(offsets.mean(0) - 0.5).max() < 0.02 and (offsets.std(0) > 0.27).all()  # uniform: std 0.289
    assert (offsets.min(0) < 0.02).all() and (offsets.max(0) > 0.98).all()
    whole = jittered.view(1, torch.Generator().manual_seed(2))
    assert not torch.equal(whole.dirs, rays.view_rays(1).dirs) and torch.equal(jittered.view(1).dirs,
                                                                              rays.view_rays(1).dirs)


def test_target_normals_face_the_camera():
    """A capture whose normal buffer faces away from the camera (another tool's convention: outward normals of a
    surface seen from inside) is the same surface: the targets are turned to face the camera, as synth's are."""
    capture, _ = _room()
    before = build_rayset(capture, "train").targets["normal"]
    for v in capture.split("train"):
        v.buffers["normal"] = -v.buffers["normal"]
    rays = build_rayset(capture, "train")
    assert torch.equal(rays.targets["normal"], before)
    assert ((rays.targets["normal"] * rays.dirs).sum(-1) <= 0).all()


def test_path_length_decision_is_logged_stored_with_the_model_and_checkpointed(demo, monkeypatch):
    """The demo's mirror faces matte walls: the measured length is the paper's 3 (logged). Where the measurement
    (tests/test_path_length.py: analytic rooms) says reflections go on, here replaced by one where every path
    keeps carrying its light, the trainer takes the limit, says the limit cuts them short, stores the length
    with the model, carries it in checkpoints and never shrinks it; a limit at max_path_length never measures."""
    import models.reconstruction.trainer as trainer_module

    capture, init = demo
    cfg = ReconstructConfig.from_dict(SMALL)
    room = Trainer(capture, init, cfg, tracer())
    room._decide_path_length()
    assert room.path_length == 3 and room.settings().path.max_path_length == 3
    assert any("path length 3 (max_path_length 3, limit 8)" in d for d in room.decisions)
    real = trainer_module.carried_throughput
    monkeypatch.setattr(trainer_module, "carried_throughput",
                        lambda *a, **k: [torch.ones_like(c) for c in real(*a, **k)] + [torch.ones(1)] * 8)
    room._decide_path_length()
    assert room.path_length == 8 and room.settings().path.max_path_length == 8
    assert room.path_config(training=True).max_path_length == 8
    assert any("path length 8" in d and "the limit cuts them short" in d for d in room.decisions)
    resumed = Trainer(capture, init, cfg, tracer())
    resumed.load_state_dict(room.state_dict())
    assert resumed.path_length == 8
    monkeypatch.setattr(trainer_module, "carried_throughput", real)
    resumed._decide_path_length()
    assert resumed.path_length == 8  # never shrinks
    capped = Trainer(capture, init, ReconstructConfig.from_dict({**SMALL, "max_path_length_limit": 3}), tracer())
    monkeypatch.setattr(trainer_module, "carried_throughput", lambda *a, **k: 1 / 0)  # never called
    capped._decide_path_length()
    assert capped.path_length == 3


def test_training_batch_is_also_scored_tonemapped_at_the_training_peak():
    """Besides the linear PSNRs (peak 1), the log carries mu-law PSNRs of diffuse, specular and their sum at the
    peak of the training targets (a lamp at 10 makes a linear score follow its few rays): equal to evaluate's
    numpy scoring of the same batch."""
    from models.metrics import hdr

    capture, init = _room()
    trainer = Trainer(capture, init, _room_config(), tracer())
    final = trainer.rays.targets["diffuse"] + trainer.rays.targets["specular"]
    assert trainer.peak == pytest.approx(float(final.max())) and trainer.peak > 0
    seen = {}
    score = trainer._loss_terms

    def spy(batch, out, reflections, flags=None, stereo=None):
        seen.update(batch=batch, out=out)
        return score(batch, out, reflections, flags, stereo)

    trainer._loss_terms = spy
    _, metrics = trainer.losses(trainer.sample_batch(), True)
    b, o = seen["batch"], seen["out"]
    layers = {"diffuse": (o.primary.diffuse, b.targets["diffuse"]), "specular": (o.specular, b.targets["specular"])}
    layers["final"] = (layers["diffuse"][0] + layers["specular"][0], layers["diffuse"][1] + layers["specular"][1])
    for layer, (pred, target) in layers.items():
        pred, target = pred.detach().numpy(), target.numpy().reshape(pred.shape)
        expect = psnr(hdr.mu_law(pred, trainer.peak), hdr.mu_law(target, trainer.peak))
        assert metrics[f"psnr_{layer}_tonemapped"] == pytest.approx(expect, abs=1e-6), layer
        assert metrics[f"psnr_{layer}"] == pytest.approx(psnr(pred, target), abs=1e-6), layer


def test_deferred_tracer_checks_train_exactly_as_checked_traces():
    """On a GPU the trainer settles the tracer's per-trace read-backs (replay overflow, zero directions) with its one
    metrics read-back (``defer_checks``); a step in which a ray outgrew the replay buffer is redone with the same
    random numbers. Forced here on the CPU with a 2-slot buffer (rays overflow in the first steps, with reflections):
    the same metrics and parameters, bit for bit, as checking at every trace."""
    capture, init = _room()
    runs = []
    for defer in (False, True):
        backend = Tracer(TracerConfig(num_threads=2, replay_capacity=2))
        trainer = Trainer(capture, init, _room_config(), backend)
        assert trainer.defer_checks is False  # a CPU trainer checks at every trace (no sync to save)
        trainer.defer_checks = defer
        trainer.train_step()  # (decides the path length: traces that grow the capacity, as the constructor's)
        backend.capacity = 2
        metrics = [trainer.train_step() for _ in range(3)]
        runs.append((metrics, {k: v.detach().clone() for k, v in trainer.params.items()}, backend.capacity))
    (checked, p_checked, cap_checked), (deferred, p_deferred, cap_deferred) = runs
    assert cap_checked > 2 and cap_deferred > 2
    for a, b in zip(checked, deferred):
        assert {k: v for k, v in a.items() if "time" not in k} == {k: v for k, v in b.items() if "time" not in k}
    for k in p_checked:
        assert torch.equal(p_checked[k], p_deferred[k]), k


def test_non_finite_gradients_skip_the_update_and_stop_training(tmp_path):
    """A step with a non-finite gradient leaves parameters and Adam's state as they were (flagged on the device);
    the flags are read back every FINITE_CHECK_EVERY steps and before every checkpoint (not per step)."""
    from models.reconstruction.trainer import FINITE_CHECK_EVERY

    capture, init = _room()
    trainer = Trainer(capture, init, _room_config(), tracer())
    metrics = trainer.train_step()
    assert np.isfinite(metrics["loss"]) and np.isfinite(metrics["psnr_specular"])
    trainer.save_checkpoint(tmp_path / "ok.pt")
    before = {k: v.detach().clone() for k, v in trainer.params.items()}
    trainer.losses = lambda batch, reflections: _nan_loss(trainer, batch, reflections)
    trainer.train_step()  # every gradient NaN: the update is skipped
    for name, p in trainer.params.items():
        assert torch.equal(p, before[name]), name
    with pytest.raises(FloatingPointError, match=r"step 2: non-finite gradient in means \(1 steps\).* since step 1"):
        trainer.save_checkpoint(tmp_path / "bad.pt")
    assert not (tmp_path / "bad.pt").exists()
    with torch.no_grad():
        trainer.params["f0"][0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match="non-finite values in f0"):
        for _ in range(FINITE_CHECK_EVERY):
            trainer.train_step()
    assert trainer.step <= FINITE_CHECK_EVERY


def test_max_thickness_flattens_thick_gaussians_inside_the_scene_only():
    """``max_thickness``: after a step, a Gaussian inside the initial box whose thinnest axis is thicker than the
    cap has that axis (and only it) at the cap; one outside the box (far field), a fixed one and the thin ones
    keep their scales; off (0), nothing is clamped. (Before the far field is added every Gaussian is held to it;
    the box is the one the far field is drawn outside of, set here as the far field's step would.)"""
    import math

    capture, init = _room()
    trainers = {cap: Trainer(capture, init, _room_config(max_thickness=cap, thickness_reflected_only=False), tracer())
                for cap in (0.0, 0.01)}
    for trainer in trainers.values():
        with torch.no_grad():
            ls = trainer.params["log_scales"]
            ls[:4] = torch.log(torch.tensor([[0.5, 0.3, 0.9], [0.5, 0.3, 0.9], [0.5, 0.3, 0.9], [0.002, 0.5, 0.5]]))
            means = trainer.params["means"]
            trainer._thickness_box = (means.amin(0).double() - 0.1, means.amax(0).double() + 0.1)
            means[1] = means[1] + 100.0  # far outside the box: a far-field Gaussian's place
            trainer.fixed[2] = True
        trainer.train_step()
    on, off = trainers[0.01], trainers[0.0]
    cap = math.log(0.01 * on.scene_size)
    ls = on.params["log_scales"].detach()
    assert ls[0, 1] == pytest.approx(cap, abs=1e-6)  # the thinnest axis, at the cap
    assert ls[0, 0] > cap + 2 and ls[0, 2] > cap + 2  # the others are not
    assert ls[1].min() > cap + 2 and ls[2].min() > cap + 2  # far field, fixed: untouched
    assert ls[3, 0] < cap  # already thin
    inside = torch.ones(len(ls), dtype=torch.bool)
    inside[1] = inside[2] = False
    assert (ls[inside].min(dim=1).values <= cap + 1e-6).all()
    assert off.params["log_scales"].detach()[0].min() > cap + 2  # off: nothing clamped
    # thickness_reflected_only (the default): only the Gaussians the mirror fills placed (what only reflections
    # train) are held
    scoped = Trainer(capture, init, _room_config(max_thickness=0.01, thickness_reflected_only=True), tracer())
    with torch.no_grad():
        scoped.params["log_scales"][:2] = torch.log(torch.tensor([[0.5, 0.3, 0.9], [0.5, 0.3, 0.9]]))
        scoped.reflected[1] = True
    scoped.train_step()
    ls = scoped.params["log_scales"].detach()
    assert ls[1, 1] == pytest.approx(cap, abs=1e-6) and ls[1, 0] > cap + 2  # a mirror fill's: clamped
    assert ls[0].min() > cap + 2  # the room's own: kept


def _nan_loss(trainer, batch, reflections):
    total, metrics = Trainer.losses(trainer, batch, reflections)
    return total * float("nan"), metrics


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: the trainer's CUDA path runs when one is present")
def test_cuda_trainer_keeps_its_state_on_the_gpu_and_matches_the_cpu():
    capture, init = _room()
    cfg = _room_config(rays_per_step=0)  # whole views: RayBatcher.view slices
    cpu = Trainer(capture, init, cfg, tracer())
    gpu = Trainer(capture, init, cfg, Tracer(TracerConfig(), device="cuda"))
    assert all(p.is_cuda for p in gpu.params.values()) and gpu.batches.table.is_cuda
    for _ in range(3):
        a, b = cpu.train_step(), gpu.train_step()
        assert abs(a["loss"] - b["loss"]) < 1e-3 * max(abs(a["loss"]), 1.0), (a, b)
    for name, p in cpu.params.items():
        torch.testing.assert_close(gpu.params[name].cpu(), p, atol=1e-3, rtol=1e-3)


def test_plane_fill_gaussians_are_priors_that_pruning_keeps_and_checkpoints_carry(demo, tmp_path):
    """``plane_fill_count``: Gaussians on the unseen parts of the room's bounding planes join the init (logged
    among the decisions); no training view sees them, so pruning by blending weight would remove them at once:
    it keeps them (they are the prior's), their geometry gets no gradient, and a checkpoint carries which they
    are."""
    capture, init = demo
    cfg = dict(SMALL, iterations=20, warmup=10, prune_from=10, prune_every=10, checkpoint_every=20,
               plane_fill_count=4000, sphere_fill=False)  # (the demo's chrome ball: sphere_fill's own test)
    trainer = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    n_prior = int(trainer.prior.sum())
    assert 0 < n_prior <= 4000 and len(trainer.params["means"]) == len(init.means) + n_prior
    assert any(d.startswith(f"plane fill: {n_prior} Gaussians") for d in trainer.decisions)
    assert trainer.prior[-n_prior:].all()
    before = trainer.params["means"][trainer.prior].detach().clone()
    for p in trainer.params.values():  # their geometry is frozen (reflections alone would swell them), not the rest
        p.grad = torch.ones_like(p)
    trainer._freeze_priors()
    for name, p in trainer.params.items():
        frozen = name in ("means", "quats", "log_scales")
        assert bool((p.grad[trainer.prior] == 0).all()) == frozen and bool((p.grad[~trainer.prior] == 1).all()), name
        p.grad = None
    trainer.config = dataclasses.replace(trainer.config, prune_min_weight=1e9, prune_views=10**6)  # pruning by weight removes all
    removed = trainer.prune()
    assert removed == len(init.means) and int(trainer.prior.sum()) == n_prior == len(trainer.params["means"])
    assert torch.equal(trainer.params["means"].detach(), before)
    trainer.save_checkpoint(tmp_path / "last.pt")
    again = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    again.load_checkpoint(tmp_path / "last.pt")
    assert torch.equal(again.prior, trainer.prior)
    off = Trainer(capture, init, ReconstructConfig.from_dict(dict(SMALL, plane_fill_count=0, sphere_fill=False)),
                  tracer())
    assert not off.prior.any() and not any(d.startswith("plane fill") for d in off.decisions)


def test_pruning_keeps_what_only_a_few_views_see_until_every_view_was_measured(demo, tmp_path):
    """A pruning step traces ``prune_views`` views, the next block of one random cycle through them, and a Gaussian
    goes only when its mean weight over the blocks that covered every view is below the threshold: one seen by a
    single view is never pruned (drawing 8 views anew at each step removed it whenever that view was not drawn),
    one no view sees goes after exactly ceil(views / prune_views) steps; the cycle and the memory survive a
    checkpoint and follow the Gaussians through the removal."""
    capture, init = demo
    cfg = dict(SMALL, plane_fill_count=0, sphere_fill=False, prune_views=2)
    trainer = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    n_views = len(trainer.rays.views)
    blocks = -(-n_views // 2)
    assert blocks >= 2
    threshold = trainer.config.prune_min_weight * (trainer.rays.views[0].camera.height / 768) ** 2
    n = len(trainer.params["means"])
    drawn = []

    def weights(views, reflections=False):  # the mean over ``views``; Gaussian 0: seen by view 0 alone (weight
        drawn.append(list(views))  # 10 x threshold x views there), Gaussian 1: by none, the others by all
        w = torch.full((len(trainer.params["means"]),), 10 * threshold)
        w[0] = 10 * threshold * n_views / len(views) if 0 in views else 0.0
        w[1] = 0.0 if len(w) == n else w[1]  # (gone after the first cycle)
        return w

    trainer.blending_weights = weights
    removed = [trainer.prune() for _ in range(blocks)]
    assert removed[:-1] == [0] * (blocks - 1) and removed[-1] == 1  # Gaussian 1 goes once all views were measured
    assert sorted(v for block in drawn for v in block) == list(range(n_views)) + list(range(2 * blocks - n_views))
    assert len(trainer.params["means"]) == n - 1 and trainer.prune_memory.shape == (n - 1, blocks)
    trainer.save_checkpoint(tmp_path / "last.pt")
    again = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    again.load_checkpoint(tmp_path / "last.pt")
    assert torch.equal(again._prune_order, trainer._prune_order) and again._prune_round == blocks
    assert torch.equal(again.prune_memory.nan_to_num(-1), trainer.prune_memory.nan_to_num(-1))
    for _ in range(3 * blocks):  # Gaussian 0 (still row 0) stays however the blocks fall
        assert trainer.prune() == 0


def test_the_plane_fill_is_relit_once_when_asked_and_says_so(demo, tmp_path):
    """``plane_fill_relight``: at ``plane_fill_relight_at`` of the way through the reflection phase the plane fill's
    Gaussians (all of them here: no mirror fill) take their plane's albedo x the traced light where they are
    (plane_fill.relight_plane_fill's own test checks the values): logged once among the decisions, their colours
    changed, and a resumed run does not do it again."""
    capture, init = demo
    cfg = dict(SMALL, iterations=12, warmup=4, plane_fill_count=4000, sphere_fill=False, plane_fill_relight=True,
               plane_fill_relight_at=0.5, checkpoint_every=6)
    trainer = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    rows = torch.nonzero(trainer.prior).reshape(-1)
    while trainer.step < 8:  # relit at step 4 + 0.5 x (12 - 4) = 8
        trainer.train_step()
    assert not any("plane fill relit" in d for d in trainer.decisions)
    before = trainer.params["diffuse"].detach()[rows].clone()
    trainer.train_step()
    lines = [d for d in trainer.decisions if "plane fill relit" in d]
    assert len(lines) == 1 and lines[0].startswith(f"step 8: plane fill relit: {len(rows)} of its {len(rows)} ")
    change = (trainer.params["diffuse"].detach()[rows] - before).abs().mean(dim=1)
    assert float(change.median()) > 1e-3  # far more than one Adam step moves them
    trainer.save_checkpoint(tmp_path / "last.pt")
    again = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    again.load_checkpoint(tmp_path / "last.pt")
    again.train_step()
    assert again.plane_fill_relit and not any("plane fill relit" in d for d in again.decisions)
    assert ReconstructConfig().plane_fill_relight is True


def test_sphere_fill_joins_the_prior_when_on_and_logs_what_it_fitted(demo, tmp_path):
    """``sphere_fill``: the Gaussians on the unseen sides of fitted spheres (tests/test_sphere_fill.py) join the
    prior, after the plane fill's, their number and every piece tried in the decisions; nothing of theirs trains
    (``fixed``: no gradient reaches any of their parameters, the plane fill's keep colour, material and opacity),
    through pruning and a checkpoint; off (the default): none."""
    capture, init = demo
    cfg = dict(SMALL, plane_fill_count=4000, sphere_fill=True)
    on = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    line = next(d for d in on.decisions if d.startswith("sphere fill: ") and "Gaussians on the unseen" in d)
    n_sphere = int(line.split()[2])
    assert n_sphere > 0 and int(on.fixed.sum()) == n_sphere and on.fixed[-n_sphere:].all()
    planes = next(d for d in on.decisions if d.startswith("plane fill: "))
    assert int(on.prior.sum()) == n_sphere + int(planes.split()[2]) == len(on.params["means"]) - len(init.means)
    assert not (on.fixed & ~on.prior).any()
    for p in on.params.values():
        p.grad = torch.ones_like(p)
    on._freeze_priors()
    plane_rows = on.prior & ~on.fixed
    for name, p in on.params.items():
        assert bool((p.grad[on.fixed] == 0).all()), name
        assert bool((p.grad[plane_rows] == 0).all()) == (name in ("means", "quats", "log_scales")), name
        assert bool((p.grad[~on.prior] == 1).all()), name
        p.grad = None
    on.config = dataclasses.replace(on.config, prune_min_weight=1e9, prune_views=10**6)
    on.prune()  # the priors stay, the fixed ones still last
    assert int(on.fixed.sum()) == n_sphere and on.fixed[-n_sphere:].all()
    on.save_checkpoint(tmp_path / "last.pt")
    again = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    again.load_checkpoint(tmp_path / "last.pt")
    assert torch.equal(again.fixed, on.fixed)
    assert ReconstructConfig().sphere_fill is False
    off = Trainer(capture, init, ReconstructConfig.from_dict(dict(SMALL, plane_fill_count=0)), tracer())
    assert not off.prior.any() and not any(d.startswith("sphere fill") for d in off.decisions)


def test_fill_colour_neighbours_stay_on_their_own_surface():
    """``surface_neighbours`` (the fill's colour smoothness): at a room's corner a wall's surfels find their
    neighbours on the wall, the floor's on the floor (the colour no longer averages across the corner:
    zoo_corridor's metal walls took the ceiling's and the floor's diffuse); a shelf 15 cm above the floor is another
    surface; a Gaussian without a normal takes its nearest as before; too few: itself."""
    from models.reconstruction.trainer import surface_neighbours
    s = np.linspace(0.0, 1.0, 21)
    a, b = np.meshgrid(s, s, indexing="ij")
    a, b = a.reshape(-1), b.reshape(-1)
    floor = np.stack([a, np.zeros_like(a), b], 1)  # y = 0
    wall = np.stack([np.zeros_like(a), a + 0.05, b], 1)  # x = 0, from the floor up
    shelf = np.stack([a[:84] * 0.5 + 0.2, np.full(84, 0.15), b[:84] * 0.5 + 0.2], 1)
    blob = np.array([[0.02, 0.02, 0.5]])
    pos = np.concatenate([floor, wall, shelf, blob])
    kind = np.repeat([0, 1, 2, 3], [len(floor), len(wall), len(shelf), 1])
    normals = np.zeros_like(pos)
    normals[kind == 0] = [0.0, 1.0, 0.0]
    normals[kind == 1] = [-1.0, 0.0, 0.0]  # either sign
    normals[kind == 2] = [0.0, 1.0, 0.0]
    idx = surface_neighbours(pos, normals, 8)
    assert idx.shape == (len(pos), 8)
    for k in (0, 1):  # corner rows included (the round blob, with no normal, may be anyone's neighbour)
        rows = np.nonzero(kind == k)[0]
        assert np.all((kind[idx[rows]] == k) | (kind[idx[rows]] == 3)), k
        assert (kind[idx[rows]] == k).mean() > 0.99
    shelf_rows = np.nonzero(kind == 2)[0]
    assert np.all((kind[idx[shelf_rows]] == 2) | (idx[shelf_rows] == shelf_rows[:, None]))
    # the blob (no normal) takes its 8 nearest of any kind
    from scipy.spatial import cKDTree
    assert sorted(idx[-1]) == sorted(cKDTree(pos).query(pos[-1], k=9)[1][1:])
    # two points on different planes: each has only itself
    two = surface_neighbours(pos[[0, len(floor)]], normals[[0, len(floor)]], 8)
    assert two.tolist() == [[0] * 8, [1] * 8]


def test_prior_smoothness_pulls_a_fill_colour_toward_its_neighbours_and_survives_pruning(demo):
    """``loss.prior_smooth``: a plane-fill Gaussian's colour is held to the mean of its 8 nearest fill neighbours'
    (reflections alone train it, one noisy sample per ray: free, zoo_lamps' unseen ceiling became confetti). Zero
    on a uniform fill; an outlier is pulled back and its neighbours toward it (gradient = finite differences);
    pruning the scene's other Gaussians leaves the term unchanged (the fill keeps its order); logged per step."""
    capture, init = demo
    cfg = dict(SMALL, iterations=4, warmup=2, plane_fill_count=4000)
    trainer = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    rows = torch.nonzero(trainer.prior).reshape(-1)
    with torch.no_grad():
        trainer.params["diffuse"][rows] = 0.5
    assert float(trainer._prior_smooth().detach()) == 0.0
    r = int(rows[len(rows) // 2])
    with torch.no_grad():
        trainer.params["diffuse"][r, 0] = 2.0
    value = trainer._prior_smooth()
    value.backward()
    value = float(value.detach())
    grad = trainer.params["diffuse"].grad
    assert float(grad[r, 0]) > 0  # gradient descent lowers the outlier
    nbrs = rows[trainer._prior_nbrs[len(rows) // 2]]
    assert float(grad[nbrs, 0].sum()) < 0  # and raises its neighbours (together: each also has neighbours of r)
    eps = 1e-3
    with torch.no_grad():
        trainer.params["diffuse"][r, 0] += eps
        up = float(trainer._prior_smooth().detach())
        trainer.params["diffuse"][r, 0] -= 2 * eps
        down = float(trainer._prior_smooth().detach())
        trainer.params["diffuse"][r, 0] += eps
    assert abs((up - down) / (2 * eps) - float(grad[r, 0])) < 1e-4 * max(1.0, abs(float(grad[r, 0])))
    trainer.params["diffuse"].grad = None
    trainer.config = dataclasses.replace(trainer.config, prune_min_weight=1e9, prune_views=10**6)
    trainer.prune()  # every Gaussian but the fill's
    assert torch.nonzero(trainer.prior).reshape(-1).tolist() == list(range(len(rows)))
    assert float(trainer._prior_smooth().detach()) == pytest.approx(value, rel=1e-6)
    assert "loss_prior_smooth" in trainer.train_step()
    off = Trainer(capture, init, ReconstructConfig.from_dict(dict(cfg, loss={"prior_smooth": 0.0})), tracer())
    assert "loss_prior_smooth" not in off.train_step()


def test_far_field_rays_from_the_cameras_in_random_directions_find_holes(demo):
    """The far field's second test: rays from the training cameras in random directions that hit nothing (a
    ceiling no camera saw: a test view turned up looks into nothing, black without the far field's shell; the
    zoo's thin-objects room). A closed box round the cameras lets none out; the same box without its top lets
    out about the top's share of the directions."""
    from models.gaussians import Gaussians
    from models.gaussians.synthetic import room_gaussians

    capture, init = demo
    trainer = Trainer(capture, init, ReconstructConfig.from_dict(dict(SMALL, iterations=2, warmup=1)), tracer())
    cams = np.stack([v.camera.origin for v in trainer.rays.views])
    centre = cams.mean(0)
    half = float(np.abs(cams - centre).max()) * 2 + 0.5
    box = room_gaussians(30000, torch.Generator().manual_seed(3), half_size=half, opacity_logit_mean=1.0)
    rel = box.means
    walls = rel.abs().amax(1) > 0.9 * half  # the six faces only, not the floating blobs
    box = Gaussians(**{k: v[walls] for k, v in box.params().items()})
    box.means = box.means + torch.tensor(centre, dtype=box.means.dtype)
    assert trainer._escaping_views(box) < 0.005
    keep = (box.means[:, 1] - float(centre[1])) < 0.9 * half  # no ceiling
    open_top = Gaussians(**{k: v[keep] for k, v in box.params().items()})
    assert 0.1 < trainer._escaping_views(open_top) < 0.3  # the top face: ~1/6 of the directions from the middle


def test_the_plane_fill_reaches_where_the_mirror_shows_the_room_behind_the_cameras(book):
    """mirror_book's cameras face the mirror: the first plane fill's box ends at them, and the back of the room is
    seen only in the mirror. When the mirror stereo has placed what the mirror shows (end of warm-up), the fill is
    carried there (plane_fill.py step 6): appended as priors (never pruned, geometry frozen), outside the first
    box and behind the cameras, logged among the decisions; the book the mirror shows is not taken for a wall."""
    # stereo_on_planes off: the extension's Gaussians alone are appended (tests/test_plane_fill.py covers it)
    cfg = dict(SMALL, warmup=0, plane_fill_count=4000, highlight_fill=False, stereo_on_planes=False)
    trainer = Trainer(*book, ReconstructConfig.from_dict(cfg), tracer())
    first = int(trainer.prior.sum())
    lo, hi, tol = trainer._room.lo.copy(), trainer._room.hi.copy(), trainer._room.tol
    assert first > 0 and trainer.far_field
    trainer.train_step()
    grown = [d for d in trainer.decisions if "plane-fill Gaussians where the mirrors show" in d]
    assert len(grown) == 1, trainer.decisions
    added = int(trainer.prior.sum()) - first
    assert added > 100 and f"added {added} plane-fill" in grown[0]
    # the book the mirror shows stands in front of the wall (points behind it): no wall there (_shown_walls)
    assert "walls they show: none" in grown[0]
    assert trainer.prior[-added:].all()  # appended last (nothing after the extension in this run)
    new = trainer.params["means"][-added:].detach().double().numpy()
    assert not ((new >= lo - tol) & (new <= hi + tol)).all(1).any()
    cams = np.stack([v.camera.origin for v in trainer.rays.views])
    forward = -np.mean([v.camera.c2w[:3, 2] for v in trainer.rays.views], axis=0)
    assert np.median((new - cams.mean(0)) @ forward) < 0  # behind the cameras
    # room closing ran after it (room_closing.py): what mirror stereo placed is known, so that side is not swept
    closing = [d for d in trainer.decisions if "on walls no training view looks at" in d]
    assert len(closing) == 1 and "+z at" not in closing[0], closing



def test_mirror_stereo_gaussians_on_the_rooms_planes_become_its_fixed_material_surfels(book):
    """stereo_on_planes (tests/test_plane_fill.py covers the geometry): at the end of warm-up the mirror stereo's
    Gaussians on a bounding plane are appended as plane-fill surfels, priors (geometry frozen) that keep their
    F0 and roughness (``reflected``, fill_matte), logged; the others stay the stereo's (matte, free)."""
    cfg = dict(SMALL, warmup=0, plane_fill_count=4000, highlight_fill=False)
    trainer = Trainer(*book, ReconstructConfig.from_dict(cfg), tracer())
    trainer.train_step()
    line = next(d for d in trainer.decisions if "of the mirror stereo's Gaussians on the room's planes" in d)
    moved = int(line.split("added ")[1].split()[0])
    assert moved > 0, trainer.decisions
    both = trainer.prior & trainer.reflected
    assert int(both.sum()) == moved
    before = {k: trainer.params[k].detach()[both].clone() for k in ("means", "f0", "roughness")}
    for _ in range(3):
        trainer.train_step()
    both = trainer.prior & trainer.reflected
    for k, v in before.items():
        assert torch.equal(trainer.params[k].detach()[both], v), k


def test_the_stereo_depth_loss_traces_the_mirrors_reflected_rays_and_resumes(book, tmp_path):
    """loss.stereo_depth: when mirror stereo runs (end of warm-up) its consistent matches become reflected rays with
    a free distance (logged); every step after traces stereo_depth_rays of them and adds the term; a checkpoint
    carries the rays, so a resumed run goes on with the same ones. Off (the default), no term and no rays."""
    cfg = dict(SMALL, warmup=0, highlight_fill=False, loss={"stereo_depth": 2.5, "stereo_depth_rays": 64})
    trainer = Trainer(*book, ReconstructConfig.from_dict(cfg), tracer())
    metrics = trainer.train_step()
    assert any("stereo depth loss on" in d for d in trainer.decisions), trainer.decisions
    origins, dirs, free = trainer.stereo_rays
    assert len(free) > 20 and (free > 0).all()  # the matches made by their own texture (49 at CI size)
    torch.testing.assert_close(dirs.norm(dim=1), torch.ones_like(free))
    assert "loss_stereo_depth" in metrics and metrics["loss_stereo_depth"] >= 0
    trainer.save_checkpoint(tmp_path / "ckpt.pt")
    # free distances 5x past the room's surfaces (each ray still starts in front of them, a tenth of the way): the
    # rays that end do so in front of them, so the term is positive
    trainer.stereo_rays = (origins, dirs, free * 5)
    assert trainer.train_step()["loss_stereo_depth"] > 0
    again = Trainer(*book, ReconstructConfig.from_dict(cfg), tracer())
    again.load_checkpoint(tmp_path / "ckpt.pt")
    for a, b in zip(again.stereo_rays, (origins, dirs, free)):
        assert torch.equal(a, b)
    off = Trainer(*book, ReconstructConfig.from_dict(dict(cfg, loss={})), tracer())
    assert "loss_stereo_depth" not in off.train_step() and off.stereo_rays is None


def test_the_far_field_is_left_out_where_no_camera_sees_past_the_room(book):
    """``far_field_hidden``: far-field Gaussians that no training camera sees past the captured room are not added
    (behind a closed wall they train on reflections slipping through it and show through any thin spot:
    zoo_lshape). With mirror_book's Gaussians opaque (as after warm-up), those behind the seen walls are left out
    and those past the room's open side (behind the cameras, where no view looks) stay; 0 keeps every one."""
    added, first = {}, {}
    for hidden in (0.05, 0.0):
        cfg = dict(SMALL, warmup=0, mirror_stereo_count=0, highlight_fill=False, plane_fill_count=20000,
                   far_field_hidden=hidden)
        trainer = Trainer(*book, ReconstructConfig.from_dict(cfg), tracer())
        n = len(trainer.params["means"])
        with torch.no_grad():
            trainer.params["opacity_logits"][:] = 6.0
        room = Gaussians(**{k: v.detach().clone() for k, v in trainer.params.items()})
        trainer.train_step()
        assert trainer.far_field_added
        added[hidden], first[hidden] = trainer.params["means"][n:].detach().clone(), room
    drawn, kept = added[0.0], added[0.05]
    assert 100 < len(kept) < 0.8 * len(drawn)
    from scipy.spatial import cKDTree

    assert cKDTree(drawn.numpy()).query(kept.numpy())[0].max() < 1e-6  # a subset of the same draw
    cams = np.stack([v.camera.origin for v in book[0].split("train")])
    forward = -np.mean([v.camera.c2w[:3, 2] for v in book[0].split("train")], axis=0)
    behind = lambda p: float(((p.double().numpy() - cams.mean(0)) @ forward < 0).mean())  # noqa: E731
    assert behind(kept) > behind(drawn) + 0.1
    # those left out: every camera's segment to them is (nearly) blocked, traced here one camera at a time
    left = drawn[torch.from_numpy(cKDTree(kept.numpy()).query(drawn.numpy())[0] > 1e-6)][:300]
    t = tracer()
    t.update(first[0.05])
    for c in cams:
        o = torch.tensor(c, dtype=torch.float32).expand(len(left), 3).contiguous()
        d = torch.nn.functional.normalize(left - o, dim=-1)
        assert float(t.trace(o, d, first[0.05]).transmittance.max()) < 0.05


def test_frozen_highlight_emitters_keep_their_geometry_and_are_not_relit(demo):
    """``highlight_frozen``: the emitters the highlight fill places at the end of warm-up join as priors (geometry
    frozen: trained free, those off the light grew into sheets under the ceiling) with the mirror fills' matte
    rule, so the plane fill's relighting, which follows them, leaves their radiance alone."""
    capture, init = demo
    cfg = dict(SMALL, iterations=12, warmup=10, prune_every=0, sphere_fill=False, highlight_frozen=True)
    trainer = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    n_fill = int(trainer.prior.sum())
    for _ in range(11):
        trainer.train_step()
    line = next(d for d in trainer.decisions if "emitting Gaussians where" in d)
    added = int(line.split("added ")[1].split()[0])
    assert added > 0, line
    rows = slice(len(trainer.prior) - added, None)  # the last fill added at that step
    assert bool(trainer.prior[rows].all()) and bool(trainer.reflected[rows].all())
    assert float(trainer.params["diffuse"][rows].mean()) > 1.0  # still lights: not relit like the plane fill
    relit = next(d for d in trainer.decisions if "plane fill relit" in d)
    assert f"{n_fill} of its {n_fill} Gaussians" in relit, relit
    for p in trainer.params.values():
        p.grad = torch.ones_like(p)
    trainer._freeze_priors()
    for name in ("means", "quats", "log_scales", "f0", "roughness"):
        assert bool((trainer.params[name].grad[rows] == 0).all()), name
    assert bool((trainer.params["diffuse"].grad[rows] == 1).all())


@pytest.mark.parametrize("growth_all", [False, True])
def test_highlight_emitters_on_a_wall_grow_at_most_the_growth_limit_also_after_a_checkpoint_and_a_prune(demo,
                                                                                                        growth_all):
    """``highlight_max_growth``: each scale of the highlight fill's emitters that ``highlight_to_walls`` moved onto
    a wall (with ``highlight_growth_all``: every emitter it placed) stays within that many times the median size
    the fill placed them all with (trained free, they grew into sheets up to 0.9 m under the demo's ceiling, one
    over its lamp); the others, placed by the sweep alone (zoo_corridor's, which training re-purposes), and every
    other Gaussian grow as before, and the limits follow the rows through a prune and a checkpoint."""
    capture, init = demo
    cfg = dict(SMALL, iterations=12, warmup=10, prune_every=0, sphere_fill=False, highlight_max_growth=2.0,
               highlight_to_walls=True, highlight_growth_all=growth_all)
    trainer = Trainer(capture, init, ReconstructConfig.from_dict(cfg), tracer())
    for _ in range(11):
        trainer.train_step()
    line = next(d for d in trainer.decisions if "emitting Gaussians where" in d)
    added = int(line.split("added ")[1].split()[0])
    snapped = int(line.split("; ")[1].split()[0])  # "...; N moved onto a wall placed just beyond; ..."
    assert "moved onto a wall" in line.split("; ")[1], line
    assert snapped < added, line  # emitters no wall took: growth_all caps them too
    n = len(trainer.prior)
    capped = torch.isfinite(trainer.scale_cap)
    assert int(capped.sum()) == (added if growth_all else snapped) and not bool(capped[:n - added].any())
    # a fill whose first and third Gaussians a wall took: only they get the limit, from the median of all
    extra = trainer.gaussians().subset(torch.arange(n - 4, n))
    rows = torch.tensor([True, False, True, False])
    trainer._replace(extra=extra, growth=2.0, growth_rows=rows)
    n = len(trainer.prior)
    placed = extra.log_scales.detach().amax(dim=1)
    assert torch.isfinite(trainer.scale_cap[n - 4:]).tolist() == rows.tolist()
    torch.testing.assert_close(trainer.scale_cap[n - 4:][rows], (placed.median() + math.log(2.0)).expand(2))
    capped = torch.isfinite(trainer.scale_cap)
    keep = torch.ones(n, dtype=torch.bool)
    keep[::3] = False  # a prune keeps the limits on their rows
    trainer._replace(keep=keep)
    state = trainer.state_dict()
    trainer.load_state_dict(state)
    was = capped
    capped = torch.isfinite(trainer.scale_cap)
    assert torch.equal(capped, was[keep])  # the same emitters, on their new rows
    with torch.no_grad():
        before = trainer.params["log_scales"].clone()
        trainer.params["log_scales"] += 5.0  # e^5 = 148x: what no emitter may keep
    trainer._clamp()
    ls = trainer.params["log_scales"].detach()
    assert bool((ls[capped] <= trainer.scale_cap[capped, None] + 1e-6).all())
    free = ~capped & ~trainer.fixed  # (the thickness limit clamps only their thinnest axis)
    grown = torch.isclose(ls[free].amax(dim=1), (before + 5.0)[free].amax(dim=1))
    assert float(grown.float().mean()) > 0.95


def test_hole_fill_is_decided_on_the_trained_model_logged_and_stored(monkeypatch):
    """``hole_fill: auto``: a trained model whose training views are opaque (a closed room: no training pixel
    keeps a transmittance above 0.5) renders with the hole fill, stored in its path settings (model.yaml) and
    said in the decisions log; one whose training views look past the scene (a wall missing) renders without
    it. Training itself never fills. ``on`` / ``off`` decide without tracing; an unknown mode is an error."""
    import models.reconstruction.trainer as trainer_module
    from models.gaussians import room_gaussians

    capture, init = _room()
    trainer = Trainer(capture, init, _room_config(), tracer())
    closed = room_gaussians(2000, torch.Generator().manual_seed(3), opacity_logit_mean=6.0)

    def decide(g):
        trainer.params = {k: v.clone().requires_grad_(True) for k, v in g.params().items()}
        trainer.hole_fill = None
        return trainer.settings().path.hole_fill

    assert decide(closed) is True
    assert "hole fill on in the renders: 0.00% of the training pixels" in trainer.decisions[-1]
    assert trainer.path_config(training=True).hole_fill is False and trainer.path_config().hole_fill is False
    # likewise the grazing offset: training starts reflections a fixed offset out, the model's renders do not
    assert trainer.path_config(training=True).origin_grazing == trainer.path_config().origin_grazing == 1.0
    assert trainer.settings().path.origin_grazing == trainer.config.origin_grazing == 0.1
    assert trainer.path_config(training=True).back_normal == trainer.path_config().back_normal == "flip"
    assert trainer.settings().path.back_normal == trainer.config.back_normal == "mirror"
    look = -torch.tensor(capture.split("train")[0].camera.c2w[:3, 2], dtype=torch.float32)  # the first view's axis
    axis = int(look.abs().argmax())
    gone = closed.means[:, axis] * look[axis].sign() > 0.9  # the wall it faces
    assert decide(Gaussians(**{k: v[~gone] for k, v in closed.params().items()})) is False
    assert "hole fill off (the training views look past the scene)" in trainer.decisions[-1]
    monkeypatch.setattr(trainer_module, "open_share", lambda *a, **k: 1 / 0)  # on / off never trace
    for mode, want in (("on", True), ("off", False)):
        forced = Trainer(capture, init, _room_config(hole_fill=mode), tracer())
        assert forced.settings().path.hole_fill is want
        assert f"hole fill {mode} (reconstruct.hole_fill)" in forced.decisions
    with pytest.raises(ValueError, match="hole_fill"):
        ReconstructConfig.from_dict({"hole_fill": "maybe"})
