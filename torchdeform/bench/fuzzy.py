"""``torchdeform bench fuzzy``: Mamdani inputs per second, against scikit-fuzzy.

Evaluates a rule base (default: the SUSILAP-G preset) on ``--inputs`` random input rows,
eager and compiled (``MamdaniSystem.compiled``), and the same system in scikit-fuzzy's
``ControlSystemSimulation`` one row at a time (its usual use) on ``--skfuzzy-inputs`` rows,
in the same run. Every row reports inputs/s, the ratio to scikit-fuzzy and the largest
difference from the eager result as a fraction of the output range. scikit-fuzzy is optional:
when it is missing the bench says so and skips its row.

Example:
    torchdeform bench fuzzy --quick
    torchdeform bench fuzzy --inputs 4000000 --threads 2 --json
"""

from __future__ import annotations

import statistics
import sys
import time

import torch

from ..errors import ConfigError
from ..options import integer
from .common import add_common, emit, machine_info

__all__ = ["COLUMNS", "add_arguments", "to_skfuzzy", "run"]

COLUMNS = [
    ("system", "system", None),
    ("mode", "mode", None),
    ("threads", "thr", None),
    ("inputs", "inputs", "{:,}"),
    ("seconds", "s (median)", "{:.4f}"),
    ("inputs_per_s", "inputs/s", "{:,.0f}"),
    ("vs_skfuzzy", "x skfuzzy", "{:,.0f}"),
    ("max_diff_of_range", "max|diff|/range", "{:.1e}"),
    ("compile_s", "compile s", "{:.1f}"),
]


def add_arguments(p) -> None:
    """The options of ``torchdeform bench fuzzy``."""
    add_common(p)
    p.add_argument("--system", default="susilap_g", help="preset name or .fis file (default susilap_g)")
    p.add_argument("--inputs", type=integer(lo=1), default=None, help="input rows for torchdeform (default 2,000,000)")
    p.add_argument("--skfuzzy-inputs", type=integer(lo=1), default=None, help="rows for scikit-fuzzy (default 300)")
    p.add_argument("--repeats", type=integer(lo=1), default=3, help="timed repeats; the median is reported")
    p.add_argument("--no-compile", action="store_true", help="skip the compiled row")


def to_skfuzzy(fis, *, points: int = 2001):
    """The same system in scikit-fuzzy (``ControlSystemSimulation``), universes of ``points`` samples.

    Supports min/max inference and the membership kinds scikit-fuzzy has.
    """
    import numpy as np
    import skfuzzy as fz
    from skfuzzy import control as ctrl

    if (fis.and_method, fis.or_method, fis.implication, fis.aggregation) != ("min", "max", "min", "max"):
        raise ConfigError(
            "system",
            "min/max inference for the scikit-fuzzy comparison",
            got=(fis.and_method, fis.or_method, fis.implication, fis.aggregation),
        )

    def mf(u, m):
        p = m.values()
        table = {
            "trapezoid": lambda: fz.trapmf(u, p),
            "triangle": lambda: fz.trimf(u, p),
            "gaussian": lambda: fz.gaussmf(u, p[0], p[1]),
            "bell": lambda: fz.gbellmf(u, *p),
            "sigmoid": lambda: fz.sigmf(u, p[0], p[1]),
        }
        if m.kind not in table:
            raise ConfigError("system", "membership kinds scikit-fuzzy has", got=m.kind)
        return table[m.kind]()

    variables = {}
    for cls, group in ((ctrl.Antecedent, fis.inputs), (ctrl.Consequent, fis.outputs)):
        for v in group:
            u = np.linspace(v.range[0], v.range[1], points)
            var = cls(u, v.name) if cls is ctrl.Antecedent else cls(u, v.name, defuzzify_method=fis.defuzzification)
            for t, m in v.terms.items():
                var[t] = mf(u, m)
            variables[v.name] = var
    rules = []
    for rule in fis.rules:
        if rule.weight != 1.0 or any(c.hedges for c in rule.antecedent + rule.consequent):
            raise ConfigError(
                "system", "rules without weights or hedges for the scikit-fuzzy comparison", got=str(rule)
            )
        terms = [variables[c.variable][c.term] for c in rule.antecedent]
        ante = terms[0]
        for t in terms[1:]:
            ante = (ante & t) if rule.connective == "and" else (ante | t)
        rules.append(ctrl.Rule(ante, [variables[c.variable][c.term] for c in rule.consequent]))
    return ctrl.ControlSystemSimulation(ctrl.ControlSystem(rules), cache=False)


def _time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def run(args) -> int:
    """Run the bench: eager, compiled and scikit-fuzzy rows; returns the exit status."""
    from ..fuzzy.commands import load

    fis = load(args.system)
    if args.threads:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    fis = fis.to(dtype)
    n = args.inputs or (20_000 if args.quick else 2_000_000)
    n_sk = args.skfuzzy_inputs or (20 if args.quick else 300)
    if n < 1 or n_sk < 1:
        raise ConfigError("--inputs", "positive row counts", got=(n, n_sk))
    gen = torch.Generator().manual_seed(0)
    lo = torch.tensor([v.range[0] for v in fis.inputs], dtype=dtype)
    hi = torch.tensor([v.range[1] for v in fis.inputs], dtype=dtype)
    x = lo + (hi - lo) * torch.rand(n, len(fis.inputs), generator=gen, dtype=dtype)
    span = torch.tensor([v.range[1] - v.range[0] for v in fis.outputs], dtype=dtype)
    name, threads = fis.name, torch.get_num_threads()
    base = dict(system=name, threads=threads, dtype=args.dtype)
    rows = []
    with torch.no_grad():
        sec, ref = _time(lambda: fis(x), args.repeats)
        rows.append(dict(base, mode="eager", inputs=n, seconds=sec, inputs_per_s=n / sec, max_diff_of_range=0.0))
        if not args.no_compile:
            chunk = min(65536, n)
            f = fis.compiled(chunk=chunk)
            t0 = time.perf_counter()
            f(x[:chunk])
            compile_s = time.perf_counter() - t0
            sec, y = _time(lambda: f(x), args.repeats)
            rows.append(
                dict(
                    base,
                    mode="compiled",
                    inputs=n,
                    seconds=sec,
                    inputs_per_s=n / sec,
                    compile_s=compile_s,
                    max_diff_of_range=float(((y - ref).abs() / span).max()),
                )
            )
    try:
        sim = to_skfuzzy(fis)
    except ImportError:
        print(
            "scikit-fuzzy rows skipped: scikit-fuzzy is not installed (pip install scikit-fuzzy packaging "
            "networkx scipy)",
            file=sys.stderr,
        )
        sim = None
    if sim is not None:
        xs = x[:n_sk].double().numpy()

        def sk():
            out = []
            for row in xs:
                for v, val in zip(fis.inputs, row):
                    sim.input[v.name] = float(val)
                sim.compute()
                out.append([sim.output.get(v.name, float("nan")) for v in fis.outputs])
            return torch.tensor(out, dtype=torch.float64)

        sec, ysk = _time(sk, max(1, min(args.repeats, 3)))
        ok = torch.isfinite(ysk).all(dim=1)
        diff = ((ysk[ok] - ref[:n_sk][ok].double()).abs() / span.double()).max() if bool(ok.any()) else None
        rows.append(
            dict(
                base,
                mode="scikit-fuzzy",
                inputs=n_sk,
                seconds=sec,
                inputs_per_s=n_sk / sec,
                max_diff_of_range=None if diff is None else float(diff),
            )
        )
        for r in rows:
            r["vs_skfuzzy"] = r["inputs_per_s"] / rows[-1]["inputs_per_s"]
    extra = {"machine": machine_info("cpu")}
    compiled = [r for r in rows if r["mode"] == "compiled"]
    if compiled:
        extra["compiled_inputs_per_s"] = compiled[0]["inputs_per_s"]
    emit("fuzzy", args, rows, COLUMNS, extra=extra)
    return 0
