"""Section timers for a training step (``python -m stages.benchmark train-step``).

The trainer and the tracer time named sections through ``self.timer``; by default that is ``NO_TIMER``, whose
sections do nothing (no clock, no device synchronisation). A ``SectionTimer`` records wall time per section,
EXCLUSIVE of the sections nested in it (a path-sampling section that calls the tracer does not count the tracer's
kernels), and synchronises the device at every boundary so that asynchronous CUDA work lands in the section that
queued it. Whatever a step spends outside every section is its host overhead.
"""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager, nullcontext
from typing import Callable


class NullTimer:
    """The default: sections cost one no-op context manager."""

    enabled = False

    def section(self, name: str):
        return nullcontext()


NO_TIMER = NullTimer()


def device_sync(device: str) -> Callable[[], None]:
    """The synchronisation a ``SectionTimer`` on ``device`` ("cpu", "cuda[:i]") needs at each boundary: torch's
    and Warp's CUDA streams on CUDA, nothing on the CPU (every launch there is synchronous)."""
    if not str(device).startswith("cuda"):
        return lambda: None
    import torch
    import warp as wp

    def sync() -> None:
        torch.cuda.synchronize()
        wp.synchronize()

    return sync


class SectionTimer:
    """Wall milliseconds per section name, exclusive of nested sections, summed until ``take()``."""

    enabled = True

    def __init__(self, sync: Callable[[], None] | None = None):
        self.sync = sync or (lambda: None)
        self.totals: dict[str, float] = defaultdict(float)  # name -> ms
        self._stack: list[list] = []  # [name, ms spent in nested sections]

    @contextmanager
    def section(self, name: str):
        self.sync()
        start = time.perf_counter()
        self._stack.append([name, 0.0])
        try:
            yield
        finally:
            self.sync()
            elapsed = (time.perf_counter() - start) * 1e3
            _, nested = self._stack.pop()
            self.totals[name] += elapsed - nested
            if self._stack:
                self._stack[-1][1] += elapsed

    def take(self) -> dict[str, float]:
        """The totals so far (ms per section), then start again from zero."""
        out = dict(self.totals)
        self.totals.clear()
        return out
