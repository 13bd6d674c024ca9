"""How ``torchdeform bench accuracy`` runs: the references, one case per row, and the command.

:func:`run_case` times one :class:`~.methods.Method` at one parameter on a scene's
:class:`~.methods.Context` and compares it with the scene's reference (:func:`dynamic_reference`,
:func:`static_reference`); :func:`run` is the command: it checks the options, plans the cases of
every chosen scene, runs them, and hands the rows to :mod:`.report`. :func:`inverse_warp_rows`
adds the rows of the fixed-point inverse warp (``--inverse-warp``).
"""

from __future__ import annotations

import contextlib
import math
import statistics
import sys
import time
from pathlib import Path

import torch

from ...errors import ConfigError, DivergenceError
from ...options import integer, number
from ...sim.engine import simulate
from ...sim.integrators import RK4
from ..common import add_common, device_sync, emit, machine_info, progress
from .methods import (
    METHODS,
    N_OUT,
    SKIPPED,
    STATIC_DT,
    Context,
    Method,
    Reference,
    StaticResolution,
    _displacement,
    kinetic_energy,
    relative_error,
)
from .report import TARGETS, mark_pareto, plot, recommend, report, static_orders
from .scenes import SCENES

__all__ = [
    "HELP",
    "COLUMNS",
    "TABLE",
    "REPEAT_LIMIT_S",
    "BLOWUP_ERROR",
    "BLOWUP_ENERGY",
    "dynamic_reference",
    "static_reference",
    "run_case",
    "add_arguments",
    "run",
    "inverse_warp_rows",
]

HELP = (
    "error against wall time of every integrator on standard scenes (load, stiff, drag, "
    "supports) and a resolution sweep; Pareto front and a computed recommendation"
)

#: Columns every row has (``None`` where a column does not apply).
COLUMNS = (
    "scene",
    "method",
    "param",
    "n",
    "dt",
    "bound_s",
    "bound_of",
    "dt_bound",
    "steps",
    "error",
    "wall_s",
    "repeats",
    "status",
    "pareto",
    "note",
)

TABLE = [
    ("scene", "scene", None),
    ("method", "method", None),
    ("param", "param", None),
    ("dt", "dt [s]", "{:.2e}"),
    ("dt_bound", "dt/bound", "{:.3g}"),
    ("steps", "steps", None),
    ("error", "error", "{:.2e}"),
    ("wall_s", "wall [s]", "{:.3g}"),
    ("status", "status", None),
    ("pareto", "pareto", None),
    ("note", "note", None),
]

REPEAT_LIMIT_S = 0.5  # runs slower than this are timed once
BLOWUP_ERROR = 10.0  # a finished run with a larger error has blown up ...
BLOWUP_ENERGY = 100.0  # ... or a kinetic energy above this many times the reference's largest


# -------------------------------------------------------------------- references


def dynamic_reference(ctx: Context, ref_div: float) -> Reference:
    """RK4 at ``rk4 bound / ref_div``, checked against RK4 at twice that step."""
    bound = ctx.bound("rk4")
    steps, dt = ctx.steps_for(bound / ref_div, multiple_of=2 * N_OUT)
    model, state0 = ctx.model, ctx.model.rest_state()
    t0 = time.perf_counter()
    _, rec = simulate(model, state0, dt, steps, integrator=RK4(), record_every=steps // N_OUT, warn=False)
    wall = time.perf_counter() - t0
    _, rec2 = simulate(
        model, state0, 2 * dt, steps // 2, integrator=RK4(), record_every=steps // (2 * N_OUT), warn=False
    )
    x = rec["x"][1:]
    scale = _displacement(x, model.X)
    kinetic = kinetic_energy(model.mass, rec["v"][1:])
    check = relative_error(rec2["x"][1:], x, scale)
    info = dict(
        method="rk4",
        dt=dt,
        dt_bound=dt / bound,
        steps=steps,
        wall_s=wall,
        max_displacement_m=scale,
        halving_diff=check,
        error_estimate=check / 15,
        text=(
            f"RK4 at dt = {dt:.3g} s (rk4 bound / {bound / dt:.3g}), {steps} steps; halving check: "
            f"RK4 at 2 dt differs by {check:.2e} (relative), so the reference is good to about "
            f"{check / 15:.1e}; max displacement {scale * 1e3:.3g} mm"
        ),
    )
    return Reference(x, scale, info, kinetic=kinetic)


def static_reference(ctx: Context, method: StaticResolution) -> Reference:
    """Equilibrium on the fine grid (``ctx.n``), Newton to 1e-10."""
    t0 = time.perf_counter()
    tol = method.tolerance(1e-10, ctx.model.dtype)
    x, it = method.solve(ctx.model, tol)
    wall = time.perf_counter() - t0
    x = x.detach().cpu()[None]
    scale = _displacement(x, ctx.model.X)
    info = dict(
        method="static",
        n=ctx.n,
        newton_iterations=it,
        wall_s=wall,
        max_displacement_m=scale,
        text=(
            f"static equilibrium at n = {ctx.n} ({ctx.n**3} nodes), implicit Euler at dt = "
            f"{STATIC_DT:g} s = Newton, {it} iterations to {tol:.1g}; compared at the coarse nodes; "
            f"max displacement {scale * 1e3:.3g} mm"
        ),
    )
    return Reference(x, scale, info)


# ----------------------------------------------------------------- run and rows


def _row(scene: str, method: Method, param, info: dict, **values) -> dict:
    row = dict.fromkeys(COLUMNS)
    row.update(scene=scene, method=method.name, param=method.label(param), pareto=False)
    row.update({k: info.get(k) for k in ("n", "dt", "bound_s", "bound_of", "dt_bound", "steps", "note")})
    row.update(values)
    return row


def run_case(ctx: Context, method: Method, param, repeats: int, *, sync=lambda: None) -> dict:
    """Run one case; returns its row (see :data:`COLUMNS`)."""
    job = method.prepare(ctx, param)
    with torch.no_grad():
        job.warmup()
        times, x = [], None
        try:
            while len(times) < repeats:
                sync()
                t0 = time.perf_counter()
                out = job.run()
                sync()
                times.append(time.perf_counter() - t0)
                x = out if x is None else x
                if times[0] > REPEAT_LIMIT_S:
                    break
        except DivergenceError as e:
            sync()
            wall = time.perf_counter() - t0
            info = dict(job.info)
            if info.get("steps") is not None:
                info["steps"] = e.step
            return _row(
                ctx.scene.name,
                method,
                param,
                info,
                wall_s=wall,
                repeats=1,
                status="diverged",
                note=f"DivergenceError at step {e.step}: {e.quantity}",
            )
    info = dict(job.info)
    if job.iters:
        info["steps"] = job.iters[0]
    wall = statistics.median(times)
    x, v = x if isinstance(x, tuple) else (x, None)
    common = dict(wall_s=wall, repeats=len(times))
    if not bool(torch.isfinite(x).all()) or (v is not None and not bool(torch.isfinite(v).all())):
        return _row(ctx.scene.name, method, param, info, status="diverged", note="non-finite positions", **common)
    err = method.compare(ctx, x)
    why = None
    if err > BLOWUP_ERROR:
        why = f"error {err:.2g} > {BLOWUP_ERROR:g}"
    elif v is not None and ctx.reference.kinetic:
        ratio = kinetic_energy(ctx.model.mass, v) / ctx.reference.kinetic
        if ratio > BLOWUP_ENERGY:
            why = f"kinetic energy {ratio:.2g}x the reference's"
    if why:
        return _row(
            ctx.scene.name,
            method,
            param,
            info,
            error=err,
            status="diverged",
            note=why + ": blowing up, not yet caught by the monitor",
            **common,
        )
    return _row(ctx.scene.name, method, param, info, error=err, status="ok", **common)


# ---------------------------------------------------------------------- command


def _list(value, key, kind, allowed=None):
    """``"a,b"`` (or a list) -> list of ``kind``; None stays None. Raises ConfigError."""
    if value is None:
        return None
    items = value if isinstance(value, (list, tuple)) else [v.strip() for v in str(value).split(",") if v.strip()]
    try:
        values = [kind(v) for v in items]
    except ValueError:
        raise ConfigError(key, f"comma-separated values of type {kind.__name__}", got=value) from None
    if not values:
        raise ConfigError(key, "at least one value", got=value)
    if allowed is not None:
        bad = [v for v in values if v not in allowed]
        if bad:
            raise ConfigError(key, "some of " + ", ".join(allowed), got=",".join(map(str, bad)))
    return values


def add_arguments(p) -> None:
    """Options of ``torchdeform bench accuracy`` (the common ones from :func:`bench.add_common`)."""
    add_common(p)
    p.set_defaults(dtype="float64", threads=1)
    p.description = (
        HELP + ". Defaults differ from bench speed: float64 and 1 thread (the scenes are "
        "tiny; one thread is fastest). Knoche relaxation is left out (it does not integrate "
        "these dynamics); 'supports' stands for falling onto supports, with the supports as "
        "fixed nodes (smooth; contact with obstacles is torchdeform.interact's)."
    )
    p.add_argument("--scenes", default=None, help="comma-separated subset of " + ",".join(SCENES) + " (default all)")
    p.add_argument("--methods", default=None, help="comma-separated subset of " + ",".join(METHODS) + " (default all)")
    p.add_argument(
        "--n", type=integer(lo=2), default=None, help="grid size of the dynamic scenes, n^3 nodes (default 5; quick 4)"
    )
    p.add_argument("--resolutions", default=None, help="grid sizes of the resolution sweep (default 3,5,9; quick 2,3)")
    p.add_argument(
        "--ref-n",
        type=integer(lo=2),
        default=None,
        help="grid size of the sweep's reference (default 17; quick 5); n-1 must divide ref-n - 1",
    )
    p.add_argument(
        "--ref-div",
        type=number(lo=1),
        default=None,
        help="reference step = RK4 bound / REF_DIV (default 20, 5 for the stiff scene; quick 5)",
    )
    p.add_argument(
        "--repeats",
        type=integer(lo=1),
        default=None,
        help=f"timed repeats, the median is kept (default 3; quick 1); runs slower than "
        f"{REPEAT_LIMIT_S:g} s are timed once",
    )
    p.add_argument("--targets", default=None, help="error targets of the recommendation (default 1e-1,1e-2,1e-4)")
    p.add_argument(
        "--inverse-warp",
        action="store_true",
        help="also rows of the fixed-point inverse warp (torchdeform.volume): round-trip error "
        "|X + u(X) - p| in voxels against iterations and wall time (scene 'inverse-warp')",
    )


def _check_args(args):
    """Validate the options; lists are parsed here so that a mistake is one ConfigError line.

    Returns ``(device, n, resolutions, ref_n)`` and sets ``args.scenes``, ``args.methods``,
    ``args.targets`` to lists (or None).
    """
    args.scenes = _list(args.scenes, "--scenes", str, list(SCENES))
    args.methods = _list(args.methods, "--methods", str, list(METHODS))
    args.targets = _list(args.targets, "--targets", float) or list(TARGETS)
    if args.threads is not None and args.threads < 1:
        raise ConfigError("--threads", "an integer >= 1", got=args.threads)
    device = str(torch.device(args.device))
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("--device", "cpu, or cuda on a machine with CUDA", got=args.device)
    n = args.n or (4 if args.quick else 5)
    if n < 3:
        raise ConfigError("--n", "an integer >= 3", got=n)
    res = _list(args.resolutions, "--resolutions", int) or list(
        StaticResolution().quick_resolutions if args.quick else StaticResolution().resolutions
    )
    ref_n = args.ref_n or (5 if args.quick else 17)
    if min(res) < 2 or ref_n < 3:
        raise ConfigError("--resolutions", "grid sizes >= 2 (and --ref-n >= 3)", got=res)
    for r in res:
        if r >= ref_n or (ref_n - 1) % (r - 1):
            raise ConfigError(
                "--resolutions",
                f"sizes n < ref-n = {ref_n} with n - 1 dividing {ref_n - 1} (e.g. 3, 5, 9 for 17)",
                got=r,
            )
    if args.ref_div is not None and not (math.isfinite(args.ref_div) and args.ref_div >= 2):
        raise ConfigError("--ref-div", "a number >= 2", got=args.ref_div)
    if args.repeats is not None and args.repeats < 1:
        raise ConfigError("--repeats", "an integer >= 1", got=args.repeats)
    if any(not (0 < t < math.inf) for t in args.targets):  # also rejects NaN
        raise ConfigError("--targets", "positive error targets", got=args.targets)
    return device, n, res, ref_n


def run(args) -> int:
    """``torchdeform bench accuracy``: compute the rows, print/write them; returns 0."""
    device, n, resolutions, ref_n = _check_args(args)
    old_threads = torch.get_num_threads()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    try:
        return _run(args, device, n, resolutions, ref_n)
    finally:
        torch.set_num_threads(old_threads)


def _plan(args, device, dtype, n, resolutions, ref_n):
    """Build each scene's :class:`Context` and its cases.

    Returns ``(plan, not_run)`` with ``plan = [(ctx, [(method, param), ...]), ...]``.
    """
    methods = [m for k, m in METHODS.items() if args.methods is None or k in args.methods]
    methods = [
        StaticResolution(resolutions=resolutions, quick_resolutions=resolutions) if m.name == "static" else m
        for m in methods
    ]
    plan, not_run = [], []
    for sc in (SCENES[s] for s in (args.scenes or SCENES)):
        ms = [m for m in methods if m.applies(sc)]
        if not ms:
            continue
        ctx = Context(sc, ref_n if sc.static else n, args.quick, dtype, device)
        cases = []
        for m in ms:
            for p in m.params(ctx):
                why = m.skip(ctx, p)
                if why:
                    not_run.append(dict(scene=sc.name, method=m.name, param=m.label(p), reason=why))
                else:
                    cases.append((m, p))
        if cases:
            plan.append((ctx, cases))
    if not plan:
        raise ConfigError(
            "--methods",
            "at least one method that applies to the chosen scenes",
            got=",".join(args.methods or []) + " on " + ",".join(args.scenes or []),
        )
    return plan, not_run


def _run(args, device, n, resolutions, ref_n) -> int:
    dtype = getattr(torch, args.dtype)
    repeats = args.repeats or (1 if args.quick else 3)
    sync = device_sync(device)
    rows, references = [], {}
    redirect = contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext()
    with redirect:
        plan, not_run = _plan(args, device, dtype, n, resolutions, ref_n)
        with progress(sum(1 + len(cases) for _, cases in plan), "bench accuracy") as bar:
            for ctx, cases in plan:
                sc = ctx.scene
                bar.set_postfix_str(f"{sc.name} reference")
                if sc.static:
                    ctx.reference = static_reference(ctx, next(m for m, _ in cases))
                else:
                    div = args.ref_div or min(sc.ref_div or 20, 5 if args.quick else math.inf)
                    ctx.reference = dynamic_reference(ctx, div)
                references[sc.name] = dict(
                    ctx.reference.info, duration_s=None if sc.static else ctx.duration, description=sc.help
                )
                bar.update(1)
                for m, p in cases:
                    bar.set_postfix_str(f"{sc.name} {m.name} {m.label(p)}")
                    rows.append(run_case(ctx, m, p, repeats, sync=sync))
                    bar.update(1)
    static_orders(rows)
    mark_pareto(rows)
    recs = recommend(rows, targets=args.targets)
    used = list(dict.fromkeys(r["method"] for r in rows))
    if getattr(args, "inverse_warp", False):  # after the recommendation: not an integrator
        inv_rows, references["inverse-warp"] = inverse_warp_rows(args.quick, dtype=dtype, repeats=repeats)
        rows += inv_rows
        mark_pareto(rows)
    machine = machine_info(device)
    extra = {
        "machine": machine,
        "dtype": args.dtype,
        "quick": bool(args.quick),
        "references": references,
        "methods": {k: METHODS[k].description for k in used},
        "skipped": dict(SKIPPED),
        "not_run": not_run,
        "error": (
            "max over the output times T/4, T/2, 3T/4, T and the nodes of |x - x_ref|, over the "
            "reference's max displacement; static rows: at the coarse nodes, against the fine grid"
        ),
        "wall_time": (
            f"perf_counter around the run after an untimed warm-up step; median of {repeats} "
            f"repeat(s), runs over {REPEAT_LIMIT_S:g} s timed once"
        ),
        "scaling": (
            "k = E h s (h spacing, s = share of the grid cells bordering the spring), c = tau k, masses from density"
        ),
        "targets": list(args.targets),
        "recommendations": recs,
    }
    out = Path(args.out) if args.out else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        plot(rows, out / "accuracy.png", references=references)
    if not args.json:
        print(
            f"accuracy against wall time, {args.dtype}, {device}, {machine['threads']} thread(s), "
            f"torch {machine['torch']}, median of {repeats} repeat(s) (runs over {REPEAT_LIMIT_S:g} s: 1)"
        )
    display = [dict(r, pareto="*" if r["pareto"] else "", note=r["note"] or "") for r in rows]
    emit("accuracy", args, rows, TABLE, extra=extra, display=display)
    if not args.json:
        print(report(extra))
        if out is not None:
            print(f"wrote {out / 'accuracy.csv'} and {out / 'accuracy.png'}")
    return 0


# ------------------------------------------------------------- inverse warp rows


def inverse_warp_rows(quick: bool, *, dtype=torch.float64, repeats: int = 3, seed: int = 0):
    """Rows of the fixed-point inverse warp (:func:`torchdeform.volume.inverse_points`).

    A ``64^3`` volume (quick ``32^3``) under ``9^3`` node offsets (quick ``5^3``), uniform random
    up to 0.15 node spacings (neighbouring nodes differ by at most 0.3 spacings per component, so
    ``|grad u|_F <= 0.9 < 1``: a contraction, well below the folding limit). At every voxel centre
    ``p``, ``X_k`` after ``k`` iterations of ``X <- p - u(X)`` (``k = 0``: first order
    ``p - u(p)``); the error is the largest round-trip residual ``|X_k + u(X_k) - p|`` in voxels
    (not relative, unlike the mechanical scenes) and the wall time that of ``inverse_points``.

    Returns:
        ``(rows, reference)``: rows with :data:`COLUMNS` (scene ``inverse-warp``, method
        ``fixed-point``, ``steps`` = iterations, ``n`` = nodes per axis) and a reference dict.
    """
    from ...volume import DisplacementField, identity_points, inverse_points, inverse_residual

    size, nodes = (32, 5) if quick else (64, 9)
    AMP = 0.15
    iters = (0, 1, 2, 4, 8) if quick else (0, 1, 2, 3, 4, 6, 8, 12, 16, 24)
    g = torch.Generator().manual_seed(seed)
    spacing = (size - 1) / (nodes - 1)
    offsets = (torch.rand(3, nodes, nodes, nodes, generator=g, dtype=torch.float64) * 2 - 1) * AMP * spacing
    field = DisplacementField(offsets.to(dtype), (size,) * 3)
    p = identity_points((size,) * 3, dtype=dtype)
    rows = []
    info = dict(n=nodes, dt=None, bound_s=None, bound_of=None, dt_bound=None)
    with torch.no_grad():
        for k in iters:
            times = []
            for _ in range(max(1, repeats)):
                t0 = time.perf_counter()
                X, _ = inverse_points(field, p, iters=k, tol=0.0)
                times.append(time.perf_counter() - t0)
            err = float(inverse_residual(field, X, p).max())
            rows.append(
                _row(
                    "inverse-warp",
                    _InverseWarp,
                    k,
                    dict(info, steps=k),
                    error=err,
                    wall_s=statistics.median(times),
                    repeats=len(times),
                    status="ok",
                    note="max |X + u(X) - p| [voxels]",
                )
            )
    reached = [r["steps"] for r in rows if r["error"] < 1e-3]
    ref = dict(
        method="exact",
        n=nodes,
        max_displacement_m=None,
        text=(
            f"fixed-point inverse warp X <- p - u(X) at all {size}^3 voxel centres, {nodes}^3 node offsets "
            f"up to {AMP:g} node spacings ({AMP * spacing:.2g} voxels), {str(dtype).replace('torch.', '')}; "
            f"error = max round-trip residual |X + u(X) - p| in voxels (exact inverse: 0); below 1e-3 "
            f"voxel from {min(reached) if reached else 'no'} iteration(s)"
        ),
    )
    return rows, ref


class _InverseWarpMethod(Method):
    name = "fixed-point"
    description = "fixed-point inverse warp X <- p - u(X) (torchdeform.volume.inverse_points)"

    def label(self, param):
        return f"{param} it"


_InverseWarp = _InverseWarpMethod()
