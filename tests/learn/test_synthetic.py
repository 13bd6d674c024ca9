"""Synthetic series (torchdeform.learn.synthetic): spring sets, dynamics against a plain edge-list
simulation, loads, noise, partial observation, files and their validation."""

import itertools
import json

import numpy as np
import pytest
import torch

import torchdeform as td
from torchdeform import learn
from torchdeform.cli import main as cli_main
from torchdeform.errors import ConfigError


# ------------------------------------------------------------------ independent oracle
def edge_list(n, offsets):
    """Springs of an n^3 cube as (a, b) flat node indices, written out from the offsets."""
    idx = lambda i, j, k: (i * n + j) * n + k
    out = []
    for i, j, k in itertools.product(range(n), repeat=3):
        for o in offsets:
            p = (i + o[0], j + o[1], k + o[2])
            if all(0 <= c < n for c in p):
                out.append((idx(i, j, k), idx(*p)))
    return out


AXES = [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
FACE = [(1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1), (0, 1, 1), (0, 1, -1)]
BODY = [(1, 1, 1), (1, 1, -1), (1, -1, 1), (1, -1, -1)]


def reference_cube(springs, k, d, m, force, steps, dt, h):
    """Plain numpy symplectic Euler of Radetzky's cube, unprojected damping (eq. 2.21)."""
    offsets = {54: AXES, 70: AXES + [(1, 1, 1), (1, -1, -1)], 86: AXES + BODY, 126: AXES + FACE}[springs]
    E = edge_list(3, offsets)
    X = np.array([[i * h, j * h, kk * h] for i, j, kk in itertools.product(range(3), repeat=3)])
    fixed = X[:, 0] == 0
    x, v = X.copy(), np.zeros_like(X)
    top = (2 * 3 + 1) * 3 + 1
    out = [x.copy()]
    for _ in range(steps):
        F = np.zeros_like(x)
        F[top] += force
        for a, b in E:
            dx, dv = x[b] - x[a], v[b] - v[a]
            l, l0 = np.linalg.norm(dx), np.linalg.norm(X[b] - X[a])
            f = k * (l - l0) / l * dx + d * dv
            F[a] += f
            F[b] -= f
        acc = F / m
        acc[fixed] = 0
        v = v + dt * acc
        x = x + dt * v
        out.append(x.copy())
    return np.array(out), len(E)


@pytest.mark.parametrize("springs", [54, 70, 86, 126])
def test_radetzky_cube_matches_edge_list_simulation(springs, device):
    s = learn.radetzky_cube(springs=springs, steps=40)
    ref, count = reference_cube(springs, 10.0, 0.1, 0.01, np.array([-0.05, 0.0, 0.0]), 40, 0.005, 0.01)
    assert int(s.spring_mask_tensor().sum()) == count == springs
    got = s.positions.reshape(41, 3, 27).transpose(0, 2, 1)
    assert np.abs(got - ref).max() < 1e-13
    # the series' own dynamics (load tables, true model) on the device of the run
    with torch.no_grad():
        again = s.simulate(s.true_model(device=device))[:, 0]
    assert again.device == device
    assert np.abs(again.cpu().numpy().reshape(41, 3, 27).transpose(0, 2, 1) - ref).max() < 1e-13
    # the lower 9 nodes never move; the top-centre node is pushed down
    assert np.array_equal(s.positions[:, :, 0], np.broadcast_to(s.positions[:1, :, 0], s.positions[:, :, 0].shape))
    assert s.positions[-1, 0, 2, 1, 1] < 0.02 - 1e-4


def test_cube_reaches_equilibrium_in_250_steps():
    s = learn.radetzky_cube(springs=70)
    assert s.positions.shape == (251, 3, 3, 3, 3) and s.steps[-1] == 250
    speed = np.abs(np.diff(s.positions, axis=0)).max(axis=(1, 2, 3, 4)) / s.dt
    assert speed[-1] < 1e-3 * speed.max()


def test_sine_drag_and_indentation_follow_their_paths(device):
    s = learn.cube_series(n=4, topology=26, load="sine", steps=60, dt=0.005, period=0.2, amplitude=0.001)
    t = s.steps * s.dt
    top = s.positions[:, 1, 3, 2, 1] - 2 * 0.01  # channel h of a top node, minus its rest position
    assert np.allclose(top, 0.001 * np.sin(2 * np.pi * t / 0.2), atol=1e-15)
    with torch.no_grad():  # the drag tables on the device of the run
        again = s.simulate(s.true_model(device=device))[:, 0, 1, 3, 2, 1].cpu().numpy() - 2 * 0.01
    assert np.allclose(again, top, atol=1e-15)
    s = learn.cube_series(n=4, load="indent", steps=100, dt=0.005, duration=0.25, amplitude=0.002)
    presc = s.prescribed()
    assert presc.sum() >= 1 and presc[3].sum() == presc.sum()  # only top nodes
    i = tuple(np.argwhere(presc)[0])
    depth = 0.03 - s.positions[:, 0][(slice(None),) + i]
    assert depth[-1] == pytest.approx(0.002) and depth[25] == pytest.approx(0.001)


def test_ramp_force_profile():
    ld = td.PointForce((1, 1, 1), (1.0, 0, 0), start=0.1, ramp=0.2)
    assert ld.factor([0.0, 0.1, 0.2, 0.3, 1.0]).tolist() == pytest.approx([0, 0, 0.5, 1, 1])


def test_heterogeneous_springs_are_harmonic_means():
    s = learn.cube_series(
        n=4,
        topology=6,
        stiffness=[10.0, 40.0],
        damping=0.1,
        regions=learn.layered_regions(learn.cube_grid(n=4)[0], layers=2),
        steps=5,
    )
    k = s.truth["stiffness"]
    # axis-D spring from layer 0 (node row 1) to layer 1 (row 2): 2 * 10 * 40 / 50 = 16
    assert k[0, 1, 1, 1] == pytest.approx(16.0)
    assert k[0, 0, 1, 1] == pytest.approx(10.0) and k[0, 2, 1, 1] == pytest.approx(40.0)
    assert k[0, 3, 1, 1] == 0.0  # no spring beyond the top


def test_noise_level_and_seed():
    clean = learn.radetzky_cube(springs=86)
    a = learn.radetzky_cube(springs=86, noise=0.01, seed=3)
    b = learn.radetzky_cube(springs=86, noise=0.01, seed=3)
    assert np.array_equal(a.positions, b.positions)
    X = clean.grid.rest_positions(dtype=torch.float64)[0].numpy()
    free = ~clean.constrained()
    rms = np.sqrt(np.mean((clean.positions - X)[:, :, free] ** 2))
    err = (a.positions - clean.positions)[:, :, free]
    assert np.std(err) == pytest.approx(0.01 * rms, rel=0.1)
    assert a.meta["noise_sigma"] == pytest.approx(0.01 * rms)


def test_partial_observation_and_sparse_times():
    observe = np.zeros((3, 3, 3), dtype=bool)
    observe[2] = True
    s = learn.radetzky_cube(springs=70, every=10, observe=observe)
    assert s.steps.tolist() == list(range(0, 251, 10))
    assert s.mask.shape == (26, 3, 3, 3) and s.mask[:, 2].all() and not s.mask[:, :2].any()
    assert (s.positions[:, :, :2] == 0).all()


def test_balloon_series_snapshots_grow():
    s = learn.balloon_series()
    assert s.steps.tolist() == [0, 50, 100, 150, 200] and s.dt == 0.02
    X = s.grid.rest_positions(dtype=torch.float64)[0].numpy()
    nodes = s.grid.nodes().numpy()
    c = X[:, nodes].mean(1)[:, None]
    r = np.linalg.norm(s.positions[:, :, nodes] - c[None], axis=1).mean(1)
    assert (np.diff(r) > 0).all()  # the body inflates between snapshots


def test_save_load_roundtrip(tmp_path):
    s = learn.cube_series(
        n=3, load="sine", steps=20, noise=0.01, regions=np.zeros((3, 3, 3), int), stiffness=[5.0], damping=[0.1]
    )
    f = s.save(tmp_path / "s.npz")
    t = learn.load_series(f)
    assert np.array_equal(s.positions, t.positions) and np.array_equal(s.mask, t.mask)
    assert t.dt == s.dt and t.grid.shape == s.grid.shape and isinstance(t.loads[0], td.Drag)
    for key in ("stiffness", "damping", "mass", "regions"):
        assert np.array_equal(s.truth[key], t.truth[key])
    # the stored truth reproduces the (clean) dynamics of the reloaded series
    with torch.no_grad():
        x = t.simulate(t.true_model())[:, 0].numpy()
    clean = learn.cube_series(n=3, load="sine", steps=20, stiffness=5.0, damping=0.1)
    assert np.abs(x - clean.positions).max() < 1e-15
    b = learn.balloon_series().save(tmp_path / "b.npz")
    assert learn.load_series(b).loads[0].field.shape == (3,) + learn.load_series(b).grid.shape


def _corrupt(tmp_path, name, edit):
    src = learn.radetzky_cube(springs=54, steps=10).save(tmp_path / "ok.npz")
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    edit(arrays, meta)
    arrays["meta"] = np.array(json.dumps(meta))
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


BAD = {
    "positions_shape": (lambda a, m: a.__setitem__("positions", a["positions"][:, :, :2]), "positions"),
    "nan": (lambda a, m: a["positions"].__setitem__((3, 0, 2, 1, 1), np.nan), "positions"),
    "meta_shape": (lambda a, m: m.__setitem__("shape", [4, 3, 3]), "positions"),
    "dt": (lambda a, m: m.__setitem__("dt", -0.1), "meta.dt"),
    "steps_len": (lambda a, m: a.__setitem__("steps", a["steps"][:-1]), "steps"),
    "steps_order": (lambda a, m: a["steps"].__setitem__(2, 1), "steps"),
    "num_steps": (lambda a, m: m.__setitem__("num_steps", 99), "meta.num_steps"),
    "mask": (lambda a, m: a.__setitem__("mask", a["mask"][:, :2]), "mask"),
    "truth": (lambda a, m: a.__setitem__("true_stiffness", np.ones((3, 3, 3, 2))), "true_stiffness"),
    "topology": (lambda a, m: m.__setitem__("topology", 26), "true_stiffness"),
    "load_node": (lambda a, m: m["loads"][0].__setitem__("nodes", [[5, 1, 1]]), "meta.loads[0].nodes"),
    "load_kind": (lambda a, m: m["loads"][0].__setitem__("kind", "push"), "meta.loads[0].kind"),
    "missing": (lambda a, m: a.pop("fixed"), "fixed"),
    "format": (lambda a, m: m.__setitem__("format", "other/9"), "meta.format"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_files_give_one_line_errors(tmp_path, case):
    edit, key = BAD[case]
    path = _corrupt(tmp_path, f"{case}.npz", edit)
    with pytest.raises(ConfigError) as e:
        learn.load_series(path)
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg and key in msg, msg


def test_not_a_series_file(tmp_path):
    p = tmp_path / "x.npz"
    p.write_text("hello")
    with pytest.raises(ConfigError, match=r"x\.npz"):
        learn.load_series(p)
    with pytest.raises(ConfigError, match="not found"):
        learn.load_series(tmp_path / "missing.npz")


def test_generator_argument_errors():
    with pytest.raises(ConfigError, match="springs"):
        learn.radetzky_cube(springs=60)
    with pytest.raises(ConfigError, match="every"):
        learn.radetzky_cube(steps=250, every=7)
    with pytest.raises(ConfigError, match="load"):
        learn.cube_series(load="twist")


def test_cli_generates_series(tmp_path, capsys):
    out = tmp_path / "c.npz"
    assert cli_main(argv=["data", "cube", "--springs", "86", "--steps", "20", "--out", str(out)]) == 0
    s = learn.load_series(out)
    assert s.grid.num_springs == 86 and s.steps[-1] == 20
    out2 = tmp_path / "n.npz"
    argv = ["data", "cube", "--n", "4", "--load", "indent", "--steps", "10", "--noise", "0.01", "--out", str(out2)]
    assert cli_main(argv=argv) == 0
    assert learn.load_series(out2).grid.shape == (4, 4, 4)
    assert cli_main(argv=["data", "cube", "--springs", "60", "--out", str(out)]) == 2
    assert "springs" in capsys.readouterr().err
