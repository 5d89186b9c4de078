"""Benchmark stage: --quick run writes JSON with every key and sane values (never timing thresholds)."""

import json
import math

import pytest

from stages.benchmark.__main__ import main, parse_args
from stages.benchmark.tracer import TARGETS

ROW_KEYS = {
    "n_gaussians", "resolution", "rays", "threads", "forward_ms", "forward_cpu_ms", "forward_backward_ms",
    "forward_backward_cpu_ms", "autograd_forward_backward_ms", "fused_over_forward", "refit_ms", "rebuild_ms",
    "step_ms", "refit_share", "rebuild_share", "kbuffer_forward_ms", "single_vs_kbuffer_speedup",
    "aabb_forward_ms", "forward_ms_by_threads", "thread_scaling", "candidates_per_ray_aabb",
    "candidates_per_ray_obb", "accepted_per_ray", "blended_per_ray", "mean_transmittance", "replay_capacity",
    "overflow_rays_first_trace", "targets_met", "refit_cpu_ms", "rebuild_cpu_ms", "kbuffer_forward_cpu_ms",
    "aabb_forward_cpu_ms", "fused_over_forward_cpu", "single_vs_kbuffer_speedup_cpu", "refit_share_cpu",
    "ordered_forward_ms", "ordered_forward_cpu_ms", "forward_parallelism", "ordered_candidates_per_ray",
    "ordered_hits_found_per_ray",
}


def test_quick_benchmark_writes_complete_json(tmp_path, capsys):
    out = tmp_path / "bench" / "tracer.json"
    assert main(["tracer", "--quick", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["benchmark"] == "tracer" and set(data["targets"]) >= set(TARGETS)
    assert {"torch", "warp", "device", "wall_s", "load_average"} <= set(data["provenance"])
    (row,) = data["results"]
    assert ROW_KEYS <= set(row), ROW_KEYS - set(row)
    for key in ROW_KEYS - {"forward_ms_by_threads", "targets_met"}:
        assert isinstance(row[key], (int, float)) and math.isfinite(row[key]) and row[key] >= 0, key
    for key in ("forward_ms", "forward_backward_ms", "kbuffer_forward_ms", "aabb_forward_ms", "refit_ms"):
        assert row[key] > 0, key
    assert 0 < row["refit_share"] < 1 and 0 < row["rebuild_share"] < 1
    assert set(row["forward_ms_by_threads"]) == {"1", "2"}
    # counts: world AABB candidates >= oriented-box candidates >= found (blended + 1 if truncated) >= blended > 0
    assert row["candidates_per_ray_aabb"] >= row["candidates_per_ray_obb"] >= row["accepted_per_ray"]
    assert row["accepted_per_ray"] >= row["blended_per_ray"] > 0
    assert 0 <= row["mean_transmittance"] <= 1
    assert row["ordered_hits_found_per_ray"] >= row["blended_per_ray"]  # (found: at least what it blends)
    assert set(row["targets_met"]) >= set(TARGETS)
    # the scene types: our default traversal blends what the single traversal blends, examines fewer Gaussians
    # than exist along the rays on the deep scenes, and Mitsuba rendered the same rays
    assert [r["scene"] for r in data["scenes"]] == ["room", "deep", "dense_room", "million"]
    for r in data["scenes"]:
        assert r["same_as_single"], r["scene"]
        for key in ("forward_ms", "single_forward_ms", "mitsuba_ms", "ours_over_mitsuba", "fused_over_forward",
                    "candidates_per_blended", "mitsuba_mean_abs_diff"):
            assert math.isfinite(r[key]) and r[key] > 0, (r["scene"], key)
        assert r["hits_found_per_ray"] <= r["accepted_per_ray"] + 1e-9
        assert r["mitsuba_mean_abs_diff"] < 0.2  # the same Gaussians (Mitsuba composites in shell-entry order)
        # an exact-order traversal examines at least the floor's boxes (per blended hit >= 1 when any is blended)
        assert 1.0 <= r["exact_order_floor"] <= r["candidates_per_blended"] * 1.15, r["scene"]  # (a ray sample)
    deep = next(r for r in data["scenes"] if r["scene"] == "deep")
    assert deep["candidates_per_blended"] < deep["single_candidates_per_blended"]
    assert all(r["wide_bvh"] for r in data["scenes"])  # the CPU default: the 8-wide tree
    printed = capsys.readouterr().out
    assert "fwd+bwd ms" in printed and "ours/mi" in printed and "8-wide tree" in printed


@pytest.mark.parametrize("scene", ["room", "deep", "dense_room"])
def test_exact_order_floor_bounds_what_the_traversals_examine(scene):
    """The floor of an exact t*-order traversal (every box entered before the t* of the last hit a ray needs) is a
    lower bound, ray by ray, of the boxes our traversals evaluate; and it counts the blended hits of the tracer."""
    import torch

    from models.tracer import Tracer, TracerConfig
    from stages.benchmark.floor import exact_order_floor
    from stages.benchmark.scene import scene_type

    gs, origins, dirs = scene_type(scene, 24, 4000, seed=5)
    for traversal in ("interval", "ordered"):
        tracer = Tracer(TracerConfig(num_threads=1, traversal=traversal))
        out = tracer.trace(origins, dirs, gs)
        lo, hi = (torch.from_numpy(a.numpy()) for a in (tracer.bvh.lowers, tracer.bvh.uppers))
        floor = exact_order_floor(gs, origins, dirs, lo, hi, tracer.config, rays=96, seed=1)
        pick = floor["picked"]
        same = out.blended_count[pick] == floor["blended"]  # float64 vs float32: a rare near-tie may differ
        assert same.float().mean() > 0.95, (scene, traversal)
        # float32 box entries vs float64: allow one box of slack where a box is entered at the needed hit's t*
        assert bool((out.candidates[pick][same] >= floor["boxes"][same] - 1).all()), (scene, traversal)
        assert floor["floor"] >= 1.0


def test_cli_rejects_bad_lists():
    with pytest.raises(SystemExit):
        parse_args(["tracer", "--sizes", "a,b"])
    with pytest.raises(ValueError, match="sizes"):
        parse_args(["tracer", "--sizes", "0"])
    with pytest.raises(ValueError, match=r"unknown scene type\(s\) \['cave'\]"):
        parse_args(["tracer", "--scenes", "room,cave"])
    _, cfg, _ = parse_args(["tracer", "--sizes", "1000", "--res", "8", "--threads", "1"])
    assert cfg.sizes == [1000] and cfg.resolutions == [8] and cfg.threads == [1] and cfg.wide_bvh
    _, cfg, _ = parse_args(["tracer", "--binary-bvh", "--octants", "never"])
    assert not cfg.wide_bvh and cfg.octants == "never"


TRAIN_STEP_KEYS = {"device", "rays", "whole_view", "n_gaussians", "step_ms", "step_ms_min", "step_cpu_ms",
                   "profiled_step_ms", "tracer_forward_ms", "tracer_backward_ms", "bvh_update_ms", "path_sampling_ms",
                   "losses_ms", "autograd_ms", "optimizer_ms", "tracer_host_ms", "host_ms", "other_host_ms"}


def test_train_step_quick_writes_complete_json(tmp_path, capsys):
    """The real training step, split into sections that add up to the profiled step (never timing thresholds)."""
    out = tmp_path / "train_step.json"
    assert main(["train-step", "--quick", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["benchmark"] == "train-step"
    rows = data["results"]
    assert [(r["rays"], r["whole_view"]) for r in rows] == [(64, None), (256, None), (32 * 24, "32x24")]
    for r in rows:
        assert TRAIN_STEP_KEYS <= set(r), TRAIN_STEP_KEYS - set(r)
        for key in TRAIN_STEP_KEYS - {"device", "whole_view", "other_host_ms"}:
            assert math.isfinite(r[key]) and r[key] >= 0, key
        assert r["tracer_forward_ms"] > 0 and r["tracer_backward_ms"] > 0 and r["optimizer_ms"] > 0
        work = sum(r[f"{k}_ms"] for k in ("tracer_forward", "tracer_backward", "bvh_update", "path_sampling",
                                           "losses", "autograd", "optimizer"))
        assert work <= r["profiled_step_ms"] * 1.5  # medians per section: their sum is about the step's
        assert r["n_gaussians"] == 2000  # no far field, no pruning: every step does the same work
    assert data["overhead_floor"]["cpu"]["rays"] == 64
    assert data["memory"]["cpu"]["peak_rss_mib"] > 0  # on CUDA also torch's and Warp's peaks
    printed = capsys.readouterr().out
    assert "trace fwd" in printed and "overhead floor (cpu, 64 rays)" in printed


def test_train_step_times_a_real_run_resumed_from_its_checkpoint(tmp_path, capsys):
    """--checkpoint: the run's own Trainer at the checkpoint's step (its Gaussians, its config), not the random
    room; a checkpoint of another config still loads and the difference is reported; the four arguments go
    together."""
    import dataclasses

    from models.reconstruction import ReconstructConfig, Trainer
    from models.settings import to_dict
    from models.tracer import Tracer, TracerConfig
    from stages.benchmark.room_capture import room_capture
    from stages.benchmark.train_step import TrainStepBenchmarkConfig, bench_checkpoint

    capture, init = room_capture(Tracer(TracerConfig(num_threads=1)), 2000, 2, 32, 24, seed=3)
    config = ReconstructConfig(iterations=100, warmup=0, rays_per_step=64, far_field="off", prune_every=0,
                               checkpoint_every=100)
    trainer = Trainer(capture, init, config, Tracer(config.tracer))
    for _ in range(3):
        trainer.train_step()
    ckpt = tmp_path / "last.pt"
    trainer.save_checkpoint(ckpt)
    cfg = TrainStepBenchmarkConfig(steps=2, warmup_steps=1, threads=1)
    row = bench_checkpoint(to_dict(config, runtime=False), capture, init, ckpt, "cpu", cfg)
    assert row["step"] == 3 and row["rays"] == 64 and row["checkpoint_config"] is None
    assert row["n_gaussians"] == len(trainer.params["means"])
    assert TRAIN_STEP_KEYS <= set(row) and row["tracer_forward_ms"] > 0

    notes = []
    other = to_dict(dataclasses.replace(config, rays_per_step=32), runtime=False)
    row = bench_checkpoint(other, capture, init, ckpt, "cpu", cfg, progress=notes.append)
    assert row["rays"] == 32 and "rays_per_step" in row["checkpoint_config"] and "rays_per_step" in notes[0]

    assert main(["train-step", "--checkpoint", str(ckpt), "--scene", "demo"]) == 1
    assert "missing --capture, --init" in capsys.readouterr().err
    bad = ["train-step", "--checkpoint", str(ckpt), "--capture", str(tmp_path / "nope"), "--init", str(ckpt)]
    assert main([*bad, "--scene", "no_such_scene"]) == 1
    assert "unknown scene 'no_such_scene'" in capsys.readouterr().err
    assert main([*bad, "--scene", "demo"]) == 1
    assert f"{tmp_path / 'nope'}: not a capture" in capsys.readouterr().err

def test_gpu_busy_is_the_median_nvml_utilisation_while_steps_repeat(monkeypatch):
    """GPU busy: NVML's utilisation (percent) sampled while the step repeats, the first quarter of the samples
    dropped (NVML averages over its own period, which may reach back before the loop), median, as a fraction;
    None where NVML cannot answer (no GPU, no pynvml): no figure rather than an error."""
    import torch

    from stages.benchmark.train_step import gpu_busy

    values = iter([0] + [70, 80, 90] * 1000)  # the probe call, then the samples
    monkeypatch.setattr(torch.cuda, "utilization", lambda *a: next(values, 80))
    steps = []
    busy = gpu_busy(lambda: steps.append(1), lambda: None, seconds=0.3, interval=0.01)
    assert steps and busy in (0.7, 0.75, 0.8, 0.85, 0.9)

    def no_nvml(*a):
        raise RuntimeError("pynvml does not seem to be installed")

    monkeypatch.setattr(torch.cuda, "utilization", no_nvml)
    assert gpu_busy(lambda: None, lambda: None, seconds=0.05) is None


def test_section_timer_is_exclusive_of_nested_sections():
    import time

    from models.profiling import NO_TIMER, SectionTimer

    timer = SectionTimer()
    with timer.section("outer"):
        time.sleep(0.02)
        with timer.section("inner"):
            time.sleep(0.03)
    with timer.section("inner"):
        time.sleep(0.01)
    totals = timer.take()
    assert 15 < totals["outer"] < 28, totals  # 20 ms of its own, not the inner 30
    assert totals["inner"] >= 38, totals
    assert timer.take() == {}
    with NO_TIMER.section("anything"):  # the default costs nothing and records nothing
        pass


def test_buffernet_step_runs_the_training_step(tmp_path, capsys):
    out = tmp_path / "bn.json"
    assert main(["buffernet-step", "--init", "tiny", "--size", "16", "--steps", "1", "--device", "cpu",
                 "--out", str(out)]) == 0
    r = json.loads(out.read_text())["result"]
    for key in ("step_ms", "vae_encode_ms", "unet_forward_backward_ms", "optimizer_ms", "loss", "peak_rss_mib"):
        assert math.isfinite(r[key]) and r[key] > 0, key
    assert r["unet_parameters"] > 0
    assert "UNet fwd+bwd" in capsys.readouterr().out
    assert main(["buffernet-step", "--init", "tiny", "--dtype", "bf16", "--device", "cpu"]) == 1  # CPU: fp32 only
