"""Model terms, constraints, batching and the stiff/extreme cases, each with a defined outcome."""

import math

import pytest
import torch

import torchdeform as td
from tests.helpers import F64, make_grid, make_model


def cube(n=3, topology=26, **kw):
    g = make_grid(n, topology=topology)
    return g, make_model(g, **kw)


# ---------------------------------------------------------------- force terms
def test_surface_force_total_is_traction_times_area(device):
    g = td.Grid((4, 5, 6), spacing=(0.01, 0.02, 0.03))
    m = td.Model(
        g, stiffness=1.0, mass=1.0, dtype=F64, device=device, loads=[td.SurfaceForce("top", (-200.0, 0.0, 50.0))]
    )
    F = m.external(0.0)
    area = (5 - 1) * 0.02 * (6 - 1) * 0.03
    assert F[0, 0].sum().item() == pytest.approx(-200.0 * area, rel=1e-12)
    assert F[0, 2].sum().item() == pytest.approx(50.0 * area, rel=1e-12)
    assert bool((F[:, :, :-1] == 0).all())  # only the top layer is loaded


def test_point_force_ramp(device):
    _g, m = cube(device=device, loads=[td.PointForce((2, 1, 1), (1.0, 2.0, 3.0), start=0.1, ramp=0.2)])
    assert m.external(0.05) is None
    assert m.external(0.2)[0, :, 2, 1, 1].tolist() == pytest.approx([0.5, 1.0, 1.5])
    assert m.external(1.0)[0, :, 2, 1, 1].tolist() == pytest.approx([1.0, 2.0, 3.0])


def test_lumped_mass_from_density_sums_to_body_mass(device):
    g = td.Grid((4, 3, 5), spacing=(0.01, 0.02, 0.005))
    m = td.Model(g, stiffness=1.0, density=1000.0, dtype=F64, device=device)
    volume = 3 * 0.01 * 2 * 0.02 * 4 * 0.005
    assert m.mass.sum().item() == pytest.approx(1000.0 * volume, rel=1e-12)
    # corners carry 1/8 of a cell, interior nodes a whole cell
    cell = 1000.0 * 0.01 * 0.02 * 0.005
    assert m.mass[0, 0, 0, 0, 0].item() == pytest.approx(cell / 8)
    assert m.mass[0, 0, 1, 1, 1].item() == pytest.approx(cell)


def test_home_and_anchor_springs_pull_back_to_rest(device):
    g = td.Grid((3, 3, 3), spacing=0.01, topology=6)
    m = td.Model(g, stiffness=0.0, mass=1.0, home=2.0, anchors=(5.0, 3), dtype=F64, device=device)
    x = m.X + 0.001
    F = m.forces(x, torch.zeros_like(x))
    anchor = g.every_kth(3).to(device, F64)
    expected = -0.001 * (2.0 + 5.0 * anchor)
    assert torch.allclose(F, expected.expand_as(F), atol=1e-15)
    assert int(anchor.sum()) == 9  # (i+j+l) % 3 == 0 on 3^3


def test_decay_is_exact_exponential_without_springs(device):
    _g, m = cube(stiffness=0.0, decay=3.0, device=device)
    st = m.rest_state()
    st = td.State(st.x, torch.ones_like(st.x))
    for integ in (td.SymplecticEuler(), td.RK4(), td.ImplicitEuler()):
        s = st
        for _ in range(10):
            s = integ.step(m, s, 0.01)
        assert torch.allclose(s.v, torch.full_like(s.v, math.exp(-0.3)), rtol=1e-12)


def test_free_fall_rk4_is_exact(device):
    _g, m = cube(stiffness=0.0, gravity=(-9.81, 0.0, 0.0), device=device)
    s = m.rest_state()
    for _ in range(20):
        s = td.RK4().step(m, s, 0.005)
    assert torch.allclose(
        s.x - m.X,
        torch.tensor([-0.5 * 9.81 * 0.1**2, 0, 0], dtype=F64, device=device).view(1, 3, 1, 1, 1).expand_as(s.x),
        atol=1e-14,
    )


# ---------------------------------------------------------------- constraints
@pytest.mark.parametrize(
    "integ", [td.ExplicitEuler(), td.SymplecticEuler(), td.DampedVerlet(kd=0.1), td.RK4(), td.ImplicitEuler()]
)
def test_fixed_nodes_stay_and_dragged_group_moves_rigidly(integ, device):
    g = td.Grid((4, 4, 4), spacing=0.01, topology=26)
    top = g.face("top")
    grip = top & g.box_mask((0, 0.01, 0.01), (1, 0.02, 0.02))  # 4 top-centre nodes
    drag = td.Drag(grip, path=[(0.0, (0, 0, 0)), (0.01, (0.002, 0.001, 0.0)), (0.02, (0.002, 0.001, -0.001))])
    m = td.Model(
        g,
        stiffness=20.0,
        damping=0.05,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        fixed=g.face("bottom"),
        drags=[drag],
        dtype=F64,
        device=device,
    )
    s = m.rest_state()
    dt = 0.2 * td.time_step_bound(m, integrator="symplectic")
    n = int(0.015 / dt)
    for _ in range(n):
        s = integ.step(m, s, dt)
    off = torch.tensor(drag.offset(s.t), dtype=F64).view(3, 1)
    u = (s.x - m.X)[0].cpu()
    assert torch.allclose(u[:, grip], off.expand(3, int(grip.sum())), atol=1e-15)
    assert bool((u[:, g.face("bottom")] == 0).all())
    assert bool(torch.isfinite(s.x).all()) and float(u[:, ~grip].abs().max()) > 0


def test_batch_equals_separate_runs(device):
    g = td.Grid((3, 4, 3), spacing=0.01, topology=18)
    k = torch.tensor([[10.0], [40.0]], dtype=F64, device=device).expand(2, g.S)
    mb = td.Model(g, stiffness=k, mass=1e-3, gravity=(-9.81, 0, 0), fixed=g.face("bottom"), dtype=F64, device=device)
    sb = mb.rest_state(batch=2)
    for _ in range(30):
        sb = td.SymplecticEuler().step(mb, sb, 1e-3)
    for b, kb in enumerate((10.0, 40.0)):
        m1 = td.Model(
            g, stiffness=kb, mass=1e-3, gravity=(-9.81, 0, 0), fixed=g.face("bottom"), dtype=F64, device=device
        )
        s1 = m1.rest_state()
        for _ in range(30):
            s1 = td.SymplecticEuler().step(m1, s1, 1e-3)
        assert torch.allclose(sb.x[b], s1.x[0], atol=1e-15)


def test_dtypes_run_and_agree(dtype, device):
    g = td.Grid((4, 4, 4), spacing=0.01)

    def build(dt):
        return td.Model(
            g,
            stiffness=20.0,
            damping=0.02,
            density=1000.0,
            gravity=(-9.81, 0, 0),
            fixed=g.face("bottom"),
            dtype=dt,
            device=device,
        )

    m, m64 = build(dtype), build(F64)
    s, _ = td.simulate(m, m.rest_state(), td.suggest_dt(m), 50)
    assert s.x.dtype == dtype and bool(torch.isfinite(s.x).all())
    s64, _ = td.simulate(m64, m64.rest_state(), td.suggest_dt(m), 50)
    assert torch.allclose(s.x.double(), s64.x, atol=1e-6)


def test_node_mask_body_outside_nodes_never_move(device):
    mask = torch.ones(4, 4, 4, dtype=torch.bool)
    mask[2:, 2:, 2:] = False  # an L-shaped body
    g = td.Grid((4, 4, 4), spacing=0.01, node_mask=mask)
    m = td.Model(
        g, stiffness=20.0, density=1000.0, gravity=(-9.81, 0, 0), fixed=g.face("bottom"), dtype=F64, device=device
    )
    assert g.num_springs < td.Grid((4, 4, 4)).num_springs
    s, _ = td.simulate(m, m.rest_state(), td.suggest_dt(m), 100)
    u = (s.x - m.X)[0].cpu()
    assert bool(u[:, ~mask].eq(0).all())
    assert float(u[:, mask].abs().max()) > 0


# ------------------------------------------------------------ extreme cases
def test_coincident_nodes_give_finite_forces_and_gradients(device):
    _g, m = cube(damping=0.1, device=device)
    x = m.X.clone()
    x[0, :, 1, 1, 1] = x[0, :, 1, 1, 2]  # two neighbours on top of each other
    x.requires_grad_(True)
    v = torch.zeros_like(x)
    F = m.forces(x, v)
    E = m.energy(td.State(x, v))["total"].sum()
    (gx,) = torch.autograd.grad(E, x)
    assert bool(torch.isfinite(F).all()) and bool(torch.isfinite(gx).all())
    s, _ = td.simulate(m, td.State(x.detach(), v), 1e-4, 200)
    # the other springs push the pair apart again
    sep = (s.x[0, :, 1, 1, 1] - s.x[0, :, 1, 1, 2]).norm()
    assert bool(torch.isfinite(s.x).all()) and float(sep) > 0


def test_inverted_cell_is_finite_and_implicit_solve_stays_definite(device):
    _g, m = cube(n=3, stiffness=1e4, fixed=None, device=device)
    x = m.X.clone()
    x[0, 0, 2, 1, 1] = m.X[0, 0, 0, 1, 1] - 0.005  # top-centre pushed through the bottom
    s = td.State(x, torch.zeros_like(x))
    integ = td.ImplicitEuler(cg_iters=300, cg_tol=1e-10)
    for _ in range(20):
        s = integ.step(m, s, 1e-2)
        assert integ.last_cg[1] <= 1e-10  # CG converged: the clamped matrix is SPD
    assert bool(torch.isfinite(s.x).all())
    e = m.energy(s)["total"].item()
    assert math.isfinite(e) and e <= m.energy(td.State(x, torch.zeros_like(x)))["total"].item()


def test_mirrored_body_is_a_documented_equilibrium(device):
    # springs see only lengths: a mirror image of the rest shape has no spring force
    _g, m = cube(fixed=None, device=device)
    x = m.X.clone()
    x[:, 0] = -x[:, 0]
    assert float(m.forces(x, torch.zeros_like(x)).abs().max()) < 1e-12


@pytest.mark.parametrize("mass", [0.0, -1e-3])
def test_zero_or_negative_mass_is_rejected(mass):
    g = td.Grid((3, 3, 3))
    with pytest.raises(td.ConfigError, match="positive mass"):
        td.Model(g, stiffness=1.0, mass=mass)


def test_zero_mass_allowed_on_fixed_nodes():
    g = td.Grid((3, 3, 3))
    mass = torch.ones(3, 3, 3)
    mass[0] = 0
    td.Model(g, stiffness=1.0, mass=mass, fixed=g.face("bottom"))


@pytest.mark.parametrize("k", [-1.0, float("nan"), float("inf")])
def test_bad_stiffness_is_rejected(k):
    with pytest.raises(td.ConfigError, match="stiffness"):
        td.Model(td.Grid((3, 3, 3)), stiffness=k, mass=1.0)


@pytest.mark.parametrize("dt", [0.0, -1e-3, float("nan")])
def test_non_positive_dt_is_rejected(dt):
    _g, m = cube()
    with pytest.raises(td.ConfigError, match="dt"):
        td.SymplecticEuler().step(m, m.rest_state(), dt)
    with pytest.raises(td.ConfigError, match="dt"):
        td.simulate(m, m.rest_state(), dt, 10)


def test_empty_node_mask_is_rejected():
    with pytest.raises(td.ConfigError, match="node_mask"):
        td.Grid((3, 3, 3), node_mask=torch.zeros(3, 3, 3, dtype=torch.bool))


@pytest.mark.parametrize("shape", [(0, 3, 3), (3, 3), (3, -1, 2)])
def test_bad_grid_shape_is_rejected(shape):
    with pytest.raises(td.ConfigError, match=r"grid\.shape"):
        td.Grid(shape)


def test_explicit_euler_without_damping_warns():
    _g, m = cube()
    with pytest.warns(td.StabilityWarning, match="unstable at every time step"):
        td.simulate(m, m.rest_state(), 1e-5, 1, integrator=td.ExplicitEuler())


def test_stiffness_per_direction_class():
    g = td.Grid((3, 3, 3), topology=26)
    m = td.Model(g, stiffness={"axis": 1.0, "face": 2.0, "body": 3.0}, mass=1.0)
    assert m.stiffness.flatten().tolist() == [1.0] * 3 + [2.0] * 6 + [3.0] * 4
    with pytest.raises(td.ConfigError, match="direction class"):
        td.Model(g, stiffness={"axis": 1.0}, mass=1.0)


def test_density_gives_thin_masked_features_positive_mass():
    mask = torch.zeros(4, 4, 4, dtype=torch.bool)
    mask[:, 1, 1] = True  # a one-node-thick rod
    mask[0] = True  # on a plate
    g = td.Grid((4, 4, 4), spacing=0.01, node_mask=mask)
    m = td.Model(g, stiffness=1.0, density=1000.0, fixed=g.face("bottom"), dtype=F64)
    assert bool((m.mass[0, 0][mask] > 0).all()) and bool((m.mass[0, 0][~mask] == 0).all())


def test_masks_given_on_the_device_build_the_same_model(device):
    """Fixed and dragged node masks may come on the model's device (a GPU mask from a segmentation)."""
    g = td.Grid((3, 3, 4), spacing=0.01, topology=26)
    top = g.face("top")

    def build(where):
        drag = td.Drag(top.to(where), offset=(1e-3, 0.0, 0.0), ramp=0.1)
        return td.Model(
            g, stiffness=1.0, mass=1.0, fixed=g.face("bottom").to(where), drags=[drag], dtype=F64, device=device
        )

    on_host, on_device = build("cpu"), build(device)
    assert torch.equal(on_device.constrained.cpu(), g.face("bottom") | top)
    assert torch.equal(on_device.free.cpu(), on_host.free.cpu()) and on_device.free.device == on_device.X.device
