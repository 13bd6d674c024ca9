"""simulate's engines (torchdeform.sim.engine): eager, native, compiled, auto.

The compiled engine runs its packed loop with the uncompiled packed step (``Engine(compile=False)``):
the same code path without a 3-60 s compile; the eager grid-layout step is the oracle.
"""

from __future__ import annotations

import pytest
import torch

import torchdeform as td
from tests.helpers import F64, make_grid, make_model
from torchdeform.errors import ConfigError
from torchdeform.sim import engine as engine_mod
from torchdeform.sim import native, native_cuda
from torchdeform.sim import threads as threads_mod
from torchdeform.sim.engine import Engine, gradient_needed
from torchdeform.sim.packed import PackedModel


def body(n=4, dtype=F64, drags=True, device=None):
    grid = make_grid(n)
    drag = [
        td.Drag(grid.index_mask([(n - 1, n // 2, n // 2)]), path=[(0.0, (0.0, 0.0, 0.0)), (0.02, (0.004, 0.002, 0.0))])
    ]
    return make_model(
        grid,
        damping=0.05,
        density=1000.0,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        drags=(drags and drag) or [],
        decay=5.0,
        dtype=dtype,
        device=device,
    )


def run(model, engine, steps=30, integrator=None, **kw):
    dt = 0.5 * td.suggest_dt(model)
    return td.simulate(
        model, model.rest_state(), dt, steps, integrator=integrator, record_every=7, engine=engine, warn=False, **kw
    )


@pytest.mark.parametrize(
    "integrator", [td.SymplecticEuler(), td.RK4(), td.ImplicitEuler(cg_iters=15)], ids=["symplectic", "rk4", "implicit"]
)
def test_compiled_engine_equals_eager(integrator, device):
    model = body(device=device)
    ref, rec_ref = run(model, "eager", integrator=integrator)
    engine = Engine(mode="compiled", compile=False)
    out, rec = run(model, engine, integrator=integrator)
    assert engine.ran == "compiled" and engine.reason == "asked for"
    assert out.x.shape == ref.x.shape and out.x.is_contiguous()
    assert torch.allclose(out.x, ref.x, atol=1e-12, rtol=0) and torch.allclose(out.v, ref.v, atol=1e-10, rtol=0)
    assert out.t == pytest.approx(ref.t, abs=1e-15)
    assert torch.equal(rec["t"], rec_ref["t"]) and rec["x"].shape == rec_ref["x"].shape
    assert torch.allclose(rec["x"], rec_ref["x"], atol=1e-12, rtol=0)


def test_auto_stays_eager_on_a_short_run(monkeypatch):
    monkeypatch.setattr(engine_mod, "_kernel_built", lambda model: False)  # a kernel still to build
    engine = Engine(mode="auto")
    run(body(), engine, steps=40)
    assert engine.ran == "eager" and engine.reason.startswith("auto: ")
    assert "<=" in engine.reason and engine.eager_ms > 0
    assert engine.summary()["requested"] == "auto" and engine.summary()["compile_s"] is None


needs_cc = pytest.mark.skipif(native.unavailable() is not None, reason=f"no C kernel here: {native.unavailable()}")


@needs_cc
def test_auto_goes_native_then_compiled_when_the_run_repays_each():
    """Eager probe -> native (the C kernel) -> native probe -> compiled, the state carried over."""
    model = body()
    ref, rec_ref = run(model, "eager", steps=40)
    engine = Engine(mode="auto", probe_steps=4, compile_s={"native": 0.0, "explicit": 0.0}, compile=False)
    out, rec = run(model, engine, steps=40)
    assert engine.ran == "compiled" and "; native;" in engine.reason and ": compiled" in engine.reason
    assert engine.native_ms > 0 and engine.compile_s is not None
    assert torch.allclose(out.x, ref.x, atol=1e-12, rtol=0)
    assert torch.allclose(rec["x"], rec_ref["x"], atol=1e-12, rtol=0)


@needs_cc
@pytest.mark.parametrize("drags", [True, False], ids=["kernel forces", "fused step"])
def test_auto_stays_native_when_a_compile_would_not_pay(drags):
    model = body(drags=drags)
    ref, rec_ref = run(model, "eager", steps=40)
    engine = Engine(mode="auto", probe_steps=4, compile_s={"native": 0.0}, compile=False)
    out, rec = run(model, engine, steps=40)
    assert engine.ran == "native" and engine.summary()["ran"] == "native"
    assert ("<= 2 x ~8 s compile" if drags else "one fused kernel (nothing to compile)") in engine.reason
    assert (engine.step.fused is None) == drags  # drags keep the update in torch
    assert torch.allclose(out.x, ref.x, atol=1e-12, rtol=0) and torch.allclose(out.v, ref.v, atol=1e-10, rtol=0)
    assert torch.allclose(rec["x"], rec_ref["x"], atol=1e-12, rtol=0)
    engine = Engine(mode="native")
    out, _ = run(model, engine, steps=40)
    assert engine.ran == "native" and engine.reason == "asked for" and torch.allclose(out.x, ref.x, atol=1e-12, rtol=0)


def test_native_engine_refuses_what_it_cannot_run():
    with pytest.raises(ConfigError, match="implicit step"):
        run(body(), "native", steps=5, integrator=td.ImplicitEuler(cg_iters=5))


@needs_cc
def test_auto_decides_native_then_compiled_by_hand():
    """With a model the kernel can run: native when the eager time to come exceeds 2 x 2 s of
    kernel build; compiled when a quarter of the native time to come exceeds 2 x 8 s of compile:
    6 ms native steps -> 16 s / 1.5 ms = 10,667 steps."""
    model = body()
    engine = Engine(mode="auto")
    built = engine_mod._kernel_built
    engine_mod._kernel_built = lambda model: False  # a kernel still to build
    try:
        assert not engine.decide(td.SymplecticEuler(), [0.05, 0.03, 0.03], 100, threads=2, model=model)
    finally:
        engine_mod._kernel_built = built
    assert engine.choice is None and "<= 2 x ~2 s C kernel build" in engine.reason
    assert engine.decide(td.SymplecticEuler(), [0.05, 0.03, 0.03], 200, threads=2, model=model)
    assert engine.choice == "native" and engine.force_form is None
    assert not engine.decide_compiled([0.01, 0.006, 0.006], 10_000)
    assert engine.decide_compiled([0.01, 0.006, 0.006], 11_000) and engine.native_ms == pytest.approx(6.0)
    assert not engine.decide_compiled([0.01, 0.006, 0.006], 10**9, fused=True)  # nothing left to compile
    assert "one fused kernel" in engine.reason
    engine = Engine(mode="auto")  # an implicit step compiles directly
    assert engine.decide(td.ImplicitEuler(), [0.05, 0.03, 0.03], 200_000, threads=2, model=model)
    assert engine.choice == "compiled"


def test_auto_decides_the_compile_on_the_steps_the_thread_governor_settled_on(monkeypatch):
    """Beside a busy process a native step's first steps run on two threads, many times slower than on
    the one the governor moves to: the compile decision waits for the governor and uses its settled
    steps. Oracle: the stand-in machine's step times, 6 ms on two threads and 0.15 ms on one; over
    20,000 steps to come a compile repays at 6 ms (30 s saved) and not at 0.15 ms (0.75 s)."""

    # the machine's load as /proc/stat would give it: another process keeps a core busy, found by the
    # governor's first look (nothing known before the run)
    monkeypatch.setattr(threads_mod.CpuSampler, "others", lambda self: 1.0)
    monkeypatch.setattr(threads_mod, "recent_load", lambda: None)
    gov = threads_mod.ThreadGovernor(2)

    class Step:  # the packed step of the run: its governor, no fused kernel
        governor, fused = gov, None

    engine = Engine(mode="auto")
    engine.ran, engine._probing, engine._samples = "native", "native", []
    steps = 0
    while engine._probing == "native":
        n = gov.choose()
        seconds = 0.006 if n == 2 else 0.00015
        gov.record(n, seconds)
        assert engine.after_packed(Step, seconds, 20_000 - steps) is Step  # stays native
        steps += 1
    assert gov.current == 1 and steps > engine.probe_steps
    assert engine.native_ms == pytest.approx(0.15) and "<= 2 x" in engine.reason


@needs_cc
def test_auto_goes_native_at_once_when_the_kernel_is_already_built():
    """A kernel in the disk cache costs no build: a run whose eager time to come exceeds twice
    loading it goes native (the same 100 steps that stay eager while the kernel is to be built)."""
    model = body()
    native.kernel(native.variant_of(PackedModel(model)))  # built and cached now
    assert engine_mod._kernel_built(model)
    engine = Engine(mode="auto")
    assert engine.decide(td.SymplecticEuler(), [0.05, 0.03, 0.03], 100, threads=2, model=model)
    assert engine.choice == "native" and "(built before)" in engine.reason


def test_auto_on_the_device_picks_an_engine_that_runs_there(device):
    """The spring kernel is C on the CPU and Triton on CUDA: ``"auto"`` goes native where that
    kernel can run (else straight to the compiled step), and the native engine's steps (dragged,
    so the update stays in torch around the kernel; and without drags, one fused kernel per step)
    follow the eager steps on the device."""
    model = body(device=device)
    engine = Engine(mode="auto")
    assert engine.decide(td.SymplecticEuler(), [0.05, 0.03, 0.03], 200_000, threads=2, model=model)
    why = native.unavailable() if device.type == "cpu" else native_cuda.unavailable()
    assert Engine.native_blocker(model, td.SymplecticEuler()) == why
    assert engine.choice == ("native" if why is None else "compiled")
    if why is not None:
        return
    for drags in (True, False):
        model = body(device=device, drags=drags)
        ref, _ = run(model, "eager")
        engine = Engine(mode="native")
        out, _ = run(model, engine)
        assert engine.ran == "native" and (engine.step.fused is None) == drags
        assert out.x.device == model.device
        assert torch.allclose(out.x, ref.x, rtol=0, atol=1e-12) and torch.allclose(out.v, ref.v, rtol=0, atol=1e-9)


def test_auto_picks_the_gather_form_only_when_the_steps_to_come_repay_its_compile():
    """Break-even by hand: gather saves eager_ms / 20 per step and costs 40 - 15 = 25 s more compile,
    paid back twice: 50 s / (30 ms / 20) = 33,333 steps."""
    eager_s = [0.05, 0.03, 0.03]  # the first step is a warm-up
    for remaining, threads, form in [
        (2_000, 2, "reduction"),
        (33_000, 2, "reduction"),
        (34_000, 2, "gather"),
        (200_000, 1, None),
    ]:
        engine = Engine(mode="auto")
        assert engine.decide(td.SymplecticEuler(), eager_s, remaining, threads=threads)
        assert engine.eager_ms == pytest.approx(30.0) and engine.force_form == form, (remaining, threads)
    engine = Engine(mode="auto")
    assert engine.decide(td.ImplicitEuler(), eager_s, 200_000, threads=2) and engine.force_form is None
    engine = Engine(mode="auto", compile_s={"explicit": 0.0}, compile=False)
    engine.decide(td.SymplecticEuler(), eager_s, 2_000, threads=2)
    model = body()
    engine._compile(model, td.SymplecticEuler(), 1e-4, None)
    assert engine.step.packed.force_form == "reduction"


def test_auto_and_compiled_with_a_gradient():
    model = body(n=4, drags=False)
    k = torch.tensor(50.0, dtype=torch.float64, requires_grad=True)
    model.stiffness = model.stiffness * k / 50.0
    assert gradient_needed(model, model.rest_state())
    engine = Engine(mode="auto", compile_s={"explicit": 0.0}, compile=False)
    out, _ = run(model, engine, steps=20)
    assert engine.ran == "eager" and "gradient" in engine.reason
    out.x.sum().backward()
    assert k.grad is not None and torch.isfinite(k.grad)
    with pytest.raises(ConfigError, match="gradient"):
        run(model, Engine(mode="compiled", compile=False), steps=5)
    with torch.no_grad():
        assert not gradient_needed(model, model.rest_state())


def test_callable_loads_and_unknown_engine():
    model = body(n=4, drags=False)
    engine = Engine(mode="auto", compile_s={"explicit": 0.0}, compile=False)
    run(model, engine, steps=20, loads=lambda t: torch.zeros(1, 3, 4, 4, 4, dtype=torch.float64))
    assert engine.ran == "eager" and "callable loads" in engine.reason
    with pytest.raises(ConfigError, match="engine"):
        Engine(mode="fast")


def test_a_callback_that_reads_no_positions_gets_the_packed_state():
    model = body(n=4)
    seen = []

    class Readings:
        reads_positions = False

        def __call__(self, step, state):
            seen.append((step, tuple(state.x.shape), state.t))

    class Positions:
        def __call__(self, step, state):
            seen.append((step, tuple(state.x.shape), state.t))

    run(model, Engine(mode="compiled", compile=False), steps=12, callback=Readings())
    shapes = {s for _, s, _ in seen}
    grid = (1, 3, 4, 4, 4)
    assert any(len(s) == 3 for s in shapes)  # packed (B, 3, P) between the looks
    assert grid in shapes  # unpacked where the run looks (step 7, 10, 12)
    assert [s for s, _, _ in seen] == list(range(1, 13))
    seen.clear()
    run(model, Engine(mode="compiled", compile=False), steps=12, callback=Positions())
    assert {s for _, s, _ in seen} == {grid}


def test_a_callback_that_changes_the_state_in_place_reaches_the_packed_engines():
    """A callback stopping the top layer at step 9 (as cautery stops burnt nodes): the packed run
    takes the change into its layout and equals the eager run; without the change it would not."""

    def stop_top(step, state):
        if step == 9:
            state.v[:, :, -1].zero_()

    model = body(n=4)
    ref, _ = run(model, "eager", steps=20, callback=stop_top)
    free, _ = run(model, "eager", steps=20)
    assert float((ref.x - free.x).abs().max()) > 1e-6  # the change matters
    for mode in ("compiled", "native"):
        if mode == "native" and native.unavailable():
            continue
        engine = Engine(mode=mode, compile=False)
        out, _ = run(model, engine, steps=20, callback=stop_top)
        assert engine.ran == mode and torch.allclose(out.x, ref.x, atol=1e-12, rtol=0), mode


def test_scene_engine_key_and_summary(tmp_path):
    import json

    from torchdeform.scene.run import load_scene, run_scene

    text = """
[grid]
shape = [4, 4, 4]
spacing = 0.01
[material]
stiffness = 50.0
damping = 0.1
[mass]
density = 1000.0
[boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]
[integrator]
name = "symplectic"
dt = "auto"
steps = 30
engine = "{engine}"
"""
    path = tmp_path / "cube.toml"
    path.write_text(text.format(engine="eager"))
    summary = run_scene(load_scene(path), tmp_path / "out", progress=False)
    assert summary["engine"]["requested"] == "eager" and summary["engine"]["ran"] == "eager"
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["engine"]["ran"] == "eager"
    path.write_text(text.format(engine="auto"))
    assert run_scene(load_scene(path), tmp_path / "out2", progress=False)["engine"]["ran"] == "eager"
    path.write_text(text.format(engine="turbo"))
    with pytest.raises(ConfigError) as e:
        load_scene(path)
    assert "integrator.engine" in str(e.value) and "cube.toml" in str(e.value) and "cube.toml:17:" in str(e.value)


@pytest.mark.parametrize("where", ["x", "v"])
def test_the_compiled_engine_checks_its_packed_state_for_non_finite_values(where):
    model = body(drags=False)
    # a non-finite load on one free node: the packed run must stop at the first check, naming it
    loads = torch.zeros(1, 3, *model.grid.shape, dtype=model.dtype)
    loads[0, 1, 2, 2, 2] = float("inf") if where == "v" else float("nan")
    with pytest.raises(td.DivergenceError, match=r"velocity|position") as err:
        run(model, Engine(mode="compiled", compile=False), steps=30, loads=loads)
    assert err.value.step == 10  # check_every = 10, on the packed state


def test_a_packed_check_sees_the_kinetic_energy_of_the_unpacked_state():
    from torchdeform.sim.compiled import compiled_step
    from torchdeform.sim.stability import DivergenceMonitor

    model = body(drags=False)
    step = compiled_step(td.SymplecticEuler(), model, 1e-4, enable=False)
    state = model.rest_state()
    state = td.State(state.x, torch.randn_like(state.v), t=0.0)
    monitor = DivergenceMonitor(model, 1e-4, td.SymplecticEuler())
    ke = float((0.5 * model.mass * state.v * state.v).sum())  # the oracle: grid layout
    monitor.limit = 1.001 * ke
    monitor.check(step.packed.pack_state(state), 1, mass=step.packed.mass)  # just under: passes
    monitor.limit = 0.999 * ke
    with pytest.raises(td.DivergenceError, match="kinetic energy"):
        monitor.check(step.packed.pack_state(state), 1, mass=step.packed.mass)
