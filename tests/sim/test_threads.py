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
    monkeypatch.setattr(T.CpuSampler, "others", lambda self: 1.0)  # /proc/stat: one core busy elsewhere
    gov, machine = ThreadGovernor(2), Machine(2)
    machine.busy = True  # no jump to see: it was busy all along
    _run(gov, machine, 200)
    assert gov.current == 1 and gov.switches == 1


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
def test_a_compiled_step_on_either_thread_count_equals_the_eager_step():
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
