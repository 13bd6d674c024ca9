"""How busy the machine is, seen from this process: CPU samples from ``/proc/stat``, without torch.

Beside a process that keeps a core busy, small tensor work on several OpenMP threads waits at
every barrier for the thread that shares its core (see :mod:`torchdeform.sim.threads`, which
chooses thread counts from these samples). :data:`since_import` starts when the package is
imported, before torch is: torch's import (about a second) is the first sample, so the first thread
count of a command is chosen with no wait of its own.

Example:
    >>> from torchdeform.cpu_load import CpuSampler
    >>> s = CpuSampler()
    >>> busy = s.others()      # None until ~0.1 s of CPU time has passed (or without /proc/stat)
    >>> busy is None or busy > -1.0
    True
"""

from __future__ import annotations

import os
import time

__all__ = ["CpuSampler", "others_busy", "since_import"]


def _machine_jiffies():
    """``(busy, total)`` CPU jiffies of the whole machine from ``/proc/stat``, or None elsewhere."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            vals = [int(v) for v in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    idle = vals[3] + vals[4]
    return sum(vals) - idle, sum(vals)


class CpuSampler:
    """CPU use of the machine and of this process since construction (see :func:`others_busy`).

    Start one before some work and ask :meth:`others` after it: how many cores other processes kept
    busy meanwhile, with no wait of its own.
    """

    def __init__(self):
        self.start = (_machine_jiffies(), time.process_time(), time.perf_counter())

    def others(self) -> float | None:
        """Cores kept busy by other processes since construction, or None (no ``/proc/stat``, too short)."""
        (m0, p0, w0), m1 = self.start, _machine_jiffies()
        wall = time.perf_counter() - w0
        if m0 is None or m1 is None or m1[1] - m0[1] < 10 * (os.cpu_count() or 1) or wall <= 0:
            return None
        cores = (os.cpu_count() or 1) * (m1[0] - m0[0]) / (m1[1] - m0[1])
        return cores - (time.process_time() - p0) / wall


def others_busy(*, seconds: float = 0.2) -> float | None:
    """Cores that other processes kept busy during ``seconds`` (Linux ``/proc/stat``), or None.

    Examples:
        >>> busy = others_busy(seconds=0.1)
        >>> busy is None or busy > -1.0
        True
    """
    s = CpuSampler()
    time.sleep(seconds)
    return s.others()


#: started when the package is imported (before torch); the first window that
#: :func:`torchdeform.sim.threads.recent_load` reads
since_import = CpuSampler()
