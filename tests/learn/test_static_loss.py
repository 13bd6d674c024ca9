"""The static-load-case loss (torchdeform.learn.static) and training/fit_fem.py.

Oracles: central finite differences of the loss itself and torch.autograd.gradcheck (float64) for
the adjoint gradient; a reference made by the lattice (the loss is zero at its true parameters and
positive away from them); the Elastic model for per-cell regions of one material; scikit-fem
(torchdeform.bench.accuracy.fem) for the fit, whose true values the script must recover.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import torchdeform as td
from torchdeform import learn
from torchdeform.errors import ConfigError
from torchdeform.learn import ElasticRegions, LoadCase, StaticLoss, face_traction, roller_faces

ROOT = Path(__file__).resolve().parents[2]
F64 = torch.float64
TRUE_E, TRUE_NU = [3e3, 8e3], [0.45, 0.49]


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def bar():
    """A 2 x 2 x 4 mm bar of two regions (per cell: x2 < 2 mm, x2 > 2 mm) and its node labels."""
    grid = td.Grid((3, 3, 5), spacing=1e-3, topology=26)
    cells = torch.zeros(2, 2, 4, dtype=torch.long)
    cells[..., 2:] = 1
    nodes = torch.zeros(3, 3, 5, dtype=torch.long)
    nodes[..., 3:] = 1
    return grid, cells, nodes


def load_cases(grid):
    """A pull with gravity (displacements observed) and a plate pressed on the far end (reactions observed)."""
    fixed = roller_faces(grid)
    plate = torch.zeros_like(fixed)
    plate[2, :, :, -1] = True
    d = torch.zeros((3,) + tuple(grid.shape), dtype=F64)
    d[2, :, :, -1] = -1e-4
    return [
        LoadCase(fixed, loads=face_traction(grid, 2, (0.0, 20.0, 100.0)), gravity=(-9.81, 0.0, 0.0), name="pull"),
        LoadCase(fixed | plate, displacement=d, name="press"),
    ]


def observed(model, cases, *, reactions=(False, True)):
    out = []
    for case, with_r in zip(cases, reactions):
        u, R = StaticLoss.solve_case(model, case, tol=1e-14)
        out.append(
            LoadCase(
                case.fixed,
                displacement=case.displacement,
                loads=case.loads,
                gravity=case.gravity,
                observed=u,
                reactions=R if with_r else None,
                name=case.name,
            )
        )
    return out


# ------------------------------------------------------------------ gradients
def test_adjoint_gradient_passes_gradcheck_for_per_region_E_and_nu():
    """Per-region E and nu as node tensors (Elastic, cells take corner means): autograd.gradcheck in float64."""
    grid, _, nodes = bar()
    truth = td.Model(
        grid,
        td.Elastic(torch.tensor(TRUE_E, dtype=F64)[nodes], torch.tensor(TRUE_NU, dtype=F64)[nodes]),
        density=1000.0,
        dtype=F64,
    )
    loss = StaticLoss(grid, observed(truth, load_cases(grid)), tol=1e-14, warm_start=False)

    def f(log_e, nu):
        E = 1e3 * torch.exp(log_e)
        return loss(td.Model(grid, td.Elastic(E[nodes], nu[nodes]), density=1000.0, dtype=F64))

    log_e = torch.tensor([1.5, 2.0], dtype=F64, requires_grad=True)  # 4.5 and 7.4 kPa
    nu = torch.tensor([0.4, 0.47], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (log_e, nu), eps=1e-6, atol=1e-9, rtol=1e-5)


def test_adjoint_gradient_of_per_node_fields_matches_central_differences():
    """Per-node E and nu (all 45 + 45 of them): directional derivatives against central differences."""
    grid, _, _ = bar()
    gen = torch.Generator().manual_seed(1)
    E_true = 3e3 * (1 + torch.rand(grid.shape, generator=gen, dtype=F64))
    nu_true = 0.3 + 0.15 * torch.rand(grid.shape, generator=gen, dtype=F64)
    truth = td.Model(grid, td.Elastic(E_true, nu_true), density=1000.0, dtype=F64)
    loss = StaticLoss(grid, observed(truth, load_cases(grid)), tol=1e-14, warm_start=False)

    def value(E, nu):
        return loss(td.Model(grid, td.Elastic(E, nu), density=1000.0, dtype=F64))

    E = (E_true * 1.2).requires_grad_()
    nu = (nu_true * 0.95).requires_grad_()
    gE, gnu = torch.autograd.grad(value(E, nu), (E, nu))
    for _ in range(2):
        dE = torch.randn(grid.shape, generator=gen, dtype=F64) * 3.0
        dnu = torch.randn(grid.shape, generator=gen, dtype=F64) * 1e-4
        with torch.no_grad():
            fd = (value(E + dE, nu + dnu) - value(E - dE, nu - dnu)) / 2
        ad = (gE * dE).sum() + (gnu * dnu).sum()
        assert abs(float(ad) / float(fd) - 1) < 1e-5, (float(ad), float(fd))


def test_region_parameters_gradient_matches_central_differences():
    """ElasticRegions per cell (log E, sigmoid nu): the raw parameters' gradient against central differences."""
    grid, cells, _ = bar()
    truth = ElasticRegions(grid, cells, E=TRUE_E, nu=TRUE_NU, density=1000.0)
    loss = StaticLoss(grid, observed(truth.model(), load_cases(grid)), tol=1e-14, warm_start=False)
    p = ElasticRegions(grid, cells, E=[4e3, 6e3], nu=[0.4, 0.45], density=1000.0)
    loss(p).backward()
    grads = torch.cat([p.raw_E.grad, p.raw_nu.grad])
    eps = 1e-5
    for i, (name, j) in enumerate([("raw_E", 0), ("raw_E", 1), ("raw_nu", 0), ("raw_nu", 1)]):
        raw = getattr(p, name)
        with torch.no_grad():
            raw[j] += eps
            up = float(loss(p))
            raw[j] -= 2 * eps
            down = float(loss(p))
            raw[j] += eps
        assert float(grads[i]) == pytest.approx((up - down) / (2 * eps), rel=1e-5), name


def test_warm_started_solves_give_the_same_loss_and_gradient():
    grid, cells, _ = bar()
    truth = ElasticRegions(grid, cells, E=TRUE_E, nu=TRUE_NU, density=1000.0)
    data = observed(truth.model(), load_cases(grid))
    values = []
    for warm in (False, True):
        loss = StaticLoss(grid, data, tol=1e-12, warm_start=warm)
        p = ElasticRegions(grid, cells, E=[4e3, 6e3], nu=[0.4, 0.45], density=1000.0)
        loss(p)  # the first call fills the warm start
        with torch.no_grad():
            p.raw_E += 0.01
        v = loss(p)
        v.backward()
        values.append((v.item(), p.raw_E.grad.clone()))
    assert values[1][0] == pytest.approx(values[0][0], rel=1e-9)
    assert torch.allclose(values[1][1], values[0][1], rtol=1e-7)


# ------------------------------------------------------------------ the loss itself
def test_loss_is_zero_at_the_truth_and_positive_away_from_it():
    grid, cells, _ = bar()
    truth = ElasticRegions(grid, cells, E=TRUE_E, nu=TRUE_NU, density=1000.0)
    loss = StaticLoss(grid, observed(truth.model(), load_cases(grid)), tol=1e-13)
    assert loss(truth).item() < 1e-20
    for name, j, step in [("raw_E", 0, 0.01), ("raw_E", 1, -0.01), ("raw_nu", 0, 0.05), ("raw_nu", 1, -0.05)]:
        p = ElasticRegions(grid, cells, E=TRUE_E, nu=TRUE_NU, density=1000.0)
        with torch.no_grad():
            getattr(p, name)[j] += step
        assert loss(p).item() > 1e-8, name


def test_per_cell_regions_of_one_material_are_the_elastic_model():
    grid, cells, _ = bar()
    a = ElasticRegions(grid, torch.zeros_like(cells), E=5e3, nu=0.45, density=1000.0).model()
    b = td.Model(grid, td.Elastic(5e3, 0.45), density=1000.0, dtype=F64)
    u = torch.randn(b.X.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    ka, kb = a.linearise(a.X).apply(u), b.linearise(b.X).apply(u)
    assert torch.allclose(ka, kb, rtol=1e-12, atol=1e-12 * float(kb.abs().max()))
    assert torch.allclose(a.stiffness_row_sums(), b.stiffness_row_sums(), rtol=1e-12)


def test_uniform_traction_gives_uniform_uniaxial_stress():
    """Rollers and face_traction: a uniform bar is in exactly uniform uniaxial stress (strain sigma/E, -nu sigma/E)."""
    grid = td.Grid((3, 4, 6), spacing=1e-3, topology=26)
    model = td.Model(grid, td.Elastic(5e3, 0.45), density=1000.0, dtype=F64)
    u, R = StaticLoss.solve_case(
        model, LoadCase(roller_faces(grid), loads=face_traction(grid, 2, (0, 0, 100.0))), tol=1e-13
    )
    X = model.X
    assert torch.allclose(u[0, 2], X[0, 2] * 100.0 / 5e3, rtol=1e-9, atol=1e-15)
    assert torch.allclose(u[0, 0], -0.45 * X[0, 0] * 100.0 / 5e3, rtol=1e-9, atol=1e-15)
    assert float(R[0, 2].sum()) == pytest.approx(-100.0 * 2e-3 * 3e-3, rel=1e-9)  # the rollers hold the pull


def test_a_trainer_recovers_lattice_made_parameters():
    grid, cells, _ = bar()
    truth = ElasticRegions(grid, cells, E=TRUE_E, nu=TRUE_NU, density=1000.0)
    loss = StaticLoss(grid, observed(truth.model(), load_cases(grid)))
    p = ElasticRegions(grid, cells, E=[5e3, 5e3], nu=[0.35, 0.35], density=1000.0)
    learn.Trainer(p, loss, optimizer="lbfgs", iterations=15, tol=1e-24, patience=3, progress=False).run()
    got = p.summary()
    assert max(abs(got["E"][i] / TRUE_E[i] - 1) for i in range(2)) < 1e-5, got
    assert max(abs(got["nu"][i] / TRUE_NU[i] - 1) for i in range(2)) < 1e-5, got


# ------------------------------------------------------------------ bad input
def test_bad_input_is_one_config_error():
    grid, cells, _ = bar()
    fixed = roller_faces(grid)
    u = torch.zeros((3,) + tuple(grid.shape), dtype=F64)
    u[2] = 1e-4
    with pytest.raises(ConfigError, match="observed displacements or reactions"):
        StaticLoss(grid, [LoadCase(fixed)])
    with pytest.raises(ConfigError, match=r"pull\.observed: expected a node field"):
        StaticLoss(grid, [LoadCase(fixed, observed=u[:, :2], name="pull")])
    with pytest.raises(ConfigError, match="fixed: expected at least one constrained"):
        StaticLoss(grid, [LoadCase(torch.zeros(grid.shape, dtype=torch.bool), observed=u)])
    with pytest.raises(ConfigError, match="reaction_mask: expected constrained entries only"):
        StaticLoss(grid, [LoadCase(fixed, reactions=u, reaction_mask=torch.ones(grid.shape, dtype=torch.bool))])
    with pytest.raises(ConfigError, match="not all zero"):
        StaticLoss(grid, [LoadCase(fixed, observed=torch.zeros_like(u))])
    with pytest.raises(ConfigError, match="finite"):
        StaticLoss(grid, [LoadCase(fixed, observed=u * float("nan"))])
    with pytest.raises(ConfigError, match="bool mask"):
        StaticLoss(grid, [LoadCase(fixed.to(F64), observed=u)])
    with pytest.raises(ConfigError, match="cases"):
        StaticLoss(grid, [])
    with pytest.raises(ConfigError, match="nu"):
        ElasticRegions(grid, cells, E=5e3, nu=0.5, density=1000.0)
    with pytest.raises(ConfigError, match="E"):
        ElasticRegions(grid, cells, E=-1.0, nu=0.4, density=1000.0)
    with pytest.raises(ConfigError, match="regions"):
        ElasticRegions(grid, torch.zeros(2, 2, 2, dtype=torch.long), E=5e3, nu=0.4, density=1000.0)
    with pytest.raises(ConfigError, match="face_traction"):
        face_traction(grid, 3, (0, 0, 1.0))
    loss = StaticLoss(grid, [LoadCase(fixed, loads=face_traction(grid, 2, (0, 0, 100.0)), observed=u)], cg_iters=2)
    with pytest.raises(ConfigError, match="cg_iters"):  # too few iterations: one sentence, not a wrong answer
        loss(ElasticRegions(grid, cells, E=5e3, nu=0.45, density=1000.0))
    other = td.Grid((3, 3, 4), spacing=1e-3)
    with pytest.raises(ConfigError, match=r"model\.grid"):
        loss(td.Model(other, td.Elastic(5e3, 0.45), density=1000.0, dtype=F64))


# ------------------------------------------------------------------ the training script
def run_script(*args):
    """``training/fit_fem.py ARGS`` in this process (its ``main``): ``(returncode, stderr)``."""
    spec = importlib.util.spec_from_file_location("fit_fem", ROOT / "training" / "fit_fem.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            status = mod.main([str(a) for a in args])
        except SystemExit as e:  # argparse
            status = e.code
    return subprocess.CompletedProcess(args, status, "", err.getvalue())


def test_fit_fem_script_writes_its_outputs(tmp_path):
    """The quick check: a 2 mm lattice, one L-BFGS step: result.json (the contract's keys) and both plots."""
    pytest.importorskip("skfem")
    r = run_script("--spacing", "0.002", "--element", "0.002", "--iterations", "1", "--quiet", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "result.json").read_text())
    for key in ("true", "learned", "relative_error", "history", "wall_seconds", "cpu_seconds", "fem"):
        assert key in res, key
    assert res["final_loss"] < res["initial_loss"]
    assert (tmp_path / "loss.png").stat().st_size > 0 and (tmp_path / "profile.png").stat().st_size > 0


@pytest.mark.slow
def test_fit_fem_script_recovers_a_coarse_block(tmp_path):
    """2 mm lattice (6 x 6 x 11 nodes), 2 mm quadratic elements: E and nu of both regions within 2 % (measured 0.62 %)."""
    pytest.importorskip("skfem")
    r = run_script("--spacing", "0.002", "--element", "0.002", "--quiet", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "result.json").read_text())
    assert res["worst_relative_error"] < 0.02, res["relative_error"]
    assert res["final_loss"] < 1e-3 * res["initial_loss"]


@pytest.mark.parametrize(
    "args, key",
    [
        (["--cases", "twist"], "--cases"),
        (["--spacing", "0.003"], "--spacing"),
        (["--nu", "0.45,0.5"], "--nu"),
        (["--E", "3000"], "--E"),
    ],
)
def test_fit_fem_script_bad_input_is_one_line_and_status_2(tmp_path, args, key):
    r = run_script(*args, "--out", str(tmp_path))
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and key in lines[0], r.stderr


def test_fit_fem_script_without_scikit_fem_is_one_line_and_status_2(tmp_path):
    """A Python where scikit-fem cannot be imported: one line naming the extra, status 2."""
    code = (
        "import sys, runpy; sys.modules['skfem'] = None; "
        f"sys.argv = ['fit_fem.py', '--out', {str(tmp_path)!r}]; "
        f"runpy.run_path({str(ROOT / 'training' / 'fit_fem.py')!r}, run_name='__main__')"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "torchdeform[fem]" in lines[0], r.stderr
