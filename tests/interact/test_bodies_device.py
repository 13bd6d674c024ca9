"""Several bodies on the run's device (``pytest --device cuda``): the tensor contact there equals the CPU's.

Oracle: the same scene on the CPU with the tensor engine (float64); on a GPU ``engine="auto"``
takes the tensor code (the C kernel is the CPU's), batches of one grid shape included.
"""

from __future__ import annotations

import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.interact.bodies import Bodies, Body


def _scene(device, engine):
    g = (-9.81, 0.0, 0.0)
    slab = td.Model(
        td.Grid((3, 5, 8), spacing=0.01), stiffness=80.0, mass=1e-3, fixed="bottom", gravity=g, dtype=F64, device=device
    )
    bodies = [Body("slab", slab)]
    for k in range(2):  # two cubes of one grid shape: one batch
        cube = td.Model(
            td.Grid((3, 3, 3), spacing=0.008, origin=(0.0205, 0.01, 0.005 + 0.035 * k)),
            40.0 * (k + 1),
            mass=1e-3,
            gravity=g,
            dtype=F64,
            device=device,
        )
        bodies.append(Body(f"cube{k}", cube))
    return Bodies(bodies, friction=0.4, engine=engine)


def test_bodies_on_the_device_follow_the_cpu(device):
    runs = {}
    for dev in (torch.device("cpu"), device):
        scene = _scene(dev, "torch" if dev.type == "cpu" else "auto")
        assert scene.groups == [[0], [1, 2]]
        states = scene.rest_states()
        states = [td.State(s.x, s.v - 0.2 * torch.eye(3, dtype=F64, device=dev)[0].view(1, 3, 1, 1, 1)) for s in states]
        assert scene.contact.engine_for(states[0].x) == "torch"  # asked for on the CPU, the only one on a GPU
        states = scene.simulate(states, dt=2e-4, steps=60)
        assert states[1].x.device.type == dev.type
        runs[dev.type] = [s.x.cpu() for s in states], float(states[0].readings["slab/cube0.contacts"][0])
    (xa, ca), (xb, cb) = runs["cpu"], runs[device.type]
    assert ca > 0 and ca == cb
    assert all(float((a - b).abs().max()) <= 1e-10 for a, b in zip(xa, xb))
