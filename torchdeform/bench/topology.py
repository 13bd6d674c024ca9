"""``torchdeform bench topology``: a full cut through an ``n^3`` body while its compiled step runs.

For every topology (``--topologies``, default 6, 18, 26) and size ``n`` (``--sizes``, default 8,
16, 32, 64; quick 8, 16) the speed cube (1 cm spacing, k = 100 N/m, c = 0.05 N s/m, 1 g per node)
runs under a compiled symplectic step that shares its fields with the model
(``compiled_step(..., editable=True)``); then a rectangular blade cuts between the two middle
layers. A row carries:

* ``springs_removed`` and ``expected``: the analytic count of REFERENCE §6.2 (6: ``n^2``,
  18: ``n^2 + 4n(n-1)``, 26: ``(3n-2)^2``);
* ``components`` after the cut (2) and ``components_ms`` (label propagation);
* ``cut_ms``: the cut itself (search and in-place removal), median of ``--repeats`` cuts;
* ``step_ms_before`` and ``step_ms_after``: median time per step of ``--steps`` steps before and
  after the cut, and ``step_ratio`` the median of their ratios (target: within 5 %). The repeats
  are interleaved (the uncut body restored in place, ``--steps`` steps, the cut, ``--steps``
  steps), so a slow drift of the machine does not read as a change;
* ``recompiles``: graphs dynamo compiled during the cut and the steps after it (target: 0).

Targets: a cut on 64^3 in < 1 ms; step time after within 5 % of before; no
recompilation. It runs on one CPU thread unless ``--threads`` says otherwise.

Example:
    torchdeform bench topology --quick
    torchdeform bench topology --json --out bench-out
"""

from __future__ import annotations

import statistics
import time

import torch

from ..errors import ConfigError
from ..options import integer
from ..outputs import axes, save_plot
from .common import add_common, emit, int_list, machine_info, progress, speed_cube

__all__ = ["COLUMNS", "add_arguments", "run", "expected_count"]

COLUMNS = [
    ("topology", "topology", None),
    ("n", "n", None),
    ("springs_removed", "removed", "{:,}"),
    ("expected", "expected", "{:,}"),
    ("components", "pieces", None),
    ("cut_ms", "cut ms", "{:.3f}"),
    ("step_ms_before", "step ms before", "{:.3f}"),
    ("step_ms_after", "step ms after", "{:.3f}"),
    ("recompiles", "recompiles", None),
    ("engine", "engine", None),
    ("threads", "threads", None),
]
SPACING = 0.01
WARM = 5  # untimed steps at the start of each timed phase


def expected_count(topology: int, n: int) -> int:
    """Springs a full cut between two adjacent layers of an ``n^3`` grid removes (REFERENCE §6.2)."""
    return {6: n * n, 14: n * n + 4 * (n - 1) ** 2, 18: n * n + 4 * n * (n - 1), 26: (3 * n - 2) ** 2}[topology]


def add_arguments(p) -> None:
    """The options of ``torchdeform bench topology``."""
    add_common(p)
    p.add_argument(
        "--sizes", type=int_list("--sizes"), default=None, help="n (n^3 nodes; default 8,16,32,64; quick 8,16)"
    )
    p.add_argument("--topologies", type=int_list("--topologies"), default=None, help="default 6,18,26")
    p.add_argument("--steps", type=integer(lo=1), default=None, help="timed steps per repeat (default 100; quick 10)")
    p.add_argument("--repeats", type=integer(lo=1), default=None, help="repeats of each timing (default 9; quick 3)")
    p.add_argument("--no-compile", action="store_true", help="eager only (no torch.compile: a smoke run)")


def _graphs() -> int:
    from torch._dynamo.utils import counters

    return int(counters["stats"]["unique_graphs"])


def _step_ms(step, ps, steps, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            ps = step.step_packed(ps)
        float(ps.x[0, 0, step.packed.G])  # reads the result: waits for the device
        times.append((time.perf_counter() - t0) / steps * 1e3)
    return statistics.median(times), ps


def _row(topology, n, steps, repeats, compiled, dtype, device):
    from ..sim.compiled import compiled_step
    from ..sim.integrators import SymplecticEuler
    from ..topology import Blade, components, cut

    model, state, dt = speed_cube(n, topology, dtype=dtype, device=device)
    step = compiled_step(SymplecticEuler(), model, dt, enable=compiled, editable=True)
    ps = step.packed.pack_state(state)
    t0 = time.perf_counter()
    ps = step.step_packed(ps)
    compile_s = time.perf_counter() - t0 if compiled else None
    if compiled and not step.compiled:
        raise RuntimeError(f"the step did not compile: {step.compile_error}")
    _, ps = _step_ms(step, ps, steps, 1)  # warm-up
    graphs = _graphs()
    span = (n + 1) * SPACING
    blade = Blade(((n // 2 - 0.5) * SPACING, -SPACING, -SPACING), (0.0, span, 0.0), (0.0, 0.0, span))
    k0 = model.stiffness.clone()  # a cut changes the stiffness alone
    before, after, cuts = [], [], []
    for _ in range(repeats):
        # interleaved: the uncut body (restored in place), the cut, the cut body
        # (each phase starts with a few untimed steps: the same warm caches before and after)
        model.stiffness.copy_(k0)
        _, ps = _step_ms(step, ps, WARM, 1)
        ms, ps = _step_ms(step, ps, steps, 1)
        before.append(ms)
        x = step.packed.unpack_state(ps).x
        t0 = time.perf_counter()
        removed = cut(model, x, blade)
        cuts.append((time.perf_counter() - t0) * 1e3)
        _, ps = _step_ms(step, ps, WARM, 1)
        ms, ps = _step_ms(step, ps, steps, 1)
        after.append(ms)
    recompiles = _graphs() - graphs
    t0 = time.perf_counter()
    _, count = components(model)
    comp_ms = (time.perf_counter() - t0) * 1e3
    return dict(
        topology=topology,
        n=n,
        springs_removed=removed,
        expected=expected_count(topology, n),
        components=count,
        cut_ms=statistics.median(cuts),
        cut_ms_min=min(cuts),
        step_ms_before=statistics.median(before),
        step_ms_after=statistics.median(after),
        step_ratio=statistics.median(a / b for a, b in zip(after, before)),
        recompiles=recompiles,
        components_ms=comp_ms,
        engine="compiled" if compiled else "eager",
        compile_s=compile_s,
        threads=torch.get_num_threads(),
        steps=steps,
        repeats=repeats,
    )


def run(args) -> int:
    """Run the bench; returns the exit status."""
    torch.set_num_threads(args.threads or 1)
    sizes = args.sizes or ([8, 16] if args.quick else [8, 16, 32, 64])
    topologies = args.topologies or [6, 18, 26]
    steps = args.steps or (10 if args.quick else 100)
    repeats = args.repeats or (3 if args.quick else 9)
    if min(sizes) < 4 or steps < 1 or repeats < 1 or not set(topologies) <= {6, 14, 18, 26}:
        raise ConfigError(
            "--sizes/--topologies/--steps/--repeats",
            "sizes >= 4, topologies of 6, 14, 18, 26, steps >= 1, repeats >= 1",
            got=(sizes, topologies, steps, repeats),
        )
    dtype = getattr(torch, args.dtype)
    rows = []
    bar = progress(len(sizes) * len(topologies), "bench topology")
    for topology in topologies:
        for n in sizes:
            rows.append(_row(topology, n, steps, repeats, not args.no_compile, dtype, args.device))
            bar.update(1)
    bar.close()
    big = [r for r in rows if r["n"] == 64]
    extra = {
        "machine": machine_info(args.device),
        "targets": {"cut_ms_64": 1.0, "step_ratio_within": 0.05, "recompiles": 0},
        "met": {
            "counts": all(r["springs_removed"] == r["expected"] and r["components"] == 2 for r in rows),
            "cut_64": None if not big else all(r["cut_ms"] < 1.0 for r in big),
            "step_time": all(abs(r["step_ratio"] - 1) <= 0.05 for r in rows),
            "no_recompile": all(r["recompiles"] == 0 for r in rows),
        },
    }
    if args.out:
        _plot(rows, args.out)
    emit("topology", args, rows, COLUMNS, extra=extra)
    return 0


def _plot(rows, out_dir) -> None:
    fig, (a, b) = axes(figsize=(10, 4.2), ncols=2)
    for topology, style in zip(sorted({r["topology"] for r in rows}), ("-o", "-s", "-^", "-d")):
        pts = sorted((r["n"], r["cut_ms"], r["step_ratio"]) for r in rows if r["topology"] == topology)
        ns = [p[0] for p in pts]
        a.plot(ns, [p[1] for p in pts], style, label=f"{topology} neighbours")
        b.plot(ns, [p[2] for p in pts], style, label=f"{topology} neighbours")
    a.axhline(1.0, color="grey", lw=0.8)
    a.set_xscale("log", base=2)
    a.set_yscale("log")
    a.set_xlabel("n (n^3 nodes)")
    a.set_ylabel("cut time (ms)")
    a.set_title("A full cut between two layers")
    b.axhspan(0.95, 1.05, color="grey", alpha=0.2)
    b.set_xscale("log", base=2)
    b.set_xlabel("n (n^3 nodes)")
    b.set_ylabel("step time after / before (median of pairs)")
    b.set_title("Step time after the cut")
    for ax in (a, b):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    save_plot(fig, out_dir, "topology.png")
