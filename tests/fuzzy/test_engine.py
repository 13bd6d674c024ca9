"""The Mamdani engine (``torchdeform.fuzzy``) against independent oracles.

Oracles (none of them produced by torchdeform):

* ``skfuzzy.control`` (scikit-fuzzy 0.5): 200 seeded random Mamdani systems and the tipping
  problem of its tutorial, all five defuzzifiers; min AND, max OR, min implication, max
  aggregation (its fixed choices);
* a numpy Mamdani evaluation (``tests.oracles.fuzzy.numpy_aggregate``) for product implication, sum
  and probabilistic-OR aggregation, product AND and probabilistic-OR OR, and hedges,
  defuzzified by ``skfuzzy.defuzz``;
* ``skfuzzy.membership`` for every membership function; REFERENCE.md 3.4 for the hedges,
  written out in numpy; weighted means for singleton outputs;
* finite differences (``torch.autograd.gradcheck``) for gradients.

Tolerance: 1e-3 of the output range (REFERENCE.md 3.5), from both engines' grids: the
torchdeform systems here use 3000 cells (``tests.oracles.fuzzy.TORCH_RES``; its midpoints contain the
odd points of the 2001-point scikit-fuzzy universes, where all term corners and peaks sit), so
the first/last maximum is located to ``range / 3000`` by torchdeform and to ``range / 2000`` by
scikit-fuzzy. At the default 1000 cells the first/last maximum alone can be off by a whole
cell, ``1e-3`` of the range.

Counted and skipped, never silently: outputs where no rule fires (scikit-fuzzy drops them;
torchdeform must return the default, checked), firing below 1e-9 (scikit-fuzzy's centroid
divides by max(area, 2.2e-16)), and for mom/som/lom maxima that are ambiguous at the engines'
precision (``tests.oracles.fuzzy.ambiguous_maximum``). mom over several separate maxima (exact ties) is
compared with the length-weighted mean of the maximising stretches instead of scikit-fuzzy's
point average, with the cell-counting error of the torchdeform grid added to the tolerance.
"""

from __future__ import annotations

import itertools
import math
import time
import warnings
import zlib
from collections import Counter, defaultdict
from dataclasses import dataclass, field

import numpy as np
import pytest
import skfuzzy as fuzz
import torch
from skfuzzy import control as ctrl
from skfuzzy.control.controlsystem import CrispValueCalculator
from torch.func import functional_call

from tests.helpers import F64
from tests.oracles.fuzzy import (
    TORCH_RES,
    ambiguous_maximum,
    build_skfuzzy,
    build_torch,
    default_dtype,
    hedge,
    mean_of_maximum,
    numpy_aggregate,
    random_points,
    random_system,
    sk_membership,
    skfuzzy_outputs,
    top_stretches,
)
from torchdeform.errors import ConfigError, NoRuleFiredError, TorchdeformError
from torchdeform.fuzzy import (
    Bell,
    Clause,
    EmptyOutputWarning,
    Gaussian,
    MamdaniSystem,
    Rule,
    Sigmoid,
    Singleton,
    Trapezoid,
    Triangle,
    Variable,
)
from torchdeform.fuzzy.membership import apply_hedges
from torchdeform.fuzzy.system import defuzzify

METHODS = ("centroid", "bisector", "mom", "som", "lom")
MAX_METHODS = ("mom", "som", "lom")
TOL = 1e-3  # of the output range


# =================================================================== 1. random systems vs skfuzzy

N_SYSTEMS = 200
POINTS = 4


@dataclass
class Agreement:
    """What the comparison of many systems found."""

    systems: int = 0
    points: int = 0
    compared: Counter = field(default_factory=Counter)  # method -> (point, output) pairs
    max_err: dict = field(default_factory=lambda: defaultdict(float))
    failures: dict = field(default_factory=lambda: defaultdict(list))
    empty: int = 0  # (point, output) with no rule firing
    empty_mismatch: list = field(default_factory=list)
    ambiguous: int = 0  # skipped for mom/som/lom
    faint: int = 0  # skipped: firing below 1e-9
    mom_ties: int = 0  # mom over separate maxima, see below
    max_ratio: float = 0.0  # their error / widened tolerance
    seconds: float = 0.0

    def record(self, method, err, context, tol=TOL):
        self.compared[method] += 1
        if tol == TOL:
            self.max_err[method] = max(self.max_err[method], err)
        else:
            self.max_ratio = max(self.max_ratio, err / tol)
        if not err <= tol and len(self.failures[method]) < 3:
            self.failures[method].append(
                f"{method}: |error| = {err:.3g} of the range (tolerance {tol:.3g})\n{context()}"
            )

    def summary(self, title) -> str:
        per = ", ".join(f"{m} {self.compared[m]} pts max {self.max_err[m]:.2e}" for m in METHODS)
        return (
            f"{title}: {self.systems} systems, {self.points} input points, {self.empty} output-points with "
            f"no rule firing, {self.faint} with firing below 1e-9, {self.ambiguous} ambiguous maxima skipped, "
            f"{self.mom_ties} mom over separate maxima (error/tolerance up to {self.max_ratio:.2f}); {per}; "
            f"{self.seconds:.1f} s"
        )


def _context(spec, x, out, values):
    def text():
        pt = ", ".join(f"{v.name}={xi!r}" for v, xi in zip(spec.inputs, x))
        vals = ", ".join(f"{k}={v!r}" for k, v in values.items())
        return f"{spec.describe()}\nat {pt}, output {out}: {vals}"

    return text


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def _ours_all_methods(fis, xt):
    """Outputs for every defuzzifier: one build, the method switched (builds are slow)."""
    ours = {}
    for m in METHODS:
        fis.defuzzification = m
        ours[m] = fis(xt).cpu().numpy()
    return ours


@pytest.fixture(scope="module")
def skfuzzy_random(device):
    t0 = time.perf_counter()
    res = Agreement()
    for seed in range(N_SYSTEMS):
        spec = random_system(seed)
        X = random_points(spec, 10_000 + seed, POINTS)
        xt = torch.tensor(X, dtype=F64, device=device)
        ours = _ours_all_methods(build_torch(spec).to(device), xt)
        sim, cons, used = build_skfuzzy(spec)
        res.systems += 1
        for p, x in enumerate(X):
            res.points += 1
            for v, xi in zip(spec.inputs, x):
                if v.name in used:
                    sim.input[v.name] = float(xi)
            sim.compute()
            for o, v in enumerate(spec.outputs):
                got = skfuzzy_outputs(sim, cons[v.name], METHODS)
                if got is None:  # no rule fired: scikit-fuzzy drops it
                    res.empty += 1
                    mine = {m: float(ours[m][p, o]) for m in METHODS}
                    if any(g != v.fallback for g in mine.values()):
                        res.empty_mismatch.append(_context(spec, x, v.name, {"default": v.fallback, **mine})())
                    continue
                u, mf, theirs = got
                if mf.max() < 1e-9:  # scikit-fuzzy divides by max(area, 2.2e-16): its centroid -> 0
                    res.faint += 1
                    continue
                ambiguous = ambiguous_maximum(u, mf)
                res.ambiguous += ambiguous
                tol = dict.fromkeys(METHODS, TOL)
                stretches = top_stretches(u, mf)
                if not ambiguous and len(stretches) > 1:
                    # mom over separate maxima (exact ties): scikit-fuzzy averages the points of
                    # its upsampled universe, where the cut points it inserts weigh some stretches
                    # more (up to ~1e-2 of the range here). Reference: the length-weighted mean of
                    # the stretches, whose ends are those cut points. torchdeform counts cells: each
                    # stretch end may gain or lose part of a cell, which moves the mean by up to
                    # spread * cell / (total length) per end; that bound is added to the tolerance.
                    theirs["mom"] = mean_of_maximum(stretches)
                    length = sum(b - a for a, b in stretches)
                    spread = stretches[-1][1] - stretches[0][0]
                    cell = v.width / TORCH_RES
                    tol["mom"] = TOL + 2 * len(stretches) * spread * cell / max(length, cell) / v.width
                    res.mom_ties += 1
                for m in METHODS:
                    if m in MAX_METHODS and ambiguous:
                        continue
                    a, b = float(ours[m][p, o]), theirs[m]
                    res.record(
                        m,
                        abs(a - b) / v.width,
                        _context(spec, x, v.name, {"torchdeform": a, "scikit-fuzzy": b}),
                        tol[m],
                    )
    res.seconds = time.perf_counter() - t0
    print("\n" + res.summary("scikit-fuzzy, random systems"))
    return res


def test_random_systems_enough_points(skfuzzy_random):
    r = skfuzzy_random
    assert r.systems == N_SYSTEMS
    assert r.compared["centroid"] >= 1000, r.summary("too few points")
    assert min(r.compared[m] for m in METHODS) >= 900, r.summary("too few points")
    assert r.empty >= 10, "the no-rule-fires path was hardly exercised"
    assert r.ambiguous <= 0.05 * r.compared["centroid"], r.summary("too many ambiguous maxima")


@pytest.mark.parametrize("method", METHODS)
def test_random_systems_match_skfuzzy(skfuzzy_random, method):
    r = skfuzzy_random
    assert not r.failures[method], "\n\n".join(r.failures[method])
    assert r.max_err[method] <= TOL


def test_random_systems_no_rule_fires_gives_default(skfuzzy_random):
    """Where scikit-fuzzy drops an output (no rule fired), torchdeform returns the variable's
    default (mid-range when None) for every defuzzifier."""
    assert not skfuzzy_random.empty_mismatch, "\n\n".join(skfuzzy_random.empty_mismatch[:3])


def test_skfuzzy_outputs_helper_is_the_control_api():
    """``skfuzzy_outputs`` (one aggregated set, five defuzzifiers) gives what
    ``ControlSystemSimulation.compute`` puts in ``sim.output`` for each ``defuzzify_method``."""
    n = 0
    for seed in range(6):
        spec = random_system(seed)
        for m in METHODS:
            sim, cons, used = build_skfuzzy(spec)
            for c in cons.values():
                c.defuzzify_method = m
            for x in random_points(spec, 10_000 + seed, 3):
                for v, xi in zip(spec.inputs, x):
                    if v.name in used:
                        sim.input[v.name] = float(xi)
                sim.compute()
                for v in spec.outputs:
                    got = skfuzzy_outputs(sim, cons[v.name], [m])
                    if got is None:
                        assert m in MAX_METHODS or v.name not in sim.output
                    else:
                        assert sim.output[v.name] == got[2][m]
                        n += 1
    assert n > 60


def test_ambiguity_detector():
    """The skip rule for mom/som/lom: only separate near-maxima count, not flat peaks."""
    u = np.linspace(0, 1, 11)
    assert not ambiguous_maximum(u, np.array([0, 0.2, 0.5, 0.5, 0.5, 0.2, 0, 0, 0.1, 0, 0]))
    assert not ambiguous_maximum(u, np.array([0, 0.2, 0.5, 0.5, 0.2, 0, 0.5, 0.5, 0.1, 0, 0]))  # exact tie
    assert ambiguous_maximum(u, np.array([0, 0.2, 0.5, 0.5, 0.2, 0, 0.49999, 0.49999, 0.1, 0, 0]))
    assert not ambiguous_maximum(u, np.array([0, 0.2, 0.5, 0.49999, 0.2, 0, 0.3, 0.1, 0.1, 0, 0]))


# =================================================================== 2. the tipping problem


def _tipping_torch(**kw):
    def abc(lo, hi):  # skfuzzy's automf(3): poor / average / good
        m = 0.5 * (lo + hi)
        return {"poor": Triangle(lo, lo, m), "average": Triangle(lo, m, hi), "good": Triangle(m, hi, hi)}

    quality, service = Variable("quality", (0, 10), abc(0, 10)), Variable("service", (0, 10), abc(0, 10))
    tip = Variable(
        "tip", (0, 25), {"low": Triangle(0, 0, 13), "medium": Triangle(0, 13, 25), "high": Triangle(13, 25, 25)}
    )
    rules = [
        "IF quality IS poor OR service IS poor THEN tip IS low",
        "IF service IS average THEN tip IS medium",
        "IF service IS good OR quality IS good THEN tip IS high",
    ]
    return MamdaniSystem("tipper", [quality, service], [tip], rules, **kw).double()


def _tipping_skfuzzy(fine: bool):
    """The tutorial's system ("Fuzzy Control Systems: The Tipping Problem"); ``fine``: universes
    of 2001 points instead of the tutorial's integers (its mom/som/lom live on the universe)."""
    q_u = np.linspace(0, 10, 2001) if fine else np.arange(0, 11, 1)
    t_u = np.linspace(0, 25, 2001) if fine else np.arange(0, 26, 1)
    quality, service = ctrl.Antecedent(q_u, "quality"), ctrl.Antecedent(q_u.copy(), "service")
    tip = ctrl.Consequent(t_u, "tip")
    quality.automf(3)
    service.automf(3)
    tip["low"] = fuzz.trimf(tip.universe, [0, 0, 13])
    tip["medium"] = fuzz.trimf(tip.universe, [0, 13, 25])
    tip["high"] = fuzz.trimf(tip.universe, [13, 25, 25])
    rules = [
        ctrl.Rule(quality["poor"] | service["poor"], tip["low"]),
        ctrl.Rule(service["average"], tip["medium"]),
        ctrl.Rule(service["good"] | quality["good"], tip["high"]),
    ]
    return ctrl.ControlSystemSimulation(ctrl.ControlSystem(rules)), tip


def _pl_centroid(xs, f):
    """Exact centroid of the piecewise-linear function through ``(xs, f(xs))`` (all kinks
    listed): per segment, integral of f = (b - a)(fa + fb)/2 and of y f = (b - a)(fa(2a + b) + fb(a + 2b))/6."""
    xs = np.asarray(xs, dtype=np.float64)
    fs = np.array([f(v) for v in xs])
    a, b, fa, fb = xs[:-1], xs[1:], fs[:-1], fs[1:]
    return np.sum((b - a) * (fa * (2 * a + b) + fb * (a + 2 * b)) / 6) / np.sum((b - a) * (fa + fb) / 2)


def test_tipping_tutorial_value():
    """Quality 6.5, service 9.8: 'average' service 0.04, 'good' 0.96, 'good' quality 0.3, so tip
    = max(min(0.04, medium), min(0.96, high)), kinks at 0.52, 13, 13.48, 24.52 -> exact centroid
    19.857759... The tutorial prints 19.847607: on its integer tip universe scikit-fuzzy inserts the
    cut points of each term but not the crossing of 'high' with the 0.04 plateau (13.48), and
    interpolates linearly over [13, 14]; that error (4e-4 of the range) is within the tolerance."""

    def tip(y):
        med = min(y / 13, (25 - y) / 12) if 0 <= y <= 25 else 0.0
        high = max(0.0, (y - 13) / 12)
        return max(min(0.04, med), min(0.96, high))

    exact = _pl_centroid([0, 0.52, 13, 13.48, 24.52, 25], tip)
    assert exact == pytest.approx(19.857759207, abs=1e-8)
    sim, _ = _tipping_skfuzzy(fine=False)
    sim.input["quality"], sim.input["service"] = 6.5, 9.8
    sim.compute()
    assert sim.output["tip"] == pytest.approx(19.847607361963192, abs=1e-9)
    ours = float(_tipping_torch().evaluate(quality=6.5, service=9.8)["tip"])  # default 1000 cells
    assert abs(ours - exact) <= 1e-5 * 25
    assert abs(ours - sim.output["tip"]) <= TOL * 25


@pytest.mark.parametrize("method", METHODS)
def test_tipping_grid(method, device):
    """mom/som/lom skip points where the maximum is reached in separate places (e.g. quality 10,
    service 0: 'low' and 'high' both fire at 1, peaks at 0 and 25, mom 12.5): the tutorial's peaks
    (0, 13, 25) are never cell midpoints (0 and 25 are the range ends), so torchdeform samples
    them at 1 - (h/2)/13 and 1 - (h/2)/12 and the grid, not the rule base, breaks the tie."""
    grid = np.linspace(0, 10, 13)
    Q, S = (a.ravel() for a in np.meshgrid(grid, grid))
    Q, S = np.r_[Q, 6.5, 3.3, 9.1], np.r_[S, 9.8, 7.7, 0.4]
    # torchdeform: the default 1000 cells for centroid / bisector, 3000 for the maxima (see top)
    ours = _tipping_torch(defuzzification=method, **({"resolution": TORCH_RES} if method in MAX_METHODS else {}))
    got = ours.to(device)(torch.tensor(np.stack([Q, S], 1), dtype=F64, device=device))[:, 0].cpu().numpy()
    sim, tip = _tipping_skfuzzy(fine=True)
    tip.defuzzify_method = method
    compared = 0
    for q, s, g in zip(Q, S, got):
        sim.input["quality"], sim.input["service"] = q, s
        sim.compute()
        if method in MAX_METHODS:
            u, mf, _ = CrispValueCalculator(tip, sim).find_memberships()
            if ambiguous_maximum(u, mf, 1e-3, ties=True):
                continue
        compared += 1
        assert abs(g - sim.output["tip"]) <= TOL * 25, (method, q, s, g, sim.output["tip"])
    assert compared >= 0.75 * len(Q)


# =================================================================== 3. other operators: numpy oracle

COMBOS = [
    dict(and_method="prod", or_method="probor", implication="prod", aggregation="sum"),
    dict(and_method="prod", or_method="probor", implication="prod", aggregation="probor"),
    dict(and_method="min", or_method="max", implication="prod", aggregation="max"),
    dict(and_method="prod", or_method="max", implication="min", aggregation="sum"),
    dict(and_method="min", or_method="probor", implication="min", aggregation="probor"),
]


@pytest.mark.parametrize("combo", COMBOS, ids=lambda c: "-".join(c.values()))
def test_operators_match_numpy_oracle(combo, device):
    """Product implication, sum/probor aggregation, prod AND, probor OR (and hedges, in half the
    systems) against the numpy evaluation + ``skfuzzy.defuzz`` on 2001-point universes."""
    t0 = time.perf_counter()
    res = Agreement()
    for seed in range(12):
        spec = random_system(500 + seed, hedges=seed % 2 == 1, methods=combo)
        X = random_points(spec, 600 + seed, 5)
        xt = torch.tensor(X, dtype=F64, device=device)
        ours = _ours_all_methods(build_torch(spec).to(device), xt)
        res.systems += 1
        for p, x in enumerate(X):
            res.points += 1
            sets = numpy_aggregate(spec, x)
            for o, v in enumerate(spec.outputs):
                u, mf = sets[v.name]
                if not mf.any():
                    res.empty += 1
                    assert all(ours[m][p, o] == v.fallback for m in METHODS), spec.describe()
                    continue
                ambiguous = ambiguous_maximum(u, mf, exact_rtol=0.0)
                res.ambiguous += ambiguous
                for m in METHODS:
                    if m in MAX_METHODS and ambiguous:
                        continue
                    a, b = float(ours[m][p, o]), float(fuzz.defuzz(u, mf, m))
                    res.record(m, abs(a - b) / v.width, _context(spec, x, v.name, {"torchdeform": a, "numpy": b}))
    res.seconds = time.perf_counter() - t0
    print("\n" + res.summary(f"numpy oracle {combo}"))
    for m in METHODS:
        assert not res.failures[m], "\n\n".join(res.failures[m])
    assert res.compared["centroid"] >= 60 and min(res.compared.values()) >= 50


# =================================================================== 4. hedges


def test_hedges_match_formulas():
    m = np.r_[
        0.0,
        1e-12,
        0.1,
        0.25,
        0.5 - 1e-12,
        0.5,
        0.5 + 1e-12,
        0.7,
        0.99,
        1.0,
        np.random.default_rng(0).uniform(0, 1, 200),
    ]
    t = torch.tensor(m, dtype=F64)
    for h in ("very", "somewhat", "extremely", "seldom", "not", "any"):
        np.testing.assert_allclose(apply_hedges(t, (h,)).numpy(), hedge(m, (h,)), rtol=0, atol=1e-14, err_msg=h)
    for hs in (("not", "very"), ("very", "not"), ("somewhat", "extremely"), ("seldom", "very", "not")):
        np.testing.assert_allclose(apply_hedges(t, hs).numpy(), hedge(m, hs), rtol=0, atol=1e-14, err_msg=str(hs))
    # spot values written out by hand: not very 0.5 = 0.75, very not 0.5 = 0.25, extremely 0.75 = 0.875
    assert float(apply_hedges(torch.tensor(0.5, dtype=F64), ("not", "very"))) == 0.75
    assert float(apply_hedges(torch.tensor(0.5, dtype=F64), ("very", "not"))) == 0.25
    assert float(apply_hedges(torch.tensor(0.75, dtype=F64), ("extremely",))) == 0.875
    assert float(apply_hedges(torch.tensor(0.125, dtype=F64), ("seldom",))) == 0.25


def test_hedges_in_rules_and_finite_gradients():
    """Hedged clauses fire at the hedged degree of the term, and the square roots keep finite
    gradients at degrees 0 and 1."""
    x = Variable("x", (0, 10), {"low": Trapezoid(0, 0, 2, 6), "high": Triangle(4, 10, 10)})
    y = Variable("y", (0, 1), {"a": Triangle(0, 0.5, 1)})
    hedges = [
        (),
        ("very",),
        ("somewhat",),
        ("extremely",),
        ("seldom",),
        ("not",),
        ("not", "very"),
        ("very", "very"),
        ("somewhat", "not"),
    ]
    rules = [f"IF x IS {' '.join(h + ('low',))} THEN y IS a" for h in hedges]
    rules += [f"IF x IS {' '.join(h + ('high',))} THEN y IS a" for h in hedges]
    fis = MamdaniSystem("hedges", [x], [y], rules).double().requires_grad_()
    X = torch.tensor(np.r_[np.linspace(-1, 11, 61), 0, 2, 4, 6, 10], dtype=F64)[:, None].requires_grad_()
    fire = fis.firing(X)
    low, high = (
        sk_membership("trapezoid", (0, 0, 2, 6), np.clip(X.detach().numpy()[:, 0], 0, 10)),
        sk_membership("triangle", (4, 10, 10), np.clip(X.detach().numpy()[:, 0], 0, 10)),
    )
    want = np.stack([hedge(low, h) for h in hedges] + [hedge(high, h) for h in hedges], 1)
    np.testing.assert_allclose(fire.detach().numpy(), want, atol=1e-14)
    fire.sum().backward()
    assert torch.isfinite(X.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in fis.parameters() if p.grad is not None)


# =================================================================== 5. membership functions


def _points(rng, corners, lo=-12.0, hi=12.0):
    c = np.asarray(corners, dtype=np.float64)
    return np.r_[rng.uniform(lo, hi, 300), c, np.nextafter(c, -np.inf), np.nextafter(c, np.inf), c - 1e-9, c + 1e-9]


@pytest.mark.parametrize(
    "case",
    [
        ("trapezoid", (-3.0, -1.0, 2.0, 5.0)),
        ("trapezoid", (-3.0, -3.0, 2.0, 5.0)),  # left shoulder a == b
        ("trapezoid", (-3.0, -1.0, 5.0, 5.0)),
        ("trapezoid", (-3.0, -3.0, 5.0, 5.0)),  # right shoulder, both
        ("trapezoid", (-3.0, 1.0, 1.0, 5.0)),
        ("trapezoid", (2.0, 2.0, 2.0, 2.0)),
        ("triangle", (-4.0, 0.5, 6.0)),
        ("triangle", (-4.0, -4.0, 6.0)),
        ("triangle", (-4.0, 6.0, 6.0)),
        ("triangle", (1.0, 1.0, 1.0)),
        ("triangle", (-10.5, -10.0, 11.0)),
        ("gaussian", (1.5, 2.5)),
        ("gaussian", (-7.0, 0.3)),
        ("gaussian", (2.0, -1.5)),  # sigma sign ignored
        ("bell", (2.0, 3.0, 1.0)),
        ("bell", (0.5, 1.0, -4.0)),
        ("bell", (4.0, 0.6, 0.0)),
        ("bell", (-2.0, 2.0, 1.0)),
        ("sigmoid", (1.0, 2.0)),
        ("sigmoid", (-3.0, -0.7)),
        ("sigmoid", (0.0, 25.0)),
    ],
    ids=str,
)
def test_membership_matches_skfuzzy(case):
    kind, params = case
    cls = {"trapezoid": Trapezoid, "triangle": Triangle, "gaussian": Gaussian, "bell": Bell, "sigmoid": Sigmoid}[kind]
    with default_dtype(F64):
        mf = cls(*params)
    corners = params if kind in ("trapezoid", "triangle") else params[:1] if kind != "bell" else params[2:]
    x = _points(np.random.default_rng(zlib.crc32(repr(case).encode())), corners)
    got = mf(torch.tensor(x, dtype=F64)).numpy()
    np.testing.assert_allclose(got, sk_membership(kind, params, x), rtol=0, atol=1e-13)


def test_membership_random_parameters_match_skfuzzy():
    rng = np.random.default_rng(42)
    for _ in range(200):
        kind = rng.choice(["trapezoid", "triangle", "gaussian", "bell", "sigmoid"])
        if kind in ("trapezoid", "triangle"):
            p = np.sort(np.round(rng.uniform(-10, 10, 4 if kind == "trapezoid" else 3), 1))  # rounding: ties
        elif kind == "gaussian":
            p = (rng.uniform(-10, 10), rng.uniform(0.1, 5))
        elif kind == "bell":
            p = (rng.uniform(0.1, 5), rng.uniform(0.3, 4), rng.uniform(-10, 10))
        else:
            p = (rng.uniform(-10, 10), rng.uniform(-5, 5))
        cls = {"trapezoid": Trapezoid, "triangle": Triangle, "gaussian": Gaussian, "bell": Bell, "sigmoid": Sigmoid}
        with default_dtype(F64):
            mf = cls[str(kind)](*p)
        x = _points(rng, p if kind in ("trapezoid", "triangle") else [])
        np.testing.assert_allclose(
            mf(torch.tensor(x, dtype=F64)).numpy(),
            sk_membership(str(kind), p, x),
            rtol=0,
            atol=1e-12,
            err_msg=f"{kind}{tuple(p)}",
        )


def test_membership_keeps_shape_and_rejects_bad_parameters():
    mf = Trapezoid(0.0, 2.0, 4.0, 6.0)
    assert mf(torch.zeros(2, 3, 4)).shape == (2, 3, 4)
    np.testing.assert_allclose(mf(torch.tensor([1.0, 3.0, 5.5])).numpy(), [0.5, 1.0, 0.25])
    for bad in (
        lambda: Trapezoid(0, 2, 1, 3),
        lambda: Triangle(3, 2, 1),
        lambda: Gaussian(0, 0),
        lambda: Bell(0, 1, 1),
        lambda: Trapezoid(0, 1, 2),
        lambda: Gaussian(0, math.nan),
    ):
        with pytest.raises(ConfigError):
            bad()


@pytest.mark.parametrize("aggregation", ["max", "sum"])
@pytest.mark.parametrize("method", ["centroid", "mom", "som", "lom"])
def test_singleton_outputs(aggregation, method, device):
    """Outputs made of singletons: centroid = weighted mean of the positions (weights: the
    aggregated degree of each singleton); mom/som/lom over the positions of largest weight."""
    x = Variable("x", (0, 10), {"lo": Trapezoid(0, 0, 2, 6), "mid": Triangle(2, 5, 8), "hi": Trapezoid(4, 8, 10, 10)})
    pos = {"large": 90.0, "small": 10.0, "medium": 45.0}  # deliberately unsorted
    y = Variable("y", (0, 100), {k: Singleton(v) for k, v in pos.items()})
    rules = [("lo", "small", 1.0), ("mid", "medium", 1.0), ("hi", "large", 1.0), ("mid", "small", 0.5)]
    fis = MamdaniSystem(
        "sing",
        [x],
        [y],
        [f"IF x IS {a} THEN y IS {b} WITH {w}" for a, b, w in rules],
        aggregation=aggregation,
        defuzzification=method,
    ).double()
    X = np.r_[np.linspace(0, 10, 41), 3.3, 6.9]
    got = fis.to(device)(torch.tensor(X, dtype=F64, device=device)[:, None])[:, 0].cpu().numpy()
    for xv, g in zip(X, got):
        w = dict.fromkeys(pos, 0.0)
        for a, b, wt in rules:
            deg = sk_membership(x.terms[a].kind, x.terms[a].values(), xv)[0] * wt
            w[b] = max(w[b], deg) if aggregation == "max" else w[b] + deg
        W, P = np.array(list(w.values())), np.array(list(pos.values()))
        if method == "centroid":
            want = (W @ P) / W.sum()
        else:
            top = P[np.isclose(W, W.max(), rtol=1e-12, atol=0)]
            want = {"mom": top.mean(), "som": top.min(), "lom": top.max()}[method]
        assert g == pytest.approx(want, abs=1e-12), (xv, w)


# =================================================================== 6. no rule fires


def _sparse(default=3.25, **kw):
    x = Variable("x", (0, 10), {"mid": Trapezoid(2, 3, 4, 5), "top": Gaussian(9.5, 3.0)})
    y = Variable("y", (0, 20), {"low": Triangle(0, 5, 10), "high": Triangle(10, 15, 20)}, default=default)
    z = Variable("z", (-4, 0), {"neg": Gaussian(-3, 1)})  # 'top' never vanishes: z always fires
    return MamdaniSystem("sparse", [x], [y, z], ["IF x IS mid THEN y IS high", "IF x IS top THEN z IS neg"], **kw)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(
    "ops",
    [{}, dict(and_method="prod", implication="prod", aggregation="sum"), dict(aggregation="probor")],
    ids=["minmax", "prodsum", "probor"],
)
def test_no_rule_fires_default_and_finite_gradients(method, ops):
    fis = _sparse(defuzzification=method, **ops).double().requires_grad_()
    X = torch.tensor([[8.0], [3.5], [0.0], [11.0]], dtype=F64, requires_grad=True)
    out = fis(X)
    assert out[0, 0] == 3.25 and out[2, 0] == 3.25 and out[3, 0] == 3.25  # y: explicit default
    assert float(out[1, 0].detach()) == pytest.approx(15.0, abs=1e-3 * 20)  # symmetric term 'high' (clip 1)
    assert torch.isfinite(out).all()
    if method in MAX_METHODS:  # piecewise constant: no graph at all
        assert not out.requires_grad
        return
    (gx,) = torch.autograd.grad(out[:, 0].sum(), X, retain_graph=True)  # y alone: no gradient where empty
    assert gx[0, 0] == 0 and gx[2, 0] == 0 and gx[3, 0] == 0
    out.sum().backward()
    assert torch.isfinite(X.grad).all()
    for name, p in fis.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name
    # default None: the middle of the range
    fis2 = _sparse(default=None, defuzzification=method, **ops).double()
    assert float(fis2(torch.tensor([[8.0]], dtype=F64))[0, 0]) == 10.0


def test_no_rule_fires_warn_and_error(device):
    X = torch.tensor([[3.5], [8.0]], device=device)
    with pytest.warns(EmptyOutputWarning, match="no rule fires for output y at x=8"):
        out = _sparse(on_empty="warn").to(device)(X)
    assert float(out[1, 0]) == 3.25
    with pytest.raises(NoRuleFiredError, match="x=8") as info:
        _sparse(on_empty="error").to(device)(X)
    assert isinstance(info.value, TorchdeformError)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _sparse(on_empty="warn").to(device)(torch.tensor([[3.5]], device=device))  # y fires; z ...
    with pytest.raises(ConfigError):
        _sparse(on_empty="ignore")


def test_firing_mass_is_the_area():
    """``defuzzify`` returns the area of the aggregated set: a triangle (0, 5, 10) clipped at
    0.5 has area (10 + 5) / 2 * 0.5 = 3.75; an empty set has mass 0."""
    h = 10 / 1000
    y = h * (torch.arange(1000, dtype=F64) + 0.5)
    tri = torch.clamp(torch.minimum(y / 5, (10 - y) / 5), 0, 1)
    agg = torch.stack([torch.minimum(tri, torch.tensor(0.5, dtype=F64)), torch.zeros_like(y)])
    value, mass = defuzzify(agg, y, h, "centroid")
    assert float(mass[0]) == pytest.approx(3.75, abs=1e-9) and float(mass[1]) == 0
    assert float(value[0]) == pytest.approx(5.0, abs=1e-12)


# =================================================================== 7. gradients


def _smooth(**kw):
    """Gaussian and bell terms only: with prod/probor/sum operators the outputs are smooth in the
    inputs and in every parameter (min/max have kinks where two degrees tie; trapezoids at their
    corners), so finite differences are valid."""
    x0 = Variable("x0", (0, 10), {"low": Gaussian(2, 1.5), "mid": Bell(2.0, 1.5, 5.0), "high": Gaussian(8, 2)})
    x1 = Variable("x1", (-1, 1), {"neg": Bell(0.6, 2.0, -1.0), "pos": Gaussian(0.8, 0.5)})
    y = Variable("y", (0, 50), {"small": Gaussian(10, 6), "medium": Bell(8, 1.5, 25), "large": Gaussian(40, 7)})
    z = Variable("z", (-5, 5), {"down": Bell(2, 1.2, -3), "up": Gaussian(3, 2)})
    rules = [
        "IF x0 IS low AND x1 IS neg THEN y IS small AND z IS down",
        "IF x0 IS mid OR x1 IS pos THEN y IS medium",
        "IF x0 IS very high THEN y IS large AND z IS up WITH 0.7",
        "IF x1 IS not neg AND x0 IS somewhat mid THEN z IS up",
    ]
    kw.setdefault("resolution", 400)
    return MamdaniSystem("smooth", [x0, x1], [y, z], rules, **kw).double()


SMOOTH_OPS = [
    dict(and_method="prod", or_method="probor", implication="prod", aggregation="sum"),
    dict(and_method="prod", or_method="probor", implication="prod", aggregation="probor"),
    dict(and_method="min", or_method="max", implication="min", aggregation="max"),
]


@pytest.mark.parametrize("method", ["centroid", "bisector"])
@pytest.mark.parametrize("ops", SMOOTH_OPS, ids=["prod-sum", "prod-probor", "min-max"])
def test_gradcheck_inputs_and_parameters(method, ops):
    """Finite differences in float64. min/max (last case) are only piecewise smooth: these seeded
    points are away from ties between degrees, and the grid cells (400) move the kinks of
    the clipped sets between cell midpoints far more than the step 1e-6."""
    fis = _smooth(defuzzification=method, **ops)
    g = torch.Generator().manual_seed(3)
    X = torch.stack(
        [0.5 + 9 * torch.rand(3, generator=g, dtype=F64), -0.9 + 1.8 * torch.rand(3, generator=g, dtype=F64)], 1
    ).requires_grad_()
    assert torch.autograd.gradcheck(fis, (X,), eps=1e-6, atol=1e-5, rtol=1e-4)
    names = [n for n, _ in fis.named_parameters()]
    params = tuple(p.detach().clone().requires_grad_() for _, p in fis.named_parameters())
    x = X.detach()

    def f(*ps):
        return functional_call(fis, dict(zip(names, ps)), (x,))

    assert torch.autograd.gradcheck(f, params, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_prod_sum_gives_every_parameter_a_gradient():
    """With prod/probor/sum every membership parameter of a used term gets a gradient (with
    min/max only the selected ones do, REFERENCE.md 3.5)."""
    fis = _smooth(**SMOOTH_OPS[0]).requires_grad_()
    fis(torch.tensor([[3.3, 0.2], [7.1, -0.4]], dtype=F64)).sum().backward()
    for name, p in fis.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and (p.grad != 0).all(), name


def test_corner_points_stay_ordered_for_any_raw():
    """``params`` is the running maximum of ``raw``: ordered whatever ``raw`` holds, and the
    membership is then that of the ordered corners (skfuzzy with ``np.maximum.accumulate``)."""
    g = np.random.default_rng(5)
    x = np.linspace(-20, 20, 401)
    for cls, kind, n in ((Trapezoid, "trapezoid", 4), (Triangle, "triangle", 3)):
        with default_dtype(F64):
            mf = cls(*range(n))
        for _ in range(100):
            raw = g.normal(0, 6, n)
            with torch.no_grad():
                mf.raw.copy_(torch.tensor(raw))
            p = mf.params.detach().numpy()
            assert (np.diff(p) >= 0).all()
            np.testing.assert_array_equal(p, np.maximum.accumulate(raw))
            mu = mf(torch.tensor(x, dtype=F64)).detach().numpy()
            np.testing.assert_allclose(mu, sk_membership(kind, p, x), atol=1e-13)
    # a large gradient step through a whole system keeps the order and finite outputs
    spec = random_system(11)
    fis = build_torch(spec, resolution=300).double().requires_grad_()
    X = torch.tensor(random_points(spec, 1, 16), dtype=F64)
    fis(X).sum().backward()
    with torch.no_grad():
        for p in fis.parameters():
            if p.grad is not None:
                p -= 1e3 * p.grad + torch.randn_like(p)
    for mfm in fis.modules():
        if isinstance(mfm, Trapezoid):
            assert (torch.diff(mfm.params) >= 0).all()
    assert torch.isfinite(fis(X)).all()


# =================================================================== 8. batching and dtypes


def _spec_with(n_in, n_out, start=0):
    seed = start
    while True:
        spec = random_system(seed)
        if len(spec.inputs) == n_in and len(spec.outputs) == n_out:
            return spec
        seed += 1


@pytest.mark.parametrize("method", METHODS)
def test_batch_shapes_and_chunks(method, device):
    spec = _spec_with(2, 2)
    fis = build_torch(spec, defuzzification=method, resolution=500).double().to(device)
    X = torch.tensor(random_points(spec, 3, 24), dtype=F64, device=device)
    out = fis(X)
    assert out.shape == (24, 2)
    assert torch.equal(fis(X.reshape(2, 3, 4, 2)), out.reshape(2, 3, 4, 2))
    assert fis(X[0]).shape == (2,)
    rows = torch.cat([fis(X[i : i + 1]) for i in range(24)])
    torch.testing.assert_close(rows, out, rtol=0, atol=1e-12)
    chunked = build_torch(spec, defuzzification=method, resolution=500, chunk=5).double().to(device)
    torch.testing.assert_close(chunked(X), out, rtol=0, atol=1e-12)
    named = fis.evaluate({v.name: X[:, k] for k, v in enumerate(spec.inputs)})
    for o, v in enumerate(spec.outputs):
        torch.testing.assert_close(named[v.name], out[:, o], rtol=0, atol=1e-12)
    with pytest.raises(ConfigError):
        fis(torch.zeros(4, 3, dtype=F64, device=device))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("ops", [{}] + COMBOS, ids=lambda c: "-".join(c.values()) or "min-max")
def test_sparsity_plan_gives_the_dense_result(method, ops, device):
    """The plan the compiled path uses skips groups that are zero on a run of cells; it must
    give the dense result (itself checked against scikit-fuzzy above) for every operator set,
    hedged consequents ("not" makes a term non-zero outside its support) and Gaussian/bell
    tails."""
    planned = 0
    for seed in range(40, 52):
        spec = random_system(seed, hedges=seed % 2 == 0)
        fis = build_torch(spec, defuzzification=method, resolution=400, **ops).double().to(device)
        plan = fis.sparsity_plan()
        for runs in plan:
            assert runs[0][0] == 0 and runs[-1][1] == 400  # the runs tile the grid
            assert all(a[1] == b[0] for a, b in itertools.pairwise(runs))
            planned += sum((b - a) * len(g) for a, b, g in runs)
        X = torch.tensor(random_points(spec, seed, 64), dtype=F64, device=device)
        dense, empty = fis.infer(X)
        sparse, empty_sparse = fis.infer(X, plan=plan)
        torch.testing.assert_close(sparse, dense, rtol=0, atol=1e-9)
        assert torch.equal(empty_sparse, empty)
    assert planned > 0


def test_sparsity_plan_skips_disjoint_terms():
    """Three trapezoids, neighbours overlapping: the plan visits one group where one term
    lives, two where two overlap, none where no term does."""
    x = Variable("x", (0, 1), {"a": Triangle(0, 0, 1), "b": Triangle(0, 1, 1)})
    y = Variable("y", (0, 10), {"lo": Trapezoid(0, 0, 2, 4), "mid": Trapezoid(3, 4, 5, 6), "hi": Trapezoid(5, 7, 8, 9)})
    fis = MamdaniSystem(
        "s", [x], [y], ["IF x IS a THEN y IS lo", "IF x IS b THEN y IS mid", "IF x IS b THEN y IS hi"], resolution=10
    ).double()
    (runs,) = fis.sparsity_plan()
    lo, mid, hi = (
        next(g for g, c in enumerate(fis._cons[0]) if c.term == y.index(t, key="")) for t in ("lo", "mid", "hi")
    )
    # cell midpoints 0.5, 1.5, ..., 9.5
    assert runs == ((0, 3, (lo,)), (3, 4, (lo, mid)), (4, 5, (mid,)), (5, 6, (mid, hi)), (6, 9, (hi,)), (9, 10, ()))


def test_compiled_rebuilds_the_plan_when_parameters_change(monkeypatch):
    """The compiled function's plan is made from the parameters; after they change (learning,
    load_state_dict) it must be rebuilt, not silently reused. torch.compile is replaced by the
    identity so that no compilation runs in the unit tests."""
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: fn)
    x = Variable("x", (0, 1), {"a": Triangle(0, 0, 1), "b": Triangle(0, 1, 1)})
    y = Variable("y", (0, 10), {"lo": Trapezoid(0, 0, 2, 4), "hi": Trapezoid(5, 7, 8, 9)})
    fis = MamdaniSystem("s", [x], [y], ["IF x IS a THEN y IS lo", "IF x IS b THEN y IS hi"]).double()
    f = fis.compiled(chunk=16)
    X = torch.linspace(0, 1, 21, dtype=F64)[:, None]
    torch.testing.assert_close(f(X), fis(X), rtol=0, atol=1e-9)
    with torch.no_grad():
        y.terms["lo"].raw.copy_(torch.tensor([0.0, 1.0, 6.0, 8.0]))  # 'lo' now reaches cells it did not
    torch.testing.assert_close(f(X), fis(X), rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_float32_matches_float64(method, device):
    """1e-4 of the range for centroid and bisector. mom/som/lom pick grid cells: a float32
    rounding may move them by one cell (range / resolution) where a plateau edge sits at a cell
    boundary, and they are compared on systems with piecewise-linear output terms only: a smooth
    peak is flat to float32 rounding over a band (|z| < (1e-6)^(1/2s) for a bell of slope s, 3% of
    the width at s = 2) that float64 resolves, which moves som/lom, and mom where peaks tie.
    Rows where an output's strongest rule fires below 1e-5 (float64) are skipped: there the result
    hangs on degrees that float32 cannot hold (e.g. "not" of a degree 1 - 3e-10 is 0 in float32,
    so no rule fires and the default is returned); for mom/som/lom also rows where the two
    strongest rules differ by less than 1e-5 (a tie in float32, not in float64)."""
    worst, compared, skipped = 0.0, 0, 0
    for seed in range(20, 32):
        spec = random_system(
            seed,
            output_kinds=("trapezoid", "triangle")
            if method in MAX_METHODS
            else ("trapezoid", "triangle", "gaussian", "bell"),
        )
        fis32 = build_torch(spec, torch.float32, defuzzification=method, resolution=1000).to(device)
        fis64 = build_torch(spec, torch.float64, defuzzification=method, resolution=1000).to(device)
        X = torch.tensor(random_points(spec, seed, 40), dtype=torch.float32, device=device)
        a, b = fis32(X).double(), fis64(X.double())
        fire = fis64.firing(X.double())
        for o, v in enumerate(spec.outputs):
            feeding = [k for k, r in enumerate(spec.rules) if any(c.var == v.name for c in r.cons)]
            ok = fire[:, feeding].amax(dim=1) >= 1e-5
            if method in MAX_METHODS:  # and near-ties of the two strongest rules: float32 merges them
                top2 = fire[:, feeding].topk(min(2, len(feeding)), dim=1).values
                gap = top2[:, 0] - top2[:, -1]
                ok &= (gap == 0) | (gap > 1e-5)
            skipped += int((~ok).sum())
            compared += int(ok.sum())
            err = ((a[ok, o] - b[ok, o]).abs() / v.width).max().item() if ok.any() else 0.0
            worst = max(worst, err)
            assert err <= 1e-4, (seed, v.name, spec.describe())
    print(f"\nfloat32 vs float64, {method}: {compared} compared, {skipped} skipped, max {worst:.2e} of the range")
    assert skipped <= 0.1 * compared


def test_dtype_changes_keep_range_end_shoulders():
    """A right shoulder ending at the range end (c == d == hi) holds inputs clipped to hi, also
    when the system was built in float32 and then made float64 (d = float32(11.16) < 11.16), or
    is fed float64 inputs: the clip bounds follow the corners' dtype. (Clipping to the exact
    11.16 > d dropped the degree to 0.)"""
    with default_dtype(torch.float32):
        x = Variable("x", (-0.3, 11.16), {"low": Trapezoid(-0.3, -0.3, 2, 5), "high": Trapezoid(7, 10, 11.16, 11.16)})
        y = Variable("y", (0, 1), {"a": Triangle(0, 0.5, 1)})
        fis = MamdaniSystem("shoulder", [x], [y], ["IF x IS high THEN y IS a", "IF x IS low THEN y IS a"])
    X = [[11.16], [20.0], [-0.3], [-5.0]]
    want = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])
    torch.testing.assert_close(fis.firing(torch.tensor(X)), want, rtol=0, atol=0)
    torch.testing.assert_close(fis.firing(torch.tensor(X, dtype=F64)), want.double(), rtol=0, atol=0)
    fis.double()
    torch.testing.assert_close(fis.firing(torch.tensor(X, dtype=F64)), want.double(), rtol=0, atol=0)
    torch.testing.assert_close(fis.float().firing(torch.tensor(X)), want, rtol=0, atol=0)


# =================================================================== 9. rule sentences


def test_parse_fields():
    r = Rule.parse("IF a IS very low OR b IS not somewhat high THEN y IS big AND z IS small WITH 0.25")
    assert r.antecedent == [Clause("a", "low", hedges=("very",)), Clause("b", "high", hedges=("not", "somewhat"))]
    assert r.consequent == [Clause("y", "big"), Clause("z", "small")]
    assert (r.connective, r.weight) == ("or", 0.25)
    r2 = Rule.parse("  if (a is Low) and (b is NOT high) then y is Big  ")
    assert r2.antecedent == [Clause("a", "Low"), Clause("b", "high", hedges=("not",))]
    assert (r2.connective, r2.weight, r2.consequent) == ("and", 1.0, [Clause("y", "Big")])


def test_parse_round_trip():
    rng = np.random.default_rng(9)
    n = 0
    for seed in range(60):
        spec = random_system(900 + seed, hedges=True)
        for r, text in zip(spec.rules, spec.sentences()):
            rule = Rule.parse(text)
            assert Rule.parse(str(rule)) == rule, text
            assert [(c.variable, c.term, c.hedges) for c in rule.antecedent] == [
                (c.var, c.term, c.hedges) for c in r.ante
            ]
            assert rule.weight == r.weight
            assert len(r.ante) == 1 or rule.connective == r.connective
            weird = Rule(rule.antecedent, rule.consequent, connective=rule.connective, weight=float(rng.uniform(0, 1)))
            assert Rule.parse(str(weird)) == weird, str(weird)  # any weight survives
            n += 1
    assert n > 200


@pytest.mark.parametrize(
    "text",
    [
        "",
        "x IS low THEN y IS big",
        "IF x IS low",
        "IF x low THEN y IS big",
        "IF x IS THEN y IS big",
        "IF x IS low THEN",
        "IF x IS low AND THEN y IS big",
        "IF x IS low THEN y IS big OR z IS small",
        "IF a IS low AND b IS high OR c IS mid THEN y IS big",
        "IF x IS bogus low THEN y IS big",
        "IF x IS low THEN y IS big WITH",
        "IF x IS low THEN y IS big WITH abc",
        "IF x IS low WITH 0.5 THEN y IS big",
        "IF x IS low THEN y IS big WITH 0.5 extra",
        "IF x IS low THEN y IS big WITH 1.5",
        "IF x IS low THEN y IS big WITH -0.1",
        "IF x IS low THEN y IS big WITH nan",
        "IF x IS low THEN y IS big AND y IS small",
        "IF x IS very THEN y IS big",
        "IF IF x IS low THEN y IS big",
    ],
)
def test_parse_errors_name_the_rule(text):
    with pytest.raises(ConfigError) as info:
        Rule.parse(text)
    assert text.strip() in str(info.value)


def test_system_rejects_unknown_names_with_the_rule():
    x = Variable("x", (0, 1), {"low": Triangle(0, 0, 1)})
    y = Variable("y", (0, 1), {"big": Triangle(0, 1, 1)})
    for bad in (
        "IF x IS high THEN y IS big",
        "IF w IS low THEN y IS big",
        "IF x IS low THEN q IS big",
        "IF x IS low THEN y IS small",
        "IF y IS big THEN y IS big",
    ):
        with pytest.raises(ConfigError, match="rule 1") as info:
            MamdaniSystem("s", [x], [y], [bad])
        assert bad in str(info.value)
