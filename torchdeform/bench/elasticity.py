r"""``torchdeform bench elasticity``: an :class:`~torchdeform.sim.material.Elastic` lattice body against finite elements, and what its cell term costs.

**Rows.** One per topology (18, 26 neighbours), Poisson ratio ``nu`` (0.3, 0.45, 0.49) and
resolution: the cell side ``h = 5 mm / r`` for the refinements ``r`` (1, 2, 4: h = 5, 2.5,
1.25 mm; the beam has ``12 r`` cells along its length). E = 5 kPa throughout.

**Accuracy.** The load cases of :mod:`.accuracy.lattice`, solved in the small-strain limit, each
against the finite-element reference :mod:`.accuracy.fem` (scikit-fem, quadratic hexahedra,
converged to about 1 %; computed once per ``nu`` and kept for the run: the reference does not
depend on the lattice):

* ``e_ratio``, ``nu_eff``: a free 10 mm cube under equal and opposite normal tractions on two
  faces (uniaxial stress): ``E`` over the ``E`` asked, and the Poisson ratio, from its mean
  strains. The calibration is exact for a uniform strain, so these are 1 and ``nu`` to the
  solver's tolerance at any ``h``;
* ``shear_ratio``: the force of simple shear of a 5 x 50 x 50 mm box between bonded plates over
  the FEM's (only where a free layer of nodes lies between the plates, ``h <= 2.5 mm``);
* ``tip_ratio``: the mean tip deflection of a 10 x 10 x 60 mm beam clamped at one end under
  gravity (1000 kg/m^3) over the FEM's: below 1 where the lattice is too stiff in bending;
* ``punch_ratio``: the force on a bonded 10 x 10 mm punch pressed 0.5 mm into a 20 x 40 x 40 mm
  block over the FEM's: above 1 where the lattice is too stiff at the punch's edge.

**Cost.** Symplectic Euler steps of the beam of the same row (clamped, under gravity, float32 by
default, ``dt`` the smaller of the two models' safe steps), timed as ``bench speed`` times a step
(warm-up excluded, enough steps for about 0.2 s, the median of ``--repeats`` runs): ``springs_ms``
with springs alone (the same ``Elastic(E, nu)`` beam with its cell term left out: the same
springs) against ``volume_ms`` with the springs and the cell term (volume and shear parts),
and ``volume_cost`` their ratio. Each model runs on the fastest engine that accepts it
(:func:`fastest_engine`: the native C kernel, else the compiled packed step, else eager, as
:class:`~torchdeform.sim.engine.Engine` decides what can run), named in ``springs_engine`` and
``volume_engine`` with the reason; the thread count of each is in the row.

Example:
    torchdeform bench elasticity --quick
    torchdeform bench elasticity --threads 2 --json --out elasticity-run
"""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path

import torch

from ..checks import usable_device
from ..errors import ConfigError
from ..options import integer, number_list
from ..outputs import axes, save_plot
from ..sim.material import POISSON_RANGE
from .accuracy.lattice import YOUNGS  # Young's modulus of every case (Pa)
from .common import add_common, device_sync, emit, int_list, machine_info, progress

__all__ = [
    "CASES",
    "COLUMNS",
    "add_arguments",
    "run",
    "require_fem",
    "fem_reference",
    "accuracy_fields",
    "fastest_engine",
    "step_times",
]

#: the load cases, in the order of the table
CASES = ("uniaxial", "shear", "cantilever", "punch")
#: the beam's density (kg/m^3)
RHO = 1000.0

COLUMNS = [
    ("topology", "topo", None),
    ("nu", "nu", "{:g}"),
    ("h_mm", "h mm", "{:g}"),
    ("e_ratio", "E/E", "{:.6f}"),
    ("nu_eff", "nu eff", "{:.4f}"),
    ("shear_ratio", "shear/FEM", "{:.3f}"),
    ("tip_ratio", "tip/FEM", "{:.3f}"),
    ("punch_ratio", "punch/FEM", "{:.3f}"),
    ("nodes", "beam nodes", "{:,}"),
    ("threads", "thr", None),
    ("springs_engine", "springs on", None),
    ("springs_ms", "springs ms", "{:.3f}"),
    ("volume_engine", "+cell term on", None),
    ("volume_ms", "+cell term ms", "{:.3f}"),
    ("volume_cost", "x", "{:.2f}"),
]


def add_arguments(p) -> None:
    """Options of ``torchdeform bench elasticity``."""
    add_common(p)
    p.add_argument(
        "--topologies",
        type=int_list("--topologies"),
        default=None,
        help="neighbours, comma-separated: 14, 18, 26 (default 18,26)",
    )
    p.add_argument(
        "--poisson",
        type=number_list(lo=1 / 6),
        default=None,
        help="Poisson ratios in [1/6, 0.5), comma-separated (default 0.3,0.45,0.49; quick 0.45)",
    )
    p.add_argument(
        "--refine",
        type=int_list("--refine"),
        default=None,
        help="refinements r: cells of h = 5 mm / r, 12 r along the beam (default 1,2,4; quick 1,2)",
    )
    p.add_argument(
        "--cases",
        default=",".join(CASES),
        help=f"load cases, comma-separated (default {','.join(CASES)})",
    )
    p.add_argument("--no-compile", action="store_true", help="never the compiled engine (quick: never)")
    p.add_argument(
        "--repeats", type=integer(lo=1), default=None, help="timed repeats, the median is kept (default 5; quick 3)"
    )


def require_fem() -> None:
    """Refuse, in one line, when the finite-element reference's libraries (the ``fem`` extra) are missing."""
    try:
        import cholespy  # noqa: F401 - only to say what is missing
        import skfem  # noqa: F401
    except ImportError as e:
        raise ConfigError(
            "bench elasticity",
            f"scikit-fem for the finite-element reference (pip install 'torchdeform[fem]'; {e})",
            show_got=False,
        ) from None


def fem_reference(nu: float, cases) -> dict:
    """The finite-element answers the lattice is divided by, for ``nu`` (E = 5 kPa), and the seconds they took.

    ``{"shear_N", "tip_m", "punch_N", "seconds"}`` (None for a case not in ``cases``). The
    functions of :mod:`.accuracy.fem` keep their results (``functools.lru_cache``): a second call
    in the same process costs nothing.
    """
    from .accuracy import fem

    t0 = time.perf_counter()
    ref = {
        "shear_N": fem.simple_shear(YOUNGS, nu).force if "shear" in cases else None,
        "tip_m": fem.cantilever_tip(YOUNGS, nu, RHO).mean if "cantilever" in cases else None,
        "punch_N": fem.bonded_punch_force(YOUNGS, nu) if "punch" in cases else None,
    }
    ref["seconds"] = time.perf_counter() - t0
    return ref


def accuracy_fields(topology: int, nu: float, refine: int, cases, ref: dict) -> dict:
    """The lattice's answers at ``h = 5 mm / refine`` and their ratios to ``ref`` (:func:`fem_reference`).

    Keys: ``e_ratio``, ``nu_eff``, ``shear_N``, ``shear_ratio``, ``tip_m``, ``tip_ratio``,
    ``punch_N``, ``punch_ratio``, ``solve_s`` (the lattice solves' wall time); None for a case not
    run (shear where the box has no free layer at this ``h``).
    """
    from .accuracy import lattice

    h = 0.005 / refine
    out: dict = dict.fromkeys(
        ("e_ratio", "nu_eff", "shear_N", "shear_ratio", "tip_m", "tip_ratio", "punch_N", "punch_ratio")
    )
    t0 = time.perf_counter()
    if "uniaxial" in cases:
        pull = lattice.lattice_uniaxial(nu, h, topology=topology, youngs_modulus=YOUNGS)
        out.update(e_ratio=pull.E / YOUNGS, nu_eff=pull.nu)
    if "shear" in cases and lattice.shear_fits(h):
        force = lattice.lattice_shear(nu, h, topology=topology, youngs_modulus=YOUNGS)
        out.update(shear_N=force, shear_ratio=force / ref["shear_N"])
    if "cantilever" in cases:
        tip = lattice.lattice_cantilever(nu, 12 * refine, topology=topology, youngs_modulus=YOUNGS, rho=RHO)
        out.update(tip_m=tip, tip_ratio=tip / ref["tip_m"])
    if "punch" in cases:
        force = lattice.lattice_punch(nu, h, topology=topology, youngs_modulus=YOUNGS)
        out.update(punch_N=force, punch_ratio=force / ref["punch_N"])
    out["solve_s"] = time.perf_counter() - t0
    return out


def fastest_engine(model, integrator, *, compile: bool = True) -> tuple:
    """The fastest engine that accepts ``model`` stepped by ``integrator``: ``(engine, why)``.

    ``"eager"`` where :meth:`Engine.blocker <torchdeform.sim.engine.Engine.blocker>` keeps the
    step eager (the reason is the engine's own words), ``"native"`` where the C kernel can make it
    (:meth:`~torchdeform.sim.engine.Engine.native_blocker`), else ``"compiled"`` (``"eager"`` when
    ``compile`` is False). A faster path that the engine learns to run shows up here by itself.
    """
    from ..sim.engine import Engine

    blocked = Engine(mode="auto").blocker(model, integrator, model.rest_state(), None)
    if blocked:
        return "eager", blocked
    why_not = Engine.native_blocker(model, integrator)
    if why_not is None:
        return "native", "the C kernel's packed step"
    if compile:
        return "compiled", f"the packed step under torch.compile ({why_not})"
    return "eager", f"{why_not}; the compiled engine left out"


def step_times(topology: int, nu: float, refine: int, *, dtype, device, compile, repeats, target_s, cache=None):
    """Time the beam's symplectic Euler step with springs alone and with the cell term; row fields.

    ``cache``: a dict that keeps the springs-alone timing per ``(topology, refine)`` within a run
    (that model does not depend on ``nu``).
    """
    from ..sim.integrators import SymplecticEuler
    from ..sim.stability import suggest_dt
    from .accuracy.lattice import cantilever_model
    from .speed import _time_mode

    cells = 12 * refine
    integ = SymplecticEuler()
    sync = device_sync(device)

    def model(n):
        return cantilever_model(cells, nu=n, topology=topology, rho=RHO, dtype=dtype, device=device)

    springs, volume = model(nu), model(nu)
    springs.volume = None  # the same body's springs without its cell term
    assert volume.volume is not None
    dt = min(suggest_dt(springs), suggest_dt(volume))

    def timed(m):
        engine, why = fastest_engine(m, integ, compile=compile)
        t = _time_mode(integ, m, m.rest_state(), dt, engine, steps=None, repeats=repeats, target_s=target_s, sync=sync)
        if t.fields["fallback"]:
            engine, why = "eager", f"{why}; the compile failed, its uncompiled packed step ran"
        return {"engine": engine, "why": why, "ms": t.sec * 1e3, "threads": t.fields["threads"]}

    key = (topology, refine, str(dtype), device)
    cache = {} if cache is None else cache
    if key not in cache:
        cache[key] = timed(springs)
    a, b = cache[key], timed(volume)
    threads = str(a["threads"]) if a["threads"] == b["threads"] else f"{a['threads']}/{b['threads']}"
    return {
        "nodes": volume.grid.num_nodes,
        "dt": dt,
        "threads": threads,
        "springs_engine": a["engine"],
        "springs_why": a["why"],
        "springs_threads": a["threads"],
        "springs_ms": a["ms"],
        "volume_engine": b["engine"],
        "volume_why": b["why"],
        "volume_threads": b["threads"],
        "volume_ms": b["ms"],
        "volume_cost": b["ms"] / a["ms"],
    }


def _options(args):
    """The checked options: ``(device, topologies, poisson, refine, cases)``; refuses a missing ``fem`` extra."""
    device = str(usable_device(args.device))
    topologies = args.topologies or [18, 26]
    for t in topologies:
        if t not in (14, 18, 26):
            raise ConfigError("--topologies", "14, 18 or 26 (Elastic needs shear springs)", got=t)
    poisson = args.poisson or ([0.45] if args.quick else [0.3, 0.45, 0.49])
    for nu in poisson:
        if not POISSON_RANGE[26][0] - 1e-12 <= nu < 0.5:
            raise ConfigError("--poisson", "Poisson ratios in [1/6, 0.5), comma-separated", got=nu)
    refine = args.refine or ([1, 2] if args.quick else [1, 2, 4])
    if max(refine) > 16:
        raise ConfigError("--refine", "refinements from 1 to 16 (h down to 0.3125 mm)", got=max(refine))
    cases = [c.strip() for c in str(args.cases).split(",") if c.strip()]
    if not cases or any(c not in CASES for c in cases):
        raise ConfigError("--cases", f"some of {', '.join(CASES)}, comma-separated", got=args.cases)
    require_fem()
    return device, topologies, poisson, sorted(set(refine)), [c for c in CASES if c in cases]


def run(args) -> int:
    """Run ``torchdeform bench elasticity``; returns the exit status."""
    device, topologies, poisson, refine, cases = _options(args)
    repeats = args.repeats or (3 if args.quick else 5)
    target_s = 0.02 if args.quick else 0.2
    dtype = getattr(torch, args.dtype)
    compile_ = not (args.no_compile or args.quick)
    saved = torch.get_num_threads()
    if args.threads:
        torch.set_num_threads(args.threads)
    rows, refs, cache = [], {}, {}
    redirect = contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext()
    try:
        with redirect, progress(len(topologies) * len(poisson) * len(refine), "bench elasticity") as bar:
            for nu in poisson:
                bar.set_postfix_str(f"FEM nu {nu:g}")
                refs[nu] = fem_reference(nu, cases)
            for topology in topologies:
                for nu in poisson:
                    for r in refine:
                        bar.set_postfix_str(f"{topology} neighbours, nu {nu:g}, h {5 / r:g} mm")
                        row = {"topology": topology, "nu": nu, "refine": r, "h_mm": 5.0 / r, "cells": 12 * r}
                        row.update(accuracy_fields(topology, nu, r, cases, refs[nu]))
                        row.update(
                            step_times(
                                topology,
                                nu,
                                r,
                                dtype=dtype,
                                device=device,
                                compile=compile_,
                                repeats=repeats,
                                target_s=target_s,
                                cache=cache,
                            )
                        )
                        rows.append(row)
                        bar.update(1)
    finally:
        torch.set_num_threads(saved)
    machine = machine_info(device)
    if args.threads:
        machine["threads"] = args.threads
    extra = {
        "machine": machine,
        "youngs_modulus": YOUNGS,
        "cases": cases,
        "fem": {str(nu): ref for nu, ref in refs.items()},
        "scenes": _SCENES,
        "timing": f"symplectic Euler on the beam of the row, {args.dtype}, {device}, the median of {repeats} "
        f"runs of enough steps for ~{target_s:g} s",
        "engines": _engines(rows),
    }
    if args.out:
        _plot(rows, Path(args.out), machine)
    if not args.json:
        print(
            f"Elastic lattice (E = {YOUNGS:g} Pa) against scikit-fem; step times on the 10 x 10 x 60 mm beam, "
            f"symplectic Euler, {args.dtype}, {device}, threads {machine['threads']}, torch {machine['torch']}"
        )
    emit("elasticity", args, rows, COLUMNS, extra=extra)
    if not args.json:
        for what, (engine, why) in extra["engines"].items():
            print(f"{what}: {engine} ({why})")
        if args.out:
            print(f"wrote {Path(args.out) / 'elasticity.csv'} and {Path(args.out) / 'elasticity.png'}")
    return 0


_SCENES = {
    "uniaxial": "free 10 mm cube, normal tractions of +-100 Pa on its two W faces (uniaxial stress)",
    "shear": "5 x 50 x 50 mm box between bonded plates, top moved 1 % of the height (h <= 2.5 mm only)",
    "cantilever": "10 x 10 x 60 mm beam clamped at one end, gravity 9.81 m/s^2 across it, 1000 kg/m^3",
    "punch": "20 x 40 x 40 mm block on a fixed base, bonded 10 x 10 mm punch pressed 0.5 mm",
}


def _engines(rows) -> dict:
    """``{"springs alone": (engine, why), "springs + cell term": (engine, why)}`` of the last row (one line each)."""
    if not rows:
        return {}
    last = rows[-1]
    return {
        "springs alone": (last["springs_engine"], last["springs_why"]),
        "springs + cell term": (last["volume_engine"], last["volume_why"]),
    }


_STYLE = {"shear": ("tab:blue", "shear"), "cantilever": ("tab:orange", "tip"), "punch": ("tab:green", "punch")}


def _plot(rows, out: Path, machine: dict) -> None:
    """``elasticity.png``: |ratio - 1| against h (left) and against the step time with the cell term (right)."""
    fig, (left, right) = axes(figsize=(11, 4.5), ncols=2)
    from matplotlib.ticker import NullLocator

    markers = dict(zip(dict.fromkeys(r["nu"] for r in rows), "osD^v<>"))
    lines = {18: "--", 26: "-", 14: ":"}
    for colour, short in _STYLE.values():
        for topology in dict.fromkeys(r["topology"] for r in rows):
            for nu, marker in markers.items():
                pts = [
                    (r["h_mm"], r["volume_ms"], abs(r[f"{short}_ratio"] - 1))
                    for r in rows
                    if r["topology"] == topology and r["nu"] == nu and r[f"{short}_ratio"] is not None
                ]
                if not pts:
                    continue
                pts.sort()
                label = f"{short}, {topology} nb, nu {nu:g}"
                kw = dict(color=colour, ls=lines.get(topology, "-"), marker=marker, label=label)
                left.plot([p[0] for p in pts], [p[2] for p in pts], **kw)
                right.plot([p[1] for p in pts], [p[2] for p in pts], **kw)
    left.set_xlabel("cell side h (mm)")
    right.set_xlabel("ms per step, springs + cell term")
    for ax in (left, right):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylabel("|lattice / FEM - 1|")
        ax.grid(True, which="both", alpha=0.3)
    hs = sorted({r["h_mm"] for r in rows})
    left.xaxis.set_minor_locator(NullLocator())
    left.set_xticks(hs, [f"{h:g}" for h in hs])
    left.invert_xaxis()
    left.set_title("error against resolution")
    right.set_title(f"error against step time (threads {machine['threads']}, torch {machine['torch']})")
    if left.lines:
        left.legend(fontsize=6, ncol=2)
    save_plot(fig, out, "elasticity.png")
