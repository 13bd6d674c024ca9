"""Bodies of one grid shape stepped in one batch (torchdeform.interact.stacking).

Oracle: the same scene stepped one body after the other (``Bodies(..., batch=False)``): the batch
must give every body the same trajectory to rounding, contacts included.
"""

from __future__ import annotations

import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.interact import ProjectionContact, Sphere, Tool
from torchdeform.interact.bodies import Bodies, Body
from torchdeform.interact.stacking import stack_key


def _pile(batch: bool, integrator=None, elastic: bool = False):
    """A fixed slab and three small cubes of different stiffness, mass and damping falling onto it."""
    g = (-9.81, 0.0, 0.0)
    slab = td.Model(td.Grid((3, 6, 10), spacing=0.01), stiffness=80.0, mass=1e-3, fixed="bottom", gravity=g, dtype=F64)
    bodies = [Body("slab", slab)]
    for k, (E, m) in enumerate([(3e3, 1e-3), (6e3, 2e-3), (1.5e3, 0.5e-3)]):
        material = td.Elastic(E, 0.4) if elastic else 40.0 * (k + 1)
        kw = dict(density=1000.0 + 300 * k) if elastic else dict(mass=m)
        cube = td.Model(
            td.Grid((3, 3, 3), spacing=0.008, origin=(0.0205 + 0.0005 * k, 0.01, 0.003 + 0.03 * k)),
            material,
            damping=0.02 * (k + 1),
            gravity=g,
            dtype=F64,
            **kw,
        )
        bodies.append(Body(f"cube{k}", cube))
    return Bodies(bodies, friction=0.4, batch=batch, integrator=integrator)


@pytest.mark.parametrize(
    ("integrator", "elastic"),
    [(None, False), (td.ImplicitEuler(cg_iters=12, cg_tol=0), False), (None, True)],
    ids=["symplectic", "implicit", "elastic"],
)
def test_a_batch_of_bodies_steps_as_the_bodies_one_by_one(integrator, elastic, one_thread):
    steps, factor = (40, 2.0) if integrator is not None else (150, 0.5)  # implicit: larger, fewer steps
    runs = {}
    for batch in (True, False):
        scene = _pile(batch, integrator, elastic)
        states = scene.rest_states()
        states = [td.State(s.x, s.v + torch.tensor([-0.2, 0.0, 0.05], dtype=F64).view(1, 3, 1, 1, 1)) for s in states]
        dt = factor * min(td.time_step_bound(b.model, integrator="symplectic") for b in scene.bodies)
        touching = [0.0, 0.0, 0.0]

        def count(step, sts, touching=touching):
            for k in range(3):
                touching[k] += float(sts[0].readings[f"slab/cube{k}.contacts"][0])

        states = scene.simulate(states, dt=dt, steps=steps, callback=count)
        runs[batch] = scene, states, touching
    batched, separate = runs[True], runs[False]
    assert batched[0].groups == [[0], [1, 2, 3]] and separate[0].groups == [[0], [1], [2], [3]]
    assert min(batched[2]) > 0 and batched[2] == separate[2], batched[2]  # every cube landed, the same contacts
    for a, b in zip(batched[1], separate[1]):
        assert float((a.x - b.x).abs().max()) <= 1e-12
        assert float((a.v - b.v).abs().max()) <= 1e-9
    moved = float((batched[1][2].x - batched[1][3].x).abs().max())
    assert moved > 0.01  # different bodies, different trajectories


def test_what_cannot_be_stacked_steps_alone():
    scene = _pile(True)
    models = [b.model for b in scene.bodies]
    assert stack_key(models[1], "symplectic") == stack_key(models[2], "symplectic")
    assert stack_key(models[0], "symplectic") != stack_key(models[1], "symplectic")  # another grid, fixed nodes
    assert stack_key(models[1], "knoche") is None and stack_key(models[1], td.ImplicitEuler()) is not None
    probe = Tool(Sphere(0.002), position=(0.1, 0.1, 0.1), name="probe")
    with_tool = td.Model(models[1].grid, 40.0, mass=1e-3, damping=0.02, gravity=(-9.81, 0, 0), dtype=F64)
    with_tool.interactions = [ProjectionContact(probe)]
    assert stack_key(with_tool, "symplectic") is None
    assert Bodies([Body(b.name, b.model) for b in scene.bodies], batch=False).groups == [[0], [1], [2], [3]]
