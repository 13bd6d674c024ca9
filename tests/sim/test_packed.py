"""The packed layout of the fast path against the grid-layout model (itself tested against the
numpy edge list in test_stencil / test_physics). No torch.compile here: the packed code is
plain tensor code and runs eagerly; the compiled kernel is compared with the eager step by the
``bench speed --quick`` smoke test."""

import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.sim.compiled import CompiledStep, ImplicitGraph
from torchdeform.sim.packed import BLOCK, PackedModel

INTEGRATORS = [
    td.ExplicitEuler(),
    td.SymplecticEuler(),
    td.DampedVerlet(kd=0.1),
    td.RK4(),
    td.ImplicitEuler(cg_iters=60, cg_tol=1e-13),
    td.ImplicitEuler(cg_iters=20, cg_tol=0, newton_iters=1),
]


def _scene(topology, mode="projected", batch=1, device=None):
    node_mask = torch.ones(5, 4, 6, dtype=torch.bool)
    node_mask[3:, 2:, :3] = False  # an L-shaped body
    grid = td.Grid((5, 4, 6), spacing=(0.01, 0.011, 0.012), topology=topology, node_mask=node_mask)
    g = torch.Generator().manual_seed(topology)
    k = 40 * (1 + torch.rand((grid.S,) + grid.shape, generator=g, dtype=F64))
    drag = td.Drag(
        grid.index_mask([(0, 0, 5)]), path=[(0.0, (0, 0, 0)), (0.004, (1e-3, 0, 0)), (0.01, (1e-3, 2e-3, 0))]
    )
    model = td.Model(
        grid,
        stiffness=k,
        damping=0.05,
        damping_mode=mode,
        density=1000.0,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom") & grid.nodes(),
        drags=[drag],
        decay=0.3,
        anchors=(5.0, 2),
        loads=[td.PointForce((4, 0, 2), (0.01, 0.0, -0.02), start=0.001, ramp=0.003)],
        dtype=F64,
        device=device,
    )
    x = model.X + 2e-4 * torch.randn((batch, 3) + grid.shape, generator=g, dtype=F64).to(model.device)
    v = 1e-2 * torch.randn((batch, 3) + grid.shape, generator=g, dtype=F64).to(model.device)
    x, v = model.constrain(x, v, 0.0)
    return model, td.State(x, v, t=0.0)


@pytest.mark.parametrize("topology", [6, 14, 18, 26])
@pytest.mark.parametrize("mode", ["projected", "unprojected"])
def test_packed_forces_equal_grid_forces(topology, mode, device):
    model, state = _scene(topology, mode, batch=2, device=device)
    pm = PackedModel(model)
    ps = pm.pack_state(state)
    F_grid = model.forces(state.x, state.v, t=0.002)
    F_packed = pm.unpack(pm.forces(ps.x, ps.v, t=0.002))
    assert torch.allclose(F_packed, F_grid, rtol=1e-12, atol=1e-14 * float(F_grid.abs().max()))
    assert torch.equal(pm.pack(F_grid)[..., : pm.G], torch.zeros_like(pm.pack(F_grid)[..., : pm.G]))
    # Gershgorin sums and stiffness products, the other spring operators of the packed model
    assert torch.allclose(pm.unpack(pm.spring_sums(pm.stiffness)), model.spring_sums(model.stiffness), rtol=1e-12)
    u = torch.randn_like(state.x)
    Ku = model.linearise(state.x).apply(u, alpha_scale=0.7, c=model.damping, projected=model.projected, c_scale=0.3)
    Ku_p = pm.unpack(
        pm.linearise(ps.x).apply(pm.pack(u), alpha_scale=0.7, c=pm.damping, projected=pm.projected, c_scale=0.3)
    )
    assert torch.allclose(Ku_p, Ku, rtol=1e-10, atol=1e-12 * float(Ku.abs().max()))


@pytest.mark.parametrize("shape", [(1, 1, 1), (2, 3, 5), (5, 4, 6), (10, 10, 40), (7, 1, 9)])
def test_packed_layout_round_trips_and_core_is_whole_blocks(shape):
    """pack/unpack round-trip any shape; the core range is a whole number of blocks, and every
    entry of a packed field outside the grid (halo and tail) is zero."""
    model = td.Model(td.Grid(shape, spacing=0.01, topology=26), stiffness=10.0, mass=1e-3, dtype=F64)
    pm = PackedModel(model)
    assert (pm.P - 2 * pm.G) % BLOCK == 0 and (shape[0] + 2) * (shape[1] + 2) * (shape[2] + 2) <= pm.P
    t = torch.randn((2, 3) + shape, dtype=F64)
    packed = pm.pack(t)
    assert packed.shape == (2, 3, pm.P)
    assert torch.equal(pm.unpack(packed), t)
    assert float(packed.abs().sum()) == pytest.approx(float(t.abs().sum()), rel=1e-12)
    assert pm.blocks(packed).shape == (2, 3, (pm.P - 2 * pm.G) // BLOCK, BLOCK)


@pytest.mark.parametrize("integ", INTEGRATORS, ids=lambda i: f"{i.name}{getattr(i, 'newton_iters', '')}")
def test_packed_steps_equal_grid_steps(integ, device):
    """20 steps through drags, a ramped load, anchors, decay and a node mask; time as a float and
    as the 0-d tensor the compiled step passes."""
    model, state = _scene(26, device=device)
    pm = PackedModel(model)
    t0 = torch.tensor(0.0, dtype=F64, device=device)
    ref, s, st = state, pm.pack_state(state), pm.pack_state(td.State(state.x, state.v, t=t0))
    for _ in range(20):
        ref = integ.step(model, ref, 5e-4)
        s = integ.step(pm, s, 5e-4)
        st = integ.step(pm, st, 5e-4)
    for packed in (s, st):
        out = pm.unpack_state(packed)
        assert torch.allclose(out.x, ref.x, rtol=0, atol=1e-12)
        assert torch.allclose(out.v, ref.v, rtol=0, atol=1e-9)
    assert float(st.t) == pytest.approx(ref.t)


def test_compiled_implicit_graph_equals_eager_step(device):
    """The compiled implicit Euler's graph (set-up, CG iterations in a while_loop, update), run
    here uncompiled, gives the eager step: a fixed iteration count, a tolerance (the loop
    condition reads the residual) and a Newton iteration."""
    model, state = _scene(18, device=device)
    for integ in (
        td.ImplicitEuler(cg_iters=7, cg_tol=0),
        td.ImplicitEuler(cg_iters=40, cg_tol=1e-9),
        td.ImplicitEuler(cg_iters=9, cg_tol=0, newton_iters=1),
    ):
        cs = CompiledStep(integ, model, 5e-4, enable=False)
        graph = ImplicitGraph(integ, cs.packed, 5e-4, None)
        ps = cs.packed.pack_state(state)
        x, v, _ = graph(ps.x, ps.v, torch.tensor(0.0, dtype=F64, device=device))
        n_graph, rel_graph = integ.last_cg
        ref = integ.step(model, state, 5e-4)
        if integ.cg_tol > 0:
            assert 1 < n_graph < 40 and rel_graph <= 1e-9
            assert integ.last_cg[0] == n_graph and integ.last_cg[1] == pytest.approx(rel_graph, rel=1e-6)
        else:
            assert n_graph == integ.cg_iters
        assert torch.allclose(cs.packed.unpack(x), ref.x, rtol=0, atol=1e-12)
        assert torch.allclose(cs.packed.unpack(v), ref.v, rtol=0, atol=1e-9)


def test_time_functions_agree_for_floats_and_tensors():
    drag = td.Drag(
        torch.ones(2, 2, 2, dtype=torch.bool), path=[(0.1, (0, 0, 0)), (0.3, (1.0, -2.0, 0.5)), (0.4, (0, 0, 1))]
    )
    load = td.PointForce((0, 0, 0), (1, 0, 0), start=0.05, ramp=0.1)
    for t in [0.0, 0.1, 0.2, 0.29999, 0.3, 0.35, 0.4, 0.7]:
        tt = torch.tensor(t, dtype=F64)
        assert torch.allclose(drag.offset(tt), torch.tensor(drag.offset(t), dtype=F64), atol=1e-15)
        assert torch.allclose(drag.velocity(tt), torch.tensor(drag.velocity(t), dtype=F64), atol=1e-12)
        assert float(load.factor(tt)) == pytest.approx(load.factor(t), abs=1e-15)


def test_spring_law_is_exactly_zero_at_rest_length():
    """``k (l - l0) / l`` is exactly 0 when ``|delta|`` rounds to ``l0``: a body at rest is an
    exact equilibrium (up to the rounding of the rest lengths themselves)."""
    from torchdeform.sim.springs import spring_law

    for dtype in (torch.float32, F64):
        delta = torch.tensor([[0.01, 0.013, 0.017], [0.0, 0.0, 0.02], [3.0, 4.0, 0.0]], dtype=dtype)
        sq = (delta * delta).sum(1)
        alpha, beta = spring_law(sq, torch.zeros_like(sq), 123.0, sq.sqrt(), 0.4, True)
        assert torch.equal(alpha, torch.zeros_like(alpha)) and beta is None
    grid = td.Grid((3, 3, 3), spacing=0.01, topology=26)
    model = td.Model(grid, stiffness=123.0, damping=0.4, mass=1.0, dtype=F64)
    pm = PackedModel(model)
    rest = pm.rest_state()
    scale = 123.0 * 0.01
    assert float(model.forces(model.X, torch.zeros_like(model.X)).abs().max()) <= 1e-14 * scale
    assert float(pm.forces(rest.x, rest.v).abs().max()) <= 1e-14 * scale


def test_packed_model_rejects_a_packed_model():
    model, _ = _scene(6)
    with pytest.raises(TypeError):
        PackedModel(PackedModel(model))


@pytest.mark.slow
@pytest.mark.parametrize(
    ("integ", "form"),
    [(td.SymplecticEuler(), "gather"), (td.SymplecticEuler(), "reduction"), (td.ImplicitEuler(cg_iters=15), None)],
    ids=["symplectic-gather", "symplectic-reduction", "implicit"],
)
def test_compiled_step_equals_eager_step_on_the_device(integ, form, device):
    """The step under ``torch.compile`` (inductor's C++ on a CPU, Triton on a GPU) on the device,
    ten steps through the drag, ramped load, anchors and node mask of the scene: the eager grid step."""
    if form == "gather" and device.type != "cpu":
        pytest.skip("the gather form is the CPU's: its unrolled Triton kernel takes minutes to compile")
    if form == "reduction" and device.type == "cpu":
        pytest.skip("the reduction form on the CPU: tests/sim/test_threads.py compiles it (one compile is enough)")
    if form is None and device.type == "cpu":
        pytest.skip("the compiled implicit step on the CPU: tests/test_compile.py (one 30 s compile is enough)")
    # the gather form's unrolled loop grows with the stencil: 6 neighbours run the same code per
    # direction and compile in a fraction of the time of 26 (the eager 26-neighbour gather form:
    # the tests above)
    model, state = _scene(6 if form == "gather" else 26, device=device)
    cs = CompiledStep(integ, model, 5e-4, force_form=form)
    ref, s = state, cs.packed.pack_state(state)
    with torch.no_grad():
        for _ in range(10):
            ref, s = integ.step(model, ref, 5e-4), cs.step_packed(s)
    assert cs.compiled, cs.compile_error
    out = cs.packed.unpack_state(s)
    assert out.x.device == model.device
    assert torch.allclose(out.x, ref.x, rtol=0, atol=1e-12)
    assert torch.allclose(out.v, ref.v, rtol=0, atol=1e-8)
