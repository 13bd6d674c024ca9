"""Octave's fuzzy-logic-toolkit rule language in the Mamdani engine: norms, hedges, refusals.

Oracles (none of them torchdeform's inference code):

* the operator formulas of Octave's toolkit (``inst/*_product.m``, ``*_sum.m``,
  ``bounded_difference.m``), written out here in numpy, on random degrees and exact 0 and 1;
* the algebraic laws of t-norms and s-norms (commutativity, associativity, neutral and
  absorbing elements, the bounds ``T <= min``, ``S >= max``, monotonicity, De Morgan duality);
* scikit-fuzzy's ``fuzzy_and`` / ``fuzzy_or`` / ``fuzzy_not`` (min, max, complement: the only
  norms it has) and ``skfuzzy.control`` with a custom AND function;
* whole systems evaluated by hand in numpy: fuzzify, hedge (Octave's powers), fold the clauses,
  weight, imply, aggregate rule by rule, centroid on the engine's grid (1000 midpoint cells);
* finite gradients at the 0/0 points of the Hamacher operators, ``gradcheck`` elsewhere.
"""

from __future__ import annotations

import itertools
from fractions import Fraction

import numpy as np
import pytest
import skfuzzy as fuzz
import torch

from torchdeform.errors import ConfigError
from torchdeform.fuzzy import MamdaniSystem, Trapezoid, Triangle, Variable
from torchdeform.fuzzy.membership import HEDGES, OCTAVE_HEDGES, apply_hedges
from torchdeform.fuzzy.system import AGGREGATIONS, AND_METHODS, IMPLICATIONS, OR_METHODS, SNORMS, TNORMS

# ------------------------------------------------------------------ numpy formulas (Octave's)


def _np_where_den(num, den, limit):
    safe = np.where(den == 0, 1.0, den)
    return np.where(den == 0, limit, num / safe)


NP_T = {
    "min": np.minimum,
    "prod": lambda a, b: a * b,
    "algebraic_product": lambda a, b: a * b,
    "bounded_difference": lambda a, b: np.maximum(0.0, a + b - 1),
    "drastic_product": lambda a, b: np.where(np.maximum(a, b) == 1, np.minimum(a, b), 0),
    "einstein_product": lambda a, b: (a * b) / (2 - (a + b - a * b)),
    "hamacher_product": lambda a, b: _np_where_den(a * b, a + b - a * b, 0),
}
NP_S = {
    "max": np.maximum,
    "probor": lambda a, b: a + b - a * b,
    "algebraic_sum": lambda a, b: a + b - a * b,
    "bounded_sum": lambda a, b: np.minimum(1, a + b),
    "drastic_sum": lambda a, b: np.where(np.minimum(a, b) == 0.0, np.maximum(a, b), 1),
    "einstein_sum": lambda a, b: (a + b) / (1 + a * b),
    "hamacher_sum": lambda a, b: _np_where_den(a + b - 2 * a * b, 1 - a * b, 1),
}
NP_AGG = {**NP_S, "sum": lambda a, b: a + b}
DUALS = [
    ("min", "max"),
    ("prod", "probor"),
    ("algebraic_product", "algebraic_sum"),
    ("bounded_difference", "bounded_sum"),
    ("drastic_product", "drastic_sum"),
    ("einstein_product", "einstein_sum"),
    ("hamacher_product", "hamacher_sum"),
]
OCTAVE_NAMES = [
    "algebraic_product",
    "algebraic_sum",
    "bounded_difference",
    "bounded_sum",
    "drastic_product",
    "drastic_sum",
    "einstein_product",
    "einstein_sum",
    "hamacher_product",
    "hamacher_sum",
]


def _degrees(seed: int = 0, n: int = 400) -> tuple:
    """All pairs of some special degrees (0, 1, 0.5, tiny, nearly 1) plus random pairs."""
    rng = np.random.default_rng(seed)
    special = np.array([0.0, 1.0, 0.5, 1e-300, 1e-9, 1 - 1e-9, 0.25, 0.75])
    pa, pb = (g.ravel() for g in np.meshgrid(special, special))
    ra, rb = rng.random(n), rng.random(n)
    return np.concatenate([pa, ra, rng.random(n // 4)]), np.concatenate([pb, rb, np.zeros(n // 4)])


def _t(x):
    return torch.as_tensor(x, dtype=torch.float64)


def _exact(x):
    return np.array([Fraction(float(v)) for v in x], dtype=object)


def close(got, want, atol=1e-15):
    torch.testing.assert_close(got, want, atol=atol, rtol=0)


def test_operator_tables_cover_octave():
    assert set(TNORMS) == set(NP_T) and set(SNORMS) == set(NP_S)
    for name in OCTAVE_NAMES:
        assert name in TNORMS or name in SNORMS
    assert AND_METHODS == IMPLICATIONS == tuple(TNORMS)
    assert tuple(SNORMS) == OR_METHODS
    assert AGGREGATIONS[:3] == ("max", "sum", "probor")  # the old names first, unchanged
    assert set(AGGREGATIONS) == set(SNORMS) | {"sum"}
    assert AND_METHODS[:2] == ("min", "prod") and OR_METHODS[:2] == ("max", "probor")


@pytest.mark.parametrize("name", list(NP_T) + list(NP_S))
def test_operator_matches_octave_formula(name):
    a, b = _degrees(1)
    ours = (TNORMS | SNORMS)[name](_t(a), _t(b)).numpy()
    # the formula in exact rational arithmetic on the same (float) degrees: Octave's Hamacher sum
    # in floats loses up to 1e-7 near (1, 1) to the cancellation in 1 - ab; ours must not
    exact = (NP_T | NP_S)[name](_exact(a), _exact(b))
    np.testing.assert_allclose(ours, np.asarray(exact, dtype=float), rtol=0, atol=1e-15)
    np.testing.assert_allclose(ours, (NP_T | NP_S)[name](a, b), rtol=0, atol=1e-6)  # Octave's floats
    for dtype in (torch.float32, torch.float64):  # and the broadcasting used by implication
        x = torch.as_tensor(a[:50], dtype=dtype)[:, None]
        y = torch.as_tensor(b[:70], dtype=dtype)[None, :]
        got = (TNORMS | SNORMS)[name](x, y)
        assert got.shape == (50, 70) and got.dtype == dtype
        assert torch.equal(got, (TNORMS | SNORMS)[name](x.expand(50, 70), y.expand(50, 70)))
        if dtype == torch.float32:  # float32 arithmetic: the formula on the rounded degrees, to 1e-6
            want = (NP_T | NP_S)[name](x.double().numpy(), y.double().numpy())
            np.testing.assert_allclose(got.double().numpy(), want, rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", list(TNORMS))
def test_tnorm_laws(name):
    T = TNORMS[name]
    a, b = (_t(v) for v in _degrees(2))
    c = _t(np.random.default_rng(3).random(a.shape[0]))
    ab = T(a, b)
    assert torch.equal(ab, T(b, a))  # commutative
    close(T(a, torch.ones_like(a)), a)  # 1 is neutral (up to rounding: 1e-300 + 1 - 1 = 0)
    assert torch.equal(T(a, torch.zeros_like(a)), torch.zeros_like(a))  # 0 absorbs
    assert bool((ab <= torch.minimum(a, b) + 1e-15).all())  # below min
    assert bool((ab >= 0).all() and (ab <= 1).all())
    assert torch.allclose(T(T(a, b), c), T(a, T(b, c)), atol=1e-12)  # associative
    assert bool((T(torch.maximum(a, c), b) >= ab - 1e-15).all())  # non-decreasing
    if name == "drastic_product":  # the smallest t-norm: below every other one
        for other in TNORMS.values():
            assert bool((ab <= other(a, b) + 1e-15).all())


@pytest.mark.parametrize("name", list(SNORMS))
def test_snorm_laws(name):
    S = SNORMS[name]
    a, b = (_t(v) for v in _degrees(4))
    c = _t(np.random.default_rng(5).random(a.shape[0]))
    ab = S(a, b)
    assert torch.equal(ab, S(b, a))
    close(S(a, torch.zeros_like(a)), a)  # 0 is neutral
    close(S(a, torch.ones_like(a)), torch.ones_like(a))  # 1 absorbs
    assert bool((ab >= torch.maximum(a, b) - 1e-15).all())  # above max
    assert bool((ab >= 0).all() and (ab <= 1).all())
    assert torch.allclose(S(S(a, b), c), S(a, S(b, c)), atol=1e-12)
    assert bool((S(torch.maximum(a, c), b) >= ab - 1e-15).all())
    if name == "drastic_sum":  # the largest s-norm
        for other in SNORMS.values():
            assert bool((ab >= other(a, b) - 1e-15).all())


@pytest.mark.parametrize(("tname", "sname"), DUALS)
def test_de_morgan_duals(tname, sname):
    a, b = _degrees(6)
    keep = (1 - (1 - a) == a) & (1 - (1 - b) == b)  # no rounding in 1 - (1 - a) (not 1e-300, 1 - 1e-9)
    a, b = _t(a[keep]), _t(b[keep])
    torch.testing.assert_close(SNORMS[sname](a, b), 1 - TNORMS[tname](1 - a, 1 - b), atol=1e-12, rtol=0)


def test_min_max_not_match_scikit_fuzzy():
    a, b = _degrees(7)
    x = np.arange(a.shape[0], dtype=float)
    _, sk_and = fuzz.fuzzy_and(x, a, x, b)
    _, sk_or = fuzz.fuzzy_or(x, a, x, b)
    np.testing.assert_array_equal(TNORMS["min"](_t(a), _t(b)).numpy(), sk_and)
    np.testing.assert_array_equal(SNORMS["max"](_t(a), _t(b)).numpy(), sk_or)
    np.testing.assert_array_equal(apply_hedges(_t(a), ("not",)).numpy(), fuzz.fuzzy_not(a))


# ------------------------------------------------------------------ hedges


def test_octave_hedge_codes_are_powers_not_after():
    """Octave: the fraction ``.dd`` raises the degree to ``dd / 10``; the minus sign then takes 1 - that."""
    m = _t(np.concatenate([[0.0, 1.0, 0.5], np.random.default_rng(8).random(100)]))
    for code, hedges in OCTAVE_HEDGES.items():
        torch.testing.assert_close(apply_hedges(m, hedges), m ** (code / 10), atol=1e-14, rtol=0)
        torch.testing.assert_close(apply_hedges(m, ("not", *hedges)), 1 - m ** (code / 10), atol=1e-14, rtol=0)
    assert set(OCTAVE_HEDGES) == {5, 20, 30, 40}
    # fuzzylite's extremely (kept) is not Octave's: they differ off 0, 0.5 and 1
    assert not torch.allclose(HEDGES["extremely"](m), HEDGES["cubed"](m))
    assert float(HEDGES["extremely"](_t(0.8))) == pytest.approx(1 - 2 * 0.2**2)


def test_cubed_is_a_hedge_in_sentences_and_not_a_name():
    from torchdeform.fuzzy import Rule

    rule = Rule.parse("IF a IS NOT Cubed low THEN y IS cubed high")
    assert rule.antecedent[0].hedges == ("not", "cubed")
    assert rule.consequent[0].hedges == ("cubed",)
    with pytest.raises(ConfigError, match="hedge"):
        Variable("a", (0, 1), {"cubed": Triangle(0, 0, 1)})


# ------------------------------------------------------------------ refusals


@pytest.mark.parametrize("method", ["wtaver", "wtsum"])
def test_sugeno_defuzzification_refused(method):
    x = Variable("x", (0, 1), {"lo": Triangle(0, 0, 1)})
    y = Variable("y", (0, 1), {"lo": Triangle(0, 0, 1)})
    with pytest.raises(ConfigError, match=r"Sugeno defuzzification .*not supported") as e:
        MamdaniSystem("s", [x], [y], ["IF x IS lo THEN y IS lo"], defuzzification=method)
    assert e.value.key == "defuzzification" and e.value.got == method


@pytest.mark.parametrize(
    ("key", "value", "says"),
    [
        ("aggregation", "min", "t-norm"),
        ("aggregation", "einstein_product", "t-norm"),
        ("implication", "max", "s-norm"),
        ("implication", "bounded_sum", "s-norm"),
        ("and_method", "hamacher_sum", "s-norm"),
        ("or_method", "drastic_product", "t-norm"),
        ("or_method", "sum", "unbounded"),
        ("and_method", "sum", "unbounded"),
        ("and_method", "nope", "one of min, prod"),
    ],
)
def test_wrong_kind_of_operator_refused(key, value, says):
    x = Variable("x", (0, 1), {"lo": Triangle(0, 0, 1)})
    y = Variable("y", (0, 1), {"lo": Triangle(0, 0, 1)})
    with pytest.raises(ConfigError, match=says) as e:
        MamdaniSystem("s", [x], [y], ["IF x IS lo THEN y IS lo"], **{key: value})
    assert e.value.key == key


# ------------------------------------------------------------------ whole systems by hand


def _tri(x, a, b, c):
    up = np.where(b > a, (x - a) / max(b - a, 1e-300), (x >= a).astype(float))
    down = np.where(c > b, (c - x) / max(c - b, 1e-300), (x <= c).astype(float))
    return np.clip(np.minimum(up, down), 0.0, 1.0)


def _trap(x, a, b, c, d):
    return np.clip(np.minimum(np.minimum((x - a) / (b - a), 1.0), (d - x) / (d - c)), 0.0, 1.0)


NP_HEDGE = {"very": lambda m: m**2, "somewhat": np.sqrt, "cubed": lambda m: m**3, "not": lambda m: 1 - m}

# inputs and output of both systems (numpy membership by hand, torch from the same corners)
STIFF = {"soft": ("tri", (0, 0, 6)), "medium": ("trap", (2, 4, 6, 8)), "hard": ("tri", (4, 10, 10))}
WET = {"dry": ("tri", (0, 0, 0.7)), "moist": ("tri", (0.3, 1, 1))}
K = {"low": ("tri", (0, 0, 50)), "mid": ("tri", (20, 50, 80)), "high": ("trap", (50, 90, 100, 110))}
RANGES = {"stiff": (0, 10), "wet": (0, 1), "k": (0, 100)}

# (rule sentence, connective, [(var, hedges, term)], [(hedges, term)], weight)
RULES_A = [
    ("IF stiff IS very soft AND wet IS NOT moist THEN k IS low", "and", [("stiff", ("very",), "soft"), ("wet", ("not",), "moist")], [((), "low")], 1.0),
    ("IF stiff IS cubed medium AND wet IS somewhat moist THEN k IS somewhat mid", "and", [("stiff", ("cubed",), "medium"), ("wet", ("somewhat",), "moist")], [(("somewhat",), "mid")], 1.0),
    ("IF stiff IS hard OR wet IS dry THEN k IS cubed high WITH 0.8", "or", [("stiff", (), "hard"), ("wet", (), "dry")], [(("cubed",), "high")], 0.8),
    ("IF stiff IS medium THEN k IS NOT very low", "and", [("stiff", (), "medium")], [(("not", "very"), "low")], 1.0),
]  # fmt: skip
# three clauses per rule (folds of three operands) and rules sharing a consequent (merged under max only)
RULES_B = [
    ("IF stiff IS somewhat soft AND wet IS very dry AND stiff IS NOT hard THEN k IS low WITH 0.9", "and", [("stiff", ("somewhat",), "soft"), ("wet", ("very",), "dry"), ("stiff", ("not",), "hard")], [((), "low")], 0.9),
    ("IF stiff IS medium OR wet IS cubed moist OR stiff IS very hard THEN k IS mid", "or", [("stiff", (), "medium"), ("wet", ("cubed",), "moist"), ("stiff", ("very",), "hard")], [((), "mid")], 1.0),
    ("IF stiff IS hard AND wet IS moist THEN k IS mid", "and", [("stiff", (), "hard"), ("wet", (), "moist")], [((), "mid")], 1.0),
    ("IF stiff IS NOT soft THEN k IS very high", "and", [("stiff", ("not",), "soft")], [(("very",), "high")], 1.0),
    ("IF wet IS moist THEN k IS very high", "and", [("wet", (), "moist")], [(("very",), "high")], 1.0),
]  # fmt: skip

COMBOS = [
    dict(and_method="min", or_method="max", implication="min", aggregation="max"),
    dict(and_method="einstein_product", or_method="hamacher_sum", implication="hamacher_product", aggregation="einstein_sum"),
    dict(and_method="hamacher_product", or_method="einstein_sum", implication="einstein_product", aggregation="hamacher_sum"),
    dict(and_method="bounded_difference", or_method="bounded_sum", implication="algebraic_product", aggregation="bounded_sum"),
    dict(and_method="algebraic_product", or_method="algebraic_sum", implication="bounded_difference", aggregation="algebraic_sum"),
    dict(and_method="drastic_product", or_method="drastic_sum", implication="min", aggregation="drastic_sum"),
    dict(and_method="min", or_method="probor", implication="drastic_product", aggregation="max"),
    dict(and_method="prod", or_method="max", implication="einstein_product", aggregation="sum"),
    dict(and_method="hamacher_product", or_method="max", implication="hamacher_product", aggregation="max"),
]  # fmt: skip


def _np_mf(spec, x):
    kind, p = spec
    return _tri(x, *p) if kind == "tri" else _trap(x, *p)


def _np_hedge(m, hedges):
    for h in reversed(hedges):
        m = NP_HEDGE[h](m)
    return m


def _torch_var(name, terms):
    mk = {"tri": Triangle, "trap": Trapezoid}
    return Variable(name, RANGES[name], {t: mk[k](*p) for t, (k, p) in terms.items()})


def _system(rules, combo, dtype=torch.float64):
    """Built in ``dtype`` (corners such as 0.3 made in float32 and then ``.double()`` stay rounded)."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        return MamdaniSystem(
            "octave",
            [_torch_var("stiff", STIFF), _torch_var("wet", WET)],
            [_torch_var("k", K)],
            [r[0] for r in rules],
            **combo,
        )
    finally:
        torch.set_default_dtype(old)


def _by_hand(rules, combo, stiff, wet) -> float:
    """The Mamdani evaluation written out: the engine's grid (1000 midpoint cells), rule by rule."""
    x = {"stiff": stiff, "wet": wet}
    terms = {"stiff": STIFF, "wet": WET}
    lo, hi = RANGES["k"]
    h = (hi - lo) / 1000
    y = lo + h * (np.arange(1000) + 0.5)
    agg = None
    for _text, conn, clauses, conseq, weight in rules:
        op = NP_T[combo["and_method"]] if conn == "and" else NP_S[combo["or_method"]]
        deg = None
        for var, hedges, term in clauses:
            d = _np_hedge(_np_mf(terms[var][term], np.float64(x[var])), hedges)
            deg = d if deg is None else op(deg, d)
        deg = deg * weight
        for hedges, term in conseq:
            implied = NP_T[combo["implication"]](np.full_like(y, deg), _np_hedge(_np_mf(K[term], y), hedges))
            agg = implied if agg is None else NP_AGG[combo["aggregation"]](agg, implied)
    mass = agg.sum()
    return float((agg * y).sum() / mass) if mass > 0 else 0.5 * (lo + hi)


POINTS = [(1.0, 0.1), (3.0, 0.45), (5.0, 0.6), (6.5, 0.35), (8.0, 0.9), (10.0, 1.0), (0.0, 0.0), (4.0, 0.7)]


@pytest.mark.parametrize("combo", COMBOS, ids=lambda c: "-".join(c.values()))
@pytest.mark.parametrize("rules", [RULES_A, RULES_B], ids=["A", "B"])
def test_system_matches_hand_evaluation(rules, combo):
    fis = _system(rules, combo)
    x = torch.tensor(POINTS, dtype=torch.float64)
    want = np.array([_by_hand(rules, combo, s, w) for s, w in POINTS])
    got = fis(x)[:, 0].numpy()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * 100)
    planned, _ = fis.infer(x, plan=fis.sparsity_plan())  # the compiled path's sparse plan: same result
    np.testing.assert_allclose(planned[:, 0].numpy(), want, rtol=0, atol=1e-9 * 100)
    if "drastic" not in " ".join(combo.values()):
        # float32 too; not with the drastic operators, which jump where a degree is 1 or 0 up to
        # rounding (probor(1, m) = 1 + m - m is 1 in float32 and 1 - 1e-16 in float64 at (5, 0.6))
        f32 = _system(rules, combo, torch.float32)(x.float())[:, 0].double().numpy()
        np.testing.assert_allclose(f32, want, rtol=0, atol=2e-3)


def test_non_max_aggregation_is_applied_per_rule():
    """Two rules with one consequent: bounded_sum of their implied sets, not their merged degree."""
    combo = dict(and_method="min", or_method="max", implication="min", aggregation="bounded_sum")
    fis = _system(RULES_B, combo)
    nu_merged = [c for c in fis._cons[0] if len(c.rules) > 1]
    assert not nu_merged  # every rule its own set
    assert [len(c.rules) for c in _system(RULES_B, dict(combo, aggregation="max"))._cons[0]] == [1, 2, 2]
    # at (8, 0.9) both 'mid' rules and both 'very high' rules fire: the sum differs from the max
    p = (8.0, 0.9)
    summed = _by_hand(RULES_B, combo, *p)
    maxed = _by_hand(RULES_B, dict(combo, aggregation="max"), *p)
    assert abs(summed - maxed) > 0.1
    assert float(fis(torch.tensor([p], dtype=torch.float64))[0, 0]) == pytest.approx(summed, abs=1e-7)


def test_skfuzzy_control_with_einstein_and():
    """scikit-fuzzy's own engine with an Einstein-product AND (min implication, max aggregation)."""
    from skfuzzy import control as ctrl

    def einstein(a, b):
        return a * b / (2.0 - (a + b - a * b))

    u = {n: np.linspace(*RANGES[n], 2001) for n in RANGES}
    stiff, wet = ctrl.Antecedent(u["stiff"], "stiff"), ctrl.Antecedent(u["wet"], "wet")
    k = ctrl.Consequent(u["k"], "k")
    for var, terms in ((stiff, STIFF), (wet, WET), (k, K)):
        for t, spec in terms.items():
            var[t] = _np_mf(spec, var.universe)
    sk_rules = [
        ctrl.Rule(stiff["soft"] & wet["dry"], k["low"], and_func=einstein),
        ctrl.Rule(stiff["medium"] & wet["moist"], k["mid"], and_func=einstein),
        ctrl.Rule(stiff["hard"] & wet["moist"], k["high"], and_func=einstein),
        ctrl.Rule(stiff["hard"] & wet["dry"], k["mid"], and_func=einstein),
    ]
    sim = ctrl.ControlSystemSimulation(ctrl.ControlSystem(sk_rules))
    ours = MamdaniSystem(
        "sk",
        [_torch_var("stiff", STIFF), _torch_var("wet", WET)],
        [_torch_var("k", K)],
        [
            "IF stiff IS soft AND wet IS dry THEN k IS low",
            "IF stiff IS medium AND wet IS moist THEN k IS mid",
            "IF stiff IS hard AND wet IS moist THEN k IS high",
            "IF stiff IS hard AND wet IS dry THEN k IS mid",
        ],
        and_method="einstein_product",
        resolution=4000,
    ).double()
    for s, w in [(1.0, 0.2), (5.0, 0.6), (7.0, 0.4), (9.0, 0.8)]:
        sim.input["stiff"], sim.input["wet"] = s, w
        sim.compute()
        got = float(ours(torch.tensor([[s, w]], dtype=torch.float64))[0, 0])
        assert got == pytest.approx(sim.output["k"], abs=1e-3 * 100), (s, w)


# ------------------------------------------------------------------ gradients


def test_operator_gradients_finite_at_corners():
    corners = [0.0, 1.0, 0.5]
    for name, op in (TNORMS | SNORMS).items():
        for a0, b0 in itertools.product(corners, corners):
            a = torch.tensor(a0, dtype=torch.float64, requires_grad=True)
            b = torch.tensor(b0, dtype=torch.float64, requires_grad=True)
            ga, gb = torch.autograd.grad(op(a, b), (a, b))
            assert torch.isfinite(ga) and torch.isfinite(gb), (name, a0, b0)


@pytest.mark.parametrize("name", list(TNORMS) + list(SNORMS))
def test_operator_gradcheck_inside(name):
    rng = np.random.default_rng(9)
    a, b = rng.uniform(0.05, 0.95, 40), rng.uniform(0.05, 0.95, 40)
    keep = (np.abs(a - b) > 1e-3) & (np.abs(a + b - 1) > 1e-3)
    a = torch.tensor(a[keep], dtype=torch.float64, requires_grad=True)
    b = torch.tensor(b[keep], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck((TNORMS | SNORMS)[name], (a, b))


@pytest.mark.parametrize("combo", COMBOS[1:3] + COMBOS[-1:], ids=lambda c: "-".join(c.values()))
def test_system_gradients_finite_at_zero_over_zero(combo):
    """Learnable corners, gradients through the Hamacher quotients at their 0/0 points: at (0, 0)
    rule B3's clauses are both 0 (Hamacher AND of 0 and 0), and cells outside a term imply 0 with
    degree 0 (Hamacher implication); at (10, 1) rule B2's OR meets 1 and 1, and rules B4 and B5
    both put 1 on the plateau of 'high' (Hamacher sum of 1 and 1 in the aggregation)."""
    fis = _system(RULES_B, combo).requires_grad_()
    x = torch.tensor([[8.0, 0.0], [10.0, 1.0], [0.0, 0.0], [5.0, 0.5]], dtype=torch.float64, requires_grad=True)
    out = fis(x)
    assert bool(torch.isfinite(out).all())
    params = [p for p in fis.parameters() if p.requires_grad]
    grads = torch.autograd.grad(out.sum(), params + [x])
    for g in grads:
        assert bool(torch.isfinite(g).all())
    assert any(bool((g != 0).any()) for g in grads[:-1])
