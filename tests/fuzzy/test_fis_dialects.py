"""``.fis`` files as MATLAB, Octave's fuzzy-logic-toolkit and fuzzylite write them.

Oracles: numpy evaluations written here from the published definitions (MATLAB's membership
functions, Octave's hedge powers and Einstein norms, fuzzylite's terms and hedges), with the
centroid integrated by the trapezoid rule on a fine grid; the written-then-read system for the
round trips (outputs must be identical); the line numbers of the texts below for the errors.
The texts are our own, written with the constructs the peers' example files use.
"""

from __future__ import annotations

import contextlib
import io
import re
import warnings

import numpy as np
import pytest
import torch

from torchdeform import cli
from torchdeform.errors import ConfigError
from torchdeform.fuzzy import MamdaniSystem, Triangle, Variable
from torchdeform.fuzzy.fis import FisWarning, fis_text, parse_fis, read_fis, write_fis
from torchdeform.fuzzy.membership import (
    Binary,
    Concave,
    Cosine,
    DiffSigmoid,
    Discrete,
    Gaussian2,
    LinS,
    LinZ,
    PiShape,
    ProdSigmoid,
    Ramp,
    Rectangle,
    Spike,
    SShape,
    ZShape,
)

# ------------------------------------------------------------------ numpy definitions


def _sig(x, a, c):
    return 1.0 / (1.0 + np.exp(-a * (x - c)))


def _zmf(x, a, b):
    m = (a + b) / 2
    return np.where(
        x <= a,
        1.0,
        np.where(x <= m, 1 - 2 * ((x - a) / (b - a)) ** 2, np.where(x <= b, 2 * ((x - b) / (b - a)) ** 2, 0.0)),
    )


def _gauss(x, s, c):
    return np.exp(-((x - c) ** 2) / (2 * s * s))


def _trimf(x, a, b, c):
    return np.clip(np.minimum((x - a) / (b - a), (c - x) / (c - b)), 0, 1)


def _einstein_product(a, b):
    return a * b / (2 - (a + b - a * b))


def _einstein_sum(a, b):
    return (a + b) / (1 + a * b)


def _centroid(y, mu):
    return np.trapezoid(y * mu, y) / np.trapezoid(mu, y)


# ------------------------------------------------------------------ Octave's dialect

OCTAVE_STYLE = """\
## An Octave-style system written for this test (## comments, as in Octave's own files)
[System]
Name='octave-style'   % a trailing comment
Type='Mamdani'
Version=3.0
NumInputs=2
NumOutputs=1
NumRules=4
AndMethod='einstein_product'
OrMethod='einstein_sum'
ImpMethod='einstein_product'
AggMethod='einstein_sum'
DefuzzMethod='centroid_integral'

[Input1]
Name='age'
Range=[20 100]
NumMFs=3
MF1='young':'zmf',[25 70]
MF2='middle':'pimf',[30 45 55 75]
MF3='old':'smf',[40 95]

[Input2]
Name='risk'
Range=[0 10]
NumMFs=3
MF1='low':'linzmf',[1 6]
MF2='medium':'gauss2mf',[1.2 4 0.8 6]
MF3='high':'linsmf',[4 9.5]

[Output1]
Name='stocks'
Range=[0 100]
NumMFs=4
MF1='few':'trimf',[0 10 40 0]    % a padded fourth parameter, as old MATLAB files have
MF2='some':'dsigmf',[0.3 30 0.25 65]
MF3='many':'psigmf',[0.2 55 -0.3 90]
MF4='most':'gaussmf',[9 88]

[Rules]
1 -3.3, 4 (1) : 2
-2.3 -1.3, 2.2 (0.5) : 1
3.05 1.4, 1 (0.8) : 1
2 2, -3 (1) : 1   % a negated consequent
"""


def _octave_oracle(age, risk):
    """The OCTAVE_STYLE system evaluated as Octave's toolkit defines it (hedge .dd = power dd/10, NOT last)."""
    young, old = _zmf(age, 25, 70), 1 - _zmf(age, 40, 95)
    middle = (1 - _zmf(age, 30, 45)) * _zmf(age, 55, 75)
    low, high = np.clip((6 - risk) / 5, 0, 1), np.clip((risk - 4) / 5.5, 0, 1)
    medium = _gauss(risk, 1.2, 4) if risk < 4 else (_gauss(risk, 0.8, 6) if risk > 6 else 1.0)
    y = np.linspace(0, 100, 20001)
    out = {
        "few": _trimf(y, 0, 10, 40),
        "some": np.abs(_sig(y, 0.3, 30) - _sig(y, 0.25, 65)),
        "many": _sig(y, 0.2, 55) * _sig(y, -0.3, 90),
        "most": _gauss(y, 9, 88),
    }
    rules = [
        (_einstein_sum(young, 1 - high**3), out["most"]),
        (0.5 * _einstein_product(1 - middle**3, 1 - low**3), out["some"] ** 2),
        (0.8 * _einstein_product(old**0.5, low**4), out["few"]),
        (_einstein_product(middle, medium), 1 - out["many"]),
    ]
    agg = np.zeros_like(y)
    for w, mu in rules:
        agg = _einstein_sum(agg, _einstein_product(w, mu))
    return _centroid(y, agg)


def test_octave_style_file_matches_octave_semantics(tmp_path):
    path = tmp_path / "octave_style.fis"
    path.write_text(OCTAVE_STYLE)
    with pytest.warns(FisWarning) as record:
        fis = read_fis(path).double()
    msgs = [str(w.message) for w in record if issubclass(w.category, FisWarning)]
    assert msgs == [f"{path}:35: [Output1] MF1: trimf takes 3 parameters; the extra [0] ignored (as MATLAB does)"]
    assert [str(r) for r in fis.rules][
        1
    ] == "IF age IS not cubed middle AND risk IS not cubed low THEN stocks IS very some WITH 0.5"
    points = [(a, r) for a in (22.0, 35.0, 50.0, 63.0, 80.0, 99.0) for r in (0.5, 3.0, 5.0, 7.2, 9.9)]
    ours = fis(torch.tensor(points, dtype=torch.float64))[:, 0].numpy()
    ref = np.array([_octave_oracle(a, r) for a, r in points])
    assert np.abs(ours - ref).max() <= 1e-3 * 100


# ------------------------------------------------------------------ fuzzylite's dialect

FUZZYLITE_STYLE = """\
#Written by hand for this test, in the style of fuzzylite's FisExporter

[System]
Name='fl-style'
Type='mamdani'
Version=6.0
NumInputs=1
NumOutputs=1
NumRules=6
AndMethod='min'
OrMethod='max'
ImpMethod='prod'
AggMethod='max'
DefuzzMethod='centroid'

[Input1]
Name='level'
Range=[0.000 10.000]
Enabled=1
NumMFs=5
MF1='low':'rampmf',[4.000 0.000]
MF2='mid':'cosinemf',[5.000 6.000]
MF3='high':'concavemf',[6.000 9.000]
MF4='bumpy':'discretemf',[1.000 0.000 3.000 1.000 4.000 0.500 6.000 1.000 8.000 0.000]
MF5='flag':'binarymf,[7.000 10.000]

[Output1]
Name='power'
Range=[0.000 1.000]
Enabled=1
Default=nan
LockPrevious=0
LockRange=1
NumMFs=4
MF1='off':'rectmf',[0.000 0.200]
MF2='mid':'spikemf',[0.500 0.600]
MF3='full':'trapmf',[0.600 0.800 1.000 1.000]
MF4='steps':'discretemf',[0.000 0.000 0.300 1.000 0.500 0.200 1.000 0.000]

[Rules]
1.010 , 1.000 (1.000) : 1
2.300 , 2.000 (1.000) : 1
3.200 , 3.000 (0.700) : 1
4.050 , 4.000 (1.000) : 1
-5.400 , 2.000 (0.500) : 1
0.990 , 4.000 (0.100) : 1
"""


def _fl_degrees(level):
    low = float(np.clip((4 - level) / 4, 0, 1))
    mid = 0.5 * (1 + np.cos(2 * np.pi * (level - 5) / 6)) if abs(level - 5) <= 3 else 0.0
    high = 3 / (12 - level) if level < 9 else 1.0
    bumpy = float(np.interp(level, [1, 3, 4, 6, 8], [0, 1, 0.5, 1, 0]))
    flag = 1.0 if level >= 7 else 0.0
    seldom = np.sqrt(low / 2) if low <= 0.5 else 1 - np.sqrt((1 - low) / 2)
    extremely = 2 * mid**2 if mid <= 0.5 else 1 - 2 * (1 - mid) ** 2
    return [seldom, extremely, 0.7 * high**2, np.sqrt(bumpy), 0.5 * (1 - flag**4), 0.1]


def _fl_oracle(level):
    y = np.linspace(0, 1, 20001)
    terms = [
        ((y >= 0) & (y <= 0.2)).astype(float),
        np.exp(-np.abs(10 / 0.6 * (y - 0.5))),
        np.clip(np.minimum((y - 0.6) / 0.2, 1.0), 0, 1),
        np.interp(y, [0, 0.3, 0.5, 1], [0, 1, 0.2, 0]),
    ]
    consequents = [0, 1, 2, 3, 1, 3]
    agg = np.zeros_like(y)
    for w, t in zip(_fl_degrees(level), consequents):
        agg = np.maximum(agg, w * terms[t])
    return _centroid(y, agg)


def test_fuzzylite_style_file_matches_fuzzylite_semantics(tmp_path):
    path = tmp_path / "fl_style.fis"
    path.write_text(FUZZYLITE_STYLE)
    with pytest.warns(FisWarning) as record:
        fis = read_fis(path, hedges="fuzzylite").double()
    lines = sorted(int(re.match(rf"{re.escape(str(path))}:(\d+): ", str(w.message)).group(1)) for w in record)
    assert lines == [19, 25, 30, 31, 32, 33]  # Enabled, binarymf's quote, Enabled, Default, LockPrevious, LockRange
    assert "[Input1] MF5: 'binarymf lacks its closing quote" in " ".join(str(w.message) for w in record)
    assert str(fis.rules[5]).startswith("IF level IS any low THEN power IS steps")
    levels = [0.0, 0.7, 1.9, 2.5, 3.6, 4.4, 5.0, 6.3, 7.0, 8.1, 9.5, 10.0]
    ours = fis(torch.tensor([[v] for v in levels], dtype=torch.float64))[:, 0].numpy()
    ref = np.array([_fl_oracle(v) for v in levels])
    assert np.abs(ours - ref).max() <= 1e-3


# ------------------------------------------------------------------ hedge dialects


def _tiny(rule_line: str, *, out_mfs="MF1='a':'trimf',[0 0 5]\nMF2='b':'trimf',[0 5 10]") -> str:
    n_out = out_mfs.count("\n") + 1
    return (
        "[System]\nName='t'\nType='mamdani'\nNumInputs=1\nNumOutputs=1\nNumRules=1\n"
        "[Input1]\nName='x'\nRange=[0 10]\nNumMFs=2\nMF1='lo':'trimf',[0 0 10]\nMF2='hi':'trimf',[0 10 10]\n"
        f"[Output1]\nName='y'\nRange=[0 10]\nNumMFs={n_out}\n{out_mfs}\n[Rules]\n{rule_line}\n"
    )


@pytest.mark.parametrize(
    "code, octave, fuzzylite",
    [
        ("1.05", ("somewhat",), ("somewhat",)),
        ("1.2", ("very",), ("very",)),
        ("1.3", ("cubed",), ("extremely",)),
        ("-1.3", ("not", "cubed"), ("not", "extremely")),
        ("1.4", ("very", "very"), ("very", "very")),
        ("1.01", None, ("seldom",)),
        ("1.99", None, ("any",)),
        ("0.99", None, ("any",)),
        ("1.1", (), None),
    ],
)
def test_hedge_codes_per_dialect(code, octave, fuzzylite):
    for dialect, expect in (("octave", octave), ("fuzzylite", fuzzylite)):
        text = _tiny(f"{code}, 2 (1) : 1")
        if expect is None:
            with pytest.raises(ConfigError, match=r"^t\.fis:20: \[Rules\] rule 1: expected a hedge code") as info:
                parse_fis(text, path="t.fis", hedges=dialect)
            assert "\n" not in str(info.value)
            continue
        fis = parse_fis(text, path="t.fis", hedges=dialect)
        assert tuple(fis.rules[0].antecedent[0].hedges) == expect
        assert fis_text(fis, hedges=dialect).splitlines()[-1].split(",")[0] == (
            "0.99" if expect == ("any",) else code if code != "1.1" else "1"
        )


def test_consequent_hedges_octave_yes_fuzzylite_no():
    text = _tiny("1, 2.2 (1) : 1")
    assert parse_fis(text).rules[0].consequent[0].hedges == ("very",)
    with pytest.raises(ConfigError, match=r"t\.fis:20: \[Rules\] rule 1: expected an output index without hedge"):
        parse_fis(text, path="t.fis", hedges="fuzzylite")
    with pytest.raises(ConfigError, match=r"^rule 1 .*no hedge on an output in the fuzzylite dialect"):
        fis_text(parse_fis(text), hedges="fuzzylite")


@pytest.mark.parametrize(
    "hedges, dialect",
    [(("extremely",), "octave"), (("seldom",), "octave"), (("any",), "octave"), (("cubed",), "fuzzylite")],
)
def test_writing_a_hedge_the_dialect_cannot_encode_names_the_rule(hedges, dialect):
    other = "fuzzylite" if dialect == "octave" else "octave"
    code = {"extremely": "1.3", "seldom": "1.01", "any": "1.99", "cubed": "1.3"}[hedges[0]]
    fis = parse_fis(_tiny(f"{code}, 2 (1) : 1"), hedges=other)
    with pytest.raises(ConfigError) as info:
        fis_text(fis, hedges=dialect)
    msg = str(info.value)
    assert msg.startswith(
        f"rule 1 (IF x IS {hedges[0]} lo THEN y IS b): expected hedges that .fis can encode in the {dialect}"
    )
    assert "\n" not in msg


def test_unknown_dialect_is_refused(tmp_path):
    for call in (
        lambda: parse_fis(_tiny("1, 1 (1) : 1"), hedges="matlab"),
        lambda: read_fis(tmp_path / "x.fis", hedges=""),
    ):
        with pytest.raises(ConfigError, match="hedges: expected 'octave' or 'fuzzylite'"):
            call()


# ------------------------------------------------------------------ new kinds round trip

NEW_KINDS = [
    ZShape(2, 6),
    SShape(3, 8),
    PiShape(1, 3, 5, 8),
    DiffSigmoid(2, 3, 1.5, 7),
    ProdSigmoid(2, 3, -1.5, 7),
    Gaussian2(1, 4, 1.5, 6),
    LinS(2, 7),
    LinZ(3, 8),
    Ramp(2, 8),
    Rectangle(3, 6),
    Concave(4, 7),
    Cosine(5, 4),
    Spike(5, 3),
    Binary(5, 10),
    Discrete(1, 0, 4, 1, 6, 0.5, 9, 0),
]


@pytest.mark.parametrize("mf", NEW_KINDS, ids=lambda mf: mf.kind)
@pytest.mark.parametrize("dialect", ["octave", "fuzzylite"])
def test_new_kind_round_trips_with_identical_outputs(tmp_path, mf, dialect, dtype):
    params = mf.values()
    again = type(mf)(*params)
    x = Variable("x", (0, 10), {"k": mf, "t": Triangle(0, 5, 10)})
    y = Variable("y", (0, 10), {"k": again, "t": Triangle(0, 2, 6)})
    fis = MamdaniSystem("kinds", [x], [y], ["IF x IS k THEN y IS t", "IF x IS very t THEN y IS k"]).to(dtype)
    path = write_fis(fis, tmp_path / "kinds.fis", hedges=dialect)
    back = read_fis(path, hedges=dialect).to(dtype)
    assert fis_text(back, hedges=dialect) == fis_text(fis, hedges=dialect)
    assert type(back.inputs[0].terms["k"]) is type(mf) and back.inputs[0].terms["k"].values() == pytest.approx(params)
    xs = torch.linspace(-1, 11, 241, dtype=dtype)[:, None]
    assert torch.equal(fis(xs), back(xs))


# ------------------------------------------------------------------ lenient reading


def test_trailing_comments_and_quotes():
    text = (
        _tiny("1, 2 (1) : 1 % a comment after a rule")
        .replace("Name='t'", "Name='50%-tip'   # name")
        .replace("Name='x'", 'Name="x"')
    )
    fis = parse_fis(text)
    assert fis.name == "50%-tip" and fis.input_names() == ["x"]


def test_unknown_keys_warn_once_each_with_file_and_line():
    text = _tiny("1, 2 (1) : 1").replace("NumRules=1\n", "NumRules=1\nDisableStructuralChecks=0\nSomeNewKey=3\n")
    text = text.replace("Range=[0 10]\nNumMFs=2\nMF1='lo'", "Range=[0 10]\nLockValueInRange=1\nNumMFs=2\nMF1='lo'")
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        parse_fis(text, path="k.fis")
    msgs = [str(w.message) for w in record if issubclass(w.category, FisWarning)]
    assert msgs == [
        "k.fis:8: [System] SomeNewKey: unknown key, ignored",
        "k.fis:12: [Input1] LockValueInRange: unknown key, ignored",
    ]


def test_lock_range_that_cannot_clip_warns():
    text = _tiny("1, 2 (1) : 1").replace("NumMFs=2\nMF1='a'", "LockRange=1\nDefault=4\nNumMFs=2\nMF1='a'")
    with pytest.warns(
        FisWarning, match=r"^l\.fis:16: \[Output1\] LockRange: ignored \(outputs stay in Range already\)"
    ):
        fis = parse_fis(text, path="l.fis")
    assert fis.outputs[0].default == 4


# ------------------------------------------------------------------ refused, one line each

BAD = [
    ("hedge 1.7", "octave", ("1, 2 (1) : 1", "1.7, 2 (1) : 1"), 20, "rule 1: expected a hedge code"),
    ("hedge 1.7 fuzzylite", "fuzzylite", ("1, 2 (1) : 1", "1.7, 2 (1) : 1"), 20, "got 1.7"),
    ("hedge 1.333", "octave", ("1, 2 (1) : 1", "1.333, 2 (1) : 1"), 20, "expected a hedge code"),
    ("norm", "octave", ("NumRules=1\n", "NumRules=1\nAndMethod='einstien_product'\n"), 7, "[System] AndMethod"),
    ("dsigmf 3", "octave", ("MF2='b':'trimf',[0 5 10]", "MF2='b':'dsigmf',[1 5 2]"), 18, "4 parameters for dsigmf"),
    ("rampmf 3", "octave", ("MF2='b':'trimf',[0 5 10]", "MF2='b':'rampmf',[1 5 2]"), 18, "2 parameters for rampmf"),
    ("discrete odd", "octave", ("MF2='b':'trimf',[0 5 10]", "MF2='b':'discretemf',[1 0 5]"), 18, "an even count"),
    (
        "lockrange clips",
        "octave",
        ("NumMFs=2\nMF1='a'", "LockRange=1\nDefault=12\nNumMFs=2\nMF1='a'"),
        16,
        "LockRange=1 would clip them",
    ),
    (
        "enabled 0",
        "octave",
        ("Range=[0 10]\nNumMFs=2\nMF1='lo'", "Range=[0 10]\nEnabled=0\nNumMFs=2\nMF1='lo'"),
        10,
        "Enabled",
    ),
    ("lockprevious", "octave", ("NumMFs=2\nMF1='a'", "LockPrevious=1\nNumMFs=2\nMF1='a'"), 16, "LockPrevious"),
    ("type-2", "octave", ("NumRules=1\n", "NumRules=1\nTypeReductionMethod='karnikmendel'\n"), 7, "type-2"),
    ("tsukamoto", "octave", ("Type='mamdani'", "Type='tsukamoto'"), 3, "Tsukamoto systems are not supported"),
    ("term half", "octave", ("MF2='b'", "MF2='half'"), 18, "not a torch Module method"),
    ("numMFs", "octave", ("NumMFs=2\nMF1='lo'", "NumMFs=3\nMF1='lo'"), 10, "NumMFs=3"),
]


def _bad_text(case):
    _, _, (old, new), _, _ = case
    text = _tiny("1, 2 (1) : 1")
    assert old in text
    text = text.replace(old, new, 1)
    return text


@pytest.mark.parametrize("case", BAD, ids=lambda c: c[0])
def test_bad_new_syntax_is_one_line_with_file_and_line(tmp_path, case):
    _, dialect, _, line, fragment = case
    path = tmp_path / "bad.fis"
    path.write_text(_bad_text(case))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FisWarning)
        with pytest.raises(ConfigError) as info:
            read_fis(path, hedges=dialect)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{path}:{line}: "), msg
    assert fragment in msg, msg


def test_empty_and_method_used_by_a_rule_is_refused():
    text = _tiny("1, 2 (1) : 1").replace("NumInputs=1", "NumInputs=1\nAndMethod=''")
    with pytest.warns(FisWarning, match=r"e\.fis:5: \[System\] AndMethod: empty \(no rule uses it\), read as 'min'"):
        assert parse_fis(text, path="e.fis").and_method == "min"


def _cli(*args):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(argv=[str(a) for a in args])
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize(
    "case", [c for c in BAD if c[0] in ("hedge 1.7", "norm", "dsigmf 3", "lockrange clips")], ids=lambda c: c[0]
)
def test_cli_show_refuses_bad_new_syntax_with_one_line(tmp_path, case):
    path = tmp_path / "bad.fis"
    path.write_text(_bad_text(case))
    code, _, err = _cli("fuzzy", "show", path)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"torchdeform: {path}:{case[3]}: "), err


def test_cli_show_prints_each_warning_as_one_line(tmp_path):
    path = tmp_path / "fl_style.fis"
    rules = FUZZYLITE_STYLE[FUZZYLITE_STYLE.index("[Rules]") :]
    path.write_text(FUZZYLITE_STYLE.replace(rules, "[Rules]\n1 , 1 (1) : 1\n").replace("NumRules=6", "NumRules=1"))
    code, out, err = _cli("fuzzy", "show", path)
    assert code == 0 and "level" in out
    lines = err.strip().splitlines()
    assert len(lines) == 6 and all(l.startswith(f"torchdeform: warning: {path}:") for l in lines), err


# ------------------------------------------------------------------ rules without an input condition


def test_a_rule_without_an_input_condition_is_skipped_with_a_warning():
    """fuzzylite writes a rule on an output of a chained system with all input indices 0 and drops
    it on reading (Octave's evalfis fails on it): read with one warning naming the line; the system
    is the file without that line (the oracle), and NumRules still counts the lines."""
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "data" / "fis" / "rule_without_input.fis"
    text = path.read_text()
    n = text.splitlines().index("0 0, 2 (1) : 1") + 1
    with pytest.warns(FisWarning, match=rf"rule_without_input\.fis:{n}: \[Rules\].*without an input condition"):
        fis = read_fis(path)
    without = parse_fis(text.replace("0 0, 2 (1) : 1\n", "").replace("NumRules=3", "NumRules=2"))
    assert len(fis.rules) == 2 == len(without.rules)
    x = torch.rand(200, 2, dtype=torch.float64) * 10
    assert torch.equal(fis.double()(x), without.double()(x))


def test_an_output_no_rule_concludes_takes_its_default():
    """The only rule on output ``z`` had no input condition: ``z`` is its default for every input."""
    text = """[System]
Name='chained'
NumInputs=1
NumOutputs=2
NumRules=2
[Input1]
Name='x'
Range=[0 1]
NumMFs=1
MF1='a':'trimf',[0 0.5 1]
[Output1]
Name='y'
Range=[0 1]
NumMFs=1
MF1='b':'trimf',[0 0.5 1]
[Output2]
Name='z'
Range=[0 4]
NumMFs=1
MF1='c':'trimf',[0 1 2]
Default=3
[Rules]
1, 1 0 (1) : 1
0, 0 1 (1) : 1
"""
    with pytest.warns(FisWarning, match=r"chained\.fis:24: \[Rules\]"):
        fis = parse_fis(text, path="chained.fis")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = fis.double()(torch.tensor([[0.2], [0.5], [0.9]], dtype=torch.float64))
    assert torch.equal(out[:, 1], torch.full((3,), 3.0, dtype=torch.float64))
    assert torch.allclose(out[:, 0], torch.full((3,), 0.5, dtype=torch.float64), atol=1e-9)  # symmetric term
