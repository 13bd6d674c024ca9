"""Forces back, grasp, tool poses (torchdeform.interact) against independent oracles.

* force balance: a sphere pressed into a block on fixed supports, settled: the force the tool
  feels equals the support reactions plus gravity (1e-9 N, float64);
* Punak's haptic force on a two-node case, computed by hand;
* the momentum a projection removes (m dv / dt) and the penalty force, by hand;
* grasped nodes follow the tool's pose change exactly (translation and rotation) and leave it
  with the tool's velocity when released;
* rotated tools: signed distances against a rotated point set (numpy rotation matrices);
* a tool with one pose per batch entry equals separate runs;
* the packed layout (compiled path's) reports the same readings.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.errors import ConfigError
from torchdeform.interact import (
    Box,
    Capsule,
    Grasp,
    HalfSpace,
    PenaltyContact,
    ProjectionContact,
    Sphere,
    Tool,
    support_reaction,
)
from torchdeform.sim.compiled import CompileFallbackWarning, compiled_step


def _weight(model):
    return (model.mass.expand(1, 1, *model.grid.shape) * model.gravity).flatten(2).sum(2)


@pytest.mark.parametrize("topology, shape", [(26, Sphere(0.015)), (18, Sphere(0.015)), (6, Box((0.015, 0.03, 0.03)))])
def test_tool_force_balances_supports_and_gravity(topology, shape, device):
    """A flat punch on the 6-neighbour block (a sphere pushes its shear-free top layer aside)."""
    grid = td.Grid((3, 3, 3), spacing=0.01, topology=topology)
    r = 0.015
    probe = Tool(shape, path=[(0.0, (0.022 + r, 0.01, 0.01)), (0.05, (0.015 + r, 0.01, 0.01))], name="probe")
    model = td.Model(
        grid,
        stiffness=30.0,
        damping=0.05,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        decay=100.0,
        fixed=grid.face("bottom"),
        interactions=[ProjectionContact(probe)],
        dtype=F64,
        device=device,
    )
    state, _ = td.simulate(model, model.rest_state(), dt=td.suggest_dt(model), steps=2000)
    felt = state.readings["probe.force"]
    balance = support_reaction(model, state) + _weight(model)
    assert state.readings["probe.contacts"].item() >= 1 and felt[0, 0] > 0.05  # it pushes up on the hand
    assert torch.allclose(felt, balance, atol=1e-9, rtol=0)
    # torque about the tool centre: the contact lies straight below it
    assert state.readings["probe.torque"].abs().max() < 1e-12


def test_haptic_force_is_minus_gain_times_mean_push_out_two_nodes(device):
    grid = td.Grid((2, 1, 1), spacing=1.0, topology=6)
    model = td.Model(grid, stiffness=1.0, mass=1.0, dtype=F64, device=device)
    tool = Tool(Sphere(1.0), position=(0.0, 0.0, 0.0), name="probe")
    contact = ProjectionContact(tool, haptic_gain=50.0)
    x = torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.6, 0.0]], dtype=F64).T.reshape(1, 3, 2, 1, 1).to(device)
    readings = {}
    x1, _ = contact.project(model, x, torch.zeros_like(x), 0.0, 0.01, readings=readings)
    # by hand: node 1 moves 0.5 along +D, node 2 moves 0.4 along +H (Punak eqs. 4-3..4-5)
    delta = np.array([[0.5, 0.0, 0.0], [0.0, 0.4, 0.0]])
    assert np.allclose(x1[0, :, :, 0, 0].T.cpu().numpy(), [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], atol=1e-15)
    assert np.allclose(readings["probe.haptic"].cpu().numpy(), -50.0 * delta.mean(0, keepdims=True), atol=1e-12)
    assert readings["probe.contacts"].tolist() == [2.0]


def test_projection_reports_the_momentum_it_removes(device):
    model = td.Model(td.Grid((1, 1, 1), spacing=1.0), stiffness=1.0, mass=2.0, dtype=F64, device=device)
    floor = Tool(HalfSpace(normal=(1.0, 0.0, 0.0)), position=(0.0, 0.0, 0.0), name="floor")
    x = torch.tensor([-0.01, 0.3, 0.0], dtype=F64, device=device).view(1, 3, 1, 1, 1)
    v = torch.tensor([-1.5, 0.2, 0.0], dtype=F64, device=device).view(1, 3, 1, 1, 1)
    readings = {}
    ProjectionContact(floor).project(model, x, v, 0.0, 0.01, readings=readings)
    # the floor stops 1.5 m/s of a 2 kg node in 0.01 s: it pushes with 300 N; the floor feels -300 N
    assert torch.allclose(readings["floor.force"].cpu(), torch.tensor([[-300.0, 0.0, 0.0]], dtype=F64))
    # torque about the floor's origin of the force on the node: r x f with r = (0, 0.3, 0), f = (300, 0, 0)
    assert torch.allclose(readings["floor.torque"].cpu(), -torch.tensor([[0.0, 0.0, -90.0]], dtype=F64))


def test_penalty_reports_minus_its_force(device):
    floor = Tool(HalfSpace(normal=(1.0, 0.0, 0.0)), position=(0.0, 0.0, 0.0), name="floor")
    c = PenaltyContact(floor, stiffness=100.0)
    x = torch.tensor([[[-0.01, 0.02, -0.03]], [[0.0] * 3], [[0.0] * 3]], dtype=F64, device=device).view(1, 3, 3)
    readings = {}
    c.project(None, x, torch.zeros_like(x), 0.0, 0.01, readings=readings)
    assert torch.allclose(readings["floor.force"].cpu(), torch.tensor([[-4.0, 0.0, 0.0]], dtype=F64))
    assert readings["floor.contacts"].tolist() == [2.0]


def _rot(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


@pytest.mark.parametrize("shape", [Box((0.3, 0.5, 0.2)), Capsule(0.2, 0.6, axis=0)])
def test_rotated_tool_distance_is_the_shape_distance_in_its_frame(shape, device):
    rng = np.random.default_rng(3)
    axis, angle, c = rng.normal(size=3), 0.7, np.array([0.1, -0.2, 0.3])
    R = _rot(axis, angle)
    tool = Tool(shape, position=tuple(c), orientation=tuple(axis / np.linalg.norm(axis) * angle))
    p = rng.uniform(-1, 1, size=(500, 3))
    d, n = tool.sdf(torch.from_numpy(p.T.copy())[None].to(device), 0.0)
    local = (p - c) @ R  # R^T (p - c), row-wise
    d0, n0 = shape.sdf(torch.from_numpy(local.T.copy())[None])  # on the CPU
    assert np.allclose(d[0, 0].cpu().numpy(), d0[0, 0].numpy(), atol=1e-14)
    assert np.allclose(n[0].cpu().numpy().T, n0[0].numpy().T @ R.T, atol=1e-14)


def test_grasped_nodes_follow_the_tool_exactly_then_move_freely(device):
    grid = td.Grid((3, 3, 3), spacing=0.01)
    c0, c1 = np.array([0.02, 0.01, 0.01]), np.array([0.03, 0.012, 0.008])
    turn = np.array([0.0, 0.0, 0.3])  # radians about W while lifting
    path = [
        (0.0, tuple(c0), (0.0, 0.0, 0.0)),
        (0.02, tuple(c0), (0.0, 0.0, 0.0)),
        (0.1, tuple(c1), tuple(turn)),
        (0.2, tuple(c1), tuple(turn)),
    ]
    jaws = Tool(Box((0.006, 0.011, 0.011)), path=path, name="forceps")  # the whole top layer
    grasp = Grasp(jaws, close=0.005, open=0.08)  # opens while still moving
    model = td.Model(
        grid,
        stiffness=20.0,
        damping=0.05,
        mass=1e-3,
        fixed=grid.face("bottom"),
        interactions=[grasp],
        dtype=F64,
        device=device,
    )
    dt = 5e-4
    states = {}

    def keep(i, s):
        states[i] = td.State(s.x.cpu(), s.v.cpu(), t=s.t, readings={k: r.cpu() for k, r in (s.readings or {}).items()})

    td.simulate(model, model.rest_state(), dt=dt, steps=260, callback=keep)
    top = model.X[0, :, 2].reshape(3, -1).T.cpu().numpy()  # rest = positions when grasped (tool still)
    assert states[20].readings["forceps.grasped"].item() == 9
    for i in (40, 120, 159):  # closed: x = c(t) + R(t) (x_grasp - c0)
        t = i * dt
        a = min(max((t - 0.02) / 0.08, 0.0), 1.0)
        c, R = c0 + a * (c1 - c0), _rot((0, 0, 1), a * 0.3)
        expect = c + (top - c0) @ R.T
        got = states[i].x[0, :, 2].reshape(3, -1).T.numpy()
        assert np.abs(got - expect).max() < 1e-14
    # released at t = 0.08 with the tool's velocity: the translation rate plus w x r
    rel = states[160]
    assert rel.readings["forceps.grasped"].item() == 0
    w = turn / 0.08
    c = c0 + 0.75 * (c1 - c0)
    v_expect = (c1 - c0) / 0.08 + np.cross(w, rel.x[0, :, 2].reshape(3, -1).T.numpy() - c)
    assert np.abs(rel.v[0, :, 2].reshape(3, -1).T.numpy() - v_expect).max() < 1e-12
    # then free: the springs pull the lifted layer back down, away from the held pose
    assert (states[260].x[0, 0, 2] - rel.x[0, 0, 2] - 100 * dt * rel.v[0, 0, 2]).abs().max() > 1e-4
    # the tissue pulled the forceps down while it lifted it
    assert states[120].readings["forceps.force"][0, 0] < 0


def test_grasp_times_are_checked():
    tool = Tool(Sphere(0.01), position=(0.0, 0.0, 0.0))
    for kwargs, key in (
        ({"close": 0.1}, "grasp"),
        ({"close": 0.2, "open": 0.1}, "grasp.open"),
        ({"close": -1.0, "open": 1.0}, "grasp.close"),
        ({"margin": -0.1}, "grasp.margin"),
    ):
        with pytest.raises(ConfigError, match=key):
            Grasp(tool, **kwargs)


def test_hold_keeps_touched_nodes_on_the_tool_until_they_pull_away(device):
    grid = td.Grid((1, 1, 1), spacing=0.01)
    # a node falling onto a rising paddle sticks to it; when the paddle drops faster than the node
    # can fall, the node leaves it
    paddle = Tool(
        HalfSpace(normal=(1.0, 0.0, 0.0)),
        path=[(0.0, (-0.005, 0.0, 0.0)), (0.05, (0.0, 0.0, 0.0)), (0.06, (-0.01, 0.0, 0.0))],
    )
    model = td.Model(
        grid,
        stiffness=1.0,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        dtype=F64,
        device=device,
        interactions=[ProjectionContact(paddle, hold=True)],
    )
    c = model.interactions[0]
    st, _ = td.simulate(model, model.rest_state(), dt=1e-3, steps=40)
    assert c._held[0].count() == 1
    assert abs(float(st.x[0, 0]) - paddle.position(st.t)[0]) < 1e-15  # riding the paddle up
    st, _ = td.simulate(model, st, dt=1e-3, steps=10)
    assert c._held[0].count() == 1  # the paddle stopped: still on it
    st, _ = td.simulate(model, st, dt=1e-3, steps=3)
    assert c._held[0].count() == 0  # it drops at 1 m/s: released
    assert float(st.x[0, 0]) > paddle.position(st.t)[0] + 1e-3


def test_motion_direction_pushes_along_the_tool_motion(device):
    # a sphere moving along +D catches an off-axis node: it leaves along D, H and W unchanged
    tool = Tool(Sphere(0.01), path=[(0.0, (0.0, 0.0, 0.0)), (1.0, (0.01, 0.0, 0.0))])
    model = td.Model(td.Grid((1, 1, 1), spacing=1.0), stiffness=1.0, mass=1.0, dtype=F64, device=device)
    x = torch.tensor([0.009, 0.004, -0.003], dtype=F64, device=device).view(1, 3, 1, 1, 1)
    t = 0.5  # centre at D = 0.005
    x1, _ = ProjectionContact(tool, direction="motion").project(model, x, torch.zeros_like(x), t, 0.01)
    d, _ = tool.sdf(x1, t)
    assert abs(d.item()) < 1e-12
    assert x1[0, 1].item() == pytest.approx(0.004, abs=1e-15) and x1[0, 2].item() == pytest.approx(-0.003, abs=1e-15)
    assert x1[0, 0].item() == pytest.approx(0.005 + math.sqrt(1e-4 - 0.004**2 - 0.003**2), abs=1e-12)


def test_one_tool_pose_per_batch_entry_equals_separate_runs(device):
    grid = td.Grid((3, 3, 3), spacing=0.01)
    centres = torch.tensor([[0.035, 0.01, 0.01], [0.033, 0.0, 0.02]], dtype=F64, device=device)
    batched = td.Model(
        grid,
        stiffness=20.0,
        damping=0.05,
        mass=1e-3,
        fixed=grid.face("bottom"),
        dtype=F64,
        device=device,
        interactions=[ProjectionContact(Tool(Sphere(0.01), position=centres))],
    )
    sb, _ = td.simulate(batched, batched.rest_state(batch=2), dt=5e-4, steps=50)
    for b in range(2):
        single = td.Model(
            grid,
            stiffness=20.0,
            damping=0.05,
            mass=1e-3,
            fixed=grid.face("bottom"),
            dtype=F64,
            device=device,
            interactions=[ProjectionContact(Tool(Sphere(0.01), position=tuple(centres[b].tolist())))],
        )
        s1, _ = td.simulate(single, single.rest_state(), dt=5e-4, steps=50)
        assert torch.allclose(sb.x[b], s1.x[0], atol=1e-15)
        assert torch.allclose(sb.readings["tool.force"][b], s1.readings["tool.force"][0], atol=1e-12)


def test_packed_layout_reports_the_same_forces(device):
    grid = td.Grid((4, 4, 4), spacing=0.01, topology=18)
    probe = Tool(Sphere(0.012), path=[(0.0, (0.045, 0.015, 0.012)), (0.01, (0.036, 0.015, 0.012))], name="probe")
    model = td.Model(
        grid,
        stiffness=30.0,
        damping=0.05,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        interactions=[ProjectionContact(probe, friction=0.3, haptic_gain=10.0)],
        dtype=F64,
        device=device,
    )
    eager, _ = td.simulate(model, model.rest_state(), dt=2e-4, steps=40)
    packed = compiled_step(td.SymplecticEuler(), model, 2e-4, enable=False).run(model.rest_state(), 40)
    assert set(packed.readings) == {"probe.force", "probe.torque", "probe.contacts", "probe.haptic"}
    assert eager.readings["probe.contacts"].item() > 0
    for k, r in eager.readings.items():
        assert torch.allclose(packed.readings[k], r, atol=1e-12), k


def test_compiled_step_runs_a_grasp_eagerly_without_trying_to_compile(device):
    grid = td.Grid((3, 3, 3), spacing=0.01)
    jaws = Tool(Box((0.004,) * 3), path=[(0.0, (0.02, 0.01, 0.01)), (0.2, (0.03, 0.01, 0.01))], name="forceps")
    model = td.Model(
        grid,
        stiffness=20.0,
        damping=0.05,
        mass=1e-3,
        fixed=grid.face("bottom"),
        dtype=F64,
        device=device,
        interactions=[Grasp(jaws, close=0.0, open=1.0)],
    )
    with pytest.warns(CompileFallbackWarning, match="Grasp runs in the eager step"):
        step = compiled_step(td.SymplecticEuler(), model, 5e-4)
    assert not step.compiled
    state = step.run(model.rest_state(), 400)  # t = 0.2: lifted (almost) 1 cm
    model.interactions = [Grasp(jaws, close=0.0, open=1.0)]  # a fresh grasp for the grid-layout run
    ref, _ = td.simulate(model, model.rest_state(), dt=5e-4, steps=400)
    assert state.x[0, 0, 2, 1, 1].item() > 0.0299
    assert torch.allclose(state.x, ref.x, atol=1e-14) and state.readings["forceps.grasped"].tolist() == [1.0]
    assert ProjectionContact(jaws, hold=True).eager_only and not ProjectionContact(jaws).eager_only
