"""Topology changes reach a compiled step through shared fields, with no recompilation.

The oracle is the eager grid-layout step of an identical model cut the same way (a separate
model object, not sharing storage).
"""

import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.interact import Sphere, Tool
from torchdeform.sim.compiled import compiled_step
from torchdeform.topology import Blade, cauterize, cut

H = 0.01


def _model(device=None):
    grid = td.Grid((5, 4, 4), spacing=H, topology=26)
    return td.Model(
        grid,
        stiffness=20.0,
        damping=0.01,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        dtype=F64,
        device=device,
    )


def _run(step, model, state, blade, tool, n=30):
    """n steps, a cut, n steps, cautery, n steps (a compiled or an eager stepper)."""
    for _ in range(n):
        state = step(state)
    cut(model, state.x, blade)
    for _ in range(n):
        state = step(state)
    cauterize(model, state, tool)
    for _ in range(n):
        state = step(state)
    return state


def _blade():
    return Blade((2.5 * H, -H, -H), (0.0, 2.5 * H, 0.0), (0.0, 0.0, 6 * H))  # a partial cut


def _tool():
    return Tool(Sphere(0.6 * H), position=(4 * H, 3 * H, 3 * H))  # burns one corner node


def test_shared_fields_are_views_of_the_packed_ones(device):
    model = _model(device)
    step = compiled_step(td.SymplecticEuler(), model, 1e-4, enable=False, editable=True)
    pm = step.packed
    assert model.stiffness.untyped_storage().data_ptr() == pm.stiffness.untyped_storage().data_ptr()
    assert model.mass.untyped_storage().data_ptr() == pm.mass.untyped_storage().data_ptr()
    model.stiffness[0, 3, 1, 1, 1] = 0.0
    assert float(pm.unpack(pm.stiffness)[0, 3, 1, 1, 1]) == 0.0


@pytest.mark.parametrize(
    "integrator", [td.SymplecticEuler(), td.ImplicitEuler(cg_iters=30, cg_tol=0)], ids=["symplectic", "implicit"]
)
def test_packed_step_after_cut_and_cautery_equals_eager_reference(integrator, device):
    ref_model = _model(device)
    ref = _run(lambda s: integrator.step(ref_model, s, 1e-4), ref_model, ref_model.rest_state(), _blade(), _tool())
    model = _model(device)
    step = compiled_step(integrator, model, 1e-4, enable=False, editable=True)
    state = model.rest_state()
    packed = step.packed

    def stepper(s):
        return packed.unpack_state(step.step_packed(packed.pack_state(s)))

    out = _run(stepper, model, state, _blade(), _tool())
    assert torch.allclose(out.x, ref.x, atol=1e-12, rtol=0)
    assert float((ref.x - ref_model.X).abs().max()) > 1e-4  # it did move


@pytest.mark.slow
def test_compiled_step_sees_a_cut_without_recompiling():
    from torch._dynamo.utils import counters

    ref_model = _model()
    eager = td.SymplecticEuler()
    ref = eager.step(ref_model, ref_model.rest_state(), 1e-4)
    ref = _run(lambda s: eager.step(ref_model, s, 1e-4), ref_model, ref, _blade(), _tool(), n=10)
    model = _model()
    step = compiled_step(td.SymplecticEuler(), model, 1e-4, editable=True)
    state = step(model.rest_state())  # compiles here
    assert step.compiled
    graphs = counters["stats"]["unique_graphs"]
    state = _run(step, model, state, _blade(), _tool(), n=10)
    assert counters["stats"]["unique_graphs"] == graphs  # no recompilation
    assert step.compiled and step.compile_error is None
    assert torch.allclose(state.x, ref.x, atol=1e-12, rtol=0)


def test_coagulation_needs_shared_rest_lengths_and_then_matches_eager(device):
    from torchdeform.errors import ConfigError
    from torchdeform.topology import coagulate

    region = torch.zeros((5, 4, 4), dtype=torch.bool)
    region[2:] = True
    model = _model(device)
    step = compiled_step(td.SymplecticEuler(), model, 1e-4, enable=False, editable=True)
    state = model.rest_state()
    with pytest.raises(ConfigError, match="editable=\\('stiffness', 'rest_length'\\)"):
        coagulate(model, state.x + 1e-4, region)
    ref_model = _model(device)
    ref = ref_model.rest_state()
    model = _model(device)
    step = compiled_step(
        td.SymplecticEuler(), model, 1e-4, enable=False, editable=("stiffness", "rest_length", "damping")
    )
    state, packed = model.rest_state(), step.packed
    for i in range(60):
        if i == 30:
            coagulate(ref_model, ref.x, region, viscosity_factor=3.0)
            coagulate(model, state.x, region, viscosity_factor=3.0)
        ref = td.SymplecticEuler().step(ref_model, ref, 1e-4)
        state = packed.unpack_state(step.step_packed(packed.pack_state(state)))
    assert torch.allclose(state.x, ref.x, atol=1e-12, rtol=0)


def _elastic_model(device=None):
    grid = td.Grid((5, 4, 4), spacing=H, topology=26)
    return td.Model(
        grid,
        td.Elastic(5e3, 0.45),
        density=1000.0,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        dtype=F64,
        device=device,
    )


@pytest.mark.parametrize("force_form", ["reduction", "native"])
def test_a_packed_step_of_an_elastic_body_sees_the_cells_a_cut_and_cautery_kill(force_form, device):
    from torchdeform.sim import native, native_cuda

    why = native.unavailable() if device.type == "cpu" else native_cuda.unavailable()
    if force_form == "native" and why:
        pytest.skip(f"no spring kernel on {device.type}: {why}")
    dt = 2e-5
    integrator = td.SymplecticEuler()
    ref_model = _elastic_model(device)
    ref = _run(lambda s: integrator.step(ref_model, s, dt), ref_model, ref_model.rest_state(), _blade(), _tool())
    model = _elastic_model(device)
    step = compiled_step(integrator, model, dt, enable=False, editable=True, force_form=force_form)
    # one kernel makes the whole step, the cell term included, on the CPU; on CUDA the springs
    assert (step.fused is not None) == (force_form == "native" and device.type == "cpu")
    packed = step.packed
    out = _run(
        lambda s: packed.unpack_state(step.step_packed(packed.pack_state(s))),
        model,
        model.rest_state(),
        _blade(),
        _tool(),
    )
    assert float(ref_model.volume[0].min()) == 0.0  # cells died
    assert torch.allclose(out.x, ref.x, atol=1e-12, rtol=0)
    assert float((ref.x - ref_model.X).abs().max()) > 1e-5  # it did move
