"""MATLAB .fis files, the `torchdeform fuzzy` CLI and the coupling of fuzzy outputs to
per-spring parameters (the fuzzy bench smoke run is in ``tests/bench/test_fuzzy.py``).

Oracles: scikit-fuzzy for the hand-written tipper file (and MATLAB's documented value for
it), the written-then-read system for the round trip (outputs must be identical), the line
numbers written into each malformed file's first line, and a per-node loop for the coupling.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from torchdeform import Grid, cli
from torchdeform.errors import ConfigError
from torchdeform.fuzzy import Bell, Gaussian, MamdaniSystem, Sigmoid, Singleton, Trapezoid, Triangle, Variable
from torchdeform.fuzzy.coupling import Ellipsoid, node_inputs, spring_parameters
from torchdeform.fuzzy.fis import fis_text, parse_fis, read_fis, write_fis

DATA = Path(__file__).resolve().parents[1] / "data" / "fis"
TIPPER = DATA / "tipper.fis"
BAD = sorted((DATA / "bad").glob("*.fis"))


def _cli(*args):
    """``torchdeform ARGS`` in this process (``cli.main``, what ``python -m torchdeform`` runs): status and output."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli.main(argv=[str(a) for a in args])
        except SystemExit as e:  # argparse's usage errors
            code = e.code
    return subprocess.CompletedProcess(args, code, out.getvalue(), err.getvalue())


# ------------------------------------------------------------------ tipper


def _skfuzzy_tipper(points):
    """MATLAB's tipper in scikit-fuzzy, written from the toolbox definitions (not from our file)."""
    skf = pytest.importorskip("skfuzzy")
    from skfuzzy import control as ctrl

    u10, u30 = np.linspace(0, 10, 2001), np.linspace(0, 30, 3001)
    service, food = ctrl.Antecedent(u10, "service"), ctrl.Antecedent(u10, "food")
    tip = ctrl.Consequent(u30, "tip")
    for name, c in (("poor", 0), ("good", 5), ("excellent", 10)):
        service[name] = skf.gaussmf(u10, c, 1.5)
    food["rancid"] = skf.trapmf(u10, [0, 0, 1, 3])
    food["delicious"] = skf.trapmf(u10, [7, 9, 10, 10])
    tip["cheap"], tip["average"], tip["generous"] = (
        skf.trimf(u30, p) for p in ([0, 5, 10], [10, 15, 20], [20, 25, 30])
    )
    rules = [
        ctrl.Rule(service["poor"] | food["rancid"], tip["cheap"]),
        ctrl.Rule(service["good"], tip["average"]),
        ctrl.Rule(service["excellent"] | food["delicious"], tip["generous"]),
    ]
    sim = ctrl.ControlSystemSimulation(ctrl.ControlSystem(rules), cache=False)
    out = []
    for s, f in points:
        sim.input["service"], sim.input["food"] = s, f
        sim.compute()
        out.append(sim.output["tip"])
    return np.array(out)


def test_tipper_file_matches_skfuzzy_and_matlab():
    fis = read_fis(TIPPER).double()
    points = [(s, f) for s in (0, 1, 2.5, 5, 7.3, 10) for f in (0, 2, 5, 8.8, 10)]
    ours = fis(torch.tensor(points, dtype=torch.float64)).numpy()[:, 0]
    ref = _skfuzzy_tipper(points)
    assert np.abs(ours - ref).max() <= 1e-3 * 30
    # MATLAB's documentation: evalfis(tipper, [1 2]) = 5.5586 (101-point defuzzification,
    # so agreement is within MATLAB's own discretisation, well inside 1e-3 of the range).
    assert abs(float(fis.evaluate(service=1.0, food=2.0)["tip"]) - 5.5586) <= 1e-3 * 30


# ------------------------------------------------------------------ round trip


def _random_system(seed: int, dialect: str = "octave") -> MamdaniSystem:
    """Hedges the ``dialect``'s rule codes encode; fuzzylite's codes hedge no consequent."""
    g = torch.Generator().manual_seed(seed)

    def r(lo, hi):
        return float(lo + (hi - lo) * torch.rand((), generator=g))

    def term(k, lo, hi, allow_singleton=False):
        c = r(lo, hi)
        w = r(0.05, 0.4) * (hi - lo)
        kinds = ["trapezoid", "triangle", "gaussian", "bell", "sigmoid"]
        kind = kinds[k % len(kinds)]
        if kind == "trapezoid":
            return Trapezoid(c - w, c - w / 3, c + w / 4, c + w)
        if kind == "triangle":
            return Triangle(c - w, c, c + w / 2)
        if kind == "gaussian":
            return Gaussian(c, w / 2)
        if kind == "bell":
            return Bell(w, r(1, 3), c)
        return Sigmoid(c, r(-3, 3) or 1.0)

    inputs = [Variable(f"in{i}", (0, 10), {f"t{k}": term(k + i, 0, 10) for k in range(3)}) for i in range(2)]
    outputs = [
        Variable("y", (-5, 5), {f"o{k}": term(k, -5, 5) for k in range(4)}, default=1.25),
        Variable("s", (0, 1), {f"p{k}": Singleton(r(0, 1)) for k in range(3)}),
    ]
    if dialect == "octave":
        hedge = ["", "very ", "not ", "somewhat ", "cubed ", "very very ", "not very "]
    else:
        hedge = ["", "very ", "not ", "somewhat ", "extremely ", "seldom ", "not very "]
    out_hedge = ["", "very ", "not "] if dialect == "octave" else [""]
    rules = []
    for k in range(6):
        i0, i1 = int(torch.randint(3, (), generator=g)), int(torch.randint(3, (), generator=g))
        conn = "AND" if k % 2 else "OR"
        rules.append(
            f"IF in0 IS {hedge[k % 7]}t{i0} {conn} in1 IS {hedge[(k + 3) % 7]}t{i1} "
            f"THEN y IS {out_hedge[(k * 2) % len(out_hedge)]}o{k % 4} AND s IS p{k % 3} WITH {0.5 + 0.1 * k:g}"
        )
    methods = [
        dict(),
        dict(and_method="prod", or_method="probor", implication="prod", aggregation="sum"),
        dict(aggregation="probor", defuzzification="bisector"),
        dict(defuzzification="mom"),
        dict(defuzzification="som", resolution=500),
        dict(defuzzification="lom"),
    ][seed % 6]
    return MamdaniSystem(f"random{seed}", inputs, outputs, rules, **methods)


@pytest.mark.parametrize("dialect", ["octave", "fuzzylite"])
@pytest.mark.parametrize("seed", range(12))
def test_write_then_read_gives_identical_outputs(tmp_path, seed, dtype, dialect):
    fis = _random_system(seed, dialect).to(dtype)
    path = write_fis(fis, tmp_path / "sys.fis", comments="round trip\ntest", hedges=dialect)
    back = read_fis(path, hedges=dialect).to(dtype)
    assert fis_text(back, hedges=dialect) == fis_text(fis, hedges=dialect)
    x = torch.rand(300, 2, dtype=dtype, generator=torch.Generator().manual_seed(seed)) * 12 - 1
    assert torch.equal(fis(x), back(x))
    assert [str(r) for r in back.rules] == [str(r) for r in fis.rules]


def test_fis_cannot_encode_some_hedges():
    fis = _random_system(0)
    fis.rules[0].antecedent[0] = type(fis.rules[0].antecedent[0])("in0", "t0", hedges=("somewhat", "very"))
    with pytest.raises(ConfigError, match=r"hedges that \.fis can encode"):
        fis_text(fis)


def test_comments_and_blank_lines_are_ignored():
    text = TIPPER.read_text()
    noisy = "\n".join(l if not l.startswith("[") else f"\n# a comment\n{l}" for l in text.splitlines())
    x = torch.rand(50, 2) * 10
    assert torch.equal(parse_fis(noisy)(x), read_fis(TIPPER)(x))


# ------------------------------------------------------------------ malformed files


def test_at_least_fifteen_malformed_files():
    assert len(BAD) >= 15


@pytest.mark.parametrize("path", BAD, ids=lambda p: p.stem)
def test_malformed_file_is_rejected_with_file_and_line(path):
    first = path.read_text().splitlines()[0]
    m = re.fullmatch(r"% expect: (\w+): (.*)", first)
    assert m, f"{path.name}: first line must say what is expected"
    line, fragment = m.groups()
    with pytest.raises(ConfigError) as info:
        read_fis(path)
    msg = str(info.value)
    assert "\n" not in msg
    where = f"{path}:{line}: " if line != "none" else f"{path}: "
    assert msg.startswith(where), msg
    assert fragment in msg, msg


@pytest.mark.parametrize("path", BAD[:4] + BAD[-2:], ids=lambda p: p.stem)
def test_cli_rejects_malformed_file_with_exit_2_and_one_line(path):
    res = _cli("fuzzy", "show", path)
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("torchdeform: ") and path.name in lines[0]


def test_missing_file_is_a_clean_error():
    res = _cli("fuzzy", "eval", "no/such/file.fis", "a=1")
    assert res.returncode == 2 and "Traceback" not in res.stderr and "no/such/file.fis" in res.stderr


# ------------------------------------------------------------------ CLI


def test_cli_show_lists_variables_terms_and_rules():
    res = _cli("fuzzy", "show", TIPPER)
    assert res.returncode == 0, res.stderr
    for word in (
        "service",
        "food",
        "tip",
        "rancid",
        "gaussian",
        "mean=5 sigma=1.5",
        "IF service IS poor OR food IS rancid THEN tip IS cheap",
    ):
        assert word in res.stdout


def test_cli_eval_pairs_json_and_csv(tmp_path):
    fis = read_fis(TIPPER).double()
    res = _cli("fuzzy", "eval", TIPPER, "service=2.5", "food=8.8", "--json")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["tip"] == pytest.approx(float(fis.evaluate(service=2.5, food=8.8)["tip"]), abs=1e-9)
    csv_in = tmp_path / "in.csv"
    csv_in.write_text("food,extra,service\n2,x,1\n8.8,y,2.5\n\n5,z,5\n")
    res = _cli("fuzzy", "eval", TIPPER, "--inputs", csv_in, "--json")
    assert res.returncode == 0, res.stderr
    rows = json.loads(res.stdout)
    expect = fis(torch.tensor([[1, 2], [2.5, 8.8], [5, 5]], dtype=torch.float64))[:, 0]
    assert [r["tip"] for r in rows] == pytest.approx(expect.tolist(), abs=1e-9)
    res = _cli("fuzzy", "eval", TIPPER, "--inputs", csv_in)
    assert res.stdout.splitlines()[0] == "service,food,tip" and len(res.stdout.splitlines()) == 4


@pytest.mark.parametrize(
    "args, needle",
    [
        (["service=1"], "missing food"),
        (["service=1", "food=abc"], "food: expected a number"),
        (["service=1", "food=2", "drink=3"], "drink"),
        (["service"], "NAME=VALUE"),
    ],
)
def test_cli_eval_bad_values(args, needle):
    res = _cli("fuzzy", "eval", TIPPER, *args)
    assert res.returncode == 2 and "Traceback" not in res.stderr and needle in res.stderr, res.stderr


def test_cli_eval_bad_csv_names_line(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("service,food\n1,2\n3,oops\n")
    res = _cli("fuzzy", "eval", TIPPER, "--inputs", bad)
    assert res.returncode == 2 and f"{bad}:3:" in res.stderr
    bad.write_text("service,drink\n1,2\n")
    res = _cli("fuzzy", "eval", TIPPER, "--inputs", bad)
    assert res.returncode == 2 and f"{bad}:1:" in res.stderr and "food" in res.stderr


def test_cli_plot_writes_pngs(tmp_path):
    res = _cli("fuzzy", "plot", TIPPER, "--out", tmp_path)
    assert res.returncode == 0, res.stderr
    names = sorted(p.name for p in tmp_path.glob("*.png"))
    assert names == sorted(
        ["mf_service.png", "mf_food.png", "mf_tip.png", "curve_service_tip.png", "curve_food_tip.png"]
    )
    assert all((tmp_path / n).stat().st_size > 5000 for n in names)


# ------------------------------------------------------------------ coupling


def test_spring_parameters_against_a_node_loop(device):
    fis = read_fis(TIPPER).double()  # the oracle's copy stays on the CPU
    grid = Grid((5, 4, 6), spacing=(0.01, 0.02, 0.01), topology=18)
    ell = Ellipsoid((0.02, 0.03, 0.025), (0.012, 0.02, 0.02))
    mask = torch.zeros(grid.shape, dtype=torch.bool)
    mask[0, :, :2] = True
    inputs = node_inputs(
        grid, fis, {"service": 3.0, "food": 4.0}, regions=[(ell, {"service": 8.0}), (mask, {"food": 9.5})]
    )
    params = spring_parameters(read_fis(TIPPER).double().to(device), grid, inputs.to(device), dtype=torch.float64)
    assert params["_evaluations"] == len(torch.unique(inputs.reshape(2, -1).T, dim=0)) <= 4
    X = grid.rest_positions(dtype=torch.float64)[0]
    tip = params["tip"]
    assert tip.device == device
    tip = tip.cpu()
    S = grid.S
    for s, d in enumerate(grid.directions):
        for i in range(grid.shape[0]):
            for j in range(grid.shape[1]):
                for k in range(grid.shape[2]):
                    a, b = (i, j, k), (i + d[0], j + d[1], k + d[2])
                    if not all(0 <= b[q] < grid.shape[q] for q in range(3)):
                        assert tip[s, i, j, k] == 0
                        continue
                    vals = []
                    for p in (a, b):
                        inside = (
                            float(
                                (
                                    (
                                        (X[(slice(None), *p)] - torch.tensor(ell.center, dtype=torch.float64))
                                        / torch.tensor(ell.radii, dtype=torch.float64)
                                    )
                                    ** 2
                                ).sum()
                            )
                            <= 1
                        )
                        service = 8.0 if inside else 3.0
                        food = 9.5 if mask[p] else 4.0
                        vals.append(float(fis.evaluate(service=service, food=food)["tip"]))
                    expect = 2 * vals[0] * vals[1] / (vals[0] + vals[1])
                    assert float(tip[s, i, j, k]) == pytest.approx(expect, rel=1e-12)
    assert tip.shape[0] == S


def test_spring_parameters_bad_shapes():
    fis = read_fis(TIPPER)
    grid = Grid((3, 3, 3), spacing=0.01, topology=6)
    with pytest.raises(ConfigError, match="shape"):
        spring_parameters(fis, grid, torch.zeros(1, 3, 3, 3))
    with pytest.raises(ConfigError, match="every input"):
        node_inputs(grid, fis, {"service": 1.0})
    with pytest.raises(ConfigError, match="input names"):
        node_inputs(grid, fis, {"service": 1.0, "food": 2.0}, regions=[(Ellipsoid((0, 0, 0), (1, 1, 1)), {"drink": 1})])
