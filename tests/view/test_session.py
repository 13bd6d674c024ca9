"""ViewerSession: the simulation behind the live viewer, against independent oracles.

* positions(): the vertices of ``cut_surfaces`` (marching tetrahedra + extension + trilinear
  interpolation, float64) at the rest state and at deformed states;
* cut: the springs removed equal a brute-force numpy crossing test over every spring;
* term: stiffness equals ``tissue_moduli([c]) / lattice_modulus`` (uniform body);
* malformed messages: ValueError and nothing changed.
"""

import math
import random
import threading

import numpy as np
import pytest
import torch

import torchdeform as td
from torchdeform.scene.mass_spring import lattice_modulus, tissue_moduli
from torchdeform.topology import cut_surfaces
from torchdeform.topology.masks import alive
from torchdeform.view.session import ViewerSession

H = 0.002  # spacing (m)
N = 6  # nodes per side


def _scene(consistency=5.0):
    grid = td.Grid((N, N, N), spacing=H, topology=26)
    k = tissue_moduli([consistency])[0] / lattice_modulus(grid)
    args = dict(
        stiffness=k,
        normalize=False,
        damping=1e-3,
        density=1000.0,
        fixed=grid.face("bottom"),
        gravity=(-9.81, 0.0, 0.0),
        decay=50.0,
    )
    return td.Scene(grid, args, integrator=td.SymplecticEuler(), dt="auto", name="cube")


@pytest.fixture
def session():
    torch.manual_seed(0)
    return ViewerSession(_scene())


def _steps(s, n):
    for _ in range(n):
        assert s.advance(0.0) == 1


def _oracle(s):
    pieces = cut_surfaces(s.grid, s.state.x.double(), s.labels)
    return np.concatenate([p.vertices for p in pieces]), np.concatenate(
        [p.faces + off for p, off in zip(pieces, np.cumsum([0] + [len(p.vertices) for p in pieces])[:-1])]
    )


def _vertices(s):
    return np.frombuffer(s.positions(), dtype="<f4").reshape(-1, 3)


def _top_vertex(s):
    """A vertex on the top face, near the middle (index of the current mesh)."""
    v = _vertices(s)
    mid = np.array([v[:, 0].max(), (N - 1) * H / 2, (N - 1) * H / 2])
    return int(np.argmin(((v - mid) ** 2).sum(1)))


# ------------------------------------------------------------------ surface
def test_positions_match_cut_surfaces_at_rest_and_deformed(session):
    s = session
    m = s.mesh()
    ref, faces = _oracle(s)
    assert m["type"] == "mesh" and m["vertices"] == len(ref) and m["version"] == 0
    assert np.array_equal(np.asarray(m["faces"]).reshape(-1, 3), faces)
    assert len(s.positions()) == 4 * 3 * len(ref)
    np.testing.assert_allclose(_vertices(s), ref, atol=1e-7)
    lo, hi = np.asarray(m["bounds"])
    np.testing.assert_allclose(lo, [-H / 2] * 3, atol=1e-9)
    np.testing.assert_allclose(hi, [(N - 0.5) * H] * 3, atol=1e-9)
    s.command({"cmd": "drag", "vertex": _top_vertex(s), "target": [(N - 1) * H + 0.002, 0.004, 0.006]})
    _steps(s, 120)
    assert float((s.state.x - s.model.X).abs().max()) > 1e-3
    ref, _ = _oracle(s)
    np.testing.assert_allclose(_vertices(s), ref, atol=1e-5)
    err = np.abs(_vertices(s) - ref).max()
    assert err < 1e-6  # float32 of positions of about 1 cm


# ------------------------------------------------------------------ drag
def test_drag_pulls_the_node_and_release_lets_go(session):
    s = session
    i = _top_vertex(s)
    target = [(N - 1) * H + 0.003, 0.005, 0.005]
    s.command({"cmd": "drag", "vertex": i, "target": target})
    d, h, w = s._drag_node
    assert d == N - 1  # the node nearest to a top vertex
    rest = s.model.X[0, :, d, h, w].clone()
    _steps(s, 150)
    x = s.state.x[0, :, d, h, w]
    np.testing.assert_allclose(x.tolist(), target, atol=1e-7)  # held exactly at the target
    below = s.state.x[0, 0, d - 1, h, w] - s.model.X[0, 0, d - 1, h, w]
    assert float(below) > 2e-4  # the body followed upwards
    assert s.stats()["drag_force"] > 0
    s.command({"cmd": "release"})
    assert s.stats()["drag_force"] == 0
    _steps(s, 400)
    assert float((s.state.x[0, :, d, h, w] - rest).norm()) < 0.3 * float((torch.tensor(target) - rest).norm())


# ------------------------------------------------------------------ tool
def test_sphere_tool_presses_and_reports_force(session):
    s = session
    r = s.tool_radius
    assert math.isclose(r, 3 * H)
    top = (N - 1) * H
    s.command({"cmd": "tool", "position": [top + r - 0.002, top / 2, top / 2]})  # 2 mm deep
    _steps(s, 200)
    st = s.stats()
    assert st["force"] > 0 and math.isfinite(st["force"])
    c = N // 2
    assert float(s.state.x[0, 0, N - 1, c, c]) < top - 5e-4  # the top pushed down
    _d, _ = s._tool.sdf(s.state.x, s.state.t)
    s.command({"cmd": "tool", "position": None})
    assert s.stats()["force"] == 0
    assert len(s.model.interactions) == 0


# ------------------------------------------------------------------ cut
def _brute_force_crossings(grid, x, origin, u, v, k):
    """Springs alive (k > 0) whose segment crosses the parallelogram o + a u + b v (plain loops in numpy)."""
    x = x[0].double().numpy()  # (3, D, H, W)
    k = k[0].numpy()
    o, u, v = (np.asarray(p, dtype=np.float64) for p in (origin, u, v))
    n = np.cross(u, v)
    n /= np.linalg.norm(n)
    G = np.array([[u @ u, u @ v], [u @ v, v @ v]])
    count = 0
    D, Hn, W = grid.shape
    for s, (dd, dh, dw) in enumerate(grid.directions):
        for i in range(D):
            for j in range(Hn):
                for m in range(W):
                    i2, j2, m2 = i + dd, j + dh, m + dw
                    if not (0 <= i2 < D and 0 <= j2 < Hn and 0 <= m2 < W) or k[s, i, j, m] == 0:
                        continue
                    p, q = x[:, i, j, m], x[:, i2, j2, m2]
                    hp, hq = (p - o) @ n, (q - o) @ n
                    if (hp > 0) == (hq > 0):
                        continue
                    r = p + hp / (hp - hq) * (q - p) - o
                    a, b = np.linalg.solve(G, [r @ u, r @ v])
                    count += bool(-1e-12 <= a <= 1 + 1e-12 and -1e-12 <= b <= 1 + 1e-12)
    return count


def test_cut_removes_the_crossing_springs_and_rebuilds_the_surface(session):
    s = session
    _steps(s, 30)  # cut the deformed body
    before = s.stats()["springs"]
    assert before == int(alive(s.model)[0].sum())
    V0, version = s.mesh()["vertices"], s.mesh_version
    blade = dict(origin=[0.0051, -0.001, -0.001], u=[0.0003, 0.013, 0.0], v=[0.0, 0.0, 0.007])
    expected = _brute_force_crossings(s.grid, s.state.x, blade["origin"], blade["u"], blade["v"], s.model.stiffness)
    s.command({"cmd": "cut", **blade})
    after = s.stats()["springs"]
    assert expected > 0 and before - after == expected
    assert after == int(alive(s.model)[0].sum())
    assert s.mesh_version == version + 1 and s.stats()["mesh_version"] == version + 1
    assert s.mesh()["vertices"] != V0 and len(torch.unique(s.labels[s.labels >= 0])) == 2
    _steps(s, 30)
    ref, _ = _oracle(s)
    np.testing.assert_allclose(_vertices(s), ref, atol=1e-5)  # the cut faces follow too
    s.command({"cmd": "reset"})
    assert s.mesh_version == version + 2 and s.stats()["springs"] == before
    assert s.mesh()["vertices"] == V0


# ------------------------------------------------------------------ term
def test_consistency_sets_the_stiffness_and_stays_stable(session):
    s = session
    L = lattice_modulus(s.grid)
    term = s.mesh()["terms"]["consistency"]
    assert term["min"] == 0 and term["max"] == 10  # derived from the modulus (E(c) has plateaus)
    assert math.isclose(tissue_moduli([term["value"]])[0], tissue_moduli([5.0])[0], rel_tol=1e-3)
    live = alive(s.model)
    ks, dts = [], []
    for c in (1.0, 5.0, 9.0, 10.0):
        s.command({"cmd": "term", "name": "consistency", "value": c})
        k = s.model.stiffness[live]
        np.testing.assert_allclose(k.double().numpy(), tissue_moduli([c])[0] / L, rtol=1e-5)
        assert torch.equal(alive(s.model), live)  # no spring revived or lost
        assert s.mesh()["terms"]["consistency"]["value"] == c
        ks.append(float(k.mean()))
        dts.append(s.dt)
    assert ks == sorted(ks) and ks[0] < ks[-1]
    assert dts[-1] < dts[0]  # stiffer: a smaller step
    assert s.dt <= 0.9 * td.time_step_bound(s.model) / math.sqrt(2) * (1 + 1e-9)
    top = (N - 1) * H
    s.command({"cmd": "tool", "position": [top + s.tool_radius - 0.001, top / 2, top / 2]})
    s.command({"cmd": "drag", "vertex": 0, "target": [0.0, -0.002, -0.002]})
    _steps(s, 600)
    assert bool(torch.isfinite(s.state.x).all()) and bool(torch.isfinite(s.state.v).all())
    assert float((s.state.x - s.model.X).abs().max()) < 0.01  # nothing flew off
    E = 0.5 * float((s.model.mass * s.state.v**2).sum())
    assert E < 1e-3


# ------------------------------------------------------------------ junk
BAD_NUMBERS = [float("nan"), float("inf"), -float("inf"), 1e300, -1e300, "1", None, True, [], {}]
BAD_POINTS = [
    [float("nan"), 0.0, 0.0],
    [0.0, float("inf"), 0.0],
    [1e3, 0.0, 0.0],
    [0.0, 0.0],
    [0.0] * 4,
    "abc",
    5,
    {"a": 1},
    [True, 0.0, 0.0],
    ["0", 0.0, 0.0],
    [None, 0.0, 0.0],
    [0.0, 0.0, -1e300],
]


def _junk(rng, V):
    kind = rng.randrange(9)
    if kind == 0:
        return rng.choice([None, 3, "play", [], ["cmd", "play"], 1.5])  # not a dict
    if kind == 1:
        return {"cmd": rng.choice(["jump", "", None, 5, "PLAY", ["play"], "cut!"])}
    if kind == 2:
        return {"cmd": rng.choice(["play", "pause", "reset", "release"]), rng.choice(["x", "value", "id"]): 1}
    if kind == 3:  # drag: bad vertex or bad target
        if rng.random() < 0.5:
            return {
                "cmd": "drag",
                "vertex": rng.choice([-1, V, 10**12, 1.5, True, "0", None, [0]]),
                "target": [0.0, 0.0, 0.0],
            }
        return {"cmd": "drag", "vertex": 0, "target": rng.choice(BAD_POINTS + [None])}
    if kind == 4:
        return {"cmd": "tool", "position": rng.choice(BAD_POINTS)}
    if kind == 5:  # cut: a bad point, zero or parallel edges
        msg = {"cmd": "cut", "origin": [0.005, 0.0, 0.0], "u": [0.0, 0.01, 0.0], "v": [0.0, 0.0, 0.01]}
        which = rng.choice(["origin", "u", "v", "parallel", "zero", "missing"])
        if which == "parallel":
            msg["v"] = [0.0, 0.02, 0.0]
        elif which == "zero":
            msg["u"] = [0.0, 0.0, 0.0]
        elif which == "missing":
            del msg[rng.choice(["origin", "u", "v"])]
        else:
            msg[which] = rng.choice(BAD_POINTS)
        return msg
    if kind == 6:
        return {
            "cmd": "term",
            "name": "consistency",
            "value": rng.choice([-0.1, 10.1, 1e9, float("nan"), float("inf"), "5", None, True, [5]]),
        }
    if kind == 7:
        return {"cmd": "term", "name": rng.choice(["stiffness", "", None, 5, "Consistency"]), "value": 5.0}
    msg = {"cmd": rng.choice(["drag", "tool", "cut", "term"])}  # missing fields
    if rng.random() < 0.5:
        msg[rng.choice(["vertex", "position", "origin", "name"])] = rng.choice(BAD_NUMBERS)
    return msg


def _snapshot(s):
    return dict(
        x=s.state.x.clone(),
        v=s.state.v.clone(),
        t=s.state.t,
        k=s.model.stiffness.clone(),
        playing=s.playing,
        version=s.mesh_version,
        dt=s.dt,
        interactions=list(s.model.interactions),
        drag=s._drag_node,
        mesh=s.mesh(),
        stats=s.stats(),
        pos=s.positions(),
    )


def test_malformed_messages_raise_and_change_nothing(session):
    s = session
    _steps(s, 5)
    s.command({"cmd": "tool", "position": [0.012, 0.005, 0.005]})
    before = _snapshot(s)
    rng = random.Random(0)
    V = s.mesh()["vertices"]
    for _n in range(1000):
        msg = _junk(rng, V)
        with pytest.raises(ValueError) as e:
            s.command(msg)
        assert "\n" not in str(e.value), msg
    after = _snapshot(s)
    for key in ("x", "v", "k"):
        assert torch.equal(before[key], after[key]) and bool(torch.isfinite(after[key]).all())
    for key in ("t", "playing", "version", "dt", "interactions", "drag", "mesh", "stats", "pos"):
        assert before[key] == after[key], key
    with pytest.raises(ValueError):
        s.advance(float("nan"))
    with pytest.raises(ValueError):
        s.advance(-1.0)


# ------------------------------------------------------------------ play, pause, reset, threads
def test_play_pause_reset_and_threads(session):
    s = session
    assert s.playing and s.stats()["playing"]
    s.command({"cmd": "pause"})
    assert s.advance(0.01) == 0 and s.stats()["sim_hz"] == 0
    s.command({"cmd": "play"})
    steps = s.advance(0.05)
    assert steps >= 1 and s.stats()["sim_hz"] > 0
    assert math.isclose(s.stats()["t"], steps * s.dt, rel_tol=1e-9)
    k0, springs = s.model.stiffness.clone(), s.stats()["springs"]
    errors = []

    def loop():
        try:
            for _ in range(20):
                s.advance(0.002)
        except Exception as exc:  # pragma: no cover
            errors.append(exc)

    thread = threading.Thread(target=loop)
    thread.start()
    top = (N - 1) * H
    for i in range(20):
        s.command({"cmd": "tool", "position": [top + s.tool_radius - 0.001, 0.004 + 1e-4 * i, 0.005]})
        s.command({"cmd": "term", "name": "consistency", "value": 2.0 + 0.2 * i})
        s.positions()
        s.stats()
    s.command({"cmd": "cut", "origin": [0.0051, -0.001, -0.001], "u": [0.0, 0.013, 0.0], "v": [0.0, 0.0, 0.007]})
    thread.join()
    assert not errors and bool(torch.isfinite(s.state.x).all())
    s.command({"cmd": "reset"})
    assert s.state.t == 0 and torch.equal(s.state.x, s.model.X) and not bool(s.state.v.any())
    assert torch.equal(s.model.stiffness, k0) and s.stats()["springs"] == springs
    assert s.stats()["force"] == 0 and s.stats()["drag_force"] == 0 and s.model.interactions == []
    c = s.mesh()["terms"]["consistency"]["value"]
    assert math.isclose(tissue_moduli([c])[0], tissue_moduli([5.0])[0], rel_tol=1e-3)
    ref, _ = _oracle(s)
    np.testing.assert_allclose(_vertices(s), ref, atol=1e-7)


def test_scene_checks():
    with pytest.raises(ValueError, match="max_nodes"):
        ViewerSession(_scene(), max_nodes=100)
    with pytest.raises(ValueError, match="Scene"):
        ViewerSession("scene.toml")
