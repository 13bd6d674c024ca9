"""``torchdeform bench speed``: spring-step throughput of symplectic Euler on a damped cube.

Msprings/s, node-steps/s and ms/step for n^3 grids, topologies, eager, native (the C kernel's
packed step) and compiled, dtypes and thread counts, against NVIDIA Warp's CPU backend (:mod:`.warp_baseline`), and implicit Euler on a
40 x 10 x 10 beam shaped like SOFA's spring-beam benchmark.

**Memory traffic.** ``bytes_per_step`` (:func:`bytes_per_step`) is the least a symplectic step
must move: every tensor it reads, read once, and the new state written once::

    bytes_per_step = 4 B 3 N e + sum of the stored bytes of the per-node and per-spring fields read

with ``B`` bodies, ``N`` nodes as the mode stores them (``D H W`` for eager, the packed length
``P`` with its halo for native and compiled), ``e`` bytes per value (4 for float32); ``4 B 3 N e``
is x and v read and written. The fields are those of the mode's model as stored: the stiffness,
rest length and damping (and a strain law's parameters), the inverse mass, the mass where the
step reads it (gravity, or the native step's fused kernel), home-spring stiffness and rest
positions where present, and the packed layout's inside-mask. A field counts only where it has a
value per node or per spring (one value, or one per spring direction, counts 0: it stays in
cache or in the code). ``gb_per_s = bytes_per_step / (s per step) / 1e9``. ``copy_gb_per_s`` is
the device's copy bandwidth (:func:`~torchdeform.bench.common.copy_bandwidth`, bytes read plus
written), measured once in the same run; ``of_copy = gb_per_s / copy_gb_per_s`` says how near a
step comes to streaming its data at the speed of a plain copy. Eager steps make many passes
over memory, so theirs is well below 1.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import statistics
import sys
import time
from pathlib import Path

import torch

from ..errors import ConfigError
from ..options import integer
from ..outputs import save_figure
from ..sim.grid import Grid
from ..sim.integrators import ImplicitEuler, SymplecticEuler
from ..sim.model import Model
from .common import (
    busy_neighbour,
    copy_bandwidth,
    device_sync,
    emit,
    format_table,
    int_list,
    machine_info,
    progress,
    speed_cube,
)

__all__ = [
    "add_arguments",
    "run",
    "speed_row",
    "beam_row",
    "beam_scene",
    "bytes_per_step",
    "SPEED_COLUMNS",
    "BEAM_COLUMNS",
]


SPEED_COLUMNS = [
    ("grid", "grid", None),
    ("topology", "topo", None),
    ("material", "material", None),
    ("mode", "mode", None),
    ("dtype", "dtype", None),
    ("threads", "thr", None),
    ("springs", "springs", "{:,}"),
    ("steps", "steps", None),
    ("ms_per_step", "ms/step", "{:.3f}"),
    ("msprings_per_s", "Msprings/s", "{:.1f}"),
    ("node_steps_per_s", "Mnode-steps/s", None),
    ("mb_per_step", "MB/step", "{:.2f}"),
    ("gb_per_s", "GB/s", "{:.2f}"),
    ("of_copy", "of copy", "{:.3f}"),
    ("vs_warp", "x Warp", "{:.2f}"),
    ("peak_rss_mb", "peak MB", "{:.0f}"),
    ("compile_s", "compile s", "{:.1f}"),
    ("compile_cache", "compile", None),
    ("max_abs_diff", "max|diff|", "{:.1e}"),
    ("vs_idle", "busy/idle", "{:.2f}"),
]
BEAM_COLUMNS = [
    ("scene", "scene", None),
    ("mode", "mode", None),
    ("dtype", "dtype", None),
    ("threads", "thr", None),
    ("cg_iters", "CG iters", None),
    ("steps", "steps", None),
    ("ms_per_step", "ms/step", "{:.2f}"),
    ("steps_per_s", "steps/s", "{:.0f}"),
    ("compile_s", "compile s", "{:.1f}"),
    ("compile_cache", "compile", None),
    ("max_abs_diff", "max|diff|", "{:.1e}"),
    ("vs_idle", "busy/idle", "{:.2f}"),
]


def add_arguments(p) -> None:
    """Options of ``torchdeform bench speed``."""
    p.add_argument("--quick", action="store_true", help="tiny sizes, few steps: a smoke run in seconds")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout, nothing else")
    p.add_argument("--out", default=None, help="folder for speed.csv and speed.png")
    p.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    p.add_argument(
        "--sizes",
        type=int_list("--sizes"),
        default=None,
        help="grid sizes n (n^3 nodes), comma-separated (default 16,32,64,128; quick 8,12)",
    )
    p.add_argument(
        "--topologies",
        type=int_list("--topologies"),
        default=None,
        help="neighbour counts, comma-separated (default 6,18,26; quick 6,26)",
    )
    p.add_argument("--dtypes", default=None, help="float32,float64 (default both; quick float32)")
    p.add_argument(
        "--threads",
        type=int_list("--threads"),
        default=None,
        help="CPU thread counts, comma-separated (default: torch's setting, as users run it; a "
        "compiled step of a small problem then runs on one thread, see step_threads)",
    )
    p.add_argument(
        "--contention",
        action="store_true",
        help="time every row twice: idle, and with a busy process beside it (rows with "
        "contention: true; the table shows busy/idle)",
    )
    p.add_argument(
        "--materials",
        default="springs",
        help="springs,elastic: the cube of equal springs (k 100 N/m; default) and/or an Elastic body "
        "(E 10 kPa, nu 0.45: springs from the cells plus the cell term); the targets compare the two at 64^3",
    )
    p.add_argument(
        "--modes",
        default=None,
        help="eager,native,compiled: the packed-step modes timed (default all that run here; "
        "native: the C kernel on the CPU, the Triton kernel on CUDA)",
    )
    p.add_argument("--no-compile", action="store_true", help="eager rows only")
    p.add_argument("--no-warp", action="store_true", help="skip the NVIDIA Warp rows")
    p.add_argument("--no-beam", action="store_true", help="skip the implicit-Euler beam")
    p.add_argument(
        "--steps", type=integer(lo=1), default=None, help="steps per timed repeat (default: enough for ~0.2 s, 3..200)"
    )
    p.add_argument(
        "--repeats", type=integer(lo=1), default=None, help="timed repeats, the median is kept (default 5; quick 3)"
    )


def beam_scene(*, dtype=torch.float32, device="cpu"):
    """The implicit benchmark, shaped like SOFA's spring-beam benchmark.

    A 16 x 4 x 4 m beam of 40 x 10 x 10 nodes (W is the long axis), 26 neighbours, stiffness 100
    and damping 1 divided by the rest length (SOFA's convention), 20 kg in all, gravity along -D,
    the w = 0 end fixed. Returns ``(model, state, dt)`` with dt = 0.01 s.
    """
    grid = Grid((10, 10, 40), spacing=(4 / 9, 4 / 9, 16 / 39), topology=26)
    fixed = torch.zeros(grid.shape, dtype=torch.bool)
    fixed[:, :, 0] = True
    model = Model(
        grid,
        stiffness=100.0,
        damping=1.0,
        normalize=True,
        mass=20.0 / grid.num_nodes,
        gravity=(-9.81, 0, 0),
        fixed=fixed,
        dtype=dtype,
        device=device,
    )
    return model, model.rest_state(), 0.01


def bytes_per_step(model, mode: str, *, batch: int = 1) -> int:
    """The bytes one symplectic Euler step of ``mode`` must move at the least (see the module docstring).

    Args:
        model: what the step reads: the grid-layout :class:`~torchdeform.sim.model.Model` for
            ``"eager"``, the :class:`~torchdeform.sim.packed.PackedModel` for ``"native"`` and
            ``"compiled"``.
        mode: ``"eager"``, ``"native"`` or ``"compiled"``.
        batch: bodies in the state ``B``.

    Returns:
        bytes: x and v (``(B, 3, N)`` values each) read and written once, plus each per-node or
        per-spring field the step reads, once (a field shared by the batch counts once).
    """
    from ..sim.packed import PackedModel

    packed = isinstance(model, PackedModel)
    if mode not in ("eager", "native", "compiled") or packed != (mode != "eager"):
        raise ValueError(f"bytes_per_step: mode {mode!r} with a {type(model).__name__}")
    nodes = model.P if packed else model.grid.num_nodes
    itemsize = torch.empty((), dtype=model.dtype).element_size()
    fields = [model.stiffness, model.rest_length, model.damping, *model.law_params, model.inv_mass]
    if model.gravity is not None or mode == "native":  # the fused kernel reads the mass always
        fields.append(model.mass)
    if model.k_home is not None:
        fields += [model.k_home, model.X]
    if packed:
        fields.append(model.inside)

    def stored(t) -> int:
        """Bytes of ``t`` as stored, 0 unless it has a value per node (per spring) along its node axes."""
        if t is None:
            return 0
        node_axes = (t.dim() - 1,) if packed else (t.dim() - 3, t.dim() - 2, t.dim() - 1)
        shape = (model.P,) if packed else model.grid.shape
        if t.dim() < len(node_axes) or any(t.shape[a] != m or t.stride(a) == 0 for a, m in zip(node_axes, shape)):
            return 0
        return math.prod(n for n, st in zip(t.shape, t.stride()) if st != 0) * t.element_size()

    return 4 * batch * 3 * nodes * itemsize + sum(stored(t) for t in fields)


def _reset_peak() -> bool:
    """Reset the process's peak resident memory (Linux ``clear_refs``); False where unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _peak_rss_mb():
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def _time_steps(step, state, steps: int, repeats: int, sync) -> float:
    """Median seconds per step over ``repeats`` runs of ``steps`` steps from ``state``."""
    times = []
    for _ in range(repeats):
        s = state
        sync()
        t0 = time.perf_counter()
        for _ in range(steps):
            s = step(s)
        sync()
        times.append((time.perf_counter() - t0) / steps)
    return statistics.median(times)


def _measure(step, state, *, steps, repeats, target_s, sync, max_steps=200):
    """Warm up (and time the first call: compilation), size and time a step.

    Returns ``(first_result, seconds_per_step, first_call_s, steps)``.
    """
    t0 = time.perf_counter()
    first = step(state)
    sync()
    first_s = time.perf_counter() - t0
    t0 = time.perf_counter()  # second warm-up call, also sizes the run
    step(state)
    sync()
    warm = max(time.perf_counter() - t0, 1e-7)
    if steps is None:
        steps = int(min(max_steps, max(3, math.ceil(target_s / warm))))
    return first, _time_steps(step, state, steps, repeats, sync), first_s, steps


@dataclasses.dataclass
class _Timed:
    """One timed mode (:func:`_time_mode`)."""

    first: object  # the state after one step, grid layout
    sec: float  # median seconds per step
    model: object  # the model the step reads: the grid-layout model (eager) or the packed one
    fields: dict  # row fields: threads, steps, compile_s, compile_cache, max_abs_diff, fallback
    retime: object  # () -> seconds per step, the same step timed again (under other conditions)
    governor: object = None  # the compiled step's thread governor (it may take fewer threads beside a busy process)


def _time_mode(
    integ, model, state, dt, mode, *, steps, repeats, target_s, sync, reference=None, max_steps=200
) -> _Timed:
    """Time ``integ`` on ``model`` from ``state``, eager (grid layout) or packed (the state kept packed between steps).

    Without gradients. ``compile_s`` is None for eager, the C kernel's build (or load) for
    ``"native"``, the first call's wall time for ``"compiled"``, whose ``compile_cache`` says
    whether inductor ``"built"`` the graph or ``"loaded"`` it from its disk cache (another
    process compiled it before). ``max_abs_diff`` compares the first step with ``reference`` (or None).
    """
    from .._compile import graph_cache_counts  # the fast path, only when timed
    from ..sim.compiled import CompiledStep

    with torch.no_grad():
        fallback, threads, cs, built_s, cache = False, torch.get_num_threads(), None, None, None
        if mode == "eager":
            step, start = (lambda s: integ.step(model, s, dt)), state
        else:
            t0 = time.perf_counter()
            cs = (
                CompiledStep(integ, model, dt, enable=False, force_form="native")
                if mode == "native"
                else CompiledStep(integ, model, dt)
            )
            step, start, threads = cs.step_packed, cs.packed.pack_state(state), cs.threads
            if mode == "native":
                step(start)  # builds (or loads) the kernel
                built_s = time.perf_counter() - t0
        counts = graph_cache_counts() if mode == "compiled" else None
        first, sec, first_s, steps = _measure(
            step, start, steps=steps, repeats=repeats, target_s=target_s, sync=sync, max_steps=max_steps
        )
        if cs is not None:
            first = cs.packed.unpack_state(first)
            fallback = not cs.compiled and mode == "compiled"
        if mode == "compiled":
            hits, misses = (a - b for a, b in zip(graph_cache_counts(), counts))
            cache = "loaded" if hits and not misses else "built" if misses else None
        diff = None
        if reference is not None:
            diff = max(float((first.x - reference.x).abs().max()), float((first.v - reference.v).abs().max()))

    def retime() -> float:
        with torch.no_grad():
            return _time_steps(step, start, steps, repeats, sync)

    compile_s = {"eager": None, "native": built_s}.get(mode, first_s)
    return _Timed(
        first,
        sec,
        model if cs is None else cs.packed,
        dict(
            threads=threads, steps=steps, compile_s=compile_s, compile_cache=cache, max_abs_diff=diff, fallback=fallback
        ),
        retime,
        cs.governor if cs else None,
    )


def speed_row(
    n: int,
    topology: int,
    mode: str,
    *,
    dtype=torch.float32,
    device="cpu",
    steps=None,
    repeats: int = 5,
    target_s: float = 0.2,
    reference=None,
    contention: bool = False,
    material: str = "springs",
) -> dict:
    """Time symplectic Euler steps on :func:`speed_cube` (of ``material``); one row of the speed table.

    ``mode`` is ``"eager"`` (``SymplecticEuler.step``, shifted slices), ``"native"`` (the packed
    step uncompiled, one C kernel per step: :func:`~torchdeform.sim.native.symplectic_step`;
    ``compile_s`` is the kernel's build, or its load from the disk cache) or ``"compiled"`` (the
    packed fast path under ``torch.compile``, :class:`~torchdeform.sim.compiled.CompiledStep`);
    the packed modes keep the state packed between steps. ``reference``: the eager state after one step, to report ``max_abs_diff``. Warm-up
    and compilation are excluded from the timing; ``compile_s`` is the first call's wall time.
    ``peak_rss_mb`` is the process's peak resident memory during the row (Linux), torch included;
    on CUDA the peak of the memory torch allocated on the device during the row.
    ``bytes_per_step``, ``gb_per_s``: :func:`bytes_per_step` and it over the time per step (GB/s).
    """
    reset = _reset_peak()
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats(torch.device(device))
    model, state, dt = speed_cube(n, topology, dtype=dtype, device=device, material=material)
    integ = SymplecticEuler()
    sync = device_sync(device)
    row = {
        "grid": f"{n}^3",
        "n": n,
        "topology": topology,
        "material": material,
        "mode": mode,
        "dtype": str(dtype).replace("torch.", ""),
        "threads": torch.get_num_threads(),
        "device": device,
        "nodes": model.grid.num_nodes,
        "springs": model.grid.num_springs,
    }
    timed = _time_mode(
        integ, model, state, dt, mode, steps=steps, repeats=repeats, target_s=target_s, sync=sync, reference=reference
    )

    row["bytes_per_step"] = bytes_per_step(timed.model, mode, batch=state.x.shape[0])

    def rates(sec):
        return dict(
            ms_per_step=sec * 1e3,
            msprings_per_s=row["springs"] / sec / 1e6,
            node_steps_per_s=row["nodes"] / sec,
            gb_per_s=row["bytes_per_step"] / sec / 1e9,
        )

    row.update(
        timed.fields,
        repeats=repeats,
        **rates(timed.sec),
        peak_rss_mb=_peak_rss_mb() if reset and device == "cpu" else None,
        contention=False,
    )
    if device.startswith("cuda"):
        row["peak_rss_mb"] = torch.cuda.max_memory_allocated(torch.device(device)) / 2**20
    if contention:
        row["_busy"] = _busy_row(row, timed, rates)
    row["_first"] = timed.first
    return row


def beam_row(
    mode: str,
    *,
    dtype=torch.float32,
    device="cpu",
    cg_iters: int = 20,
    steps=None,
    repeats: int = 5,
    target_s: float = 0.5,
    reference=None,
    contention: bool = False,
) -> dict:
    """Implicit Euler steps per second on :func:`beam_scene`.

    ``cg_iters`` CG iterations, no tolerance: every step does exactly that many, as SOFA's
    benchmark. ``mode``, ``threads`` and ``contention`` as in :func:`speed_row`.
    """
    model, state, dt = beam_scene(dtype=dtype, device=device)
    integ = ImplicitEuler(cg_iters=cg_iters, cg_tol=0)
    sync = device_sync(device)
    row = {
        "scene": "beam 40x10x10",
        "mode": mode,
        "dtype": str(dtype).replace("torch.", ""),
        "threads": torch.get_num_threads(),
        "device": device,
        "nodes": model.grid.num_nodes,
        "springs": model.grid.num_springs,
        "dt": dt,
        "cg_iters": cg_iters,
    }
    timed = _time_mode(
        integ,
        model,
        state,
        dt,
        mode,
        steps=steps,
        repeats=repeats,
        target_s=target_s,
        sync=sync,
        reference=reference,
        max_steps=100 if mode == "eager" else 500,
    )

    def rates(sec):
        return dict(ms_per_step=sec * 1e3, steps_per_s=1.0 / sec)

    row.update(timed.fields, repeats=repeats, **rates(timed.sec), contention=False)
    if contention:
        row["_busy"] = _busy_row(row, timed, rates)
    row["_first"] = timed.first
    return row


def _busy_row(row: dict, timed: _Timed, rates) -> dict:
    """``row`` timed again (``timed.retime()``) beside a busy process: ``contention: true``, ``vs_idle``."""
    gov = timed.governor
    before = dict(gov.steps) if gov is not None else {}
    with busy_neighbour():
        busy = timed.retime()
    # steps per thread count while busy (a compiled step's governor may drop threads)
    used = {n: k - before.get(n, 0) for n, k in gov.steps.items() if k > before.get(n, 0)} if gov else None
    return dict(
        row,
        **rates(busy),
        contention=True,
        vs_idle=timed.sec / busy,
        compile_s=None,
        compile_cache=None,
        threads_busy=used,
    )


def _warp_row(n, topology, dtype, steps, repeats, target_s, reference):
    from .warp_baseline import warp_speed_row

    row = warp_speed_row(
        n,
        topology=topology,
        variant="atomic",
        dtype=dtype,
        steps=steps,
        repeats=repeats,
        target_s=target_s,
        reference=reference,
    )
    for key in ("peak_rss_mb", "bytes_per_step", "gb_per_s"):
        row.setdefault(key, None)
    return row


def _options(args):
    """The checked options: ``(device, sizes, topologies, dtypes, threads)``."""
    device = str(torch.device(args.device))
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("--device", "cpu, or cuda on a machine with CUDA", got=args.device)
    sizes = args.sizes or ([8, 12] if args.quick else [16, 32, 64, 128])
    topologies = args.topologies or ([6, 26] if args.quick else [6, 18, 26])
    dtypes = (args.dtypes or ("float32" if args.quick else "float32,float64")).split(",")
    threads = args.threads or [torch.get_num_threads()]
    if min(sizes) < 2:
        raise ConfigError("--sizes", "grid sizes >= 2", got=sizes)
    for t in topologies:
        if t not in (6, 14, 18, 26):
            raise ConfigError("--topologies", "6, 14, 18 or 26", got=t)
    for d in dtypes:
        if d not in ("float32", "float64"):
            raise ConfigError("--dtypes", "float32 and/or float64, comma-separated", got=args.dtypes)
    if min(threads) < 1:
        raise ConfigError("--threads", "integers >= 1", got=threads)
    if args.steps is not None and args.steps < 1:
        raise ConfigError("--steps", "an integer >= 1", got=args.steps)
    materials = [m.strip() for m in str(args.materials).split(",") if m.strip()]
    if not materials or any(m not in ("springs", "elastic") for m in materials):
        raise ConfigError("--materials", "springs and/or elastic, comma-separated", got=args.materials)
    args.materials = materials
    modes = [m.strip() for m in str(args.modes or "eager,native,compiled").split(",") if m.strip()]
    if not modes or any(m not in ("eager", "native", "compiled") for m in modes):
        raise ConfigError("--modes", "eager, native and/or compiled, comma-separated", got=args.modes)
    args.modes = modes
    return device, sizes, topologies, dtypes, threads


def _plan(args, device, sizes, topologies, dtypes, threads):
    """``(tasks, warp_ok, warp_why)``: the measurements ``[(kind, n, topology, dtype, threads, mode, material), ...]``."""
    from ..sim import native

    modes = ["eager"] if args.no_compile else ["eager", "compiled"]
    # the kernel's packed step, uncompiled (the "native" engine): C on the CPU where a C compiler
    # works, Triton on CUDA
    native_ok = not native.unavailable_on(device)
    torch_modes = ["eager", "native", "compiled"] if native_ok and not args.no_compile else modes
    torch_modes = [m for m in torch_modes if m in getattr(args, "modes", torch_modes)]
    warp_ok, warp_why = (False, "--no-warp") if args.no_warp else (False, "Warp runs on the CPU rows only")
    if not args.no_warp and device == "cpu":
        from .warp_baseline import warp_available

        warp_ok, warp_why = warp_available()
    # --quick compiles one shape only (the smallest grid, first topology): compilation costs
    # 10-60 s per shape on 2 cores, the smoke run must stay well under a minute.
    tasks = [
        ("torch", n, t, d, th, m, mat)
        for d in dtypes
        for th in threads
        for t in topologies
        for n in sizes
        for mat in args.materials
        for m in torch_modes
        if not (m != "eager" and args.quick and (n, t) != (min(sizes), topologies[0]))
        and not (mat == "elastic" and t == 6)
    ]
    if warp_ok:
        tasks += [
            ("warp", n, t, d, 1, "warp", "springs")
            for d in dtypes
            for t in topologies
            for n in sizes
            if not (args.quick and (n, t) != (min(sizes), topologies[-1]))
        ]
    if not args.no_beam:
        tasks += [
            ("beam", None, None, d, th, m, "springs")
            for d in dtypes[:1]
            for th in threads
            for m in modes
            if not (args.quick and m == "compiled")
        ]
    return tasks, warp_ok, warp_why


def _run_tasks(args, tasks, device, repeats, target_s):
    """Run the measurements; returns ``(rows, beam_rows)``."""
    rows, beam_rows, refs, beam_refs = [], [], {}, {}
    saved_threads = torch.get_num_threads()
    redirect = contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext()
    try:
        with redirect, progress(len(tasks), "bench speed") as bar:
            for kind, n, t, d, th, m, mat in tasks:
                bar.set_postfix_str(f"{kind} {n or ''} {t or ''} {mat} {d} {th}thr {m}")
                torch.set_num_threads(th)
                dtype = getattr(torch, d)
                if kind == "beam":
                    # ~1 s per repeat: a few-ms step timed over only ~60 steps is at the mercy
                    # of a busy host's hiccups.
                    row = beam_row(
                        m,
                        dtype=dtype,
                        device=device,
                        steps=args.steps,
                        repeats=repeats,
                        target_s=target_s if args.quick else 1.0,
                        reference=beam_refs.get(d),
                        contention=args.contention,
                    )
                    first = row.pop("_first")
                    beam_refs.setdefault(d, first)
                    beam_rows += [row] + ([row.pop("_busy")] if args.contention else [])
                elif kind == "warp":
                    row = _warp_row(n, t, dtype, args.steps, repeats, target_s, refs.get((n, t, d, "springs")))
                    rows.append(row)
                else:
                    row = speed_row(
                        n,
                        t,
                        m,
                        dtype=dtype,
                        device=device,
                        steps=args.steps,
                        repeats=repeats,
                        target_s=target_s,
                        reference=refs.get((n, t, d, mat)),
                        contention=args.contention,
                        material=mat,
                    )
                    first = row.pop("_first")
                    refs.setdefault((n, t, d, mat), first)
                    rows += [row] + ([row.pop("_busy")] if args.contention else [])
                bar.update(1)
    finally:
        torch.set_num_threads(saved_threads)
    return rows, beam_rows


def run(args) -> int:
    """Run ``torchdeform bench speed``; returns the exit status."""
    device, sizes, topologies, dtypes, threads = _options(args)
    repeats = args.repeats or (3 if args.quick else 5)
    target_s = 0.02 if args.quick else 0.2
    tasks, warp_ok, warp_why = _plan(args, device, sizes, topologies, dtypes, threads)
    copy_gb_per_s = copy_bandwidth(device)  # before the rows: its buffers are freed again
    rows, beam_rows = _run_tasks(args, tasks, device, repeats, target_s)

    warp_by = {
        (r["n"], r["topology"], r["dtype"]): r["msprings_per_s"]
        for r in rows
        if r["mode"].startswith("warp") and not r.get("contention")
    }
    for r in rows:
        r.setdefault("material", "springs")
        r["node_steps_per_s"] = float(r["node_steps_per_s"])
        w = warp_by.get((r["n"], r["topology"], r["dtype"])) if r["material"] == "springs" else None
        r["vs_warp"] = r["msprings_per_s"] / w if w and not r["mode"].startswith("warp") else None
        r["of_copy"] = None if r.get("gb_per_s") is None else r["gb_per_s"] / copy_gb_per_s
    headline = [
        r
        for r in rows
        if (r["n"], r["topology"], r["dtype"], r["mode"], r["material"]) == (64, 26, "float32", "compiled", "springs")
        and not r.get("contention")
    ]
    headline = max(headline, key=lambda r: r["threads"]) if headline else None
    ratio = headline["vs_warp"] if headline else None
    bandwidth_case = _bandwidth_case(rows)
    machine = machine_info(device)
    machine.pop("threads")
    extra = {
        "machine": machine,
        "scene": _SCENE,
        "ratio_vs_warp": ratio,
        "ratio_vs_warp_case": "64^3, 26 neighbours, float32, symplectic Euler, compiled (most threads) "
        "over Warp CPU (atomic edge list, 1 thread)",
        "warp": "measured" if warp_ok else f"skipped: {warp_why}",
        "copy_gb_per_s": copy_gb_per_s,
        "bandwidth_case": bandwidth_case,
        "beam_scene": _BEAM,
        "beam": beam_rows,
        "targets": _targets(rows, beam_rows),
        "launch_shapes": _launch_shapes(),
    }
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        _speed_plot(rows, Path(args.out) / "speed.png", machine)
    display = [
        dict(
            r,
            node_steps_per_s=f"{r['node_steps_per_s'] / 1e6:.2f}",
            mb_per_step=None if r.get("bytes_per_step") is None else r["bytes_per_step"] / 1e6,
            mode=r["mode"]
            + (" (eager fallback)" if r.get("fallback") else "")
            + (" busy" if r.get("contention") else "")
            + _threads_note(r),
        )
        for r in rows
    ]
    beam_display = [dict(r, mode=r["mode"] + (" busy" if r.get("contention") else "")) for r in beam_rows]
    if not args.json:
        print(f"symplectic Euler on a damped n^3 cube, {device}, torch {machine['torch']}")
        print(f"copy bandwidth (read + write): {copy_gb_per_s:.1f} GB/s")
        if not warp_ok:
            print(f"Warp rows skipped: {warp_why}")
    emit("speed", args, rows, SPEED_COLUMNS, extra=extra, display=display)
    if not args.json:
        if beam_rows:
            print(f"\nimplicit Euler: {_BEAM}")
            print(format_table(beam_display, BEAM_COLUMNS))
        if ratio is not None:
            print(
                f"\nratio_vs_warp (64^3, 26 neighbours, float32, compiled, {headline['threads']} threads): {ratio:.1f}x"
            )
        for shape in extra["launch_shapes"]:
            print(
                f"Triton launch shapes, {shape['kernel']} at P = {shape['P']:,} x {shape['bodies']} (block, planes, warps: ms): "
                + ", ".join(
                    f"{c['block']},{c['planes']},{c['warps']}{',bits' if c['bits'] else ''}: "
                    + ("failed" if c["ms"] is None else f"{c['ms']:.3f}")
                    for c in shape["timed"]
                )
            )
        if bandwidth_case is not None:
            b = bandwidth_case
            print(
                f"bandwidth (256^3, 26 neighbours, float32, {b['mode']}): {b['gb_per_s']:.1f} GB/s, "
                f"{b['of_copy']:.2f} of copy ({b['bytes_per_step'] / 1e6:.0f} MB per step in {b['ms_per_step']:.2f} ms)"
            )
        for name, t in extra["targets"].items():
            print(
                f"{name}: {t['value']:.3g} (target {t['target']:g}{', busy/idle ' + format(t['busy_vs_idle'], '.2f') if t.get('busy_vs_idle') is not None else ''}): "
                f"{'met' if t['met'] else 'missed'}"
            )
        if args.out:
            print(f"wrote {Path(args.out) / 'speed.csv'} and {Path(args.out) / 'speed.png'}")
    return 0


def _bandwidth_case(rows) -> dict | None:
    """The memory traffic of the fastest packed row (native or compiled) at 256^3, 26 neighbours, float32 (most threads, idle), or None."""
    case = [
        r
        for r in rows
        if (r["n"], r["topology"], r["dtype"]) == (256, 26, "float32")
        and r["mode"] in ("native", "compiled")
        and r["material"] == "springs"
        and not r.get("contention")
    ]
    if not case:
        return None
    most = max(r["threads"] for r in case)
    r = min((r for r in case if r["threads"] == most), key=lambda r: r["ms_per_step"])
    return {
        "case": f"256^3, 26 neighbours, float32, symplectic Euler, {r['mode']} (most threads)",
        "mode": r["mode"],
        "bytes_per_step": r["bytes_per_step"],
        "ms_per_step": r["ms_per_step"],
        "gb_per_s": r["gb_per_s"],
        "of_copy": r["of_copy"],
        "threads": r["threads"],
    }


def _launch_shapes() -> list:
    """The Triton kernel's launch shapes timed in this process (:data:`~torchdeform.sim.native_cuda.timings`), per kernel and size."""
    from ..sim import native_cuda

    return [
        {
            "kernel": kernel,
            "P": P,
            "bodies": B,
            "timed": [dict(c._asdict(), ms=ms) for c, ms in times],
            "chosen": native_cuda.chosen[(kernel, P, plane, B)]._asdict(),
        }
        for (kernel, P, plane, B), times in native_cuda.timings.items()
    ]


def _threads_note(row) -> str:
    """`` (1 thread 93%)``: the thread count a busy row's governor ran most steps on, when not the row's."""
    used = row.get("threads_busy")
    if not used:
        return ""
    n, k = max(used.items(), key=lambda item: item[1])
    return "" if n == row["threads"] else f" ({n} thread{'s' if n > 1 else ''} {100 * k / sum(used.values()):.0f}%)"


#: speed targets on 2 cores: the implicit beam (SOFA about 110 on a desktop CPU) and 64^3 explicit
TARGETS = {"beam_steps_per_s": 220.0, "msprings_64": 1000.0, "busy_vs_idle": 0.4, "elastic_vs_springs_64": 0.5}


def _targets(rows, beam_rows) -> dict:
    """The fastest packed float32 beam and 64^3, 26-neighbour rows against :data:`TARGETS` (those measured).

    Packed: ``"compiled"`` or ``"native"`` (the engines ``torchdeform run`` picks from); the busy
    ratio is that of the same engine and thread count.
    """
    out = {}

    def pick(rs, **key):
        return [
            r
            for r in rs
            if r["mode"] in ("compiled", "native")
            and r["dtype"] == "float32"
            and all(r.get(k) == v for k, v in key.items())
        ]

    for name, rs, value in (
        ("beam_steps_per_s", pick(beam_rows), "steps_per_s"),
        ("msprings_64", pick(rows, n=64, topology=26, material="springs"), "msprings_per_s"),
    ):
        idle = [r for r in rs if not r.get("contention")]
        if not idle:
            continue
        best = max(idle, key=lambda r: r[value])
        busy = [r for r in rs if r.get("contention") and (r["threads"], r["mode"]) == (best["threads"], best["mode"])]
        ratio = busy[0]["vs_idle"] if busy else None
        met = best[value] >= TARGETS[name] and (ratio is None or ratio >= TARGETS["busy_vs_idle"])
        out[name] = {
            "value": best[value],
            "target": TARGETS[name],
            "mode": best["mode"],
            "threads": best["threads"],
            "busy_vs_idle": ratio,
            "met": met,
        }
    elastic = _elastic_target(pick(rows, n=64, topology=26, material="elastic"), out.get("msprings_64"))
    if elastic is not None:
        out["elastic_vs_springs_64"] = elastic
    return out


def _elastic_target(rows, springs) -> dict | None:
    """The fastest Elastic 64^3 row's throughput over the fastest springs row's (one run), or None."""
    idle = [r for r in rows if not r.get("contention")]
    if not idle or springs is None:
        return None
    best = max(idle, key=lambda r: r["msprings_per_s"])
    busy = [r for r in rows if r.get("contention") and (r["threads"], r["mode"]) == (best["threads"], best["mode"])]
    ratio = busy[0]["vs_idle"] if busy else None
    value = best["msprings_per_s"] / springs["value"]
    target = TARGETS["elastic_vs_springs_64"]
    return {
        "value": value,
        "target": target,
        "mode": best["mode"],
        "threads": best["threads"],
        "busy_vs_idle": ratio,
        "met": value >= target and (ratio is None or ratio >= TARGETS["busy_vs_idle"]),
    }


_SCENE = (
    "symplectic Euler, dt 1e-4 s, damped cube (1 cm spacing, k 100 N/m, c 0.05 N s/m, 1 g nodes), "
    "no gravity; msprings_per_s = springs / (s per step) / 1e6, median over repeats, warm-up excluded; "
    "peak_rss_mb: peak resident memory of the process during the row (CUDA: peak device memory torch allocated); "
    "bytes_per_step: x and v read and written once plus the per-node and per-spring fields read once; "
    "gb_per_s = bytes_per_step / (s per step) / 1e9; of_copy = gb_per_s / copy_gb_per_s (device copy, read + write)"
)
_BEAM = (
    "40x10x10 nodes, 26 neighbours, k 100/l0, c 1/l0, 20 kg, one end fixed, gravity, dt 0.01 s, "
    "exactly cg_iters CG iterations per step (SOFA's spring-beam benchmark shape)"
)


def _speed_plot(rows, path: Path, machine: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    topologies = sorted({r["topology"] for r in rows})
    fig, axes = plt.subplots(1, len(topologies), figsize=(4.5 * len(topologies), 4), sharey=True, squeeze=False)
    for ax, topo in zip(axes[0], topologies):
        keys = sorted({(r["mode"], r["dtype"], r["threads"]) for r in rows if r["topology"] == topo})
        for mode, dt, th in keys:
            pts = sorted(
                (r["nodes"], r["msprings_per_s"])
                for r in rows
                if (r["topology"], r["mode"], r["dtype"], r["threads"]) == (topo, mode, dt, th)
            )
            style = {"compiled": "-", "native": "-.", "eager": "--"}.get(mode, ":")
            ax.plot(*zip(*pts), marker="o", ls=style, label=f"{mode} {dt} {th} thr")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("nodes")
        ax.set_title(f"{topo} neighbours")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("Msprings/s")
    axes[0][-1].legend(fontsize=7)
    fig.suptitle(f"spring-step throughput, symplectic Euler ({machine['device']}, torch {machine['torch']})")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
