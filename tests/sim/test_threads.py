"""The thread governor of compiled steps, against a made-up machine whose step times are known.

The oracle is the machine model itself: the governor must end on the count that is faster there,
not probe an idle machine at all, and come back to the full count when the machine frees up.
One slow test compiles a small step with run-time threads and checks it against the eager step.
"""

import random

import pytest
import torch

import torchdeform as td
from torchdeform.sim import threads as T
from torchdeform.sim.compiled import CompiledStep
from torchdeform.sim.threads import ThreadGovernor, omp_threads


class Machine:
    """Step times (s) of a 2-thread step: 2.6 ms idle, 7 ms beside a busy process; 1 thread: 5 ms; +-10% noise."""

    def __init__(self, seed=0):
        self.busy, self.rng = False, random.Random(seed)

    def __call__(self, n):
        base = 5.0 if n == 1 else (7.0 if self.busy else 2.6)
        return base * self.rng.uniform(0.9, 1.1) / 1e3


def _run(gov, machine, steps):
    total = 0.0
    for _ in range(steps):
        n = gov.choose()
        t = machine(n)
        gov.record(n, t)
        total += t
    return total


def test_an_idle_machine_is_never_probed():
    gov, machine = ThreadGovernor(2, busy_cores=None), Machine()
    _run(gov, machine, 2000)
    assert gov.steps == {2: 2000} and gov.switches == 0 and gov.current == 2


def test_a_busy_neighbour_moves_the_step_to_one_thread_and_back():
    gov, machine = ThreadGovernor(2, busy_cores=None), Machine(1)
    _run(gov, machine, 100)
    machine.busy = True
    steps_before = dict(gov.steps)
    governed = _run(gov, machine, 600)
    assert gov.current == 1
    assert gov.steps[1] - steps_before.get(1, 0) > 500  # most busy steps ran on one thread
    fixed = sum(machine(2) for _ in range(600))  # what 2 threads would have cost
    assert governed < 0.85 * fixed
    machine.busy = False
    _run(gov, machine, 600)
    assert gov.current == 2  # the full count won a later probe


def test_a_machine_busy_from_the_start_is_noticed(monkeypatch):
    monkeypatch.setattr(T, "recent_load", lambda: None)  # nothing known before the run: the first window looks
    monkeypatch.setattr(T.CpuSampler, "others", lambda self: 1.0)  # /proc/stat: one core busy elsewhere
    gov, machine = ThreadGovernor(2), Machine(2)
    machine.busy = True  # no jump to see: it was busy all along
    _run(gov, machine, 200)
    assert gov.current == 1 and gov.switches == 1


def test_a_load_known_before_the_run_starts_it_on_one_thread_and_no_probe_runs_while_it_lasts(monkeypatch):
    """Busy before and during the run: every step on one thread (a probe of two threads beside a busy
    process cost 0.1 s on the demo's liver); free again: the full count is probed and kept."""
    load = {"cores": 1.0}
    monkeypatch.setattr(T, "recent_load", lambda: load["cores"])  # the set-up saw a core busy elsewhere
    monkeypatch.setattr(T.CpuSampler, "others", lambda self: load["cores"])
    gov, machine = ThreadGovernor(2), Machine(3)
    machine.busy = True
    _run(gov, machine, 3000)
    assert gov.steps == {1: 3000} and gov.switches == 0
    load["cores"], machine.busy = 0.0, False
    _run(gov, machine, 600)
    assert gov.current == 2 and gov.switches == 1


def test_a_load_too_short_to_measure_delays_the_probe(monkeypatch):
    """A window of a few fast steps says nothing (fewer than 10 jiffies a core): no probe until it does."""
    monkeypatch.setattr(T, "recent_load", lambda: 1.0)
    gov = ThreadGovernor(2)
    monkeypatch.setattr(T.CpuSampler, "others", lambda self: None)  # every window too short
    _run(gov, lambda n: 1e-4, 2000)
    assert gov.steps == {1: 2000}


def test_recent_load_reads_windows_of_at_least_a_tenth_of_a_second(monkeypatch):
    """Oracle: a stand-in sampler that tells once its window is long enough; the reading is kept
    for the calls that follow within ``max_age`` and forgotten after it."""
    clock = {"t": 100.0}
    monkeypatch.setattr(T.time, "perf_counter", lambda: clock["t"])

    class Sampler:
        def __init__(self):
            self.start = (None, 0.0, clock["t"])

        def others(self):
            return 0.8 if clock["t"] - self.start[2] >= 0.1 else None

    monkeypatch.setattr(T, "CpuSampler", Sampler)
    monkeypatch.setattr(T, "_window", Sampler())
    monkeypatch.setattr(T, "_last", None)
    assert T.recent_load() is None  # nothing yet, and no wait for it
    clock["t"] += 1.0  # torch's import
    assert T.recent_load() == 0.8
    clock["t"] += 0.05
    assert T.recent_load() == 0.8  # too short a window: the latest reading
    clock["t"] += 30.0
    assert T.recent_load() is None  # an old window and an old reading: nothing recent is known


def test_a_lost_probe_does_not_probe_again_at_every_step():
    # 2 threads slow down for good, but one thread is slower still: stay, and stop probing
    gov = ThreadGovernor(2, busy_cores=None)
    _run(gov, lambda n: 2.6e-3 if n == 2 else 5e-3, 50)
    _run(gov, lambda n: 6e-3 if n == 2 else 9e-3, 1000)
    assert gov.current == 2 and gov.steps[1] <= 4  # one probe (its first step retraces)


def test_one_thread_has_no_choice():
    gov = ThreadGovernor(1)
    _run(gov, Machine(), 100)
    assert gov.options == [1] and gov.steps == {1: 100}


def test_omp_threads_restores_the_setting():
    before = torch.get_num_threads()
    with omp_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


def test_which_steps_get_a_governor():
    model = td.Model(td.Grid((8, 8, 8), spacing=0.01, topology=26), stiffness=10.0, mass=1e-3)
    assert CompiledStep(td.SymplecticEuler(), model, 1e-4, threads=2).governor is not None
    assert CompiledStep(td.SymplecticEuler(), model, 1e-4, threads=1).governor is None
    assert CompiledStep(td.SymplecticEuler(), model, 1e-4, threads=2, enable=False).governor is None
    assert CompiledStep(td.ImplicitEuler(), model, 1e-4, threads=2).governor is None  # always serial


@pytest.mark.slow
def test_a_compiled_step_on_either_thread_count_equals_the_eager_step(monkeypatch):
    monkeypatch.setattr(T, "recent_load", lambda: 0.0)  # an idle machine: the governor starts on both threads
    grid = td.Grid((8, 8, 8), spacing=0.01, topology=26)
    model = td.Model(
        grid,
        stiffness=20.0,
        damping=0.01,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        dtype=torch.float64,
    )
    integ, dt = td.SymplecticEuler(), 1e-4
    cs = CompiledStep(integ, model, dt, threads=2, force_form="reduction")  # the quicker compile
    ps, ref = cs.packed.pack_state(model.rest_state()), model.rest_state()
    for i in range(12):
        if i == 6:  # as after a busy neighbour: one thread from now on
            cs.governor.current = 1
        ps = cs.step_packed(ps)
        ref = integ.step(model, ref, dt)
    assert cs.compiled and cs.governor.steps == {2: 6, 1: 6}
    got = cs.packed.unpack_state(ps)
    assert torch.allclose(got.x, ref.x, rtol=0, atol=1e-12) and torch.allclose(got.v, ref.v, rtol=0, atol=1e-9)
    assert float((ref.x - model.X).abs().max()) > 1e-9  # it moved


def test_outputs_take_one_thread_after_a_busy_run_measured_without_a_wait(monkeypatch):
    """After a run, the sampler started before it says how busy the machine was; one thread needs no measure."""
    before = torch.get_num_threads()
    waited = []
    monkeypatch.setattr(T, "others_busy", lambda seconds: waited.append(seconds) or 0.0)
    try:
        torch.set_num_threads(2)
        monkeypatch.setattr(T.CpuSampler, "others", lambda self: 1.0)  # a core busy elsewhere during the run
        assert T.after_step_threads(since=T.CpuSampler()) == 1
        monkeypatch.setattr(T.CpuSampler, "others", lambda self: 0.1)  # idle
        assert T.after_step_threads(since=T.CpuSampler()) == 2
        assert waited == []  # the run's own sample: no 0.1 s sample of its own
        monkeypatch.setattr(T.CpuSampler, "others", lambda self: None)  # a run too short to tell
        assert T.after_step_threads(since=T.CpuSampler()) == 2 and waited == [0.1]
        torch.set_num_threads(1)
        assert T.after_step_threads() == 1 and waited == [0.1]  # nothing to choose, nothing measured
    finally:
        torch.set_num_threads(before)
