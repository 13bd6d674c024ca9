"""The NVIDIA Warp baseline of ``torchdeform bench speed`` (``torchdeform.bench.warp_baseline``).

The Warp steps must be torchdeform's step (same springs, same integrator): both variants are
compared with the eager ``SymplecticEuler`` after 1 and 20 steps. The missing-Warp path and the
edge list run without Warp; everything that launches a kernel skips when warp-lang is absent.
"""

import subprocess
import sys

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.oracles.edge_list import EdgeList
from torchdeform.bench import warp_baseline as bench_warp
from torchdeform.bench.common import speed_cube

pytestmark = pytest.mark.slow  # a bench smoke run

#: (positions m, velocities m/s) tolerances of the Warp step against the eager step; float32
#: differs by summation order and one reciprocal (positions are ~4 cm, so 1 ulp ~ 4e-9 m).
TOL = {torch.float32: (1e-6, 1e-5), torch.float64: (1e-12, 1e-12)}


@pytest.fixture
def wp():
    return pytest.importorskip("warp")


def _eager(model, state, dt, steps):
    with torch.no_grad():
        for _ in range(steps):
            state = td.SymplecticEuler().step(model, state, dt)
    return state


# --------------------------------------------------------------- no warp needed
def test_import_does_not_import_warp():
    code = "import sys, torchdeform.bench.warp_baseline; assert 'warp' not in sys.modules, 'warp imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_warp_missing(monkeypatch):
    monkeypatch.setitem(sys.modules, "warp", None)  # import warp -> ImportError
    ok, why = bench_warp.warp_available()
    assert ok is False
    assert why == bench_warp.INSTALL_HINT and "pip install warp-lang" in why
    model, state, _dt = speed_cube(3, 6)
    with pytest.raises(RuntimeError, match="warp-lang is not installed"):
        bench_warp.WarpSprings(model, state)
    with pytest.raises(RuntimeError, match="warp-lang is not installed"):
        bench_warp.warp_speed_row(3, topology=6, steps=1, repeats=1)


@pytest.mark.parametrize("topology", [6, 14, 18, 26])
def test_edge_list_is_the_grid(topology):
    """Every spring once, as the independent oracle lists them; rest lengths from the coordinates."""
    shape = (3, 4, 5)
    mask = torch.ones(shape, dtype=torch.bool)
    mask[0, 0, :2] = False  # a node mask removes springs too
    grid = td.Grid(shape, spacing=(0.01, 0.02, 0.015), topology=topology, node_mask=mask)
    model = td.Model(grid, stiffness=100.0, damping=0.05, mass=1e-3, dtype=torch.float64)
    e = bench_warp.edge_list(model)
    assert len(e["i"]) == grid.num_springs
    oracle = EdgeList(shape, grid.spacing, topology, mask.numpy())
    flat = [int(np.ravel_multi_index(ijk, shape)) for ijk in oracle.nodes]
    want = {(min(flat[a], flat[b]), max(flat[a], flat[b])): l0 for (a, b, _), l0 in zip(oracle.springs, oracle.l0)}
    got = {(int(i), int(j)): float(l0) for i, j, l0 in zip(e["i"], e["j"], e["l0"])}
    assert set(got) == set(want)
    assert max(abs(got[p] - want[p]) for p in want) < 1e-15
    assert np.all(e["k"] == 100.0) and np.all(e["c"] == 0.05)
    assert e["i"].dtype == np.int32 and e["l0"].dtype == np.float64


# -------------------------------------------------------------------- with warp
@pytest.mark.parametrize("topology", [6, 26])
@pytest.mark.parametrize("variant", bench_warp.VARIANTS)
def test_warp_step_is_the_eager_step(wp, variant, topology, dtype):
    model, state, dt = speed_cube(5, topology, dtype=dtype)
    sim = bench_warp.WarpSprings(model, state, variant=variant)
    tol_x, tol_v = TOL[dtype]
    done = 0
    for steps in (1, 20):
        sim.step(dt, steps=steps - done)
        done = steps
        got, want = sim.state(), _eager(model, state, dt, steps)
        assert got.x.dtype == dtype and got.x.shape == (1, 3, 5, 5, 5)
        assert got.t == pytest.approx(want.t)
        dx, dv = float((got.x - want.x).abs().max()), float((got.v - want.v).abs().max())
        assert dx < tol_x and dv < tol_v, (variant, steps, dx, dv)
        assert float((want.x - state.x).abs().max()) > 10 * dx  # it moved, and the same way


@pytest.mark.parametrize("variant", bench_warp.VARIANTS)
def test_fixed_nodes_and_reset(wp, variant):
    """Fixed nodes (zero inverse mass) stay put; ``set_state`` restarts from a given state."""
    grid = td.Grid((4, 3, 5), spacing=0.01, topology=18)
    model = td.Model(grid, stiffness=100.0, damping=0.05, mass=1e-3, fixed=grid.face("bottom"))
    dt = 1e-4
    x0 = model.X + 1e-4 * torch.randn(model.X.shape)
    state = td.State(x0, torch.zeros_like(x0))
    sim = bench_warp.WarpSprings(model, state, variant=variant)
    sim.step(dt, steps=7)
    want = _eager(model, state, dt, 7)
    got = sim.state()
    assert float((got.x - want.x).abs().max()) < 1e-6
    assert torch.equal(got.x[..., 0, :, :], x0[..., 0, :, :])
    sim.set_state(state)
    sim.step(dt, steps=3)
    assert float((sim.state().x - _eager(model, state, dt, 3).x).abs().max()) < 1e-6


def test_unsupported_model(wp):
    grid = td.Grid((3, 3, 3), spacing=0.01, topology=6)
    model = td.Model(grid, stiffness=100.0, mass=1e-3, gravity=(-9.81, 0, 0))
    with pytest.raises(ValueError, match="gravity"):
        bench_warp.WarpSprings(model, model.rest_state())
    with pytest.raises(ValueError, match="variant"):
        bench_warp.WarpSprings(model, model.rest_state(), variant="scatter")


@pytest.mark.parametrize("variant", bench_warp.VARIANTS)
def test_warp_speed_row(wp, variant):
    row = bench_warp.warp_speed_row(6, topology=26, variant=variant, steps=3, repeats=2)
    keys = {
        "grid",
        "n",
        "topology",
        "mode",
        "dtype",
        "threads",
        "device",
        "nodes",
        "springs",
        "steps",
        "repeats",
        "ms_per_step",
        "msprings_per_s",
        "node_steps_per_s",
        "compile_s",
        "max_abs_diff",
        "fallback",
    }
    assert set(row) == keys
    grid = td.Grid((6, 6, 6), topology=26)
    assert row["springs"] == grid.num_springs and row["nodes"] == grid.num_nodes == 216
    assert (row["mode"], row["threads"], row["device"], row["dtype"]) == (f"warp-{variant}", 1, "cpu", "float32")
    assert (row["steps"], row["repeats"], row["grid"]) == (3, 2, "6^3")
    assert row["ms_per_step"] > 0 and row["compile_s"] >= 0
    assert row["msprings_per_s"] == pytest.approx(row["springs"] / row["ms_per_step"] * 1e3 / 1e6, rel=1e-12)
    assert row["node_steps_per_s"] == pytest.approx(row["nodes"] / row["ms_per_step"] * 1e3, rel=1e-12)
    assert row["max_abs_diff"] < 1e-6
    # a given reference is used as is: a wrong one shows up in max_abs_diff
    model, state, dt = speed_cube(6, 26)
    ref = _eager(model, state, dt, 1)
    bad = td.State(ref.x + 1e-3, ref.v, t=ref.t)
    assert bench_warp.warp_speed_row(6, topology=26, variant=variant, steps=1, repeats=1, reference=bad)[
        "max_abs_diff"
    ] == pytest.approx(1e-3, rel=1e-3)
