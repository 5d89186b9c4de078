"""stage.json memory figures: on CUDA both allocators (torch's and Warp's pool) are reported, and their sum."""

import sys
import types

import torch

from stages.provenance import peak_memory


def test_cpu_reports_rss_only():
    out = peak_memory("cpu")
    assert set(out) == {"peak_rss_mib"} and out["peak_rss_mib"] > 0


def test_cuda_reports_torch_and_warp(monkeypatch):
    """A fake CUDA device (no GPU here): the keys, their sources and the sum."""
    mib = 2**20
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda: 300 * mib)
    monkeypatch.setattr(torch.cuda, "max_memory_reserved", lambda: 400 * mib)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda: (1000 * mib, 1600 * mib))
    fake_warp = types.SimpleNamespace(is_mempool_enabled=lambda device: True,
                                      get_mempool_used_mem_high=lambda device: 200 * mib)
    monkeypatch.setitem(sys.modules, "warp", fake_warp)
    out = peak_memory("cuda")
    assert out["peak_cuda_torch_mib"] == 300 and out["peak_cuda_torch_reserved_mib"] == 400
    assert out["peak_cuda_warp_mib"] == 200 and out["peak_cuda_mib"] == 500
    assert out["cuda_device_used_mib"] == 600
    # Warp allocating outside a pool: its figure is unknown (None), not 0, and the sum is torch's alone
    monkeypatch.setitem(sys.modules, "warp", types.SimpleNamespace(is_mempool_enabled=lambda device: False))
    out = peak_memory("cuda")
    assert out["peak_cuda_warp_mib"] is None and out["peak_cuda_mib"] == 300
