"""Tools and contact (torchdeform.interact) against independent oracles.

* signed distances: analytic numpy distances (sphere, half-space) and brute force over densely
  sampled surfaces (capsule, box);
* projection puts every penetrating node on the surface (1e-12, float64) and leaves the others;
* a body dropped on a floor never gains energy (symplectic Euler alone loses energy in free
  fall, so any gain would come from the contact) and ends above it;
* a particle on an incline with Coulomb friction sticks for tan(theta) <= mu and slides with the
  analytic acceleration g (sin theta - mu cos theta) above;
* penalty contact passes gradcheck with respect to its stiffness and the tool's position;
* the packed layout (the compiled path's) gives the same contact step as the grid layout;
* every response queues its step on the device without reading a value back (on CUDA, torch's
  sync debug mode raises on any wait), and takes the same step as on the CPU.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.helpers import no_host_wait
from torchdeform.errors import ConfigError
from torchdeform.interact import (
    Box,
    Capsule,
    Grasp,
    HalfSpace,
    PenaltyContact,
    ProjectionContact,
    Sphere,
    StrainLimit,
    Tool,
)
from torchdeform.sim.packed import PackedModel


def _points(n=400, scale=2.0, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-scale, scale, size=(n, 3))


def _sdf(shape, p, device="cpu"):
    d, n = shape.sdf(torch.from_numpy(p.T.copy())[None].to(device))
    return d[0, 0].cpu().numpy(), n[0].cpu().numpy().T


def test_sphere_and_halfspace_distances_are_analytic(device):
    p = _points()
    d, n = _sdf(Sphere(0.7), p, device)
    r = np.linalg.norm(p, axis=1)
    assert np.allclose(d, r - 0.7, atol=1e-14) and np.allclose(n, p / r[:, None], atol=1e-14)
    normal = np.array([1.0, 2.0, -2.0]) / 3.0
    d, n = _sdf(HalfSpace(normal=(1.0, 2.0, -2.0)), p, device)
    assert np.allclose(d, p @ normal, atol=1e-14) and np.allclose(n, normal[None], atol=1e-15)


def _surface_samples(shape, m=60):
    """Dense points on the surface of a capsule or box (brute-force oracle)."""
    u = np.linspace(-1, 1, m)
    if isinstance(shape, Box):
        h = np.array(shape.half_extents)
        pts = []
        for a in range(3):
            b, c = [i for i in range(3) if i != a]
            for s in (-1, 1):
                g1, g2 = np.meshgrid(u * h[b], u * h[c], indexing="ij")
                q = np.zeros(g1.shape + (3,))
                q[..., a], q[..., b], q[..., c] = s * h[a], g1, g2
                pts.append(q.reshape(-1, 3))
        return np.concatenate(pts)
    R, L, a = shape.radius, shape.half_length, shape.axis
    th, ph = np.meshgrid(np.linspace(0, 2 * np.pi, 2 * m), np.linspace(0, np.pi, m), indexing="ij")
    ball = np.stack([np.cos(th) * np.sin(ph), np.sin(th) * np.sin(ph), np.cos(ph)], -1).reshape(-1, 3) * R
    side = np.stack([np.cos(th[:, 0]), np.sin(th[:, 0])], -1) * R
    pts = [ball[s * ball[:, a] >= 0] + s * L * np.eye(3)[a] for s in (-1, 1)]  # the outer half-balls
    for z in np.linspace(-L, L, m):
        q = np.zeros((len(side), 3))
        q[:, [i for i in range(3) if i != a]] = side
        q[:, a] = z
        pts.append(q)
    return np.concatenate(pts)


def _inside(shape, p):
    if isinstance(shape, Box):
        return (np.abs(p) < np.array(shape.half_extents)).all(1)
    a = shape.axis
    q = np.zeros_like(p)
    q[:, a] = np.clip(p[:, a], -shape.half_length, shape.half_length)
    return np.linalg.norm(p - q, axis=1) < shape.radius


@pytest.mark.parametrize(
    "shape",
    [Capsule(0.5, 0.8, axis=0), Capsule(0.3, 0.0, axis=2), Box((0.6, 0.9, 0.4))],
    ids=["capsule-d", "capsule-ball", "box"],
)
def test_capsule_and_box_distances_match_brute_force(shape, device):
    p = _points(300, 1.6, seed=1)
    d, n = _sdf(shape, p, device)
    surf = _surface_samples(shape)
    brute = np.sqrt(((p[:, None] - surf[None]) ** 2).sum(-1)).min(1)
    sign = np.where(_inside(shape, p), -1.0, 1.0)
    assert np.abs(d - sign * brute).max() < 0.03  # surface sampled every ~0.03
    # the projected point lies on the surface, at distance |d| from p
    q = p - d[:, None] * n
    dq, _ = _sdf(shape, q, device)
    assert np.abs(dq).max() < 1e-12
    assert np.allclose(np.linalg.norm(p - q, axis=1), np.abs(d), atol=1e-12)


@pytest.mark.parametrize(
    "shape",
    [Sphere(0.015), Capsule(0.008, 0.01, axis=1), Box((0.01, 0.02, 0.012)), HalfSpace(normal=(1.0, 0.5, 0.0))],
    ids=["sphere", "capsule", "box", "half-space"],
)
def test_projection_puts_penetrating_nodes_on_the_surface(shape, device):
    grid = td.Grid((6, 6, 6), spacing=0.005)
    tool = Tool(shape, position=(0.0125, 0.0125, 0.0125))
    model = td.Model(grid, stiffness=1.0, mass=1e-3, dtype=torch.float64, device=device)
    g = torch.Generator().manual_seed(3)
    x = model.X + 1e-3 * torch.randn(model.X.shape, generator=g, dtype=torch.float64).to(device)
    v = torch.randn(x.shape, generator=g, dtype=torch.float64).to(device)
    d0, n0 = tool.sdf(x, 0.0)
    x1, v1 = ProjectionContact(tool).project(model, x, v, 0.0, 1e-3)
    d1, _ = tool.sdf(x1, 0.0)
    inside = d0 < 0
    assert int(inside.sum()) > 5
    assert float(d1[inside.expand_as(d1)].abs().max()) < 1e-12  # on the surface
    assert torch.equal(torch.where(inside, x, x1), x) and torch.equal(torch.where(inside, v, v1), v)
    vn = (v1 * n0).sum(1, keepdim=True)
    assert float(vn[inside].min()) >= -1e-12  # no approaching speed left


def test_fixed_nodes_are_not_projected(device):
    grid = td.Grid((3, 3, 3), spacing=0.01)
    model = td.Model(grid, stiffness=1.0, mass=1e-3, fixed=grid.face("bottom"), dtype=torch.float64, device=device)
    floor = Tool(HalfSpace(normal=(1.0, 0.0, 0.0)), position=(0.005, 0.0, 0.0))  # above the bottom layer
    x, _ = ProjectionContact(floor).project(model, model.X.clone(), torch.zeros_like(model.X), 0.0, 1e-3)
    assert torch.equal(x[:, :, 0], model.X[:, :, 0])  # fixed layer stays
    assert torch.allclose(x[:, 0, 1:], model.X[:, 0, 1:])  # the others were above already


def _energy(model, state):
    return float(model.energy(state)["total"][0])


def test_body_dropped_on_a_floor_never_gains_energy(device):
    grid = td.Grid((2, 2, 2), spacing=0.01, topology=26)
    floor = Tool(HalfSpace(normal=(1.0, 0.0, 0.0)), position=(-0.02, 0.0, 0.0))  # 2 cm below the body
    model = td.Model(
        grid,
        stiffness=50.0,
        mass=1e-3,
        gravity=(-9.81, 0.0, 0.0),
        interactions=[ProjectionContact(floor)],
        dtype=torch.float64,
        device=device,
    )
    state = model.rest_state()
    e0 = _energy(model, state)
    energies, lowest = [], []
    integ = td.SymplecticEuler()
    for _ in range(1500):
        state = integ.step(model, state, 2e-4)
        energies.append(_energy(model, state))
        lowest.append(float(state.x[:, 0].min()))
    assert min(lowest) >= -0.02 - 1e-12  # never below the floor
    assert max(energies) <= e0 + 1e-12 * abs(e0)  # never above the start
    assert energies[-1] < e0 - 0.5 * 1e-3 * 8 * 9.81 * 0.01  # the inelastic impacts dissipated


@pytest.mark.parametrize("ratio", [0.8, 1.25])
def test_incline_sticks_below_the_friction_angle_and_slides_above(ratio, device):
    theta = math.radians(25.0)
    mu = math.tan(theta) / ratio  # ratio < 1: mu > tan(theta) sticks; > 1 slides
    normal = (math.cos(theta), math.sin(theta), 0.0)
    grid = td.Grid((1, 1, 1), spacing=0.01)
    floor = Tool(HalfSpace(normal=normal), position=(0.0, 0.0, 0.0))  # the node rests on the plane
    g = 9.81
    model = td.Model(
        grid,
        stiffness=1.0,
        mass=1e-3,
        gravity=(-g, 0.0, 0.0),
        interactions=[ProjectionContact(floor, friction=mu)],
        dtype=torch.float64,
        device=device,
    )
    state, _ = td.simulate(model, model.rest_state(), dt=1e-4, steps=2000)  # 0.2 s
    node = state.x[0, :, 0, 0, 0].cpu()
    s = float((node * torch.tensor([-math.sin(theta), math.cos(theta), 0.0], dtype=torch.float64)).sum())  # downhill
    height = float((node * torch.tensor(normal, dtype=torch.float64)).sum())
    assert abs(height) < 1e-12  # stays on the plane
    if ratio < 1:
        assert abs(s) < 1e-12
    else:
        a = g * (math.sin(theta) - mu * math.cos(theta))
        assert s == pytest.approx(0.5 * a * 0.2**2, rel=0.01)


def test_penalty_contact_gradcheck_stiffness_and_tool_position(device):
    grid = td.Grid((2, 2, 2), spacing=0.01)
    X = grid.rest_positions(dtype=torch.float64, device=device)

    def forces(k, centre):
        tool = Tool(Sphere(0.008), position=lambda t: centre)
        contact = PenaltyContact(tool, stiffness=k, damping=0.0)
        model = td.Model(grid, stiffness=5.0, mass=1e-3, interactions=[contact], dtype=torch.float64, device=device)
        x = X + 0.001
        state = td.SymplecticEuler().step(model, td.State(x, torch.zeros_like(x)), 1e-3)
        return state.x

    k = torch.tensor(40.0, dtype=torch.float64, device=device, requires_grad=True)
    centre = torch.tensor([0.0, 0.0, 0.003], dtype=torch.float64, device=device, requires_grad=True)
    d, _ = Sphere(0.008).sdf(X + 0.001 - centre.detach().view(1, 3, 1, 1, 1))
    assert float(d.abs().min()) > 1e-4 and int((d < 0).sum()) >= 1  # away from contact onset
    assert torch.autograd.gradcheck(forces, (k, centre))


def test_packed_layout_gives_the_same_contact_step(device):
    grid = td.Grid((4, 5, 3), spacing=0.01, topology=26)
    probe = Tool(Sphere(0.012), path=[(0.0, (0.045, 0.02, 0.01)), (0.01, (0.035, 0.02, 0.01))])
    floor = Tool(HalfSpace(normal=(1.0, 0.0, 0.0)), position=(-0.001, 0.0, 0.0))
    model = td.Model(
        grid,
        stiffness=30.0,
        damping=0.02,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        interactions=[
            ProjectionContact([probe, floor], friction=0.3),
            PenaltyContact(probe, stiffness=5.0, damping=0.01),
        ],
        dtype=torch.float64,
        device=device,
    )
    pm = PackedModel(model)
    state, packed = model.rest_state(), pm.rest_state()
    integ = td.SymplecticEuler()
    for _ in range(20):
        state = integ.step(model, state, 5e-4)
        packed = integ.step(pm, packed, 5e-4)
    assert torch.allclose(pm.unpack_state(packed).x, state.x, atol=1e-14, rtol=0)
    assert torch.allclose(pm.unpack_state(packed).v, state.v, atol=1e-11, rtol=0)


def _responses_over_steps(device, steps=3, batch=1):
    """Every response of torchdeform.interact applied to a body for a few steps: ``(x, v, readings)``."""
    grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
    model = td.Model(grid, stiffness=20.0, mass=1e-3, fixed=grid.face("bottom"), dtype=torch.float64, device=device)
    probe = Tool(Sphere(0.012), path=[(0.0, (0.042, 0.015, 0.015)), (0.01, (0.035, 0.015, 0.015))], name="probe")
    turned = Tool(Box((0.004, 0.006, 0.03)), position=(0.03, 0.0, 0.015), orientation=(0.0, 0.0, 0.3), name="box")
    floor = Tool(HalfSpace(normal=(1.0, 0.2, 0.0)), position=(0.001, 0.0, 0.0), name="floor")
    jaws = Tool(Box((0.004,) * 3), path=[(0.0, (0.03, 0.01, 0.01)), (0.01, (0.033, 0.01, 0.01))], name="forceps")
    responses = [
        ProjectionContact([probe, turned, floor], friction=0.3, haptic_gain=5.0),
        ProjectionContact(probe, direction="motion"),
        PenaltyContact([turned, floor], stiffness=5.0, damping=0.01),
        Grasp(jaws, close=0.0, open=1.0),
        StrainLimit(min_ratio=0.95, max_ratio=1.05, passes=2),
    ]
    gen = torch.Generator().manual_seed(5)
    x = model.X + 2e-3 * torch.randn((batch, *model.X.shape[1:]), generator=gen, dtype=torch.float64).to(device)
    v = 0.01 * torch.randn(x.shape, generator=gen, dtype=torch.float64).to(device)
    readings = {}
    with no_host_wait(device):
        for k in range(1, steps + 1):
            for r in responses:
                f = r.force(model, x, v, 1e-3 * k)
                v = v if f is None else v + 1e-3 * f / model.mass
                x, v = r.project(model, x, v, 1e-3 * k, 1e-3, readings=readings)
    return x, v, readings


@pytest.mark.parametrize("batch", [1, 2])
def test_responses_on_the_reached_nodes_equal_the_dense_responses(monkeypatch, batch):
    """Eager CPU contact responds on the nodes a tool reaches (gathered, written back): the same
    positions, velocities and readings (forces, torques, contacts, haptic) as the dense response
    over every node, which compiled and differentiated steps take."""
    from torchdeform.interact import contact

    cpu = torch.device("cpu")
    calls, reached = [], contact.ProjectionContact._respond_reached

    def counted(self, *args):
        calls.append(1)
        return reached(self, *args)

    monkeypatch.setattr(contact.ProjectionContact, "_respond_reached", counted)
    x, v, got = _responses_over_steps(cpu, steps=4, batch=batch)
    assert len(calls) == 4 * 4  # four tools of two projections, every step: the gathered path ran
    monkeypatch.setattr(contact, "_gathered", lambda *args: False)
    xd, vd, dense = _responses_over_steps(cpu, steps=4, batch=batch)
    assert torch.allclose(x, xd, atol=1e-15, rtol=0) and torch.allclose(v, vd, atol=1e-13, rtol=0)
    assert set(got) == set(dense) and float(dense["probe.contacts"].sum()) > 0
    for key, value in dense.items():
        assert torch.allclose(got[key], value, rtol=1e-12, atol=1e-15), key
    assert float(dense["probe.force"].abs().max()) > 0 and float(dense["probe.haptic"].abs().max()) > 0


def test_responses_queue_on_the_device_without_waiting_for_it(device):
    x, v, readings = _responses_over_steps(device)
    x_ref, v_ref, ref = _responses_over_steps(torch.device("cpu"))  # the oracle: the same steps on the CPU
    assert ref["probe.contacts"].item() > 0 and ref["forceps.grasped"].item() > 0 and ref["box.contacts"].item() > 0
    assert torch.allclose(x.cpu(), x_ref, rtol=0, atol=1e-12) and torch.allclose(v.cpu(), v_ref, rtol=0, atol=1e-9)
    assert set(readings) == set(ref)
    for k, r in ref.items():
        assert torch.allclose(readings[k].cpu(), r, rtol=1e-9, atol=1e-12), k


@pytest.mark.parametrize(
    "make, key",
    [
        (lambda: Sphere(-1.0), "sphere.radius"),
        (lambda: Capsule(0.1, -0.2), "capsule.half_length"),
        (lambda: Capsule(0.1, 0.2, axis=3), "capsule.axis"),
        (lambda: Box((0.1, 0.0, 0.1)), "box.half_extents"),
        (lambda: HalfSpace(normal=(0.0, 0.0, 0.0)), "half_space.normal"),
        (lambda: Tool(Sphere(0.1), path=[(0.0, (0, 0, 0)), (0.0, (1, 0, 0))]), "tool.path"),
        (lambda: Tool(Sphere(0.1)), "tool"),
        (lambda: Tool("sphere", position=(0, 0, 0)), "tool.shape"),
        (lambda: ProjectionContact(Tool(Sphere(0.1), position=(0, 0, 0)), friction=-1.0), "contact.friction"),
        (lambda: PenaltyContact(Tool(Sphere(0.1), position=(0, 0, 0)), stiffness=0.0), "contact.stiffness"),
        (
            lambda: td.Model(td.Grid((2, 2, 2), spacing=0.01), stiffness=1.0, mass=1.0, interactions=[object()]),
            "interactions",
        ),
    ],
)
def test_bad_tool_input_is_one_clear_error(make, key):
    with pytest.raises(ConfigError) as e:
        make()
    assert e.value.key == key
