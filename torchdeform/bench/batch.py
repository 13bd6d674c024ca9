"""``torchdeform bench batch``: many bodies stepped in one batch.

**Scene.** The speed scene (:func:`~torchdeform.bench.common.speed_cube`: an ``n^3`` damped cube,
1 cm spacing, k = 100 N/m, c = 0.05 N s/m, 1 g nodes, no gravity, dt = 1e-4 s; default n = 16,
26 neighbours, float32), ``B`` bodies of it in one state ``(B, 3, n, n, n)``, all sharing the
model. Body 0 is the speed scene's own start; the others start from their own small random
perturbations (:func:`batch_state`).

**Engines.** ``eager`` (:meth:`SymplecticEuler.step <torchdeform.sim.integrators.Integrator.step>`
on the grid layout), ``native`` (one kernel per step: C on the CPU, Triton on CUDA,
:func:`~torchdeform.sim.native.symplectic_step`; where that kernel runs) and ``compiled``
(:class:`~torchdeform.sim.compiled.CompiledStep` on the packed layout, the state kept packed
between steps; one compilation per batch size). Each row
is timed as in ``bench speed`` (warm-up and compilation excluded, the median of the repeats, the
device synchronised before and after each timed run of steps, none inside it).

**Rows.** ``ms_per_step``; ``body_steps_per_s = B / (s per step)``; ``per_body_speedup``: that
over the same engine's one-body row (how much cheaper a body's step gets in a batch);
``max_abs_diff``: body 0 after one step against the same engine's one-body run (m and m/s;
batching must not change a body). The target: 1,024 bodies at least 100 times faster per body
than one (:data:`TARGET_SPEEDUP`), by the compiled engine (eager with ``--no-compile``).

Example:
    torchdeform bench batch --quick
    torchdeform bench batch --device cuda --bodies 1,16,128,1024,4096 --json --out batch-run
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import torch

from ..checks import check_memory, usable_device
from ..errors import ConfigError
from ..options import integer
from ..outputs import axes, save_plot
from ..sim.integrators import SymplecticEuler
from ..sim.model import State
from .common import add_common, device_sync, emit, int_list, machine_info, progress, speed_cube

__all__ = [
    "COLUMNS",
    "TARGET_BODIES",
    "TARGET_SPEEDUP",
    "add_arguments",
    "run",
    "batch_state",
    "batch_row",
    "memory_needed",
]

#: the batch size of the target, and how many times faster per body it must step than one body
TARGET_BODIES = 1024
TARGET_SPEEDUP = 100.0

COLUMNS = [
    ("bodies", "bodies", "{:,}"),
    ("engine", "engine", None),
    ("threads", "thr", None),
    ("steps", "steps", None),
    ("ms_per_step", "ms/step", "{:.3f}"),
    ("body_steps_per_s", "body-steps/s", "{:,.0f}"),
    ("per_body_speedup", "per body x", "{:.1f}"),
    ("peak_mb", "peak MB", "{:.0f}"),
    ("compile_s", "compile s", "{:.1f}"),
    ("max_abs_diff", "max|diff|", "{:.1e}"),
]


def add_arguments(p) -> None:
    """Options of ``torchdeform bench batch``."""
    add_common(p)
    p.add_argument(
        "--bodies",
        type=int_list("--bodies"),
        default=None,
        help="batch sizes B, comma-separated (default 1,16,128,1024; quick 1,8; 1 is always run: the reference)",
    )
    p.add_argument("--size", type=integer(lo=2), default=16, help="nodes per edge n of each body (default 16)")
    p.add_argument("--topology", type=integer(lo=6), default=26, help="neighbours: 6, 14, 18 or 26 (default 26)")
    p.add_argument("--no-compile", action="store_true", help="the eager engine only")
    p.add_argument(
        "--steps", type=integer(lo=1), default=None, help="steps per timed repeat (default: enough for ~0.2 s, 3..200)"
    )
    p.add_argument(
        "--repeats", type=integer(lo=1), default=None, help="timed repeats, the median is kept (default 5; quick 3)"
    )


def batch_state(model, state: State, bodies: int, *, seed: int = 0) -> State:
    """``bodies`` bodies of ``model`` in one state ``(bodies, 3, D, H, W)`` on the model's device.

    Body 0 is ``state`` (one body); body ``b > 0`` starts at the rest positions plus 0.1 mm and
    with 1 mm/s Gaussian noise per coordinate, drawn on the CPU from a generator seeded with
    ``seed + 1`` (the draws of all bodies together), like :func:`~torchdeform.bench.common.speed_cube`.
    """
    if bodies == 1:
        return state
    g = torch.Generator().manual_seed(seed + 1)
    shape = (bodies - 1, *model.X.shape[1:])
    dx = (1e-4 * torch.randn(shape, generator=g, dtype=model.dtype)).to(model.device)
    dv = (1e-3 * torch.randn(shape, generator=g, dtype=model.dtype)).to(model.device)
    return State(torch.cat([state.x, model.X + dx]), torch.cat([state.v, dv]), t=state.t)


def memory_needed(n: int, bodies: int, *, itemsize: int = 4) -> int:
    """Bytes a step of ``bodies`` bodies of ``n^3`` nodes needs at the least.

    Six fields of ``(bodies, 3, (n + 2)^3)`` values (the packed length with its halo, a lower
    bound): the state, the new state and two temporaries; the eager step's peak measured on a
    CPU is about nine ``(bodies, 3, n^3)`` fields, which is less than this for no ``n``
    below 16 and about as much at 16.
    """
    return 6 * bodies * 3 * (n + 2) ** 3 * itemsize


def batch_row(
    model,
    state: State,
    dt: float,
    engine: str,
    *,
    device="cpu",
    steps=None,
    repeats: int = 5,
    target_s: float = 0.2,
) -> dict:
    """Time ``engine`` (``"eager"``, ``"native"`` or ``"compiled"``) stepping the batch ``state``; one row.

    ``state``: ``(B, 3, D, H, W)`` on ``model``'s device. The row has ``bodies``, ``ms_per_step``,
    ``body_steps_per_s`` (B / s per step), ``peak_mb`` (the process's peak resident memory on a
    CPU, the device memory torch allocated on CUDA, MiB), the compiled engine's ``compile_s``,
    ``compile_cache`` and ``fallback``, and ``_first``: the batch after one step, a grid-layout
    :class:`~torchdeform.sim.model.State` ``(B, 3, D, H, W)``.
    """
    from .speed import _peak_rss_mb, _reset_peak, _time_mode

    if engine not in ("eager", "native", "compiled"):
        raise ValueError(f"batch_row: engine 'eager', 'native' or 'compiled', got {engine!r}")
    cuda = device.startswith("cuda")
    reset = _reset_peak()
    if cuda:
        torch.cuda.reset_peak_memory_stats(torch.device(device))
    bodies = state.x.shape[0]
    timed = _time_mode(
        SymplecticEuler(),
        model,
        state,
        dt,
        engine,
        steps=steps,
        repeats=repeats,
        target_s=target_s,
        sync=device_sync(device),
    )
    peak = (
        torch.cuda.max_memory_allocated(torch.device(device)) / 2**20 if cuda else (_peak_rss_mb() if reset else None)
    )
    fields = {k: timed.fields[k] for k in ("threads", "steps", "compile_s", "compile_cache", "fallback")}
    return {
        "bodies": bodies,
        "engine": engine,
        "grid": f"{model.grid.shape[0]}^3",
        "topology": model.grid.topology,
        "dtype": str(model.dtype).replace("torch.", ""),
        "device": device,
        "nodes_per_body": model.grid.num_nodes,
        **fields,
        "repeats": repeats,
        "ms_per_step": timed.sec * 1e3,
        "body_steps_per_s": bodies / timed.sec,
        "peak_mb": peak,
        "_first": timed.first,
    }


def _diff(a: State, b: State) -> float:
    return max(float((a.x - b.x).abs().max()), float((a.v - b.v).abs().max()))


def _options(args):
    """The checked options: ``(device, n, topology, bodies, dtype)``."""
    device = str(usable_device(args.device))
    if args.topology not in (6, 14, 18, 26):
        raise ConfigError("--topology", "6, 14, 18 or 26", got=args.topology)
    bodies = sorted({1, *(args.bodies or ([1, 8] if args.quick else [1, 16, 128, 1024]))})
    dtype = getattr(torch, args.dtype)
    n = args.size
    check_memory(
        "--bodies",
        memory_needed(n, bodies[-1], itemsize=torch.empty((), dtype=dtype).element_size()),
        f"a batch of {bodies[-1]:,} bodies of {n}^3 nodes",
        device=device,
        got=bodies[-1],
    )
    return device, n, args.topology, bodies, dtype


def run(args) -> int:
    """Run ``torchdeform bench batch``; returns the exit status."""
    device, n, topology, bodies, dtype = _options(args)
    from ..sim import native

    engines = ["eager"] if args.no_compile else ["eager", "compiled"]
    # the kernel's fused step (C on the CPU, Triton on CUDA), where it runs
    if not args.no_compile and not native.unavailable_on(device):
        engines.insert(1, "native")
    repeats = args.repeats or (3 if args.quick else 5)
    target_s = 0.02 if args.quick else 0.2
    saved = torch.get_num_threads()
    if args.threads:
        torch.set_num_threads(args.threads)
    rows, ref = [], {}
    redirect = contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext()
    try:
        model, one, dt = speed_cube(n, topology, dtype=dtype, device=device)
        with redirect, progress(len(engines) * len(bodies), "bench batch") as bar:
            for engine in engines:
                for b in bodies:
                    bar.set_postfix_str(f"{engine} {b} bodies")
                    state = batch_state(model, one, b)
                    row = batch_row(
                        model, state, dt, engine, device=device, steps=args.steps, repeats=repeats, target_s=target_s
                    )
                    del state
                    out = row.pop("_first")
                    first = State(out.x[:1].clone(), out.v[:1].clone(), t=out.t)  # body 0
                    del out
                    if b == 1:
                        ref[engine] = (first, row["body_steps_per_s"])
                    row["per_body_speedup"] = row["body_steps_per_s"] / ref[engine][1]
                    row["max_abs_diff"] = None if b == 1 else _diff(first, ref[engine][0])
                    rows.append(row)
                    bar.update(1)
    finally:
        torch.set_num_threads(saved)
    compiled_vs_eager = _diff(ref["compiled"][0], ref["eager"][0]) if "compiled" in ref else None
    target = _target(rows, engines[-1])
    machine = machine_info(device)
    extra = {
        "machine": machine,
        "scene": f"{n}^3 damped cube, {topology} neighbours, {args.dtype}, symplectic Euler, dt {dt:g} s "
        "(bench speed's scene), B bodies in one state (B, 3, n, n, n)",
        "compiled_vs_eager": compiled_vs_eager,
        "target": target,
        "met": target["met"],
    }
    if args.out:
        _plot(rows, Path(args.out), machine, n, topology)
    if not args.json:
        print(
            f"symplectic Euler on B bodies of a damped {n}^3 cube, {topology} neighbours, {device}, torch {machine['torch']}"
        )
    emit("batch", args, rows, COLUMNS, extra=extra)
    if not args.json:
        if compiled_vs_eager is not None:
            print(f"one body, one step: compiled vs eager {compiled_vs_eager:.1e}")
        if target["value"] is None:
            print(f"target: {TARGET_BODIES:,} bodies >= {TARGET_SPEEDUP:g}x faster per body than one: not measured")
        else:
            print(
                f"target: {TARGET_BODIES:,} bodies >= {TARGET_SPEEDUP:g}x faster per body than one "
                f"({target['engine']}): {target['value']:.1f}x, {'met' if target['met'] else 'missed'}"
            )
        if args.out:
            print(f"wrote {Path(args.out) / 'batch.csv'} and {Path(args.out) / 'batch.png'}")
    return 0


def _target(rows, engine: str) -> dict:
    """The ``engine``'s :data:`TARGET_BODIES` row against :data:`TARGET_SPEEDUP` (``met`` None if not run)."""
    row = next((r for r in rows if r["engine"] == engine and r["bodies"] == TARGET_BODIES), None)
    value = None if row is None or row.get("fallback") else row["per_body_speedup"]
    return {
        "bodies": TARGET_BODIES,
        "per_body_speedup": TARGET_SPEEDUP,
        "engine": engine,
        "value": value,
        "met": None if value is None else bool(value >= TARGET_SPEEDUP),
    }


def _plot(rows, out: Path, machine: dict, n: int, topology: int) -> None:
    fig, ax = axes(figsize=(6.5, 4.5))
    for engine in dict.fromkeys(r["engine"] for r in rows):
        pts = sorted((r["bodies"], r["body_steps_per_s"]) for r in rows if r["engine"] == engine)
        ax.plot(*zip(*pts), marker="o", ls="-" if engine == "compiled" else "--", label=engine)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("bodies in the batch")
    ax.set_ylabel("body-steps/s")
    ax.set_title(f"{n}^3 bodies, {topology} neighbours ({machine['device']}, torch {machine['torch']})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_plot(fig, out, "batch.png")
