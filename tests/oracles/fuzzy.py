"""Independent oracles for the Mamdani engine tests (``tests/fuzzy/test_engine.py``).

Nothing here calls the inference code of torchdeform. Systems are described by plain
dataclasses (:class:`SystemSpec`) from which three things are built:

* the torchdeform system (:func:`build_torch`), from the rule *sentences* only;
* the same system in ``skfuzzy.control`` (:func:`build_skfuzzy`), with membership functions
  sampled by ``skfuzzy.membership`` on fine universes;
* a numpy Mamdani evaluation with any AND / OR / implication / aggregation
  (:func:`numpy_mamdani`), defuzzified by ``skfuzzy.defuzz``.

Grids. Every universe is ``np.linspace(lo, hi, GRID)`` (step ``range / 2000``). Every corner
point, peak and centre of a term lies on an *odd* point of that grid or on a range end. The
torchdeform systems use ``TORCH_RES = 3000`` cells, whose midpoints
``lo + (k + 1/2) range / 3000`` include every odd grid point (``j / 2000 = (k + 1/2) / 3000``
for ``j = (2k + 1) / 3``), so both engines sample the peaks of triangles, Gaussians and bells
at their exact top (degree 1). That matters for mean/smallest/largest of maximum: two rules
firing at the same level then tie in both engines. The remaining discretisation of
scikit-fuzzy (linear interpolation of Gaussian and bell terms between grid points, first and
last maximum located on its grid) is below ``range / 2000`` in position and about ``1e-5`` in
degree.
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass, field

import numpy as np
import skfuzzy as fuzz
import torch
from skfuzzy import control as ctrl
from skfuzzy.control.controlsystem import CrispValueCalculator

GRID = 2001  # points of every scikit-fuzzy / numpy universe (step range / 2000)
TORCH_RES = 3000  # torchdeform cells: their midpoints contain the odd points of GRID
KINDS_RANDOM = ("trapezoid", "triangle", "gaussian", "bell")


# ------------------------------------------------------------------ descriptions


@dataclass
class TermSpec:
    """One term: ``kind`` and parameters in torchdeform's order (see membership.py)."""

    name: str
    kind: str
    params: tuple

    def describe(self) -> str:
        return f"{self.name} = {self.kind}({', '.join(repr(float(p)) for p in self.params)})"


@dataclass
class VarSpec:
    name: str
    lo: float
    hi: float
    terms: list
    default: float | None = None

    @property
    def width(self) -> float:
        return self.hi - self.lo

    @property
    def universe(self) -> np.ndarray:
        return np.linspace(self.lo, self.hi, GRID)

    @property
    def fallback(self) -> float:
        """What torchdeform must return when no rule fires."""
        return 0.5 * (self.lo + self.hi) if self.default is None else self.default

    def term(self, name) -> TermSpec:
        return next(t for t in self.terms if t.name == name)

    def describe(self) -> str:
        d = "" if self.default is None else f" default={self.default!r}"
        lines = [f"{self.name} in [{self.lo!r}, {self.hi!r}]{d}:"]
        lines += [f"    {t.describe()}" for t in self.terms]
        return "\n".join(lines)


@dataclass
class ClauseSpec:
    var: str
    term: str
    hedges: tuple = ()  # outermost first, as in the sentence ("not", "very")

    def sentence(self) -> str:
        return " ".join([self.var, "IS", *self.hedges, self.term])


@dataclass
class RuleSpec:
    ante: list
    cons: list  # [ClauseSpec] (no hedges on outputs here)
    connective: str = "and"
    weight: float = 1.0

    def sentence(self) -> str:
        s = (
            f"IF {f' {self.connective.upper()} '.join(c.sentence() for c in self.ante)} "
            f"THEN {' AND '.join(c.sentence() for c in self.cons)}"
        )
        return s + (f" WITH {self.weight!r}" if self.weight != 1.0 else "")


@dataclass
class SystemSpec:
    name: str
    inputs: list
    outputs: list
    rules: list
    methods: dict = field(default_factory=dict)  # and_method, or_method, implication, aggregation

    def var(self, name) -> VarSpec:
        return next(v for v in self.inputs + self.outputs if v.name == name)

    def sentences(self) -> list:
        return [r.sentence() for r in self.rules]

    def describe(self) -> str:
        m = ", ".join(f"{k}={v}" for k, v in self.methods.items()) or "min/max/min/max"
        lines = [f"system {self.name} ({m})", "inputs:"]
        lines += ["  " + v.describe().replace("\n", "\n  ") for v in self.inputs]
        lines += ["outputs:"] + ["  " + v.describe().replace("\n", "\n  ") for v in self.outputs]
        lines += ["rules:"] + [f"  {k + 1}. {s}" for k, s in enumerate(self.sentences())]
        return "\n".join(lines)


# ------------------------------------------------------------------ membership (scikit-fuzzy)


def sk_membership(kind: str, params, x) -> np.ndarray:
    """Degrees from ``skfuzzy.membership`` for a term given in torchdeform's parameter order."""
    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    p = [float(v) for v in params]
    if kind == "trapezoid":
        return fuzz.trapmf(x, p)
    if kind == "triangle":
        return fuzz.trimf(x, p)
    if kind == "gaussian":
        return fuzz.gaussmf(x, p[0], p[1])
    if kind == "bell":
        return fuzz.gbellmf(x, p[0], p[1], p[2])
    if kind == "sigmoid":
        return fuzz.sigmf(x, p[0], p[1])
    raise ValueError(kind)


HEDGE_FORMULAS = {  # REFERENCE.md 3.4 (fuzzylite's definitions), written out in numpy
    "very": lambda m: m**2,
    "somewhat": np.sqrt,
    "extremely": lambda m: np.where(m <= 0.5, 2 * m**2, 1 - 2 * (1 - m) ** 2),
    "seldom": lambda m: np.where(m <= 0.5, np.sqrt(m / 2), 1 - np.sqrt((1 - m) / 2)),
    "not": lambda m: 1 - m,
    "any": np.ones_like,
}


def hedge(m, hedges) -> np.ndarray:
    m = np.asarray(m, dtype=np.float64)
    for h in reversed(tuple(hedges)):
        m = HEDGE_FORMULAS[h](m)
    return m


# ------------------------------------------------------------------ random systems


def _odd(j: int) -> int:
    """Nearest odd grid index inside ``[1, GRID - 2]``."""
    j = int(min(max(j, 1), GRID - 2))
    return j if j % 2 else (j + 1 if j + 1 <= GRID - 2 else j - 1)


def random_terms(rng, lo, hi, n, *, output: bool, kinds=KINDS_RANDOM) -> list:
    """``n`` terms spread over ``[lo, hi]``, corners on odd grid points (or the range ends)."""
    u = np.linspace(lo, hi, GRID)
    spacing = (GRID - 1) / n  # in grid steps
    centres = np.sort(rng.uniform(0.05, 0.95, n)) * (GRID - 1)
    terms = []
    for i, c in enumerate(centres):
        kind = str(rng.choice(kinds))
        name = f"{kind[:4]}{i}"
        half_l = max(30, int(spacing * rng.uniform(0.6, 1.8)))
        half_r = max(30, int(spacing * rng.uniform(0.6, 1.8)))
        jc = _odd(int(c))
        if kind == "triangle":
            a = u[_odd(jc - half_l)] if jc - half_l >= 1 else u[0]
            c3 = u[_odd(jc + half_r)] if jc + half_r <= GRID - 2 else u[-1]
            params = (a, u[jc], c3)
        elif kind == "trapezoid":
            top = int(spacing * rng.uniform(0.0, 0.5))
            jb, jc2 = jc, _odd(jc + top)
            a = u[_odd(jb - half_l)] if jb - half_l >= 1 else u[0]
            d = u[_odd(jc2 + half_r)] if jc2 + half_r <= GRID - 2 else u[-1]
            a = min(a, u[jb])
            d = max(d, u[jc2])
            b, cc = u[jb], u[jc2]
            if i == 0 and rng.uniform() < 0.4:  # left shoulder at the range end
                a = b = u[0]
            if i == n - 1 and rng.uniform() < 0.4:  # right shoulder at the range end
                cc = d = u[-1]
            params = (a, b, cc, d)
        elif kind == "gaussian":
            params = (u[jc], (hi - lo) / n * rng.uniform(0.35, 0.9))
        else:  # bell: width, slope, centre
            slope = rng.uniform(1.0, 2.0) if output else rng.uniform(1.0, 3.0)
            params = ((hi - lo) / n * rng.uniform(0.35, 0.9), slope, u[jc])
        terms.append(TermSpec(name, kind, tuple(float(p) for p in params)))
    return terms


def random_range(rng):
    width = float(np.round(10 ** rng.uniform(0, 2), 2))
    lo = float(np.round(width * rng.uniform(-2, 2), 2))
    return lo, float(np.round(lo + width, 2))


def random_system(seed: int, *, n_rules=(2, 9), hedges=False, methods=None, output_kinds=KINDS_RANDOM) -> SystemSpec:
    """A random Mamdani system: 1-3 inputs, 1-2 outputs, 2-7 terms per variable, rules with
    AND or OR over 1-3 inputs (some clauses negated, or random hedges), weights, 1-2
    consequents. Terms: trapezoid, triangle, Gaussian, bell (outputs: ``output_kinds``)."""
    rng = np.random.default_rng(seed)
    n_in, n_out = int(rng.integers(1, 4)), int(rng.integers(1, 3))
    inputs, outputs = [], []
    for i in range(n_in):
        lo, hi = random_range(rng)
        inputs.append(VarSpec(f"x{i}", lo, hi, random_terms(rng, lo, hi, int(rng.integers(2, 8)), output=False)))
    for o in range(n_out):
        lo, hi = random_range(rng)
        default = None if rng.uniform() < 0.5 else float(np.round(lo + (hi - lo) * rng.uniform(0, 1), 3))
        outputs.append(
            VarSpec(
                f"y{o}",
                lo,
                hi,
                random_terms(rng, lo, hi, int(rng.integers(2, 8)), output=True, kinds=output_kinds),
                default,
            )
        )
    rules = []
    for _ in range(int(rng.integers(*n_rules))):
        k = int(rng.integers(1, min(3, n_in) + 1))
        ante = []
        for v in [inputs[j] for j in rng.permutation(n_in)[:k]]:
            h = ()
            if hedges:
                h = tuple(rng.choice(["very", "somewhat", "extremely", "seldom", "not"], size=int(rng.integers(0, 3))))
            elif rng.uniform() < 0.15:
                h = ("not",)
            ante.append(ClauseSpec(v.name, v.terms[int(rng.integers(len(v.terms)))].name, h))
        outs = [outputs[j] for j in rng.permutation(n_out)[: 1 if n_out == 1 or rng.uniform() < 0.6 else 2]]
        cons = [ClauseSpec(v.name, v.terms[int(rng.integers(len(v.terms)))].name) for v in outs]
        weight = 1.0 if rng.uniform() < 0.7 else float(np.round(rng.uniform(0.2, 0.95), 2))
        rules.append(RuleSpec(ante, cons, "or" if rng.uniform() < 0.4 else "and", weight))
    for v in outputs:  # every output in at least one rule
        if not any(c.var == v.name for r in rules for c in r.cons):
            r = rules[int(rng.integers(len(rules)))]
            r.cons = list(r.cons) + [ClauseSpec(v.name, v.terms[0].name)]
    return SystemSpec(f"random{seed}", inputs, outputs, rules, dict(methods or {}))


def random_points(spec: SystemSpec, seed: int, n: int) -> np.ndarray:
    """``(n, n_inputs)`` inputs, a few a little outside the ranges (both engines clip)."""
    rng = np.random.default_rng(seed)
    cols = [rng.uniform(v.lo - 0.05 * v.width, v.hi + 0.05 * v.width, n) for v in spec.inputs]
    return np.stack(cols, axis=1)


# ------------------------------------------------------------------ builders


@contextlib.contextmanager
def default_dtype(dtype):
    """Create modules in ``dtype``: parameters of membership functions are made in the default
    dtype, and ``.double()`` afterwards would keep them rounded to float32."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(old)


def build_torch(spec: SystemSpec, dtype=torch.float64, **kwargs):
    """The torchdeform system, from the rule sentences, built in ``dtype``."""
    from torchdeform.fuzzy import MamdaniSystem, Variable
    from torchdeform.fuzzy.membership import make

    def var(v):
        return Variable(v.name, (v.lo, v.hi), {t.name: make(t.kind, *t.params) for t in v.terms}, default=v.default)

    opts = dict(spec.methods)
    opts.setdefault("resolution", TORCH_RES)
    opts.update(kwargs)
    with default_dtype(dtype):
        return MamdaniSystem(
            spec.name, [var(v) for v in spec.inputs], [var(v) for v in spec.outputs], spec.sentences(), **opts
        )


def build_skfuzzy(spec: SystemSpec):
    """``(ControlSystemSimulation, {output name: Consequent}, used input names)``; min AND
    (fmin), max OR (fmax), min implication, max accumulation (scikit-fuzzy's defaults)."""
    assert not spec.methods or spec.methods == {
        "and_method": "min",
        "or_method": "max",
        "implication": "min",
        "aggregation": "max",
    }
    used = {c.var for r in spec.rules for c in r.ante}
    ants = {}
    for v in spec.inputs:
        if v.name in used:
            a = ctrl.Antecedent(v.universe, v.name)
            for t in v.terms:
                a[t.name] = sk_membership(t.kind, t.params, a.universe)
            ants[v.name] = a
    cons = {}
    for v in spec.outputs:
        c = ctrl.Consequent(v.universe, v.name, defuzzify_method="mom")  # compute() defuzzifies: cheaply
        for t in v.terms:
            c[t.name] = sk_membership(t.kind, t.params, c.universe)
        cons[v.name] = c
    rules = []
    for r in spec.rules:
        terms = []
        for cl in r.ante:
            assert cl.hedges in ((), ("not",)), "scikit-fuzzy knows only NOT (~)"
            t = ants[cl.var][cl.term]
            terms.append(~t if cl.hedges else t)
        ante = functools.reduce((lambda a, b: a & b) if r.connective == "and" else (lambda a, b: a | b), terms)
        out = [cons[cl.var][cl.term] % r.weight if r.weight != 1.0 else cons[cl.var][cl.term] for cl in r.cons]
        rules.append(ctrl.Rule(ante, out))
    sim = ctrl.ControlSystemSimulation(ctrl.ControlSystem(rules))
    return sim, cons, sorted(used)


def skfuzzy_outputs(sim, consequent, methods):
    """After ``sim.compute()``: ``(universe, aggregated set, {method: crisp value})`` of one
    consequent, or ``None`` where scikit-fuzzy drops the output (no rule fired).

    This is ``CrispValueCalculator.defuzz`` (what ``compute`` and ``defuzz_consequents`` call)
    with the aggregated set built once for all methods: ``find_memberships`` (scikit-fuzzy's
    upsampled universe with the cut points inserted, min implication, max accumulation), then
    ``skfuzzy.defuzz``; no term memberships or a zero set (centroid/bisector raise
    EmptyMembershipError) is what makes ``sim.output`` lack the output."""
    u, mf, term_mfs = CrispValueCalculator(consequent, sim).find_memberships()
    if not term_mfs or mf.sum() == 0:
        return None
    return u, mf, {m: float(fuzz.defuzz(u, mf, m)) for m in methods}


# ------------------------------------------------------------------ numpy Mamdani


def _tnorm(a, b, method):
    return np.fmin(a, b) if method == "min" else a * b


def _snorm(a, b, method):
    if method == "max":
        return np.fmax(a, b)
    if method == "sum":
        return a + b
    return a + b - a * b


def numpy_aggregate(spec: SystemSpec, x) -> dict:
    """``{output: (universe, aggregated set)}`` at one input point ``x`` (``(n_inputs,)``),
    evaluated term by term in numpy: exact input degrees (``skfuzzy.membership`` at the clipped
    input), AND/OR/implication/aggregation from ``spec.methods`` (defaults min/max/min/max)."""
    m = {"and_method": "min", "or_method": "max", "implication": "min", "aggregation": "max", **spec.methods}
    xin = {v.name: float(np.clip(xi, v.lo, v.hi)) for v, xi in zip(spec.inputs, x)}
    fire = []
    for r in spec.rules:
        deg = None
        for cl in r.ante:
            t = spec.var(cl.var).term(cl.term)
            d = hedge(sk_membership(t.kind, t.params, xin[cl.var])[0], cl.hedges)
            if deg is None:
                deg = d
            elif r.connective == "and":
                deg = _tnorm(deg, d, m["and_method"])
            else:
                deg = _snorm(deg, d, m["or_method"])
        fire.append(float(deg) * r.weight)
    out = {}
    for v in spec.outputs:
        u = v.universe
        agg = None
        for r, alpha in zip(spec.rules, fire):
            for cl in r.cons:
                if cl.var != v.name:
                    continue
                t = v.term(cl.term)
                implied = _tnorm(alpha, hedge(sk_membership(t.kind, t.params, u), cl.hedges), m["implication"])
                agg = implied if agg is None else _snorm(agg, implied, m["aggregation"])
        out[v.name] = (u, np.zeros_like(u) if agg is None else agg)
    return out


# ------------------------------------------------------------------ maxima


def ambiguous_maximum(u, mf, rel: float = 1e-4, *, ties: bool = False, exact_rtol: float = 1e-14) -> bool:
    """True when mean/smallest/largest of maximum of the set ``mf`` on ``u`` are not well
    defined at the precision of the engines, i.e. when they jump under perturbations of the
    degrees that are below the engines' discretisation or rounding (scikit-fuzzy compares float
    equality on its universe; torchdeform treats degrees within ``1e-12`` (float64) of the top
    as ties, and samples other points):

    * a separate stretch of the set lies within ``rel`` (relative) of the top without reaching
      it (scikit-fuzzy interpolates Gaussian/bell inputs: ~1e-5 in degree), or
    * the smallest / largest / mean point within ``1e-9`` of the top differ from those exactly at
      the top by more than ``2.5e-4`` of the range (a top that is flat up to
      rounding, e.g. a sum of two plateaus plus the 1e-16 tail of a Gaussian);
    * ``ties=True``: also when the top is reached in two or more separate stretches (for terms
      whose peaks the torchdeform grid cannot sample exactly).

    "The top" is ``mf >= max * (1 - exact_rtol)``: 1e-14 for scikit-fuzzy's upsampled sets (its
    inserted cut points may sit an ulp below the cut), 0 for sets defuzzified by ``==`` directly.
    """
    order = np.argsort(u, kind="stable")
    u, mf = np.asarray(u)[order], np.asarray(mf)[order]
    top = mf.max()
    if top <= 0:
        return False
    near = mf >= top * (1 - rel)
    exact = mf >= top * (1 - exact_rtol)
    edges = np.diff(np.concatenate([[0], near.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    if ties and len(starts) > 1:
        return True
    if any(not exact[s:e].any() for s, e in zip(starts, ends)):
        return True
    flat, ex = u[mf >= top * (1 - 1e-9)], u[exact]
    jump = max(abs(flat.min() - ex.min()), abs(flat.max() - ex.max()), abs(flat.mean() - ex.mean()))
    return jump > 2.5e-4 * (u[-1] - u[0])


def top_stretches(u, mf) -> list:
    """``[(start, end), ...]``: the separate stretches of ``u`` where ``mf`` reaches its top (up
    to rounding), from the first to the last point of each."""
    order = np.argsort(u, kind="stable")
    u, mf = np.asarray(u)[order], np.asarray(mf)[order]
    at = (mf >= mf.max() * (1 - 1e-14)).astype(np.int8)
    edges = np.diff(np.concatenate([[0], at, [0]]))
    return [(u[s], u[e - 1]) for s, e in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))]


def mean_of_maximum(stretches) -> float:
    """The mean of the maximising set: the length-weighted mean of the stretch centres (the
    continuous definition; stretches of length zero count only when all are points)."""
    a, b = np.array(stretches, dtype=np.float64).T
    if (b - a).sum() == 0:
        return float(a.mean())
    return float(np.sum(0.5 * (a + b) * (b - a)) / np.sum(b - a))
