"""How many threads each compiled step runs on: a governor that watches step times.

A compiled explicit step on several OpenMP threads is fast on an idle machine, but when another
process holds a core, the thread sharing that core holds up the others at every barrier: at 64^3
on 2 cores a step took 2.6 ms idle and 5-8 ms beside a busy process, slower than one thread alone
(about 5 ms, on the free core). The compiled code is therefore generated for a thread count
chosen at run time (inductor's ``cpp.dynamic_threads``), and :class:`ThreadGovernor` picks that
count step by step:

* It starts on one thread when other processes kept at least half a core busy lately
  (:func:`recent_load`: for a command, over torch's import).
* It stays on its current count while the step times hold. When the median of the last
  ``window`` steps stays above ``jump`` times the best median seen at that count for another
  ``window`` steps (a process started beside it, not a hiccup), or when the first window finds other processes busy on the machine
  (:func:`others_busy`, from ``/proc/stat``), it probes: ``probe`` steps on the next smaller
  count.
* It moves to the probed count when that is faster by the ``margin``; otherwise it goes back.
* Away from the full count it probes the full count again every ``period`` steps, the period
  doubling up to ``max_period`` while the probes lose, so it returns when the machine is free; not
  while ``/proc/stat`` shows the machine still busy (a probe of two threads beside a busy process
  cost 0.1 s on the demo's liver).

On an idle machine nothing jumps and nothing is probed: the governor costs one clock read per
step. The first step on a new count makes dynamo trace the step again (its guards include the
thread count; about 1 s, the generated code comes from inductor's cache), and that step is not
counted as a probe sample.

Example (a made-up machine: 2.6 ms per step on 2 threads when idle, 7 ms beside a busy
process, 5 ms on one thread either way):

    >>> def step_ms(n, busy):
    ...     return 5.0 if n == 1 else (7.0 if busy else 2.6)
    >>> gov = ThreadGovernor(2, busy_cores=None)  # busy_cores=None: no look at /proc/stat
    >>> def run(steps, busy):
    ...     for _ in range(steps):
    ...         n = gov.choose()
    ...         gov.record(n, step_ms(n, busy) / 1e3)
    >>> run(50, busy=False); gov.current
    2
    >>> run(50, busy=True); gov.current      # the times jumped: one thread probed, and kept
    1
    >>> run(100, busy=False); gov.current    # the full count is probed again now and then
    2
"""

from __future__ import annotations

import contextlib
import statistics
import time
from collections import Counter, deque

import torch

from .. import cpu_load
from ..cpu_load import CpuSampler, others_busy

__all__ = [
    "ThreadGovernor",
    "CpuSampler",
    "others_busy",
    "omp_threads",
    "after_step_threads",
    "setup_threads",
    "recent_load",
]

#: other processes keeping this many cores busy make small work run on one thread
BUSY_CORES = 0.5


#: the window :func:`recent_load` reads: from the package's import, then from its latest reading
_window: CpuSampler = cpu_load.since_import
#: the latest reading: ``(cores, time.perf_counter())``
_last: tuple | None = None


def recent_load(*, max_age: float = 10.0) -> float | None:
    """Cores other processes kept busy lately, with no wait: None when nothing recent is known.

    Read over the window since the package's import or since the previous reading, when that window
    is long enough to tell (~0.1 s) and at most ``max_age`` seconds old; else the previous reading
    if it is that recent. A command's first reading covers torch's import.
    """
    global _window, _last
    now = time.perf_counter()
    if now - _window.start[2] > max_age:  # an old window averages over what no longer is
        _window = CpuSampler()
    else:
        others = _window.others()
        if others is not None:
            _window, _last = CpuSampler(), (others, now)
            return others
    return _last[0] if _last is not None and now - _last[1] <= max_age else None


@contextlib.contextmanager
def omp_threads(n: int):
    """Run the block with ``n`` OpenMP threads in the calling thread, then restore torch's setting."""
    before = torch.get_num_threads()
    if n == before:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class ThreadGovernor:
    """Chooses the thread count of every compiled step from the step times (module docstring).

    Use: ``n = gov.choose()``, run the step on ``n`` threads (:func:`omp_threads`), then
    ``gov.record(n, seconds)``.

    Args:
        threads: the full thread count (the first choice).
        window: steps whose median is the current step time.
        probe: steps timed on another count before deciding.
        jump: a window median above ``jump`` x the best one at this count starts a probe.
        margin: move to the probed count when its median is below ``margin`` x the current one.
        period, max_period: away from the full count, probe it again after ``period`` steps,
            doubling after every lost probe up to ``max_period``.
        busy_cores: other processes keeping this many cores busy start on one thread (the load of
            the last seconds, :func:`recent_load`, where known) or start a probe (checked once, over
            the first ~0.1 s of steps, where it is not); away from the full count they hold off its
            probes. None: no look at the load.

    Attributes:
        current: the count steps run on (outside probes).
        steps: ``Counter`` of steps per thread count.
        switches: how many times :attr:`current` changed.
        recent: the latest step times (s) on the current count, at most ``window`` of them.
    """

    def __init__(
        self,
        threads: int,
        *,
        window: int = 8,
        probe: int = 3,
        jump: float = 1.5,
        margin: float = 0.9,
        period: int = 32,
        max_period: int = 512,
        busy_cores: float = BUSY_CORES,
    ):
        self.full = self.current = max(1, int(threads))
        self.options = sorted({self.full, max(1, self.full // 2), 1}, reverse=True)
        self.window, self.probe_steps, self.jump, self.margin = int(window), int(probe), float(jump), float(margin)
        self.base_period, self.max_period, self.busy_cores = int(period), int(max_period), busy_cores
        self.recent: deque = deque(maxlen=self.window)
        self.best = float("inf")
        self.period = self.countdown = self.base_period
        self.probing: int | None = None
        self.probe_times: list = []
        self.seen: set = set()  # counts run so far (a first step traces: not timed)
        self.steps: Counter = Counter()
        self.switches = 0
        self.slow = 0  # steps in a row whose window is above jump x best
        #: started at the first recorded step (not during the compile, whose compiler runs beside it)
        self._sampler: CpuSampler | None = None
        self._sample = self.full > 1 and busy_cores is not None
        #: the machine's load since the last probe of the full count (None: not watched)
        self._load: CpuSampler | None = None
        if self._sample:
            known = recent_load()
            if known is not None:  # the load before the run (the set-up) already tells: no first look
                self._sample = False
                if known > busy_cores:
                    self.current = self._smaller()
                    self._load = CpuSampler()

    @property
    def settled(self) -> bool:
        """Whether the step times now say what a step costs on this machine.

        The first look at the machine's load is done (or not asked for), no probe is under way, and
        ``recent`` holds at least ``probe`` steps on the current count. Until then a step may run
        on a count the governor is about to leave (two threads beside a busy process: many times
        slower).
        """
        return not self._sample and self.probing is None and len(self.recent) >= min(self.window, self.probe_steps)

    def choose(self) -> int:
        """The thread count of the next step."""
        return self.probing if self.probing is not None else self.current

    def record(self, threads: int, seconds: float) -> None:
        """Account one step of ``seconds`` on ``threads`` threads (the count :meth:`choose` gave)."""
        self.steps[threads] += 1
        if self._sample and self._sampler is None:
            self._sampler = CpuSampler()
        if threads not in self.seen:  # the first step on a count traces it again
            self.seen.add(threads)
            return
        if self.probing is not None:
            self.probe_times.append(seconds)
            if len(self.probe_times) >= self.probe_steps:
                self._conclude()
            return
        self.recent.append(seconds)
        if len(self.recent) < self.window or len(self.options) == 1:
            return
        now = statistics.median(self.recent)
        if self._sample:  # once (after ~0.1 s of steps): is the machine busy from the start?
            assert self._sampler is not None  # started at the first recorded step
            others = self._sampler.others()
            if others is not None:
                self._sample = False
                if others > self.busy_cores and self.current == self.full:
                    self._load = CpuSampler()
                    return self._start(self._smaller())
        if now <= self.best:
            self.best = now
        if now > self.jump * self.best and self.current != self.options[-1]:
            # a jump that lasts a whole window (not one hiccup of the host): probe, which on a
            # new count costs a trace
            self.slow += 1
            if self.slow > self.window:
                return self._start(self._smaller())
        else:
            self.slow = 0
        if self.current != self.full:
            self.countdown -= 1
            if self.countdown <= 0:
                if self._load is not None and self.busy_cores is not None:
                    others = self._load.others()
                    if others is None and self._load.start[0] is not None:  # too short to tell: wait
                        self.countdown = self.period
                        return
                    if others is not None and others > self.busy_cores:
                        # still busy beside it: a probe would only cost steps on the full count
                        self._load, self.countdown = CpuSampler(), self.period
                        return
                self._start(self.full)

    def _smaller(self) -> int:
        return next(n for n in self.options if n < self.current)

    def _start(self, n: int) -> None:
        self.probing, self.probe_times, self.slow = n, [], 0

    def _conclude(self) -> None:
        # against the latest steps on the current count (the window may still hold older ones)
        probing = self.probing
        assert probing is not None  # the end of a probe
        now = statistics.median(list(self.recent)[-self.probe_steps :])
        probed = statistics.median(self.probe_times)
        if probed < self.margin * now:
            if probing < self.current and self.busy_cores is not None:
                self._load = CpuSampler()  # watch the load: no probe of the full count while it stays busy
            self.current, self.switches = probing, self.switches + 1
            self.recent.clear()
            self.recent.extend(self.probe_times)
            self.best = probed
            self.period = self.base_period
        else:  # the probe lost: this is the new normal
            self.best = now
            if self.current != self.full:
                self.period = min(2 * self.period, self.max_period)
        self.countdown = self.period
        self.probing = None

    def summary(self) -> dict:
        """``{"threads": current, "steps_per_threads": {n: steps}, "switches": k}``."""
        return {
            "threads": self.current,
            "steps_per_threads": dict(sorted(self.steps.items())),
            "switches": self.switches,
        }


def after_step_threads(*, busy: float | None = None, since: CpuSampler | None = None) -> int:
    """Threads for the work after a simulation (outputs, plots, renders): one beside a busy process.

    Small tensor operations on several OpenMP threads wait at every barrier for the thread that
    shares its core with another process (a thousand times longer than on one thread), so the
    post-processing of a run takes one thread when other processes keep at least half a core busy
    (``busy``: cores; else measured by ``since``, a :class:`CpuSampler` started before the
    simulation, at no cost; else :func:`others_busy` over 0.1 s), and torch's setting otherwise.
    On one thread already there is nothing to choose (and nothing is measured).

    Examples:
        >>> after_step_threads(busy=1.0)
        1
        >>> after_step_threads(busy=0.0) == torch.get_num_threads()
        True
    """
    if torch.get_num_threads() == 1:
        return 1
    if busy is None and since is not None:
        busy = since.others()  # None when the run was too short to tell
    if busy is None:
        busy = others_busy(seconds=0.1)
    return _one_if_busy(busy)


def _one_if_busy(busy: float | None) -> int:
    """One thread when other processes keep :data:`BUSY_CORES` or more busy, else torch's setting."""
    return 1 if busy is not None and busy >= BUSY_CORES else torch.get_num_threads()


def setup_threads() -> int:
    """Threads for a run's set-up (building the body, its stability bound, settling): one beside a busy process.

    As :func:`after_step_threads`, with the load of the last seconds (:func:`recent_load`; for a
    command, over torch's import) and no wait: torch's setting when nothing recent is known.
    Beside a busy process the demo's set-up (its liver and stability bound) took 11.8 s on two threads
    and 2.6 s on one, as long as on an idle machine.

    Examples:
        >>> setup_threads() in (1, torch.get_num_threads())
        True
    """
    return 1 if torch.get_num_threads() == 1 else _one_if_busy(recent_load())
