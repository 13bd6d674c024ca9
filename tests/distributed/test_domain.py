"""Domain decomposition: 2 and 3 ranks (torchrun, gloo on 127.0.0.1) against one process's
``simulate`` (float64, 100 steps, fixed nodes, a drag across every slab, a blade cutting through the
slab boundaries half way), explicit and implicit, 6 and 26 neighbours, an Elastic body (its cells
across the slab boundaries, killed by the blade there); the slab bookkeeping and bad input on one
process."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import torchdeform as td
from torchdeform.distributed.domain import decompose, decomposed_simulate, slab_rows
from torchdeform.topology import cut

from . import domain_cases as cases

HERE = Path(__file__).parent


def reference(name, with_cut=True):
    """One process: ``simulate`` with the blade applied after the step that reaches its time.

    Returns the record; ``reference.model`` is the model at the end (cut).
    """
    model, integrator, ((at, blade),) = cases.build(name)

    def cut_once(i, state):
        if with_cut and abs(state.t - at) < 1e-6 * cases.DT:
            cut(model, state.x, blade)

    _, rec = td.simulate(
        model,
        cases.start(model),
        cases.DT,
        cases.STEPS,
        integrator=integrator,
        record_every=cases.RECORD_EVERY,
        callback=cut_once,
        warn=False,
    )
    reference.model = model
    return rec


def launch(n, out, names):
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        str(n),
        str(HERE / "domain_cases.py"),
        str(out),
        *names,
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=240, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[:3000] + "\n...\n" + done.stderr[-3000:]


# 2 ranks: every integrator family once (symplectic Euler's halo is RK4's first stage, plain implicit
# 26 is the Elastic case's springs; implicit Euler on 6 neighbours runs on 3 ranks); 3 ranks (a
# middle slab with two halos): the implicit case, whose CG reduces over every rank (the Elastic
# body's cells across both of a middle slab's boundaries:
# test_the_slabs_of_an_elastic_body_keep_its_cells_through_a_cut)
RUNS = {2: ["rk4_26", "verlet26_law_mask", "implicit26_elastic"], 3: ["implicit6"]}


@pytest.mark.parametrize("ranks", sorted(RUNS))
@pytest.mark.slow
def test_ranks_follow_the_single_process_trajectory(tmp_path, ranks):
    launch(ranks, tmp_path, RUNS[ranks])
    for name in RUNS[ranks]:
        rec = reference(name)
        got = np.load(tmp_path / f"{name}.npz")
        assert got["x"].shape == tuple(rec["x"].shape) == (11, 1, 3) + cases.SHAPE
        np.testing.assert_array_equal(got["t"], rec["t"].numpy())
        tol = 1e-12 if name.startswith("implicit") else 0.0  # explicit: the same bits; CG sums differ
        assert np.abs(got["x"] - rec["x"].numpy()).max() <= tol, name
        assert np.abs(got["v"] - rec["v"].numpy()).max() <= tol, name
        # every exchange sent one layer each way per inner boundary: B x C x H x W doubles
        layer = 3 * cases.SHAPE[1] * cases.SHAPE[2] * 8
        assert int(got["bytes"]) % layer == 0 and int(got["bytes"]) >= int(got["exchanges"]) * layer
        if "kappa" in got.files:  # an Elastic body: the cells gathered from the slabs are those the blade left
            whole = reference.model
            assert (got["kappa"] == 0).any() and np.array_equal(got["kappa"], whole.volume[0].numpy()), name
            assert np.array_equal(got["mu_cells"], whole.mu_cells.numpy()), name
            assert np.array_equal(got["stiffness"], whole.stiffness.numpy()), name


def test_the_cases_exercise_the_cut_and_the_drag():
    """The blade changes the trajectory (so the runs above compare a cut body), the drag moves the far face."""
    for name in ("rk4_26", "implicit6"):
        a, b = reference(name), reference(name, with_cut=False)
        assert float((a["x"][-1] - b["x"][-1]).abs().max()) > 1e-5
        assert float((a["x"][-1, 0, 2, 1:, :, -1] - a["x"][0, 0, 2, 1:, :, -1]).abs().min()) > 3e-3


def test_slabs_cover_the_rows_and_refuse_more_ranks_than_rows():
    for depth in (1, 2, 7, 96):
        for world in range(1, min(depth, 5) + 1):
            rows = slab_rows(depth, world)
            assert rows[0][0] == 0 and rows[-1][1] == depth
            assert all(a[1] == b[0] for a, b in itertools.pairwise(rows))
            sizes = [hi - lo for lo, hi in rows]
            assert min(sizes) >= 1 and max(sizes) - min(sizes) <= 1
    with pytest.raises(td.ConfigError, match="at most 4 ranks"):
        slab_rows(4, 5)


def test_a_slab_is_the_global_model_restricted_to_its_rows():
    model, _, _ = cases.build("verlet26_law_mask")
    for rank in range(3):
        slab = decompose(model, rank, 3)
        e_lo, e_hi = slab.extent
        assert slab.grid.shape == (e_hi - e_lo,) + cases.SHAPE[1:]
        assert torch.equal(slab.X, model.X[:, :, e_lo:e_hi])
        assert torch.equal(slab.mass.expand(1, 1, *slab.grid.shape), model.mass[:, :, e_lo:e_hi])
        assert torch.equal(slab.constrained, model.constrained[e_lo:e_hi])
        assert torch.equal(slab.grid.nodes(), model.grid.nodes()[e_lo:e_hi])
        # the forces on owned nodes equal the global forces when the halo holds the global values
        x = model.X + 1e-3 * torch.randn(
            model.X.shape, generator=torch.Generator().manual_seed(rank), dtype=torch.float64
        )
        v = torch.randn(x.shape, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
        f = model.forces(x, v, t=0.0)
        lf = td.Model.forces(slab, x[:, :, e_lo:e_hi].clone(), v[:, :, e_lo:e_hi].clone(), t=0.0)
        assert torch.equal(lf[:, :, slab.owned], f[:, :, slab.rows[0] : slab.rows[1]])
    from torchdeform.interact import StrainLimit

    model.interactions = [StrainLimit()]
    with pytest.raises(td.ConfigError, match="tool interactions"):
        decompose(model, 0, 2)


def test_the_slabs_of_an_elastic_body_keep_its_cells_through_a_cut():
    """Three slabs of an Elastic body, each cut by the case's blade at the positions the whole body is cut
    at: forces on owned nodes equal the whole body's to the bit, stiffness products (springs and volume
    term) to round-off, Gershgorin rows exactly."""
    model, _, ((_, blade),) = cases.build("implicit26_elastic")
    gen = torch.Generator().manual_seed(3)
    x, v, u = (model.X + s * torch.randn(model.X.shape, generator=gen, dtype=torch.float64) for s in (1e-3, 1, 1))
    slabs = [decompose(model, rank, 3) for rank in range(3)]
    cut(model, x, blade)
    assert bool((model.volume[0] == 0).any())  # the blade killed cells across every slab boundary
    f, ku, rows = model.forces(x, v), model.linearise(x).apply(u), model.stiffness_row_sums()
    for slab in slabs:
        (e_lo, e_hi), (lo, hi) = slab.extent, slab.rows
        xl = x[:, :, e_lo:e_hi].clone()
        cut(slab, xl, blade)
        lf = td.Model.forces(slab, xl, v[:, :, e_lo:e_hi].clone())
        lku = td.Model.linearise(slab, xl).apply(u[:, :, e_lo:e_hi].clone())
        assert torch.equal(lf[:, :, slab.owned], f[:, :, lo:hi])
        assert torch.allclose(lku[:, :, slab.owned], ku[:, :, lo:hi], rtol=1e-13, atol=1e-13 * float(ku.abs().max()))
        assert torch.equal(slab.stiffness_row_sums()[:, :, slab.owned], rows[:, :, lo:hi])


def test_one_process_is_simulate(tmp_path):
    model, integrator, _cuts = cases.build("implicit26")
    run = decomposed_simulate(model, cases.start(model), cases.DT, 20, integrator=integrator, record_every=5)
    model, integrator, _ = cases.build("implicit26")
    final, rec = td.simulate(model, cases.start(model), cases.DT, 20, integrator=integrator, record_every=5, warn=False)
    assert torch.equal(run.final.x, final.x) and torch.equal(run.record["x"], rec["x"])
    assert run.comm_s == 0 and run.model.halo.exchanges == 0


@pytest.mark.parametrize("factor", [3.0, 0.5])
def test_a_divergence_stops_as_simulate_does(factor):
    """Above the bound a runaway names a safe dt; within it, a 1e30 N load is not blamed on dt."""
    g = td.Grid((6, 3, 3), spacing=0.01, topology=6)
    loads = [] if factor > 1 else [td.PointForce((5, 1, 1), (1e30, 0.0, 0.0))]
    model = td.Model(
        g,
        stiffness=50.0,
        mass=1e-3,
        fixed=g.face("bottom"),
        gravity=(-9.81, 0.0, 0.0),
        loads=loads,
        dtype=torch.float64,
    )
    dt = factor * td.time_step_bound(model)
    with pytest.raises(td.DivergenceError) as one:
        td.simulate(model, model.rest_state(), dt, 400, warn=False)
    with pytest.raises(td.DivergenceError) as slabs:
        decomposed_simulate(model, model.rest_state(), dt, 400)
    assert slabs.value.step == one.value.step and slabs.value.safe_dt == one.value.safe_dt
    assert (slabs.value.safe_dt is None) == (factor < 1) and (slabs.value.cause is None) == (factor > 1)


def test_unsupported_integrators_are_refused():
    model, _, _ = cases.build("symplectic6")
    with pytest.raises(td.ConfigError, match="domain-decomposed"):
        decomposed_simulate(model, model.rest_state(), 1e-4, 2, integrator=td.ProjectiveDynamics())


SCENE = """\
[grid]
shape = [6, 4, 5]
spacing = 0.01
topology = 26
[material]
stiffness = 300.0
damping = 0.2
[mass]
density = 1000.0
[boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]
[[drags]]
face = "w+"
path = [[0.0, [0.0, 0.0, 0.0]], [0.02, [0.0, 0.0, 0.003]]]
[[cuts]]
origin = [-0.005, 0.015, -0.005]
u = [0.08, 0.0, 0.0]
v = [0.0, 0.0, 0.025]
at = 0.01
[integrator]
name = "{name}"
dt = 2e-4
steps = 100
engine = "eager"
[output]
record_every = 20
"""


@pytest.mark.parametrize("integrator", ["rk4"])
@pytest.mark.slow
def test_the_same_scene_file_runs_on_two_ranks(tmp_path, integrator):
    """``torchrun -m torchdeform run`` writes the one-process outputs (same trajectory, energies after the cut).

    The slabs step the grid layout's eager form; the one-process run is asked for the same engine, so
    the two agree to the bit (a packed engine sums the springs in another order)."""
    scene = tmp_path / "slab.toml"
    scene.write_text(SCENE.replace("{name}", integrator))
    from torchdeform import cli

    assert cli.main(argv=["run", str(scene), "--out", str(tmp_path / "one"), "--quiet"]) == 0
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        "2",
        "-m",
        "torchdeform",
        "run",
        str(scene),
        "--out",
        str(tmp_path / "two"),
        "--quiet",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    assert "domain-decomposed" not in done.stderr
    one, two = np.load(tmp_path / "one" / "trajectory.npz"), np.load(tmp_path / "two" / "trajectory.npz")
    for key in ("t", "x", "v", "kinetic"):
        np.testing.assert_array_equal(one[key], two[key], err_msg=key)
    # spring energies: one process uses each frame's springs; the decomposed run the final (cut) springs
    # for every frame, so they agree from the cut (t = 0.01 s) on
    cut = one["t"] >= 0.01 - 1e-9
    for key in ("elastic", "total"):
        np.testing.assert_array_equal(one[key][cut], two[key][cut], err_msg=key)
    import json

    summary = json.loads((tmp_path / "two" / "summary.json").read_text())
    assert summary["domain"]["ranks"] == 2 and [p["rows"] for p in summary["domain"]["per_rank"]] == [[0, 3], [3, 6]]
    assert all(p["exchanges"] == 4 * 100 + 1 for p in summary["domain"]["per_rank"])  # RK4: 4 per step, 1 cut


@pytest.mark.slow
def test_more_ranks_than_rows_stops_every_rank_with_one_line(tmp_path):
    scene = tmp_path / "bad.toml"
    scene.write_text(SCENE.replace("{name}", "rk4").replace("shape = [6, 4, 5]", "shape = [2, 4, 5]"))
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        "3",
        "-m",
        "torchdeform",
        "run",
        str(scene),
        "--out",
        str(tmp_path / "out"),
        "--quiet",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode != 0
    ours = [line for line in done.stderr.splitlines() if line.startswith("torchdeform:")]
    assert len(ours) == 1 and "at most 2 ranks" in ours[0], done.stderr[-2000:]
    assert "exitcode  : 2" in done.stderr and not (tmp_path / "out").exists()  # (then torchrun's report)


@pytest.mark.parametrize(
    "edit,match",
    [
        (
            (
                "[output]",
                '[[cautery]]\ntool = "probe"\nat = 0.0\n[[tools]]\nname = "probe"\nshape = "sphere"\n'
                'radius = 0.002\ncontact = "none"\npath = [[0.0, [0.05, 0.02, 0.02]]]\n[output]',
            ),
            "tools",
        ),
        (("at = 0.01", "at = 0.01\ngape = 0.2"), "gape"),
        (("[output]", "[tear]\nmax_strain = 0.5\n[output]"), "tear"),
    ],
)
def test_what_a_decomposed_run_cannot_do_is_refused(tmp_path, edit, match):
    from torchdeform.distributed.commands import scene_cuts

    scene = tmp_path / "bad.toml"
    scene.write_text(SCENE.replace("{name}", "rk4").replace(*edit))
    with pytest.raises(td.ConfigError, match=match):
        scene_cuts(td.load_scene(scene))


def test_a_scene_of_several_bodies_is_refused_before_any_rank_work(tmp_path):
    """The decomposed run reads the scene before any collective: a [[bodies]] scene is one line."""
    import argparse

    from torchdeform.distributed.commands import _run_decomposed

    args = argparse.Namespace(
        scene=str(HERE.parents[1] / "scenes" / "organs.toml"), out=str(tmp_path / "o"), force=False, device=None
    )
    with pytest.raises(td.ConfigError, match=r"bodies: .* runs in one process"):
        _run_decomposed(args, 0, 2)
