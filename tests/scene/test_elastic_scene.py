"""Scene files that speak Young's modulus, Poisson ratio and tissue words, and the static integrator.

Oracles: the tissue library (``fuzzy/tissues.toml`` through :func:`tissue_parameters`) for E, nu, eta
and density; models built directly with the Python API (``td.Model(grid, td.Elastic(E, nu), ...)``)
for what a scene must build; Kelvin-Voigt ``c = k eta / E`` against the springs' own stiffness;
``td.solve_static`` called directly, and a dense linear solve (the stiffness matrix by autograd of the
forces at rest, ``numpy.linalg.solve``) for the sag of a clamped beam under a small load.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

import torchdeform as td
from torchdeform import cli
from torchdeform.fuzzy import tissue_parameters, tissues
from torchdeform.scene import load_scene, run_scene
from torchdeform.scene.mass_spring import DEFAULT_POISSON_RATIO, StaticSolve, kelvin_voigt_damping

BLOCK = """
[grid]
shape = [3, 3, 4]
spacing = 0.01
topology = 26

[material]
tissue = "liver"

[boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]

[integrator]
name = "symplectic"
dt = "auto"
steps = 4
"""

BEAM = """
[grid]
shape = [3, 3, 6]
spacing = 0.005
topology = 26

[material]
youngs_modulus = 5e6
poisson_ratio = 0.45

[mass]
density = 1000.0

[boundary]
fixed = "w-"
gravity = [-9.81, 0.0, 0.0]

[integrator]
name = "static"
tol = 1e-9
"""


def write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def edit(text, old, new):
    assert old in text
    return text.replace(old, new, 1)


def line_containing(text, needle):
    return next(i for i, line in enumerate(text.splitlines(), 1) if needle in line)


# ------------------------------------------------------------------ the tissue library
def test_every_tissue_has_a_nearly_incompressible_poisson_ratio_with_its_source():
    for name, entry in tissues().items():
        nu = entry["poisson_ratio"]
        assert 0.45 <= nu <= 0.49, name
        assert "Poisson ratio" in entry["source"], name
        assert tissue_parameters(name)["poisson_ratio"] == nu


# ------------------------------------------------------------------ [material] tissue
def test_tissue_is_the_librarys_elastic_solid_with_kelvin_voigt_damping_and_density(tmp_path):
    scene = load_scene(write(tmp_path, BLOCK))
    liver = tissue_parameters("liver")
    material = scene.model_args["stiffness"]
    assert isinstance(material, td.Elastic)
    assert material.youngs_modulus == pytest.approx(liver["youngs_modulus"], rel=1e-12)
    assert material.poisson_ratio == liver["poisson_ratio"] == 0.49
    assert scene.model_args["density"] == liver["density"] == 1060.0  # no [mass] section needed
    model = scene.build()
    assert model.volume is not None
    # Kelvin-Voigt: every spring's dashpot is its stiffness times the retardation time eta / E
    tau = liver["viscosity"] / liver["youngs_modulus"]
    k = model.stiffness.double()
    assert torch.allclose(model.damping.double(), k * tau, rtol=1e-6, atol=0)
    assert bool((model.damping > 0).any())
    ref = td.Model(
        scene.grid,
        td.Elastic(liver["youngs_modulus"], 0.49),
        damping=(k * tau)[0],
        density=1060.0,
        fixed=scene.grid.face("bottom"),
        gravity=(-9.81, 0, 0),
    )
    assert torch.equal(model.stiffness, ref.stiffness) and torch.equal(model.volume[0], ref.volume[0])
    assert torch.equal(model.mass, ref.mass)


def test_kelvin_voigt_damping_is_k_times_the_retardation_time():
    grid = td.Grid((4, 3, 5), spacing=0.002, topology=18)
    k = td.Model(grid, td.Elastic(2000.0, 0.47), density=1000.0, dtype=torch.float64).stiffness[0]
    assert torch.allclose(kelvin_voigt_damping(grid, 2000.0, 0.47, 3e-4), 3e-4 * k, rtol=1e-12, atol=0)


def test_explicit_mass_damping_and_poisson_ratio_win(tmp_path):
    text = edit(BLOCK, 'tissue = "liver"', 'tissue = "liver"\npoisson_ratio = 0.3\ndamping = 0.002')
    scene = load_scene(write(tmp_path, text + "\n[mass]\ndensity = 1000.0\n"))
    assert scene.model_args["stiffness"].poisson_ratio == 0.3
    assert scene.model_args["damping"] == 0.002 and scene.model_args["density"] == 1000.0
    assert torch.all(scene.build().damping == 0.002)


@pytest.mark.parametrize("word", ['"soft"', "3.0"])
def test_consistency_terms_and_numbers_take_the_default_poisson_ratio_and_need_mass(word, tmp_path):
    text = edit(BLOCK, '"liver"', word)
    with pytest.raises(td.ConfigError, match=r"a \[mass\] section \(required\) unless \[material\] tissue"):
        load_scene(write(tmp_path, text))
    scene = load_scene(write(tmp_path, text + "\n[mass]\ndensity = 1000.0\n"))
    material = scene.model_args["stiffness"]
    assert material.poisson_ratio == DEFAULT_POISSON_RATIO == 0.45
    assert material.youngs_modulus == pytest.approx(td.scene.mass_spring.tissue_moduli([json.loads(word)])[0])
    assert scene.model_args["damping"].shape == (scene.grid.S, *scene.grid.shape)  # Kelvin-Voigt


def test_stiffness_and_spring_modulus_models_are_unchanged(tmp_path):
    text = edit(BLOCK, 'tissue = "liver"', "stiffness = 5.0") + "\n[mass]\ndensity = 1000.0\n"
    model = load_scene(write(tmp_path, text)).build()
    ref = td.Model(model.grid, stiffness=5.0, density=1000.0, fixed=model.grid.face("bottom"), gravity=(-9.81, 0, 0))
    assert model.volume is None and model.damping is None and torch.equal(model.stiffness, ref.stiffness)


# ------------------------------------------------------------------ [[regions]] of an elastic body
def test_regions_give_per_node_youngs_modulus_and_poisson_ratio(tmp_path):
    regions = """
    [[regions]]
    box = {lo = [0.0, 0.0, 0.02], hi = [0.02, 0.02, 0.03]}
    youngs_modulus = 20000.0
    poisson_ratio = 0.3

    [[regions]]
    sphere = {center = [0.0, 0.0, 0.0], radius = 0.011}
    tissue = "brain"
    """
    text = edit(BLOCK, 'tissue = "liver"', "youngs_modulus = 5000.0\npoisson_ratio = 0.45")
    scene = load_scene(write(tmp_path, text + "\n[mass]\ndensity = 1000.0\n" + regions))
    grid = scene.grid
    box = grid.box_mask((0.0, 0.0, 0.02), (0.02, 0.02, 0.03))
    X = grid.rest_positions(dtype=torch.float64)[0]
    ball = (X**2).sum(0) <= 0.011**2 * (1 + 1e-12)
    brain = tissue_parameters("brain")
    E = torch.full(grid.shape, 5000.0, dtype=torch.float64)
    nu = torch.full(grid.shape, 0.45, dtype=torch.float64)
    E[box], nu[box] = 20000.0, 0.3
    E[ball], nu[ball] = brain["youngs_modulus"], brain["poisson_ratio"]  # later regions on top
    material = scene.model_args["stiffness"]
    assert torch.allclose(material.youngs_modulus, E, rtol=1e-12) and torch.equal(material.poisson_ratio, nu)
    assert int(box.sum()) == 18 and int(ball.sum()) == 4
    assert "damping" not in scene.model_args  # youngs_modulus: no viscosity known, no automatic damping
    model = scene.build()
    ref = td.Model(grid, td.Elastic(E, nu), density=1000.0)
    assert torch.allclose(model.stiffness, ref.stiffness, rtol=1e-6) and torch.allclose(
        model.volume[0], ref.volume[0], rtol=1e-6
    )


def test_region_tissues_bring_their_retardation_time_and_density(tmp_path):
    region = """
    [[regions]]
    box = {lo = [0.0, 0.0, 0.02], hi = [0.02, 0.02, 0.03]}
    tissue = "muscle"
    """
    scene = load_scene(write(tmp_path, BLOCK + region))
    grid = scene.grid
    box = grid.box_mask((0.0, 0.0, 0.02), (0.02, 0.02, 0.03))
    liver, muscle = tissue_parameters("liver"), tissue_parameters("muscle")
    E = torch.where(box, muscle["youngs_modulus"], liver["youngs_modulus"]).double()
    nu = torch.where(box, muscle["poisson_ratio"], liver["poisson_ratio"]).double()
    tau = torch.where(
        box, muscle["viscosity"] / muscle["youngs_modulus"], liver["viscosity"] / liver["youngs_modulus"]
    ).double()
    assert torch.allclose(scene.model_args["damping"], kelvin_voigt_damping(grid, E, nu, tau), rtol=1e-12)
    rho = torch.where(box, muscle["density"], liver["density"]).double()
    assert torch.allclose(scene.model_args["mass"], td.lumped_mass(grid, 1.0)[0, 0] * rho, rtol=1e-12)
    inside = tuple(int(i) for i in box.nonzero()[0])
    assert float(scene.build().mass[(0, 0, *inside)]) > 0


# ------------------------------------------------------------------ the static integrator
def _dense_sag(model) -> torch.Tensor:
    """Displacements of the linearised body at rest under its gravity: a dense solve on the free nodes."""
    X = model.X.detach()
    free = (~model.constrained).view(-1)
    n = X[0, 0].numel()

    def forces(x):
        return model.forces(x.view_as(X), torch.zeros_like(X))[0].reshape(3, n)[:, free].reshape(-1)

    x0 = X.reshape(-1).clone()
    f0 = forces(x0)  # gravity alone at rest (the springs are at rest length)
    J = torch.autograd.functional.jacobian(forces, x0)  # dF/dx, (3 m, 3 n)
    cols = torch.zeros(3, n, dtype=torch.bool)
    cols[:, free] = True
    K = -J[:, cols.reshape(-1)].numpy()
    u = np.linalg.solve(K, f0.detach().numpy())  # K u = f
    out = torch.zeros(3, n, dtype=X.dtype)
    out[:, free] = torch.from_numpy(u).view(3, -1)
    return out.view(X.shape[1:])


def test_static_scene_reaches_solve_static_and_the_dense_sag_of_a_clamped_beam(tmp_path):
    scene = load_scene(write(tmp_path, BEAM))
    assert isinstance(scene.integrator, StaticSolve) and scene.dtype == torch.float64  # a static solve's default
    out = tmp_path / "out"
    summary = run_scene(scene, out, progress=False)
    model = scene.build()
    direct, info = td.solve_static(model, tol=1e-9)
    assert info["converged"]
    data = np.load(out / "trajectory.npz")
    assert data["x"].shape == (2, 3, 3, 3, 6) and np.array_equal(data["x"][0], data["X"])  # rest, equilibrium
    assert np.allclose(data["x"][-1], direct.x[0].float().numpy(), rtol=0, atol=1e-9)
    assert np.all(data["v"] == 0) and str(data["integrator"]) == "static"
    st = summary["static"]
    assert st["converged"] and st["residual"] <= 1e-9 and st["iterations"] == info["iterations"]
    assert summary["steps"] == 0 and summary["frames"] == 2 and summary["dt_s"] is None
    assert json.loads((out / "summary.json").read_text())["static"] == st
    assert sorted(summary["outputs"]) == ["energy.png", "summary.json", "trajectory.npz"]
    # a small sag (0.1 % of the length): the linear dense solve agrees with the nonlinear equilibrium
    u = direct.x[0] - model.X[0]
    dense = _dense_sag(model)
    tip = u[0, :, :, -1].mean()
    assert float(tip) < 0 and abs(float(tip)) < 1e-3 * 0.025
    assert float(dense[0, :, :, -1].mean()) == pytest.approx(float(tip), rel=2e-3)
    assert float((u - dense).abs().max()) < 5e-3 * float(dense.abs().max())
    assert summary["max_displacement_m"] == pytest.approx(float(u.norm(dim=0).max()), rel=1e-6)


def test_static_loads_are_taken_at_full_strength(tmp_path):
    text = BEAM + '\n[[loads]]\nface = "w+"\ntraction = [-20.0, 0.0, 0.0]\nstart = 0.1\nramp = 0.2\n'
    scene = load_scene(write(tmp_path, text))
    assert scene.integrator.time == pytest.approx(0.3)
    summary = run_scene(scene, tmp_path / "out", progress=False)
    model = scene.build()
    rest = model.rest_state()
    direct, _ = td.solve_static(model, state=td.State(rest.x, rest.v, t=0.3), tol=1e-9)
    x = np.load(tmp_path / "out" / "trajectory.npz")["x"][-1]
    assert np.allclose(x, direct.x[0].numpy(), atol=1e-9) and summary["static"]["time_s"] == pytest.approx(0.3)
    no_load, _ = td.solve_static(model, tol=1e-9)
    assert float(direct.x[0, 0, :, :, -1].mean()) < float(no_load.x[0, 0, :, :, -1].mean())  # pushed down


def test_static_that_does_not_converge_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys):
    path = write(tmp_path, edit(BEAM, "tol = 1e-9", "tol = 1e-12\nmax_iter = 1"))
    out = tmp_path / "out"
    assert cli.main(argv=["run", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    line = line_containing(path.read_text(), "max_iter")
    assert err.count("\n") == 1 and err.startswith(f"torchdeform: {path}:{line}: integrator.max_iter:"), err
    assert "did not converge" in err and "nothing was written" in err
    assert not out.exists() or not any(out.iterdir())


def test_static_cli_prints_one_line(tmp_path, capsys):
    path = write(tmp_path, BEAM)
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "static equilibrium in" in captured.out and "relative residual" in captured.out and captured.err == ""


# ------------------------------------------------------------------ bad input at the CLI
_REGION = "\n[[regions]]\nbox = {lo = [0.0, 0.0, 0.0], hi = [0.01, 0.01, 0.01]}\n"
_E_NU = "youngs_modulus = 5000.0\npoisson_ratio = 0.45"
_ELASTIC = edit(BLOCK, 'tissue = "liver"', _E_NU) + "\n[mass]\ndensity = 1000.0\n"
BAD = {
    # id: (scene text, key, expected text, text of the line it points to)
    "nu 0.5": (
        edit(_ELASTIC, "poisson_ratio = 0.45", "poisson_ratio = 0.5"),
        "material.poisson_ratio",
        "a Poisson ratio in [0.25, 0.5)",
        "poisson_ratio",
    ),
    "nu below 0.25": (
        edit(_ELASTIC, "poisson_ratio = 0.45", "poisson_ratio = 0.2"),
        "material.poisson_ratio",
        "a Poisson ratio in [0.25, 0.5)",
        "poisson_ratio",
    ),
    "nu not a number": (
        edit(_ELASTIC, "poisson_ratio = 0.45", 'poisson_ratio = "0.45"'),
        "material.poisson_ratio",
        "a Poisson ratio",
        "poisson_ratio",
    ),
    "E zero": (
        edit(_ELASTIC, "youngs_modulus = 5000.0", "youngs_modulus = 0.0"),
        "material.youngs_modulus",
        "Young's modulus E in Pa (> 0)",
        "youngs_modulus",
    ),
    "E negative": (
        edit(_ELASTIC, "youngs_modulus = 5000.0", "youngs_modulus = -5000.0"),
        "material.youngs_modulus",
        "Young's modulus E in Pa (> 0)",
        "youngs_modulus",
    ),
    "E not a number": (
        edit(_ELASTIC, "youngs_modulus = 5000.0", 'youngs_modulus = "5 kPa"'),
        "material.youngs_modulus",
        "Young's modulus E in Pa",
        "youngs_modulus",
    ),
    "tissue nu 0.5": (
        edit(BLOCK, 'tissue = "liver"', 'tissue = "liver"\npoisson_ratio = 0.5'),
        "material.poisson_ratio",
        "a Poisson ratio in [0.25, 0.5)",
        "poisson_ratio",
    ),
    "tissue on non-cubic cells": (
        edit(BLOCK, "spacing = 0.01", "spacing = [0.01, 0.01, 0.02]"),
        "material.tissue",
        "cubic cells",
        "tissue =",
    ),
    "region nu": (
        _ELASTIC + _REGION + "poisson_ratio = 0.6\n",
        "regions[0].poisson_ratio",
        "a Poisson ratio in [0.25, 0.5)",
        "poisson_ratio = 0.6",
    ),
    "region E": (
        _ELASTIC + _REGION + "youngs_modulus = -1.0\n",
        "regions[0].youngs_modulus",
        "Young's modulus E in Pa (> 0)",
        "youngs_modulus = -1.0",
    ),
    "region E not a number": (
        _ELASTIC + _REGION + 'youngs_modulus = "stiff"\n',
        "regions[0].youngs_modulus",
        "Young's modulus E in Pa",
        'youngs_modulus = "stiff"',
    ),
    "region stiffness in an elastic body": (
        _ELASTIC + _REGION + "stiffness = 3.0\n",
        "regions[0].stiffness",
        "in a region of an elastic body",
        "stiffness = 3.0",
    ),
    "region E in a body of springs": (
        edit(_ELASTIC, _E_NU, "stiffness = 5.0") + _REGION + "youngs_modulus = 5000.0\n",
        "regions[0].youngs_modulus",
        "needs an elastic body",
        "youngs_modulus = 5000.0",
    ),
    "region with nothing": (_ELASTIC + _REGION, "regions[0]", "at least one of the keys youngs_modulus", "[[regions]]"),
    "static with dt": (edit(BEAM, "tol = 1e-9", "dt = 0.01"), "integrator.dt", 'no dt with name = "static"', "dt ="),
    "static max_iter 0": (
        edit(BEAM, "tol = 1e-9", "max_iter = 0"),
        "integrator.max_iter",
        "an integer >= 1",
        "max_iter",
    ),
    "static tol 0": (edit(BEAM, "tol = 1e-9", "tol = 0.0"), "integrator.tol", "a positive number", "tol ="),
    "static with record_every": (
        BEAM + "\n[output]\nrecord_every = 2\n",
        "output.record_every",
        'no record_every with [integrator] name = "static"',
        "record_every",
    ),
}


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_bad_elastic_and_static_input_is_one_line_exit_2(case, tmp_path, capsys):
    text, key, expected, needle = BAD[case]
    path = write(tmp_path, text, "bad.toml")
    line = line_containing(path.read_text(), needle)
    rc = cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.endswith("\n") and err.count("\n") == 1, err
    assert err.startswith(f"torchdeform: {path}:{line}: {key}: expected"), err
    assert expected in err, err
    assert not (tmp_path / "out").exists()


def test_bad_poisson_ratio_in_a_subprocess_is_one_line_exit_2(tmp_path):
    path = write(tmp_path, edit(BLOCK, 'tissue = "liver"', 'tissue = "liver"\npoisson_ratio = 0.5'), "bad.toml")
    proc = subprocess.run(
        [sys.executable, "-m", "torchdeform", "run", str(path), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    line = line_containing(path.read_text(), "poisson_ratio")
    assert proc.stderr.count("\n") == 1
    assert proc.stderr.startswith(f"torchdeform: {path}:{line}: material.poisson_ratio: expected a Poisson ratio")
