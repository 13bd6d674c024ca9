"""Contact between deformable bodies (torchdeform.interact.bodies) against independent oracles.

* Static stack (a 3^3 block on a 4^3 block whose base is fixed, gravity along -D, global drag):
  the oracle for the forces is the balance of a body at rest: the base's support reaction is the
  weight of both blocks and the contact force on the upper block is its weight (1e-6 relative).
  The oracle for the shape is a constrained minimum of the total potential energy of both blocks
  (springs + gravity, written here in numpy on the explicit edge list of
  :class:`tests.oracles.edge_list.EdgeList` and the energy of :mod:`tests.oracles.contact_equilibrium`,
  nothing from torchdeform's spring operator), solved with scipy's SLSQP subject to
  non-penetration written independently: every node of the upper block's bottom face stays above
  the bilinear top face of the lower block, and every node of the lower block's top face under the
  upper block stays below the bilinear bottom face of the upper block (vertical gaps, whose
  feasible set is the same as the normal distances'). The KKT conditions of the result are checked
  (stationarity, feasibility, multipliers >= 0) before it is used. Frictionless (with friction the
  resting shape depends on the history, not only on the energy).
* Two free bodies thrown at each other (no gravity, nothing fixed): total momentum ``sum m v`` is
  conserved to 1e-9 of the momentum scale at every step; kinetic + elastic energy never exceeds
  its start (the contact is inelastic); the centres of mass keep their order along the throw and
  the penetration readings stay below the closing speed times the step.
* Friction (a block on a fixed larger block, the slope emulated by tilting gravity by ``theta``
  from -D): for ``tan(theta) = 0.8 mu`` the block sticks after landing and the contact force
  balances its weight; for ``tan(theta) = 1.3 mu`` it slides with the analytic acceleration
  ``g (sin theta - mu cos theta)``.
* Implicit Euler carries the same stack: the weight of both blocks on the base (1e-6 relative).
* Bad input: one-line ConfigErrors naming the bodies.

* A finer block on a coarser one (nine nodes inside one cell of the other body) settles to the
  same balance of forces.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import scipy.optimize
import torch

import torchdeform as td
from tests.oracles.contact_equilibrium import edges_from, energy, gradient, one_blas_thread
from tests.oracles.edge_list import EdgeList
from torchdeform.errors import ConfigError
from torchdeform.interact.bodies import Bodies, Body
from torchdeform.interact.reactions import support_reaction

G = 9.81
H = 0.01  # spacing (m) of every block here
K = 50.0  # spring stiffness (N/m)
M = 1e-3  # node mass (kg)
F64 = torch.float64
LOWER, UPPER = (4, 4, 4), (3, 3, 3)
#: the upper block's bottom face lies inside the lower block's top face, 0.5 mm above it
UPPER_ORIGIN = (0.0305, 0.005, 0.005)
W_UPPER = M * 27 * G  # weights (N)
W_BOTH = M * (64 + 27) * G


def _stack(friction, *, integrator=None, upper_spacing=H, upper_origin=UPPER_ORIGIN):
    lower = td.Model(
        td.Grid(LOWER, spacing=H), stiffness=K, mass=M, fixed="bottom", gravity=(-G, 0, 0), decay=50.0, dtype=F64
    )
    upper = td.Model(
        td.Grid(UPPER, spacing=upper_spacing, origin=upper_origin),
        stiffness=K,
        mass=M,
        gravity=(-G, 0, 0),
        decay=50.0,
        dtype=F64,
    )
    return Bodies([Body("lower", lower), Body("upper", upper)], friction=friction, integrator=integrator)


def _run(scene, states, dt, steps):
    return scene.simulate(states, dt=dt, steps=steps)


@functools.cache
def _stack_with_friction():
    """The stack with mu = 0.5 after 1.2 s (dt = 1 ms, decay 50/s), and the state one step later."""
    scene = _stack(0.5)
    states = _run(scene, scene.rest_states(), 1e-3, 1200)
    return scene, states, scene.step(states, 1e-3)


@functools.cache
def _stack_frictionless():
    """The frictionless stack: 0.8 s at dt = 1 ms, then 0.1 s at dt = 0.25 ms; the last two states.

    (Without friction the block's sideways position is held by nothing but the dent it makes: the
    second stage, at a smaller step, is compared with the oracle before it drifts.)
    """
    scene = _stack(0.0)
    states = _run(scene, scene.rest_states(), 1e-3, 800)
    states = _run(scene, states, 2.5e-4, 400)
    return scene, states, scene.step(states, 2.5e-4)


def _readings(states):
    r = states[1].readings
    assert r is not None and set(r) == {"lower/upper.force", "lower/upper.contacts", "lower/upper.penetration"}
    assert all(torch.equal(r[k], states[0].readings[k]) for k in r)  # the same readings on both bodies
    return r


# ----------------------------------------------------------------------------------------- the stack
def test_stack_support_carries_both_weights_and_contact_carries_the_upper(one_thread):
    scene, states, after = _stack_with_friction()
    lower = scene.bodies[0].model
    for s in (states, after):
        reaction = support_reaction(lower, s[0])[0]
        assert float(reaction[0]) == pytest.approx(W_BOTH, rel=1e-6)  # (a) both blocks' weight, along +D
        # sideways: 0 in equilibrium; what is left is the last of the settling (1.4e-7 of the weight)
        assert float(reaction[1:].abs().max()) < 1e-6 * W_BOTH
        force = _readings(s)["lower/upper.force"][0]
        # (b) lower carries the upper's weight (achieved 1.7e-6: the friction's share in the reading)
        assert float(force[0]) == pytest.approx(W_UPPER, rel=1e-5)
        assert float(force[1:].abs().max()) < 1e-6 * W_UPPER
        assert float(_readings(s)["lower/upper.contacts"][0]) > 0
    # nearly at rest: the last step moved the nodes by 1e-6 h, at speeds below 0.01 mm/s (what is
    # left of the settling after 1.2 s: the contacts resolved one colour after another settle slowly)
    assert max(float((a.x - b.x).abs().max()) for a, b in zip(states, after)) < 1e-5 * H
    assert max(float(s.v.abs().max()) for s in after) < 2e-5


def test_fine_block_on_a_coarse_block_settles(one_thread):
    """A finer block whose nine bottom nodes all fall into one cell of the lower block settles too.

    A 3^3 block of spacing 4 mm (0.8 cm wide, 27 g) on the 4^3 block of spacing 1 cm, over the lower
    block's middle top cell, mu = 0.5, decay 50/s: the nine contacts share four corners of the lower
    block and are resolved one after another (colours), so they do not overshoot; the rocking
    dies out (node speeds halve every 0.4 s: 1.4e-5 m/s after 1.6 s) and the forces reach the
    weights (achieved 9e-7 on the base, 4e-6 in the contact reading).
    """
    scene = _stack(0.5, upper_spacing=0.004, upper_origin=(0.0302, 0.011, 0.011))
    states = _run(scene, scene.rest_states(), 1e-3, 1600)
    after = scene.step(states, 1e-3)
    assert float(support_reaction(scene.bodies[0].model, after[0])[0, 0]) == pytest.approx(W_BOTH, rel=2e-6)
    assert float(_readings(after)["lower/upper.force"][0, 0]) == pytest.approx(W_UPPER, rel=1e-5)
    assert float(_readings(after)["lower/upper.contacts"][0]) == 9
    assert max(float(s.v.abs().max()) for s in after) < 2e-5


def _bilinear_gap(p, corners, above):
    """Vertical gap (m) of point ``p`` (3,) above (``above``) or below the bilinear face ``corners`` (4, 3).

    The corners are ordered (0, 0), (0, 1), (1, 0), (1, 1) in the face's two lateral axes. Solves
    ``X_lat(s, t) = p_lat`` by Newton, then ``gap = +-(p_D - X_D(s, t))``. Returns the gap and its
    gradient with respect to ``p`` (3,) and to the corners (4, 3): by implicit differentiation,
    ``(1, -c)`` on ``p`` and ``-b_k (1, -c)`` on corner ``k`` (times the sign), ``c = dX_D/d(s, t)
    (dX_lat/d(s, t))^-1`` the slope of the face: the gradient is along the face's normal.
    """

    def face(s, t):
        b = np.array([(1 - s) * (1 - t), (1 - s) * t, s * (1 - t), s * t])
        db = np.array([[-(1 - t), -(1 - s)], [-t, 1 - s], [1 - t, -s], [t, s]])
        return b @ corners, corners.T @ db, b

    s = t = 0.5
    for _ in range(30):
        X, J, _ = face(s, t)
        ds, dt = np.linalg.solve(J[1:], p[1:] - X[1:])
        s, t = s + ds, t + dt
    X, J, b = face(s, t)
    c = J[0] @ np.linalg.inv(J[1:])
    normal = np.array([1.0, -c[0], -c[1]])
    sign = 1.0 if above else -1.0
    return sign * (p[0] - X[0]), sign * normal, -sign * b[:, None] * normal[None]


@functools.cache
def _stack_oracle():
    """The constrained minimum of the stack's potential energy: ``(x (N, 3), gaps, multipliers, KKT residual (N))``.

    Nodes: the lower block's (C order), then the upper block's. Variables: displacements of the
    free nodes in units of the spacing; energy in units of ``k h^2``.
    """
    low, up = EdgeList(LOWER, (H,) * 3, 26), EdgeList(UPPER, (H,) * 3, 26)
    n_low = low.N
    X = np.concatenate([low.X, up.X + np.asarray(UPPER_ORIGIN)])
    e_low, e_up = edges_from(low, K), edges_from(up, K)
    edges = tuple(np.concatenate([a, b + (n_low if i < 2 else 0)]) for i, (a, b) in enumerate(zip(e_low, e_up)))
    mass, gravity = np.full(len(X), M), np.array([-G, 0.0, 0.0])
    free = np.flatnonzero(~np.concatenate([low.X[:, 0] == 0.0, np.zeros(up.N, bool)]))
    top = LOWER[0] - 1
    cons = []  # (node, the four corners of the face it must not cross, above?)
    for ijk in up.nodes:  # the upper block's bottom nodes, above the lower block's top face
        if ijk[0] == 0:
            p = X[n_low + up.index[ijk]]
            i, j = int(p[1] // H), int(p[2] // H)
            face = [low.index[(top, i + a, j + b)] for a in (0, 1) for b in (0, 1)]
            cons.append((n_low + up.index[ijk], face, True))
    for ijk in low.nodes:  # the lower block's top nodes under the upper block, below its bottom face
        rel = (low.X[low.index[ijk]][1:] - np.asarray(UPPER_ORIGIN[1:])) / H
        if ijk[0] == top and (rel > 0).all() and (rel < np.array(UPPER[1:]) - 1).all():
            i, j = (int(r) for r in rel)
            face = [n_low + up.index[(0, i + a, j + b)] for a in (0, 1) for b in (0, 1)]
            cons.append((low.index[ijk], face, False))
    assert len(cons) == 9 + 4
    column = {node: c for c, node in enumerate(free)}
    e_scale = K * H * H

    def positions(u):
        x = X.copy()
        x[free] += H * u.reshape(-1, 3)
        return x

    def fun(u):
        return energy(positions(u), edges, mass, gravity) / e_scale

    def jac(u):
        return (gradient(positions(u), edges, mass, gravity)[free] * H / e_scale).ravel()

    def gaps(u):
        x = positions(u)
        return np.array([_bilinear_gap(x[a], x[f], above)[0] for a, f, above in cons]) / H

    def gaps_jac(u):
        x = positions(u)
        out = np.zeros((len(cons), 3 * len(free)))
        for r, (a, f, above) in enumerate(cons):
            _, ga, gf = _bilinear_gap(x[a], x[f], above)
            for node, g in [(a, ga)] + list(zip(f, gf)):
                if node in column:
                    out[r, 3 * column[node] : 3 * column[node] + 3] += g
        return out

    with one_blas_thread():
        res = scipy.optimize.minimize(
            fun,
            np.zeros(3 * len(free)),
            jac=jac,
            method="SLSQP",
            constraints=[{"type": "ineq", "fun": gaps, "jac": gaps_jac}],
            options={"ftol": 1e-15, "maxiter": 1000},
        )
        assert res.success, res.message
        # KKT: the energy gradient is a non-negative combination of the gradients of the active gaps
        g, J, c = jac(res.x), gaps_jac(res.x), gaps(res.x)
        active = c < 1e-9
        lam = np.zeros(len(cons))
        lam[active] = np.linalg.lstsq(J[active].T, g, rcond=None)[0]
        residual = np.abs(g - J.T @ lam).max() * e_scale / H  # N
    return positions(res.x), c * H, lam * e_scale / H, residual


def _flat(states):
    return np.concatenate([s.x[0].reshape(3, -1).T.numpy() for s in states])


def test_stack_interface_matches_the_constrained_energy_minimum(one_thread):
    x_eq, gaps, lam, residual = _stack_oracle()
    # the oracle is a KKT point: no penetration, forces balanced to 1e-6 of a node's weight (achieved
    # 3e-7: 3e-9 N, i.e. ~1e-10 m at 50 N/m), pushes only
    assert gaps.min() > -1e-12 and residual < 1e-6 * M * G and lam.min() > -1e-6 * M * G
    # the upper block's nine bottom nodes bear on the lower block
    assert (lam[:9] > 0.1 * M * G).all() and np.allclose(gaps[:9], 0.0, atol=1e-12)
    assert lam[:9].sum() == pytest.approx(W_UPPER, rel=1e-6)  # and carry its weight
    assert (gaps[9:] > 1e-3 * H).all()  # the lower's top nodes stay below the upper's (sagging) bottom face
    _, states, after = _stack_frictionless()
    x_sim = 0.5 * (_flat(states) + _flat(after))  # the middle of the chatter (see the failing test above)
    # Achieved: 0.9e-4 h (0.9e-6 m, along D). The contact is first order and the chatter's offset
    # is O(dt^2): about 2e-3 h at dt = 1 ms, 1e-4 h at 0.25 ms. With a
    # resolution that comes to rest the stationary state would be the KKT point up to the normal's
    # tilt in the lower block's edge cells, O(penetration / h) ~ 1e-3 rad at 1 ms.
    assert np.abs(x_sim - x_eq).max() < 1e-3 * H
    # the sagging of the stack is reproduced, not just its rest shape: the oracle moved the upper block 1.4 mm
    assert np.abs(x_eq - _flat(_stack(0.0).rest_states())).max() > 1e-3


def test_implicit_euler_carries_the_stack(one_thread):
    # The contact acts after the integrator's step, whatever the integrator: the resolution is first
    # order in dt with implicit Euler too (only the stationary forces are checked here, which the
    # order does not change).
    scene = _stack(0.5, integrator=td.ImplicitEuler(cg_tol=1e-10))
    states = _run(scene, scene.rest_states(), 1e-2, 160)
    reaction = support_reaction(scene.bodies[0].model, states[0])[0]
    assert float(reaction[0]) == pytest.approx(W_BOTH, rel=1e-6)
    assert float(_readings(states)["lower/upper.force"][0, 0]) == pytest.approx(W_UPPER, rel=1e-6)


# ---------------------------------------------------------------------------------------- momentum
@pytest.mark.parametrize("damping, friction", [(None, 0.0), (0.05, 0.3)], ids=["undamped", "damped-friction"])
def test_thrown_bodies_conserve_momentum_and_never_gain_energy(damping, friction, one_thread):
    dt = 5e-4
    a = td.Model(td.Grid((3, 3, 3), spacing=H), stiffness=K, mass=M, damping=damping, dtype=F64)
    b = td.Model(
        td.Grid((3, 3, 3), spacing=H, origin=(0.025, 0.004, 0.003)),  # 5 mm above, offset sideways
        stiffness=K,
        mass=2 * M,
        damping=damping,
        dtype=F64,
    )
    models = (a, b)
    scene = Bodies([Body("a", a), Body("b", b)], friction=friction)
    states = scene.rest_states()
    states[0].v[:, 0] = 0.4  # a up, b down: they close at 0.7 m/s
    states[1].v[:, 0] = -0.3

    def momentum(st):
        return sum((m.mass * s.v).flatten(2).sum(2)[0].numpy() for m, s in zip(models, st))

    def work(st):  # kinetic + elastic (J)
        return sum(float(m.energy(s)["kinetic"][0] + m.energy(s)["elastic"][0]) for m, s in zip(models, st))

    def com(m, s):
        return float((m.mass * s.x)[0, 0].sum() / (m.mass.expand_as(s.x[:, :1])).sum())

    p0, e0 = momentum(states), work(states)
    scale = sum(float((m.mass * s.v).abs().sum()) for m, s in zip(models, states))  # 0.0324 kg m/s
    seen = {"dp": 0.0, "gain": -math.inf, "order": math.inf, "pen": 0.0, "contacts": 0}

    def record(k, st):
        seen["dp"] = max(seen["dp"], float(np.abs(momentum(st) - p0).max()) / scale)
        seen["gain"] = max(seen["gain"], work(st) - e0)
        seen["order"] = min(seen["order"], com(b, st[1]) - com(a, st[0]))
        r = st[0].readings
        seen["pen"] = max(seen["pen"], float(r["a/b.penetration"][0]))
        seen["contacts"] += int(r["a/b.contacts"][0] > 0)

    end = scene.simulate(states, dt=dt, steps=200, callback=record)
    assert seen["contacts"] > 10  # they did collide
    assert seen["dp"] < 1e-9  # achieved: 2e-16
    assert seen["gain"] <= 1e-12 * e0  # achieved: 0 (the start is the maximum)
    assert work(end) < 0.9 * e0  # the collision dissipated (inelastic): 27% lost undamped, 74% damped
    assert seen["order"] > 0.5 * H  # the centres never crossed: b stays above a
    assert seen["pen"] < 0.7 * dt  # below the closing speed times the step (achieved 2.5e-4 m vs 3.5e-4)
    assert com(b, end[1]) - com(a, end[0]) > seen["order"]  # and they move apart again


# ---------------------------------------------------------------------------------------- friction
def _slope(ratio, mu, dt, steps):
    """A 3^3 block (27 g) released 10 um above a fixed 3x8x4 block, gravity tilted by ``atan(ratio mu)``.

    Returns ``(theta, times, mean H velocity, mean H position of the bottom nodes, contact force (T, 3))``.
    """
    theta = math.atan(ratio * mu)
    base = td.Grid((3, 8, 4), spacing=H)
    lower = td.Model(base, stiffness=K, mass=M, fixed=torch.ones(base.shape, dtype=torch.bool), dtype=F64)
    upper = td.Model(
        td.Grid((3, 3, 3), spacing=H, origin=(0.02001, 0.005, 0.005)),  # 10 um above the top face (D = 0.02)
        stiffness=K,
        mass=M,
        damping=0.1,  # calms the block's own vibrations (no effect on its sliding)
        gravity=(-G * math.cos(theta), G * math.sin(theta), 0.0),  # the slope goes down towards +H
        dtype=F64,
    )
    scene = Bodies([Body("lower", lower), Body("upper", upper)], friction=mu)
    rows = []

    def record(k, st):
        x, v = st[1].x[0], st[1].v[0]
        f = st[1].readings["lower/upper.force"][0] if st[1].readings else torch.zeros(3, dtype=F64)
        rows.append((k * dt, float(v[1].mean()), float(x[1, 0].mean()), *f.tolist()))

    scene.simulate(scene.rest_states(), dt=dt, steps=steps, callback=record)
    r = np.array(rows)
    return theta, r[:, 0], r[:, 1], r[:, 2], r[:, 3:]


def test_block_on_a_gentle_slope_sticks(one_thread):
    mu = 0.5
    theta, t, _, bottom, force = _slope(0.8, mu, 1e-3, 300)
    late = t >= 0.15
    # after landing (where it slips 0.3 mm while the normal force builds up), the bottom stays put:
    # achieved 8e-8 m over 0.15 s, against 2.6 cm in 0.2 s for the steep slope below
    assert np.ptp(bottom[late]) < 5e-4 * H  # the last of the settling: 1.4e-4 h back and forth, no creep
    # and the contact balances the weight: W cos(theta) along +D, W sin(theta) up the slope
    # (achieved 4e-5 and 7e-4 relative, averaged over the block's remaining vibration)
    mean = force[late].mean(0)
    assert mean[0] == pytest.approx(W_UPPER * math.cos(theta), rel=2e-3)
    assert -mean[1] == pytest.approx(W_UPPER * math.sin(theta), rel=2e-3)
    assert -mean[1] / mean[0] < mu  # inside the friction cone


def test_block_on_a_steep_slope_slides_with_the_coulomb_acceleration(one_thread):
    mu, dt = 0.5, 2.5e-4
    theta, t, v, bottom, _ = _slope(1.3, mu, dt, 800)
    expected = G * (math.sin(theta) - mu * math.cos(theta))  # 1.234 m/s^2
    window = t >= 0.05  # after landing
    measured = np.polyfit(t[window], v[window], 1)[0]
    # first order in dt (the normal is tilted where nodes of the fixed block poke into the block's
    # edge cells): measured / expected = 0.89 at dt = 1 ms, 0.96 at 0.5 ms, 0.991 at 0.25 ms
    assert measured == pytest.approx(expected, rel=0.02)
    assert bottom[-1] - bottom[0] > 1.5 * H  # it slides (2.6 cm in 0.2 s)


# ---------------------------------------------------------------------------------------- bad input
def test_bodies_that_start_inside_each_other_are_one_clear_error(one_thread):
    scene = _stack(0.0, upper_origin=(0.025, 0.005, 0.005))  # upper's bottom face 5 mm inside the lower
    with pytest.raises(ConfigError) as e:
        scene.simulate(scene.rest_states(), dt=1e-3, steps=1)
    message = str(e.value)
    assert "lower" in message and "upper" in message and "\n" not in message


def test_nameless_and_duplicate_bodies_are_one_clear_error():
    m1 = td.Model(td.Grid((2, 2, 2), spacing=H), stiffness=K, mass=M, dtype=F64)
    m2 = td.Model(td.Grid((2, 2, 2), spacing=H, origin=(0.05, 0.0, 0.0)), stiffness=K, mass=M, dtype=F64)
    with pytest.raises(ConfigError) as e:
        Body("", m1)
    assert e.value.key == "bodies.name" and "\n" not in str(e.value)
    with pytest.raises(ConfigError) as e:
        Bodies([Body("a", m1), Body("a", m2)])
    assert "'a'" in str(e.value) and "\n" not in str(e.value)
