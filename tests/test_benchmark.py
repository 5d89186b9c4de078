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
    # counts: world AABB candidates >= oriented-box candidates >= accepted >= blended > 0
    assert row["candidates_per_ray_aabb"] >= row["candidates_per_ray_obb"] >= row["accepted_per_ray"]
    assert row["accepted_per_ray"] >= row["blended_per_ray"] > 0
    assert 0 <= row["mean_transmittance"] <= 1
    assert row["ordered_hits_found_per_ray"] <= row["accepted_per_ray"]
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
    deep = next(r for r in data["scenes"] if r["scene"] == "deep")
    assert deep["candidates_per_blended"] < deep["single_candidates_per_blended"]
    printed = capsys.readouterr().out
    assert "fwd+bwd ms" in printed and "ours/mi" in printed


def test_cli_rejects_bad_lists():
    with pytest.raises(SystemExit):
        parse_args(["tracer", "--sizes", "a,b"])
    with pytest.raises(ValueError, match="sizes"):
        parse_args(["tracer", "--sizes", "0"])
    with pytest.raises(ValueError, match=r"unknown scene type\(s\) \['cave'\]"):
        parse_args(["tracer", "--scenes", "room,cave"])
    _, cfg, _ = parse_args(["tracer", "--sizes", "1000", "--res", "8", "--threads", "1"])
    assert cfg.sizes == [1000] and cfg.resolutions == [8] and cfg.threads == [1]
