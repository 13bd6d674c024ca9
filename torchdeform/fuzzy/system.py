"""Mamdani inference: batched, differentiable, CPU and CUDA.

For each row of crisp inputs ``x`` (shape ``(N, n_inputs)``):

1. **fuzzify**: every input term's degree, hedges applied per clause;
2. **fire**: each rule's degree = its clauses folded with the AND method (a t-norm) or the OR
   method (an s-norm), times the rule weight;
3. **imply**: each consequent term (hedges applied) combined with its rule's degree by the
   implication (a t-norm: ``min`` clips, ``prod`` scales);
4. **aggregate** per output: the implied sets folded with the aggregation (an s-norm, or the
   unbounded ``sum``), one rule at a time;
5. **defuzzify** per output: ``centroid``, ``bisector``, ``mom``, ``som`` or ``lom``.

Operators (``a``, ``b`` degrees in ``[0, 1]``); the long names are those of Octave's
fuzzy-logic-toolkit, ``prod``/``probor`` MATLAB's:

======================  =====================================  ========================
name                    ``T(a, b)`` / ``S(a, b)``               allowed as
======================  =====================================  ========================
``min``                 ``min(a, b)``                          AND, implication
``prod``                ``a b``                                AND, implication
``algebraic_product``   ``a b`` (same as ``prod``)             AND, implication
``bounded_difference``  ``max(0, a + b - 1)`` (Lukasiewicz)    AND, implication
``drastic_product``     ``min(a, b)`` if ``max(a, b) = 1``,    AND, implication
                        else 0
``einstein_product``    ``a b / (2 - (a + b - a b))``          AND, implication
``hamacher_product``    ``a b / (a + b - a b)``; 0 at (0, 0)   AND, implication
``max``                 ``max(a, b)``                          OR, aggregation
``probor``              ``a + b - a b``                        OR, aggregation
``algebraic_sum``       ``a + b - a b`` (same as ``probor``)   OR, aggregation
``bounded_sum``         ``min(1, a + b)``                      OR, aggregation
``drastic_sum``         ``max(a, b)`` if ``min(a, b) = 0``,    OR, aggregation
                        else 1
``einstein_sum``        ``(a + b) / (1 + a b)``                OR, aggregation
``hamacher_sum``        ``(a + b - 2 a b) / (1 - a b)``;       OR, aggregation
                        1 at (1, 1)
``sum``                 ``a + b`` (not bounded by 1)           aggregation
======================  =====================================  ========================

The t-norms (AND, implication) have 1 as neutral element and the s-norms (OR, aggregation) 0,
so a clause list or a set of rules is folded pairwise, left to right. Octave's toolkit takes
any function name for any of the four methods; here a t-norm is refused as OR method or
aggregation and an s-norm as AND method or implication (:class:`~torchdeform.errors.ConfigError`
saying which kind it is): Octave aggregates over every rule, the zero sets of rules that do
not fire included, so a t-norm aggregation is 0 almost everywhere. For three or more operands
the drastic operators are folded pairwise (the associative n-ary drastic product and sum);
Octave's own n-ary forms differ there (its ``drastic_sum`` of a list containing a 0 is the
list's maximum). Every operator is differentiable wherever it is smooth: the Hamacher
quotients take their limits at 0/0 with safe denominators (finite gradients there), the
drastic ones are piecewise (``torch.where``).

``wtaver`` and ``wtsum`` (Sugeno defuzzification, :data:`SUGENO_DEFUZZIFIERS`) are refused
by :class:`MamdaniSystem` with a :class:`~torchdeform.errors.ConfigError`: the engine is
Mamdani only.

Output sets live on a grid of ``resolution`` cells over the output range (midpoints), so the
centroid is the midpoint rule: for the piecewise-linear sets of typical tissue rule bases its
error is below ``1e-5`` of the range at the default 1000 cells (checked against
scikit-fuzzy's exact piecewise-linear centroid in the tests); a side steeper than one cell (a
vertical side inside the range, or a set clipped at a tiny degree) can move it by up to about a
quarter cell. mom/som/lom are located to one cell. Outputs whose terms are all
singletons are defuzzified over the singleton positions instead (weighted mean for
``centroid``).

When no rule fires for a row and output (zero firing mass), that output takes the output
variable's ``default``; ``on_empty="warn"`` also warns, ``"error"`` raises
:class:`~torchdeform.errors.NoRuleFiredError` instead. Gradients stay finite there.

With ``max`` aggregation, rules that share a consequent term (and its hedges) are merged first
(the maximum of their degrees), so the grid work grows with the number of distinct consequent
terms, not with the number of rules. This is exact for every implication: a t-norm is
non-decreasing in the rule degree, so ``T(max(a1, a2), m) = max(T(a1, m), T(a2, m))``, and
``max`` is idempotent. Every other aggregation is applied per rule.

Example:
    >>> from torchdeform.fuzzy import MamdaniSystem, Variable, Trapezoid, Triangle
    >>> service = Variable("service", (0, 10), {"poor": Triangle(0, 0, 5), "good": Triangle(5, 10, 10)})
    >>> tip = Variable("tip", (0, 25), {"low": Triangle(0, 0, 13), "high": Triangle(13, 25, 25)})
    >>> fis = MamdaniSystem("tipper", [service], [tip],
    ...                     ["IF service IS poor THEN tip IS low", "IF service IS good THEN tip IS high"])
    >>> round(float(fis.evaluate(service=9.0)["tip"]), 2)
    20.87
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import nn

from ..checks import check_memory
from ..errors import ConfigError, NoRuleFiredError
from .membership import apply_hedges
from .rules import Rule

__all__ = [
    "AND_METHODS",
    "OR_METHODS",
    "IMPLICATIONS",
    "AGGREGATIONS",
    "DEFUZZIFIERS",
    "SUGENO_DEFUZZIFIERS",
    "TNORMS",
    "SNORMS",
    "ON_EMPTY",
    "EmptyOutputWarning",
    "ResolutionWarning",
    "MamdaniSystem",
    "defuzzify",
]


def _min(a, b):
    return torch.minimum(a, b)


def _max(a, b):
    return torch.maximum(a, b)


def _product(a, b):
    return a * b


def _probor(a, b):
    return a + b - a * b


def _add(a, b):
    return a + b


def _bounded_difference(a, b):
    return (a + b - 1.0).clamp_min(0.0)


def _bounded_sum(a, b):
    return (a + b).clamp_max(1.0)


def _drastic_product(a, b):
    return torch.where(torch.maximum(a, b) >= 1.0, torch.minimum(a, b), 0.0)


def _drastic_sum(a, b):
    return torch.where(torch.minimum(a, b) <= 0.0, torch.maximum(a, b), 1.0)


def _einstein_product(a, b):
    return a * b / (2.0 - (a + b - a * b))  # denominator >= 1 on [0, 1]


def _einstein_sum(a, b):
    return (a + b) / (1.0 + a * b)  # denominator >= 1 on [0, 1]


def _hamacher_product(a, b):
    den = a + b - a * b  # >= max(a, b) on [0, 1], also rounded; 0 only at (0, 0), where the limit is 0
    ok = den > 0
    return torch.where(ok, a * b / torch.where(ok, den, 1.0), 0.0)


def _hamacher_sum(a, b):
    # (a + b - 2ab) / (1 - ab), written as its dual 1 - hamacher_product(1 - a, 1 - b): the same
    # number, without the cancellation of 1 - ab near (1, 1), where the limit is 1
    return 1.0 - _hamacher_product(1.0 - a, 1.0 - b)


#: t-norms: AND methods and implications (name -> binary operator on degree tensors, broadcasting)
TNORMS = {
    "min": _min,
    "prod": _product,
    "algebraic_product": _product,
    "bounded_difference": _bounded_difference,
    "drastic_product": _drastic_product,
    "einstein_product": _einstein_product,
    "hamacher_product": _hamacher_product,
}
#: s-norms: OR methods and aggregations
SNORMS = {
    "max": _max,
    "probor": _probor,
    "algebraic_sum": _probor,
    "bounded_sum": _bounded_sum,
    "drastic_sum": _drastic_sum,
    "einstein_sum": _einstein_sum,
    "hamacher_sum": _hamacher_sum,
}
#: aggregations: the s-norms and the unbounded ``sum``
_AGGREGATORS = {"max": _max, "sum": _add, **SNORMS}

AND_METHODS = tuple(TNORMS)
OR_METHODS = tuple(SNORMS)
IMPLICATIONS = tuple(TNORMS)
AGGREGATIONS = tuple(_AGGREGATORS)
DEFUZZIFIERS = ("centroid", "bisector", "mom", "som", "lom")
#: Sugeno defuzzification methods (weighted average, weighted sum): refused, the engine is Mamdani only
SUGENO_DEFUZZIFIERS = ("wtaver", "wtsum")
ON_EMPTY = ("default", "warn", "error")


class EmptyOutputWarning(UserWarning):
    """No rule fired for some input rows; their output took the variable's default."""


class ResolutionWarning(UserWarning):
    """An output term narrower than the defuzzification cells: sampled there it counts little or nothing."""


def _check_method(key: str, value, allowed: tuple, what: str = "") -> None:
    """Refuse a method outside ``allowed``, saying what kind of operator was given instead."""
    if value in allowed:
        return
    expected = f"one of {', '.join(allowed)}" + (f" ({what})" if what else "")
    if not isinstance(value, str):
        pass
    elif value in SUGENO_DEFUZZIFIERS:
        expected += (
            f"; Sugeno defuzzification ({value}: weighted {'average' if value == 'wtaver' else 'sum'} "
            "of rule outputs) is not supported: the engine is Mamdani only"
        )
    elif value in TNORMS:
        expected += f"; {value} is a t-norm (an AND method or implication)"
    elif value in _AGGREGATORS:
        kind = "an s-norm (an OR method or aggregation)" if value in SNORMS else "unbounded (an aggregation only)"
        expected += f"; {value} is {kind}"
    raise ConfigError(key, expected, got=value)


@dataclass(frozen=True)
class _Consequent:
    """One implied set of an output: rules (indices) feeding it and the term with hedges."""

    rules: tuple
    term: int
    hedges: tuple


class MamdaniSystem(nn.Module):
    """A Mamdani fuzzy system.

    Args:
        name: a name (shown by ``torchdeform fuzzy show``, written to ``.fis``).
        inputs: input :class:`Variable` s, in order (the column order of ``x``).
        outputs: output :class:`Variable` s, in order.
        rules: :class:`Rule` s or rule sentences (``"IF a IS low THEN y IS high"``).
        and_method: a t-norm (:data:`AND_METHODS`: ``"min"``, ``"prod"``, Octave's
            ``"einstein_product"`` ...; see the module docstring).
        or_method: an s-norm (:data:`OR_METHODS`: ``"max"``, ``"probor"``, ``"bounded_sum"`` ...).
        implication: a t-norm (:data:`IMPLICATIONS`): ``"min"`` clips, ``"prod"`` scales.
        aggregation: an s-norm or ``"sum"`` (:data:`AGGREGATIONS`).
        defuzzification: ``"centroid"``, ``"bisector"``, ``"mom"``, ``"som"`` or ``"lom"``
            (``"wtaver"``/``"wtsum"``, Sugeno's, are refused).
        resolution: grid cells per output range (midpoint rule).
        on_empty: what happens when no rule fires for a row: ``"default"`` (the output's
            default), ``"warn"`` (default and an :class:`EmptyOutputWarning`) or ``"error"``.
        chunk: rows evaluated at once (bounds memory at ``chunk * resolution`` per output).

    Call it with ``x`` of shape ``(N, n_inputs)`` (or ``(..., n_inputs)``) to get
    ``(N, n_outputs)`` (``(..., n_outputs)``), or use :meth:`evaluate` with names.
    Parameters (membership-function corners and widths) are ``nn.Parameter`` s with
    ``requires_grad=False``; ``system.requires_grad_()`` makes them learnable.
    """

    def __init__(
        self,
        name: str,
        inputs,
        outputs,
        rules,
        *,
        and_method: str = "min",
        or_method: str = "max",
        implication: str = "min",
        aggregation: str = "max",
        defuzzification: str = "centroid",
        resolution: int = 1000,
        on_empty: str = "default",
        chunk: int = 8192,
    ):
        super().__init__()
        self.name = str(name)
        for key, value, allowed, what in (
            ("and_method", and_method, AND_METHODS, "t-norms"),
            ("or_method", or_method, OR_METHODS, "s-norms"),
            ("implication", implication, IMPLICATIONS, "t-norms"),
            ("aggregation", aggregation, AGGREGATIONS, "s-norms and sum"),
            ("defuzzification", defuzzification, DEFUZZIFIERS, "Mamdani"),
            ("on_empty", on_empty, ON_EMPTY, ""),
        ):
            _check_method(key, value, allowed, what)
        self.and_method, self.or_method, self.implication = and_method, or_method, implication
        self.aggregation, self.defuzzification, self.on_empty = aggregation, defuzzification, on_empty
        if int(resolution) < 2:
            raise ConfigError("resolution", "an integer >= 2", got=resolution)
        self.resolution, self.chunk = int(resolution), max(1, int(chunk))
        if not inputs or not outputs:
            raise ConfigError("system", "at least one input and one output", got=(len(inputs), len(outputs)))
        self.inputs, self.outputs = nn.ModuleList(inputs), nn.ModuleList(outputs)
        names = [v.name for v in self.inputs] + [v.name for v in self.outputs]
        if len(set(names)) != len(names):
            raise ConfigError("variables", "distinct names for all inputs and outputs", got=names)
        for v in self.outputs:
            kinds = {mf.is_singleton for mf in v.terms.values()}
            if len(kinds) > 1:
                raise ConfigError(f"{v.name}.terms", "all singletons or none (no mixing)", got=v.term_names)
        self.rules = [r if isinstance(r, Rule) else Rule.parse(r) for r in rules]
        if not self.rules:
            raise ConfigError("rules", "at least one rule", got=[])
        # one input row needs its aggregate and every consequent group's set over the cells
        check_memory(
            "resolution",
            4.0 * self.resolution * (2 + len(self.rules)),
            f"{self.resolution} output cells",
            got=self.resolution,
        )
        self._compile_rules()
        self._check_cells()

    def _check_cells(self) -> None:
        """Warn about output terms that the defuzzification cells sample too coarsely to count."""
        for v in self.outputs:
            mfs = v.terms
            if next(iter(mfs.values())).is_singleton or self.resolution > 10**6:  # fine enough for any term
                continue
            lo, hi = v.range
            h = (hi - lo) / self.resolution
            y = lo + h * (torch.arange(self.resolution, dtype=torch.float64) + 0.5)
            for name, mf in mfs.items():
                with torch.no_grad():
                    peak = float(mf(y.to(self.dtype)).max())
                if peak < 0.5:
                    warnings.warn(
                        f"{self.name}: output {v.name}'s term {name} is narrower than the defuzzification "
                        f"cells ({h:.3g} wide at resolution {self.resolution}): sampled there its "
                        f"membership peaks at {peak:.2g}, so it adds "
                        f"{'nothing' if peak == 0 else 'too little'} to {v.name}; raise the resolution",
                        ResolutionWarning,
                        stacklevel=3,
                    )

    # ------------------------------------------------------------ structure

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the parameters (follows ``.to()``, ``.double()``)."""
        return self.inputs[0].bounds.dtype

    @property
    def device(self) -> torch.device:
        """The device of the parameters (follows ``.to()``): inputs that are not tensors are made there."""
        return self.inputs[0].bounds.device

    def input_names(self) -> list:
        """The input variable names, in order (the columns of ``x``)."""
        return [v.name for v in self.inputs]

    def output_names(self) -> list:
        """The output variable names, in order (the columns of the outputs)."""
        return [v.name for v in self.outputs]

    def _compile_rules(self) -> None:
        """Resolve names to indices once; check every clause."""
        ins = {v.name: i for i, v in enumerate(self.inputs)}
        outs = {v.name: i for i, v in enumerate(self.outputs)}
        self._ante = []  # per rule: [(input index, term index, hedges)]
        per_output = [dict() for _ in self.outputs]
        for r, rule in enumerate(self.rules):
            key = f"rule {r + 1} ({rule})"
            clauses = []
            for c in rule.antecedent:
                if c.variable not in ins:
                    raise ConfigError(key, f"an input variable ({', '.join(ins)})", got=c.variable)
                clauses.append((ins[c.variable], self.inputs[ins[c.variable]].index(c.term, key=key), c.hedges))
            self._ante.append(clauses)
            for c in rule.consequent:
                if c.variable not in outs:
                    raise ConfigError(key, f"an output variable ({', '.join(outs)})", got=c.variable)
                o = outs[c.variable]
                t = self.outputs[o].index(c.term, key=key)
                # merged before implication only under max, where it is exact (module docstring)
                group = (t, c.hedges) if self.aggregation == "max" else (t, c.hedges, r)
                per_output[o].setdefault(group, []).append(r)
        self._cons = [[_Consequent(tuple(rs), g[0], g[1]) for g, rs in groups.items()] for groups in per_output]

    # ------------------------------------------------------------ inference

    def fuzzify(self, x: torch.Tensor) -> list:
        """Degrees of every input term: a list over inputs of ``(N, T_i)``.

        ``x``: ``(N, n_inputs)`` (clipped to each input's range).
        """
        out = []
        for i, v in enumerate(self.inputs):
            b = v.bounds.to(x.dtype)  # rounded like the corners: a shoulder at the range end holds
            xi = x[:, i].clamp(b[0], b[1])
            out.append(torch.stack([mf(xi) for mf in v.terms.values()], dim=1))
        return out

    def firing(self, x: torch.Tensor) -> torch.Tensor:
        """Rule degrees ``(N, R)`` (weights applied) for inputs ``x``: ``(N, n_inputs)``."""
        mu = self.fuzzify(x)
        cols = []
        for rule, clauses in zip(self.rules, self._ante):
            method = self.and_method if rule.connective == "and" else self.or_method
            deg = None
            for i, t, hedges in clauses:
                d = apply_hedges(mu[i][:, t], hedges)
                deg = d if deg is None else (TNORMS if rule.connective == "and" else SNORMS)[method](deg, d)
            cols.append(deg * rule.weight if rule.weight != 1.0 else deg)
        return torch.stack(cols, dim=1)

    def output_grid(self, o: int, dtype, device) -> tuple:
        """Where output ``o``'s sets are sampled: ``(y (U,), nu (G, U), cell width or None)``.

        ``nu`` holds each consequent group's term degrees (hedges applied); for an all-singleton
        output ``y`` are the singleton positions and ``nu`` the indicator of each group's term.
        """
        v = self.outputs[o]
        groups = self._cons[o]
        mfs = list(v.terms.values())
        if mfs[0].is_singleton:
            y = torch.stack([mf.params[0] for mf in mfs]).to(dtype=dtype, device=device)
            eye = torch.eye(len(mfs), dtype=dtype, device=device)
            return y, _stack([apply_hedges(eye[g.term], g.hedges) for g in groups], y), None
        lo, hi = v.range
        h = (hi - lo) / self.resolution
        y = lo + h * (torch.arange(self.resolution, dtype=dtype, device=device) + 0.5)
        return y, _stack([apply_hedges(mfs[g.term](y), g.hedges) for g in groups], y), h

    def aggregate(self, fire: torch.Tensor, o: int, nu: torch.Tensor, *, cells=None) -> torch.Tensor:
        """Aggregated output set ``(N, U)`` of output ``o`` from rule degrees ``fire`` ``(N, R)``.

        ``cells`` (a tuple of ``(start, stop, groups)`` from :meth:`sparsity_plan`) restricts the
        work to the groups whose degree is non-zero in each run of cells; the result is the same,
        because a group whose term is 0 on a cell adds nothing there (every t-norm gives
        ``T(a, 0) = 0`` and 0 is neutral for every s-norm and for sum).
        """
        if cells is None:
            return self._aggregate_groups(fire, o, nu, range(len(self._cons[o])))
        parts = [self._aggregate_groups(fire, o, nu[:, a:b], groups) for a, b, groups in cells]
        return torch.cat(parts, dim=1)

    def _aggregate_groups(self, fire, o, nu, groups) -> torch.Tensor:
        imply, aggregate = TNORMS[self.implication], _AGGREGATORS[self.aggregation]
        agg = None
        for g in groups:
            rules = self._cons[o][g].rules
            alpha = fire[:, rules[0]] if len(rules) == 1 else fire[:, list(rules)].amax(dim=1)
            implied = imply(alpha[:, None], nu[g][None, :])
            agg = implied if agg is None else aggregate(agg, implied)
        if agg is None:  # no group: nothing fires here
            return torch.zeros(fire.shape[0], nu.shape[-1], dtype=fire.dtype, device=fire.device)
        return agg

    def sparsity_plan(self) -> tuple:
        """Which consequent groups can be non-zero where.

        Per output, ``None`` (singleton outputs: evaluated densely) or a tuple of cell runs
        ``(start, stop, groups)`` covering the output grid, ``groups`` the indices of the groups
        whose term degree is positive on every cell of the run (computed from the current
        membership parameters).

        Tissue rule bases have 4-7 terms per output of which at most 2-3 overlap anywhere, so
        :meth:`infer` with this plan does a fraction of the dense work. The plan is only valid
        for the parameters it was made from: :meth:`compiled` rebuilds it when they change.
        """
        plans = []
        with torch.no_grad():
            for o in range(len(self.outputs)):
                _, nu, h = self.output_grid(o, self.dtype, self.device)
                if h is None:
                    plans.append(None)
                    continue
                active = (nu > 0).T.tolist()  # (U, G)
                runs, start = [], 0
                for u in range(1, len(active) + 1):
                    if u == len(active) or active[u] != active[start]:
                        runs.append((start, u, tuple(g for g, on in enumerate(active[start]) if on)))
                        start = u
                plans.append(tuple(runs))
        return tuple(plans)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Crisp outputs ``(..., n_outputs)`` for inputs ``x``: ``(..., n_inputs)``."""
        return self._run(x, self.infer, self.chunk, pad=False)

    def compiled(self, *, chunk: int = 65536):
        """The same evaluation through ``torch.compile``.

        Fused kernels that visit only the consequent groups that can be non-zero on each run of
        output cells (see :meth:`sparsity_plan`); for large batches without gradients. Compiling
        costs ~10-20 s on first use and again whenever the membership parameters have changed since
        the last call (the plan depends on them); the last chunk is padded so that one shape is
        compiled. Returns ``f(x) -> outputs`` like ``self(x)``.
        """
        from .._compile import inductor_options

        cache = {}

        def run(x):
            key = self._parameter_snapshot()
            if "key" not in cache or not _same(cache["key"], key):
                plan = self.sparsity_plan()
                cache.update(
                    key=key,
                    fn=torch.compile(
                        lambda part: self.infer(part, plan=plan), dynamic=False, options=inductor_options()
                    ),
                )
            return self._run(x, cache["fn"], chunk, pad=True)

        return run

    def _parameter_snapshot(self) -> list:
        return [t.detach().clone() for t in list(self.parameters()) + list(self.buffers())]

    def _run(self, x, infer, chunk: int, pad: bool) -> torch.Tensor:
        x = x if torch.is_tensor(x) else torch.as_tensor(x, device=self.device)
        if not x.is_floating_point():
            x = x.to(torch.get_default_dtype())
        if x.shape[-1] != len(self.inputs):
            raise ConfigError(
                "inputs",
                f"a last dimension of {len(self.inputs)} ({', '.join(self.input_names())})",
                got=tuple(x.shape),
            )
        lead = x.shape[:-1]
        flat = x.reshape(-1, len(self.inputs))
        n = flat.shape[0]
        ys, empties = [], []
        for s in range(0, n, chunk):
            part = flat[s : s + chunk]
            if pad and part.shape[0] < chunk:
                part = torch.cat([part, part[-1:].expand(chunk - part.shape[0], -1)])
            out, e = infer(part)
            ys.append(out)
            empties.append(e)
        y = (torch.cat(ys) if len(ys) != 1 else ys[0])[:n]
        self._check_empty((torch.cat(empties) if len(empties) != 1 else empties[0])[:n], flat)
        return y.reshape(*lead, len(self.outputs))

    def infer(self, x: torch.Tensor, *, plan: tuple | None = None) -> tuple:
        """Outputs ``(N, n_outputs)`` and the zero-firing-mass mask ``(N, n_outputs)`` for one chunk.

        ``x``: ``(N, n_inputs)``; no checks, no Python branching on data (compilable).

        ``plan`` (from :meth:`sparsity_plan`, made from the current parameters) skips the
        consequent groups that are zero on a run of output cells; same result, less work.
        """
        fire = self.firing(x)
        outs, empties = [], []
        for o, v in enumerate(self.outputs):
            grid, nu, h = self.output_grid(o, x.dtype, x.device)
            cells = None if plan is None else plan[o]
            if cells is not None and self.defuzzification == "centroid":
                # centroid from per-run sums: the (N, U) aggregate is never assembled
                mass = moment = 0
                for a, b, groups in cells:
                    agg = self._aggregate_groups(fire, o, nu[:, a:b], groups)
                    mass = mass + agg.sum(dim=1)
                    moment = moment + (agg * grid[a:b]).sum(dim=1)
                value = moment / torch.where(mass > 0, mass, torch.ones_like(mass))
                mass = mass * h
            else:
                value, mass = defuzzify(self.aggregate(fire, o, nu, cells=cells), grid, h, self.defuzzification)
            empty = mass <= 0
            outs.append(torch.where(empty, torch.full_like(value, v.default), value))
            empties.append(empty)
        return torch.stack(outs, dim=1), torch.stack(empties, dim=1)

    def _check_empty(self, empty: torch.Tensor, x: torch.Tensor) -> None:
        if self.on_empty == "default" or not bool(empty.any()):
            return
        rows, cols = torch.nonzero(empty, as_tuple=True)
        r, o = int(rows[0]), int(cols[0])
        point = ", ".join(f"{n}={float(v):.6g}" for n, v in zip(self.input_names(), x[r]))
        msg = (
            f"{self.name}: no rule fires for output {self.outputs[o].name} at {point} "
            f"({int(empty.any(dim=1).sum())} of {empty.shape[0]} input rows)"
        )
        if self.on_empty == "error":
            raise NoRuleFiredError(msg)
        warnings.warn(msg + "; using the output's default", EmptyOutputWarning, stacklevel=3)

    def evaluate(self, values: dict | None = None, /, **named) -> dict:
        """Crisp outputs by name: ``evaluate(consistency=5.5) -> {"spring_const": ..., ...}``.

        Values may be numbers or tensors of one shape (broadcast together); the results have
        that shape. Every input must be given.
        """
        values = dict(values or {}, **named)
        missing = [n for n in self.input_names() if n not in values]
        unknown = [n for n in values if n not in self.input_names()]
        if missing or unknown:
            raise ConfigError(
                "inputs",
                f"exactly the inputs {', '.join(self.input_names())}",
                got=f"missing {missing}, unknown {unknown}" if missing else f"unknown {unknown}",
                show_got=True,
            )
        cols = torch.broadcast_tensors(
            *[torch.as_tensor(values[n], dtype=self.dtype, device=self.device) for n in self.input_names()]
        )
        out = self(torch.stack(cols, dim=-1))
        return {n: out[..., k] for k, n in enumerate(self.output_names())}

    def extra_repr(self) -> str:
        """The settings for ``repr``: name, rule count and the inference methods."""
        return (
            f"name={self.name!r}, rules={len(self.rules)}, and={self.and_method}, or={self.or_method}, "
            f"implication={self.implication}, aggregation={self.aggregation}, "
            f"defuzzification={self.defuzzification}, resolution={self.resolution}"
        )


def _stack(rows: list, y: torch.Tensor) -> torch.Tensor:
    """The groups' degrees ``(G, U)`` on the points ``y`` ``(U,)``; ``(0, U)`` for an output no rule concludes."""
    return torch.stack(rows) if rows else y.new_zeros((0, len(y)))


def _same(a: list, b: list) -> bool:
    return len(a) == len(b) and all(
        s.dtype == t.dtype and s.device == t.device and torch.equal(s, t) for s, t in zip(a, b)
    )


def defuzzify(agg: torch.Tensor, y: torch.Tensor, h: float | None, method: str) -> tuple:
    """Crisp values of aggregated sets.

    Args:
        agg: ``(N, U)`` degrees on the points ``y``.
        y: ``(U,)`` cell midpoints of width ``h`` (continuous sets, midpoint rule), or singleton
            positions (``h=None``).
        h: the cell width, or ``None`` for singletons.
        method: ``centroid``, ``bisector``, ``mom``, ``som``, ``lom``.

    Returns:
        ``(value (N,), mass (N,))``; ``mass`` is the firing mass (area, or summed singleton
        degrees). Where ``mass == 0`` the value is meaningless (the caller substitutes).
    """
    mass = agg.sum(dim=1)
    has = mass > 0
    safe = torch.where(has, mass, torch.ones_like(mass))
    if h is None:  # singletons: sort positions (they may be learned)
        y, order = torch.sort(y)
        agg = agg[:, order]
    if method == "centroid":
        return (agg * y).sum(dim=1) / safe, mass * (h or 1.0)
    if method == "bisector":
        cum = torch.cumsum(agg, dim=1)
        half = 0.5 * mass
        k = torch.searchsorted(cum.detach().contiguous(), half.detach()[:, None].contiguous()).clamp_max(
            agg.shape[1] - 1
        )
        before = torch.where(k > 0, cum.gather(1, (k - 1).clamp_min(0)), torch.zeros_like(k, dtype=agg.dtype))
        cell = agg.gather(1, k)
        yk = y[k[:, 0]]
        if h is None:
            return yk, mass
        frac = (half[:, None] - before) / torch.where(cell > 0, cell, torch.ones_like(cell))
        return yk - 0.5 * h + h * frac[:, 0].clamp(0, 1), mass * h
    top = agg.amax(dim=1, keepdim=True)
    rtol = max(1e-12, 8 * torch.finfo(agg.dtype).eps)  # ties up to rounding: ~1e-6 in float32, 1e-12 in float64
    on = (agg >= top * (1 - rtol)) & (top > 0)
    if method == "mom":
        n = on.sum(dim=1)
        return (on.to(agg.dtype) @ y) / n.clamp_min(1), mass * (h or 1.0)
    idx = torch.arange(agg.shape[1], device=agg.device)
    if method == "som":
        k = torch.where(on, idx, agg.shape[1]).amin(dim=1).clamp_max(agg.shape[1] - 1)
    else:
        k = torch.where(on, idx, -1).amax(dim=1).clamp_min(0)
    return y[k], mass * (h or 1.0)
