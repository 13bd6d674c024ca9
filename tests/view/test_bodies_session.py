"""BodiesSession: the live viewer of several bodies, against an independent run.

Oracles:

* the simulation: after N steps of the session, every body's surface vertices equal the
  ``cut_surfaces`` vertices (marching tetrahedra + extension + trilinear interpolation, float64) of
  that body's nodes after N steps of ``Bodies.simulate`` with the same time step, from a fresh
  ``Bodies`` built from the scene (its own run, not the session's); the time step is recomputed here
  from the bodies' stability bounds;
* the frame: its bytes are the bodies' vertices in the order of the mesh's parts, then the tools'
  poses (the tool's path, read here from the scene text);
* commands: play, pause, reset do what they say; the single-body interactions raise ValueError
  naming the command, and nothing changes;
* the server: a page connected to it gets the mesh with one part per body, then frames of its size.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torchdeform.scene import load_scene
from torchdeform.scene.animation import BODY_COLOURS
from torchdeform.sim.stability import time_step_bound
from torchdeform.topology import cut_surfaces
from torchdeform.view.bodies import BodiesSession
from torchdeform.view.session import frame_size

STEPS = 40
TWO = """
[[bodies]]
name = "lower"
[bodies.grid]
shape = [4, 4, 4]
spacing = 0.01
[bodies.material]
stiffness = 50.0
[bodies.mass]
mass = 0.001
[bodies.boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]
decay = 50.0

[[bodies]]
name = "upper"
[bodies.grid]
shape = [3, 3, 3]
spacing = 0.01
origin = [0.0305, 0.005, 0.005]
[bodies.material]
stiffness = 50.0
[bodies.mass]
mass = 0.001
[bodies.boundary]
gravity = [-9.81, 0.0, 0.0]
decay = 50.0
[[bodies.tools]]
name = "probe"
shape = "sphere"
radius = 0.004
path = [[0.0, [0.08, 0.015, 0.015]], [1.0, [0.06, 0.015, 0.015]]]

[integrator]
name = "symplectic"
dt = "auto"
steps = 100
"""


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("two") / "two.toml"
    path.write_text(TWO)
    return load_scene(path)


def _oracle_vertices(grid, x) -> np.ndarray:
    pieces = cut_surfaces(grid, x.double(), torch.where(grid.nodes(), 0, -1))
    return np.concatenate([p.vertices for p in pieces])


def test_surfaces_follow_an_independent_run_of_the_bodies(scene):
    s = BodiesSession(scene)
    bodies = scene.bodies()
    models = [b.model for b in bodies.bodies]
    bound = min(time_step_bound(m, integrator=bodies.integrator) for m in models)
    assert s.dt == pytest.approx(scene.safety * bound, rel=1e-12)  # dt = "auto", as torchdeform run

    m = s.mesh()
    assert m["surface"] == "bodies" and m["commands"] == ["play", "pause", "reset"]
    assert [p["name"] for p in m["parts"]] == ["lower", "upper"]
    assert [p["color"] for p in m["parts"]] == [list(c) for c in BODY_COLOURS[:2]]
    faces = np.asarray(m["faces"]).reshape(-1, 3)
    first = 0
    for p in m["parts"]:  # each part's triangles use only its own vertices
        part = faces[sum(q["triangles"] for q in m["parts"][: m["parts"].index(p)]) :][: p["triangles"]]
        assert part.min() >= first and part.max() < first + p["vertices"]
        first += p["vertices"]
    assert first == m["vertices"] and len(m["colors"]) == 3 * m["vertices"]

    for _ in range(STEPS):
        assert s.advance(0.0) == 1  # one step per call with no wall time to spend
    states = bodies.simulate(bodies.rest_states(), dt=s.dt, steps=STEPS)
    got = s.body_vertices()
    assert len(got) == 2
    moved = 0.0
    for n, (model, state) in enumerate(zip(models, states)):
        ref = _oracle_vertices(model.grid, state.x)
        assert got[n].shape == ref.shape == (m["parts"][n]["vertices"], 3)
        np.testing.assert_allclose(got[n].numpy(), ref, rtol=0, atol=1e-6)
        moved = max(moved, float(np.abs(ref - _oracle_vertices(model.grid, model.X)).max()))
    assert moved > 1e-3  # the upper body fell (its gap is 0.5 mm, then it rests on the lower)

    frame = np.frombuffer(s.positions(), dtype="<f4")
    assert len(frame) * 4 == frame_size(m)
    V = m["vertices"]
    np.testing.assert_array_equal(frame[: 3 * V].reshape(-1, 3), torch.cat(got).numpy())
    t = STEPS * s.dt  # the probe's path: from D = 0.08 m down 0.02 m per second
    np.testing.assert_allclose(frame[3 * V : 3 * V + 3], [0.08 - 0.02 * t, 0.015, 0.015], atol=1e-6)
    stats = s.stats()
    assert stats["t"] == pytest.approx(t) and "lower/upper" in stats["contact"] and stats["contact"]["lower/upper"] > 0


def test_play_pause_reset_and_refusals(scene):
    s = BodiesSession(scene)
    rest = [v.clone() for v in s.body_vertices()]
    s.command({"cmd": "pause"})
    assert s.advance(0.0) == 0 and not s.stats()["playing"]
    s.command({"cmd": "play"})
    for _ in range(5):
        s.advance(0.0)
    assert s.stats()["t"] > 0
    for msg in (
        {"cmd": "drag", "vertex": 0, "target": [0.0, 0.0, 0.0]},
        {"cmd": "tool", "position": [0.0, 0.0, 0.0]},
        {"cmd": "cut", "origin": [0, 0, 0], "u": [0, 1, 0], "v": [0, 0, 1]},
        {"cmd": "term", "name": "consistency", "value": 5},
        {"cmd": "release"},
    ):
        t = s.stats()["t"]
        with pytest.raises(ValueError, match=f"^{msg['cmd']}: not with several bodies"):
            s.command(msg)
        assert s.stats()["t"] == t
    with pytest.raises(ValueError, match="unknown value"):
        s.command({"cmd": "play", "value": 1})
    s.command({"cmd": "reset"})
    assert s.stats()["t"] == 0.0 and s.stats()["playing"]
    for a, b in zip(rest, s.body_vertices()):
        assert torch.equal(a, b)


def test_the_server_sends_one_part_per_body(scene):
    pytest.importorskip("websockets")
    from websockets.sync.client import connect

    from torchdeform.view.server import Viewer

    v = Viewer(BodiesSession(scene)).start()
    try:
        url = f"ws://127.0.0.1:{v.port}/ws?token={v.token}"
        with connect(url, origin=f"http://127.0.0.1:{v.port}", open_timeout=10) as ws:  # pyright: ignore[reportArgumentType]
            mesh = json.loads(ws.recv(timeout=10))
            assert mesh["type"] == "mesh" and [p["name"] for p in mesh["parts"]] == ["lower", "upper"]
            ws.send(json.dumps({"cmd": "cut", "origin": [0, 0, 0], "u": [0, 1, 0], "v": [0, 0, 1]}))
            sizes = []
            while len(sizes) < 3:
                msg = ws.recv(timeout=10)
                if isinstance(msg, bytes):
                    sizes.append(len(msg))
        assert sizes == [frame_size(mesh)] * 3
        assert v.ignored == 1  # the cut, refused with its one line
    finally:
        v.stop()
