"""The volume term on the packed layout (torch on the padded grid, and the C kernel) and in the packed engines.

The oracle is the grid-layout :func:`torchdeform.sim.material.volume_forces` (itself checked against
autograd of the energy in test_material.py) and the eager step of the same model.
"""

from __future__ import annotations

import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.sim import native_volume
from torchdeform.sim.packed import PackedModel

needs_kernel = pytest.mark.skipif(native_volume.native.unavailable() is not None, reason="no C compiler")


def _elastic(shape=(5, 6, 7), nu=0.45, dtype=F64, **kw):
    grid = td.Grid(shape, spacing=0.01, topology=26)
    return td.Model(grid, td.Elastic(5e3, nu), density=1000.0, dtype=dtype, **kw)


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("threads", [1, 2])
def test_the_kernel_and_the_padded_grid_give_the_grid_layout_forces(dtype, threads):
    # 24 x 20 x 9 nodes: the core range is long enough for each thread to start inside it
    model = _elastic((24, 20, 9), dtype=dtype)
    pm = PackedModel(model)
    torch.manual_seed(0)
    x = model.X + 2e-3 * torch.randn(2, *model.X.shape[1:], dtype=dtype)
    ref = model.volume_forces(x)
    xp = pm.pack(x)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        native = pm.volume_forces(xp, impl="native")
    finally:
        torch.set_num_threads(before)
    tol = 1e-12 if dtype == F64 else 2e-5
    scale = float(ref.abs().max())
    assert scale > 0
    assert float((pm.unpack(pm.volume_forces(xp, impl="torch")) - ref).abs().max()) <= tol * scale
    assert float((pm.unpack(native) - ref).abs().max()) <= tol * scale
    assert float(native.abs().sum()) == pytest.approx(float(ref.abs().sum()), rel=tol * 10)  # nothing in the halo


@needs_kernel
def test_per_node_moduli_reach_the_kernel_cell_by_cell():
    grid = td.Grid((5, 6, 7), spacing=0.01, topology=26)
    E = torch.linspace(2e3, 9e3, 5, dtype=F64).view(5, 1, 1).expand(grid.shape).contiguous()
    model = td.Model(grid, td.Elastic(E, 0.48), mass=1e-3, dtype=F64)
    pm = PackedModel(model)
    x = model.X + 2e-3 * torch.randn_like(model.X)
    assert torch.allclose(
        pm.unpack(pm.volume_forces(pm.pack(x), impl="native")), model.volume_forces(x), rtol=0, atol=1e-12
    )


@needs_kernel
def test_the_native_engine_steps_an_elastic_body_as_the_eager_step_does():
    model = _elastic(gravity=(-9.81, 0.0, 0.0), fixed=td.Grid((5, 6, 7), spacing=0.01).face("w-"))
    dt = 0.5 * td.time_step_bound(model, integrator="symplectic")
    states = {}
    for mode in ("eager", "native"):
        engine = td.Engine(mode=mode)
        states[mode], _ = td.simulate(model, model.rest_state(), dt, 100, engine=engine, warn=False)
        if mode == "native":  # one fused kernel: springs (stiffness from the cells), the cell term, the update
            assert (
                engine.step.fused is not None
                and "-cellterm" in engine.step.fused
                and engine.step.fused.endswith("-cells")
            )
    moved = float((states["eager"].x - model.X).abs().max())
    assert moved > 1e-4
    assert float((states["native"].x - states["eager"].x).abs().max()) <= 1e-12 * moved * 1e3


def test_the_packed_implicit_step_and_its_volume_product_follow_the_grid_layout():
    model = _elastic(nu=0.49, gravity=(-9.81, 0.0, 0.0), fixed=td.Grid((5, 6, 7), spacing=0.01).face("w-"))
    pm = PackedModel(model)
    torch.manual_seed(1)
    x = model.X + 1e-3 * torch.randn_like(model.X)
    u = torch.randn_like(x)
    ref = model.linearise(x).apply(u)
    got = pm.unpack(pm.linearise(pm.pack(x)).apply(pm.pack(u)))
    assert torch.allclose(got, ref, rtol=1e-10, atol=1e-10 * float(ref.abs().max()))
    integ = td.ImplicitEuler(cg_iters=400, cg_tol=1e-13)
    dt = 20 * td.time_step_bound(model, integrator="symplectic")
    s, sp = model.rest_state(), pm.rest_state()
    for _ in range(5):
        s = integ.step(model, s, dt)
        assert integ.last_cg[1] <= 1e-13
        sp = integ.step(pm, sp, dt)
        assert integ.last_cg[1] <= 1e-13
    moved = float((s.x - model.X).abs().max())
    assert moved > 1e-5
    assert float((pm.unpack(sp.x) - s.x).abs().max()) <= 1e-9 * moved


@pytest.mark.slow
def test_the_compiled_engine_steps_an_elastic_body_as_the_eager_step_does():
    model = _elastic(gravity=(-9.81, 0.0, 0.0), fixed=td.Grid((5, 6, 7), spacing=0.01).face("w-"))
    dt = 0.5 * td.time_step_bound(model, integrator="symplectic")
    eager, _ = td.simulate(model, model.rest_state(), dt, 50, engine=td.Engine(mode="eager"), warn=False)
    engine = td.Engine(mode="compiled")
    compiled, _ = td.simulate(model, model.rest_state(), dt, 50, engine=engine, warn=False)
    assert engine.step.compiled
    moved = float((eager.x - model.X).abs().max())
    assert float((compiled.x - eager.x).abs().max()) <= 1e-9 * moved


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_springs_made_from_cells_in_the_kernel_equal_the_stored_stiffness(dtype):
    grid = td.Grid((9, 8, 7), spacing=0.01, topology=26)
    nodes = torch.ones(grid.shape, dtype=torch.bool)
    nodes[6:, 5:, :3] = False  # a notch: cells, springs and nodes missing
    grid = td.Grid((9, 8, 7), spacing=0.01, topology=26, node_mask=nodes)
    E = torch.linspace(2e3, 9e3, 7, dtype=dtype).view(1, 1, 7).expand(grid.shape).contiguous()
    model = td.Model(grid, td.Elastic(E, 0.3), damping=0.02, density=1000.0, dtype=dtype)
    pm = PackedModel(model)
    assert pm.cell_springs is not None and native_volume.native.variant_of(pm).cells
    torch.manual_seed(2)
    x = pm.pack(model.X + 1e-3 * torch.randn_like(model.X)) * pm.inside
    v = pm.pack(torch.randn_like(model.X)) * pm.inside
    ref = pm.spring_forces(x, v)  # the torch gather form, per-spring stiffness
    got = native_volume.native.spring_forces(pm, x, v)
    assert float((got - ref).abs().max()) <= (1e-12 if dtype == F64 else 1e-5) * float(ref.abs().max())


def test_a_stiffness_changed_after_building_keeps_per_spring_stiffness():
    model = _elastic()
    model.stiffness = model.stiffness * 2  # e.g. a learned scale
    assert PackedModel(model).cell_springs is None
    assert PackedModel(_elastic()).cell_springs is not None
    assert PackedModel(_elastic(), share=True).cell_springs is None  # editable: cuts change single springs
