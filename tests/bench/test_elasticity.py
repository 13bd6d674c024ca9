"""``torchdeform bench elasticity``: its load cases, its engine choice and the command's output.

Oracles: the continuum's answer to uniaxial stress (a uniform strain ``t / E`` along the pull and
``-nu t / E`` across it, which the lattice must reproduce at any resolution) and the
finite-element reference (:mod:`torchdeform.bench.accuracy.fem`, scikit-fem) for the cantilever;
the engine choice is checked against what :class:`torchdeform.Engine` refuses.
"""

import json
import sys

import pytest
import torch

import torchdeform as td
from torchdeform import cli
from torchdeform.bench import elasticity
from torchdeform.bench.accuracy import lattice
from torchdeform.sim import native


@pytest.mark.parametrize("topology", [18, 26])
@pytest.mark.parametrize("nu", [0.25, 0.49])
def test_uniaxial_cube_has_the_asked_moduli_at_any_resolution(topology, nu):
    for h in (0.005, 0.0025):
        pull = lattice.lattice_uniaxial(nu, h, topology=topology, traction=50.0)
        assert pull.strain_axial == pytest.approx(50.0 / lattice.YOUNGS, rel=1e-8)
        for lateral in pull.strain_lateral:
            assert lateral == pytest.approx(-nu * 50.0 / lattice.YOUNGS, rel=1e-8)
        assert pytest.approx(lattice.YOUNGS, rel=1e-8) == pull.E and pull.nu == pytest.approx(nu, abs=1e-8)


def test_load_cases_refuse_spacings_that_do_not_fit():
    assert lattice.shear_fits(0.0025) and not lattice.shear_fits(0.005)
    with pytest.raises(td.ConfigError, match="free layer"):
        lattice.lattice_shear(0.3, 0.005)
    with pytest.raises(td.ConfigError, match="whole cells"):
        lattice.lattice_uniaxial(0.3, 0.003)


def test_small_strain_reaction_balances_a_prescribed_stretch():
    """A bar pulled by moving one end: the two ends' reactions are equal and opposite, the inside is in equilibrium."""
    model = lattice._elastic((3, 3, 5), 0.005, 0.3, 26, lattice.YOUNGS, mass=1.0)
    grid = model.grid
    ub = torch.zeros_like(model.X)
    ub[0, 2, :, :, -1] = 1e-4
    u, R = lattice.small_strain(model, fixed=grid.face("w-") | grid.face("w+"), ub=ub)
    assert torch.equal(u[0, :, :, :, -1], ub[0, :, :, :, -1])
    pull = float(R[0, 2, :, :, -1].sum())
    assert pull > 0 and float(R[0, 2, :, :, 0].sum()) == pytest.approx(-pull, rel=1e-8)
    assert float(R[0, :, :, :, 1:-1].abs().max()) < 1e-9 * pull


def test_fastest_engine_follows_the_engine():
    integ = td.SymplecticEuler()
    springs = lattice.cantilever_model(12, nu=0.25, dtype=torch.float32)
    engine, why = elasticity.fastest_engine(springs, integ)
    assert engine == ("native" if native.unavailable() is None else "compiled"), why
    assert elasticity.fastest_engine(springs, integ, compile=False)[0] in ("native", "eager")
    volume = lattice.cantilever_model(12, nu=0.45, dtype=torch.float32)
    blocked = td.Engine(mode="auto").blocker(volume, integ, volume.rest_state(), None)
    engine, why = elasticity.fastest_engine(volume, integ)
    assert (engine == "eager") == (blocked is not None) and (blocked is None or why == blocked)
    springs.stiffness = springs.stiffness.clone().requires_grad_()  # a learned parameter: eager only
    engine, why = elasticity.fastest_engine(springs, integ)
    assert engine == "eager" and "gradient" in why


def test_bench_elasticity_quick_json(capsys, tmp_path):
    argv = ["bench", "elasticity", "--quick", "--json", "--topologies", "26", "--cases", "uniaxial,cantilever"]
    assert cli.main(argv=[*argv, "--threads", "1", "--out", str(tmp_path)]) == 0
    doc = json.loads(capsys.readouterr().out)  # stdout holds exactly one JSON document
    assert doc["bench"] == "elasticity" and doc["cases"] == ["uniaxial", "cantilever"]
    assert doc["machine"]["threads"] == 1 and doc["fem"]["0.45"]["tip_m"] < 0
    rows = doc["rows"]
    assert [(r["topology"], r["nu"], r["h_mm"], r["cells"]) for r in rows] == [(26, 0.45, 5.0, 12), (26, 0.45, 2.5, 24)]
    for r in rows:
        assert abs(r["e_ratio"] - 1) < 1e-3 and abs(r["nu_eff"] - 0.45) < 0.01
        assert 0.5 < r["tip_ratio"] < 1.05
        assert r["tip_ratio"] == pytest.approx(r["tip_m"] / doc["fem"]["0.45"]["tip_m"])
        assert r["shear_ratio"] is None and r["punch_ratio"] is None  # not asked for
        assert r["springs_ms"] > 0 and r["volume_ms"] > 0
        assert r["volume_cost"] == pytest.approx(r["volume_ms"] / r["springs_ms"])
        assert r["springs_engine"] in ("native", "eager") and r["volume_engine"] in ("native", "eager")
        assert r["springs_threads"] >= 1 and r["volume_threads"] >= 1
    assert rows[0]["tip_ratio"] < rows[1]["tip_ratio"]  # too stiff in bending, less so when finer
    assert rows[0]["nodes"] == 3 * 3 * 13 and rows[1]["nodes"] == 5 * 5 * 25
    assert set(doc["engines"]) == {"springs alone", "springs + cell term"}
    assert (tmp_path / "elasticity.csv").is_file() and (tmp_path / "elasticity.png").is_file()


def test_bench_elasticity_without_scikit_fem(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "skfem", None)  # import skfem raises ImportError
    assert cli.main(argv=["bench", "elasticity", "--quick"]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "torchdeform[fem]" in lines[0] and "scikit-fem" in lines[0], captured.err
    assert captured.out == ""


@pytest.mark.parametrize(
    ("option", "value"),
    [("--topologies", "6"), ("--poisson", "0.5"), ("--cases", "uniaxial,bend"), ("--refine", "32")],
)
def test_bench_elasticity_refuses_bad_options(capsys, option, value):
    assert cli.main(argv=["bench", "elasticity", option, value]) == 2
    err = capsys.readouterr().err
    assert option in err and "Traceback" not in err


def test_bench_elasticity_prints_its_table(capsys):
    argv = ["bench", "elasticity", "--quick", "--topologies", "26", "--cases", "uniaxial", "--threads", "1"]
    assert cli.main(argv=argv) == 0
    out = capsys.readouterr().out
    assert "E/E" in out and "nu eff" in out and "+cell term ms" in out and "1.000000" in out
    assert "springs alone:" in out and "springs + cell term:" in out
