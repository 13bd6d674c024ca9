"""The haptic loop (torchdeform.interact.HapticLoop).

* the local contact model: ``K = sum_i k_i n_i n_i^T`` over the touched nodes against an
  independent edge list (each node's spring stiffnesses summed one spring at a time) and the
  analytic sphere normals; a tick renders ``F_b - K (p - p_b)`` exactly;
* direct mode returns the force of a plain simulation of the same steps (grid layout, eager);
* the loop keeps a fixed tick rate, and bad input is one clear error.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from tests.oracles.edge_list import EdgeList
from torchdeform.errors import ConfigError
from torchdeform.interact import HapticLoop, ProjectionContact, Sphere, Tool


def _body(n=5, topology=18, device=None):
    grid = td.Grid((n, n, n), spacing=0.01, topology=topology)
    model = td.Model(grid, stiffness=40.0, damping=0.1, mass=1e-3, fixed=grid.face("bottom"), dtype=F64, device=device)
    return grid, model


def test_local_model_stiffness_and_rendered_force(device):
    grid, model = _body(device=device)
    r, c = 0.02, np.array([0.04 + 0.02 - 0.004, 0.02, 0.021])  # 4 mm into the top, a little off-centre
    loop = HapticLoop(model, Sphere(r), start=tuple(c), dt=2e-4, mode="local", compiled=False)
    loop.advance()
    f_b, p_b, K = loop.local_model()
    assert np.allclose(p_b, c)
    # the touched nodes: on the sphere after the projection (and free)
    x = loop.step.packed.unpack_state(loop.state).x[0].reshape(3, -1).T.cpu().numpy()
    dist = np.linalg.norm(x - c, axis=1)
    free = model.free[0, 0].expand(grid.shape).reshape(-1).cpu().numpy() > 0
    touched = free & (dist <= r + 1e-8)
    assert touched.sum() >= 3
    edges = EdgeList(grid.shape, (0.01,) * 3, 18)
    k_node = np.zeros(edges.N)
    for a, b, _ in edges.springs:
        k_node[a] += 40.0
        k_node[b] += 40.0
    order = [edges.index[tuple(int(i) for i in np.unravel_index(j, grid.shape))] for j in range(x.shape[0])]
    k_grid = k_node[order]
    n = (x - c) / dist[:, None]
    K_ref = sum(k_grid[i] * np.outer(n[i], n[i]) for i in np.flatnonzero(touched))
    assert np.allclose(K, K_ref, rtol=1e-12, atol=1e-12)
    p = c + np.array([-0.001, 0.0005, 0.0])
    assert np.allclose(loop.tick(p), f_b - K_ref @ (p - c), atol=1e-12)


def test_direct_mode_equals_a_plain_simulation(device):
    grid, model = _body(4, 26, device)
    start = np.array([0.03 + 0.01 + 0.001, 0.01, 0.01])
    loop = HapticLoop(model, Sphere(0.01), start=tuple(start), dt=2e-4, mode="direct", steps_per_tick=4, compiled=False)
    path = [start - np.array([0.004 * k / 20, 0.0, 0.0]) for k in range(20)]
    with loop:
        forces = [loop.tick(p) for p in path]
    # the same: the tool held at each tick's position for 4 steps, after the loop's 4 warm-up steps
    pos = torch.tensor(start, dtype=F64, device=device)
    tool = Tool(Sphere(0.01), position=pos, name="haptic")
    plain = td.Model(
        grid,
        stiffness=40.0,
        damping=0.1,
        mass=1e-3,
        fixed=grid.face("bottom"),
        dtype=F64,
        device=device,
        interactions=[ProjectionContact(tool)],
    )
    state, _ = td.simulate(plain, plain.rest_state(), dt=2e-4, steps=4)
    for p, f in zip(path, forces):
        pos.copy_(torch.tensor(p))
        state, _ = td.simulate(plain, state, dt=2e-4, steps=4)
        assert np.allclose(f, state.readings["haptic.force"][0].cpu().numpy(), atol=1e-12)
    assert forces[-1][0] > 0


def test_tick_rate_and_stats():
    _, model = _body(3, 6)
    loop = HapticLoop(model, Sphere(0.01), start=(0.05, 0.01, 0.01), dt=1e-4, rate=500.0, mode="local", compiled=False)
    with loop:
        for _ in range(100):
            loop.tick((0.05, 0.01, 0.01))
    s = loop.stats()
    assert s["mode"] == "local" and s["ticks"] == 100 and s["body_steps"] > 0
    assert 400 < s["force_hz"] <= 501


@pytest.mark.parametrize(
    "kwargs, key",
    [
        ({"mode": "fast"}, "haptic.mode"),
        ({"rate": 0.0}, "haptic.rate"),
        ({"dt": -1.0}, "haptic.dt"),
        ({"steps_per_tick": 0}, "haptic.steps_per_tick"),
    ],
)
def test_bad_loop_options(kwargs, key):
    _, model = _body(3, 6)
    args = dict(dt=1e-4, compiled=False) | kwargs
    with pytest.raises(ConfigError, match=key):
        HapticLoop(model, Sphere(0.01), start=(0.05, 0.01, 0.01), **args)


def test_tick_rejects_a_nan_position():
    _, model = _body(3, 6)
    loop = HapticLoop(model, Sphere(0.01), start=(0.05, 0.01, 0.01), dt=1e-4, mode="direct", compiled=False)
    with pytest.raises(ConfigError, match=r"haptic\.position"):
        loop.tick((float("nan"), 0.0, 0.0))
