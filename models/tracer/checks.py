"""Deferred checks: the tracer's two host read-backs per trace, collected on the device and read once by the caller.

Every trace reads back whether a ray outgrew its replay buffer (then the trace re-runs with more slots) and whether
a direction has zero length (an error). On a GPU each read-back is a host-device synchronisation: the host waits for
the trace kernel instead of queueing the work after it (the training step's path sampling, losses, ...). Inside
``Tracer.deferred_checks()`` traces only collect both as device scalars; the caller adds ``flags()`` to a read-back
it makes anyway (the trainer: its step metrics) and passes the two numbers to ``settle``, which raises on a zero
direction and, when a trace was incomplete, grows the replay capacity and says so: the caller then redoes the work
(outputs of rays that outgrew the buffer are zeros until then), with the same random numbers, so the result is the
one a checked run gives.

    with tracer.deferred_checks() as checks:
        out = trace_paths(tracer.trace, ...)
    needed, zero_dirs = torch.stack([..., *checks.flags()]).tolist()[-2:]
    if checks.settle(needed, zero_dirs):
        ...  # redo without deferral
"""

from __future__ import annotations

from typing import Callable

import torch

ZERO_DIRS_MESSAGE = "dirs contains zero-length directions"


class DeferredChecks:
    """Device scalars collected by the traces run inside ``Tracer.deferred_checks()``."""

    def __init__(self, device: torch.device, grow: Callable[[int], None]):
        self.device = device
        self.grow = grow                          # the tracer's: make room for a ray that needed this many slots
        self.needed: list[torch.Tensor] = []     # per trace: the most replay slots a ray needed (0: none overflowed)
        self.zero_dirs: list[torch.Tensor] = []  # per trace: how many directions had zero length

    def flags(self) -> torch.Tensor:
        """[2] float64 on the device: (most slots a ray needed, 0 if none overflowed; zero-length directions)."""
        zero = torch.zeros((), dtype=torch.float64, device=self.device)
        needed = torch.stack(self.needed).max().double() if self.needed else zero
        zeros = torch.stack(self.zero_dirs).sum().double() if self.zero_dirs else zero
        return torch.stack([needed, zeros])

    def settle(self, needed: float, zero_dirs: float) -> bool:
        """The read-back values of ``flags()``: raises on zero directions; True (capacity grown) when a trace was
        incomplete and the work must be redone."""
        if zero_dirs > 0:
            raise ValueError(ZERO_DIRS_MESSAGE)
        if needed > 0:
            self.grow(int(needed))
            return True
        return False
