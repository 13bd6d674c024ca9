"""The C contact kernel against the tensor code it replaces (the oracle: ``engine="torch"``).

The tensor code's physics is checked in test_bodies.py (static stack against a constrained energy
minimum, momentum, friction); here the kernel must give the same trajectories to rounding: the
same constraints, colours and impulses.
"""

from __future__ import annotations

import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.interact import native_contact
from torchdeform.interact.bodies import Bodies, Body, BodyContact

needs_kernel = pytest.mark.skipif(native_contact.unavailable() is not None, reason="no C compiler")


def _scene(engine, dtype, friction):
    """A soft block dropped onto a fixed block, batch 2: the second entry tilted (normals off the axes)."""
    lower = td.Model(
        td.Grid((5, 6, 5), spacing=0.01), stiffness=60.0, mass=1e-3, fixed="bottom", gravity=(-9.81, 0, 0), dtype=dtype
    )
    upper = td.Model(
        td.Grid((3, 4, 3), spacing=0.008, origin=(0.045, 0.011, 0.013)),
        stiffness=40.0,
        mass=2e-3,
        gravity=(-9.81, 0, 0),
        dtype=dtype,
    )
    bodies = Bodies([Body("lower", lower), Body("upper", upper)], friction=friction, engine=engine)
    states = bodies.rest_states(batch=2)
    c, s = torch.cos(torch.tensor(0.3, dtype=dtype)), torch.sin(torch.tensor(0.3, dtype=dtype))
    x = states[1].x.clone()
    centre = x[1].mean(dim=(1, 2, 3), keepdim=True)
    d, h = x[1, 0] - centre[0], x[1, 1] - centre[1]
    x[1, 0], x[1, 1] = centre[0] + c * d - s * h, centre[1] + s * d + c * h  # the second entry tilted
    states[1] = td.State(x, states[1].v + torch.tensor([-0.3, 0.05, 0.0], dtype=dtype).view(1, 3, 1, 1, 1))
    return bodies, states


@needs_kernel
@pytest.mark.parametrize(("dtype", "tol"), [(F64, 1e-12), (torch.float32, 2e-5)])
@pytest.mark.parametrize("friction", [0.0, 0.6])
def test_the_kernel_follows_the_tensor_code(dtype, tol, friction, one_thread):
    runs = {}
    for engine in ("torch", "native"):
        bodies, states = _scene(engine, dtype, friction)
        assert bodies.contact.engine_for(states[0].x) == engine
        counts = []
        for _ in range(120):
            states = bodies.step(states, 5e-4)
            counts.append(states[0].readings["lower/upper.contacts"].clone())
        runs[engine] = states, torch.stack(counts)
    (st, ct), (sn, cn) = runs["torch"], runs["native"]
    assert float(ct.sum()) > 200 and bool((ct > 3).any(0).all())  # in contact, in both batch entries
    assert torch.equal(ct, cn)
    scale = 0.05  # m: the scene's size
    for a, b in zip(st, sn):
        assert float((a.x - b.x).abs().max()) <= tol * scale
        assert float((a.v - b.v).abs().max()) <= tol * 10
        for key in a.readings:
            assert torch.allclose(a.readings[key], b.readings[key], rtol=1e3 * tol, atol=1e3 * tol), key


def test_engine_choice():
    assert BodyContact(engine="torch").engine_for(torch.zeros(1)) == "torch"
    with pytest.raises(td.ConfigError, match=r"contact\.engine"):
        BodyContact(engine="cuda")
    with pytest.raises(td.ConfigError, match="float32 or float64"):
        BodyContact(engine="native").engine_for(torch.zeros(1, dtype=torch.float16))
    auto = BodyContact().engine_for(torch.zeros(1, dtype=torch.float16))
    assert auto == "torch"


def test_a_diverging_body_is_named():
    """Ten times the stability bound: the run stops with a DivergenceError naming the body that blew up."""
    bodies, states = _scene("auto", F64, 0.5)
    bound = td.time_step_bound(bodies.bodies[0].model, integrator="symplectic")
    with pytest.raises(td.DivergenceError, match=r"body '(lower|upper)'") as caught:
        bodies.simulate(states, dt=10 * bound, steps=400)
    assert caught.value.step <= 400 and caught.value.safe_dt is not None
    bad = [td.State(s.x.clone(), s.v.clone()) for s in states]
    bad[1].v[0, 0, 0, 0, 0] = float("nan")
    with pytest.raises(td.ConfigError, match=r"bodies\.upper\.state\.v"):
        bodies.simulate(bad, dt=1e-4, steps=1)
