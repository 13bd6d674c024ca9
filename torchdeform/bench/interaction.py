"""``torchdeform bench interaction``: a tool touching the tissue, at simulation and haptic rates.

Two kinds of rows:

* ``mode = step``: steps per second of a sphere tool (radius 3 spacings) pressing 2 spacings
  into the top of an ``n^3``, 26-neighbour body (1 cm spacing, bottom fixed), with projection
  contact and the force readout inside the step; compiled (and eager with ``--eager``) for
  ``n`` in ``--sizes`` (default 8, 16, 24, 32, 48; quick 8, 16). Target: >= 1,000 steps/s at
  ``n = 24`` on 2 CPU cores (goal ``n = 32``).
* ``mode = haptic``: :class:`~torchdeform.interact.haptic.HapticLoop` on an ``n^3`` body
  (``--haptic-size``, default 64; quick 24) driven for ``--seconds`` by a device path that
  presses the tool in: the force output rate (target: 1 kHz) and the body's own rate.

Rows carry ``n``, ``topology``, ``mode``, ``engine``, ``hz``, ``force_N`` (the tool's force along
D at the end), ``compile_s`` and ``threads``.

It runs on one CPU thread unless ``--threads`` says otherwise: an interactive step on a body this
small is short, and with two threads each step waits at OpenMP barriers; when another process
keeps a core busy, those waits grow a hundredfold (16^3: 7,900 steps/s on one thread, 64 on two
with a busy neighbour; measured 2026-11-24 on the 2-core CI machine).

Example:
    torchdeform bench interaction --quick
    torchdeform bench interaction --json --out bench-out
"""

from __future__ import annotations

import statistics
import time

import torch

from ..errors import ConfigError
from ..options import integer, number
from ..outputs import axes, save_plot
from .common import add_common, emit, int_list, machine_info, progress

__all__ = ["COLUMNS", "add_arguments", "run", "pressing_scene"]

COLUMNS = [
    ("n", "n", None),
    ("topology", "topology", None),
    ("mode", "mode", None),
    ("engine", "engine", None),
    ("hz", "Hz", "{:,.0f}"),
    ("body_hz", "body Hz", "{:,.0f}"),
    ("force_N", "force N", "{:.4f}"),
    ("compile_s", "compile s", "{:.1f}"),
    ("threads", "threads", None),
]
SPACING = 0.01


def add_arguments(p) -> None:
    """The options of ``torchdeform bench interaction``."""
    add_common(p)
    p.add_argument(
        "--sizes",
        type=int_list("--sizes"),
        default=None,
        help="body sizes n (n^3 nodes) of the step rows (default 8,16,24,32,48; quick 8,16)",
    )
    p.add_argument("--haptic-size", type=integer(lo=2), default=None, help="n of the haptic row (default 64; quick 24)")
    p.add_argument(
        "--seconds", type=number(lo=0, lo_open=True), default=None, help="haptic run time (default 3; quick 1)"
    )
    p.add_argument("--steps", type=integer(lo=1), default=None, help="timed steps per repeat (default 300; quick 100)")
    p.add_argument("--eager", action="store_true", help="also time the eager step")
    p.add_argument("--no-compile", action="store_true", help="eager only (no torch.compile: a smoke run)")


def pressing_scene(n: int, *, dtype=torch.float32, device="cpu", path: bool = True):
    """The bench body and tool: ``(model, tool, dt)``.

    An ``n^3`` 26-neighbour body (k = 50 N/m, c = 0.1 N s/m, 1 g per node, bottom fixed), a sphere
    of radius 3 spacings above the top centre; with ``path`` it presses 2 spacings in over 0.1 s.
    """
    from ..interact import ProjectionContact, Sphere, Tool
    from ..sim.grid import Grid
    from ..sim.model import Model
    from ..sim.stability import time_step_bound

    grid = Grid((n, n, n), spacing=SPACING, topology=26)
    top, mid, r = (n - 1) * SPACING, (n - 1) * SPACING / 2, 3 * SPACING
    above = (top + r, mid, mid)
    if path:
        tool = Tool(Sphere(r), path=[(0.0, above), (0.1, (top + r - 2 * SPACING, mid, mid))], name="probe")
    else:
        tool = Tool(Sphere(r), position=torch.tensor(above, dtype=torch.float64), name="probe")
    model = Model(
        grid,
        stiffness=50.0,
        damping=0.1,
        mass=1e-3,
        fixed=grid.face("bottom"),
        dtype=dtype,
        device=device,
        interactions=[ProjectionContact(tool)],
    )
    return model, tool, 0.9 * time_step_bound(model)


def _step_row(n, engine, steps, repeats, dtype, device):
    from ..sim.compiled import compiled_step
    from ..sim.integrators import SymplecticEuler

    model, _, dt = pressing_scene(n, dtype=dtype, device=device)
    step = compiled_step(SymplecticEuler(), model, dt, enable=engine == "compiled")
    ps = step.packed.pack_state(model.rest_state())
    t0 = time.perf_counter()
    ps = step.step_packed(ps)
    compile_s = time.perf_counter() - t0 if engine == "compiled" else None
    if engine == "compiled" and not step.compiled:
        raise RuntimeError(f"the step did not compile: {step.compile_error}")
    # press to the bottom of the path first: the timed steps all have contact
    while ps.t < 0.1:
        ps = step.step_packed(ps)
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            ps = step.step_packed(ps)
        force = float(ps.readings["probe.force"][0, 0])  # reads the result: waits for the device
        rates.append(steps / (time.perf_counter() - t0))
    return dict(
        n=n,
        topology=26,
        mode="step",
        engine=engine,
        hz=statistics.median(rates),
        body_hz=None,
        force_N=force,
        contacts=int(ps.readings["probe.contacts"][0]),
        compile_s=compile_s,
        threads=torch.get_num_threads(),
        steps=steps,
        repeats=repeats,
        dt_s=dt,
    )


def _haptic_row(n, seconds, dtype, device, compiled=True):
    from ..interact import HapticLoop, Sphere

    model, tool, dt = pressing_scene(n, dtype=dtype, device=device, path=False)
    model.interactions = []  # the loop adds the device's tool
    start = tuple(float(c) for c in tool.position(0.0))
    loop = HapticLoop(
        model, Sphere(3 * SPACING), start=start, dt=dt, rate=1000.0, mode="local", name="probe", compiled=compiled
    )
    ticks = int(seconds * 1000)
    with loop:
        for k in range(ticks):  # press 2 spacings in, then hold
            depth = 2 * SPACING * min(1.0, 2.0 * k / ticks)
            force = loop.tick((start[0] - depth, start[1], start[2]))
        stats = loop.stats()
    return dict(
        n=n,
        topology=26,
        mode="haptic",
        engine="compiled" if loop.step.compiled else "eager",
        hz=stats["force_hz"],
        body_hz=stats["body_hz"],
        force_N=float(force[0]),
        compile_s=loop.compile_s,
        threads=torch.get_num_threads(),
        ticks=stats["ticks"],
        body_steps=stats["body_steps"],
        dt_s=dt,
    )


def run(args) -> int:
    """Run the bench; returns the exit status."""
    torch.set_num_threads(args.threads or 1)
    sizes = args.sizes or ([8, 16] if args.quick else [8, 16, 24, 32, 48])
    hn = args.haptic_size or (24 if args.quick else 64)
    seconds = args.seconds or (1.0 if args.quick else 3.0)
    steps = args.steps or (100 if args.quick else 300)
    if min(sizes + [hn]) < 4 or steps < 1 or seconds <= 0:
        raise ConfigError(
            "--sizes/--haptic-size/--steps/--seconds",
            "sizes >= 4, steps >= 1, seconds > 0",
            got=(sizes, hn, steps, seconds),
        )
    dtype = getattr(torch, args.dtype)
    engines = ["eager"] if args.no_compile else ["compiled"] + (["eager"] if args.eager else [])
    rows = []
    bar = progress(len(sizes) * len(engines) + 1, "bench interaction")
    for n in sizes:
        for engine in engines:
            rows.append(_step_row(n, engine, steps, 3, dtype, args.device))
            bar.update(1)
    rows.append(_haptic_row(hn, seconds, dtype, args.device, compiled=not args.no_compile))
    bar.update(1)
    bar.close()
    r24 = next((r for r in rows if r["mode"] == "step" and r["engine"] == "compiled" and r["n"] == 24), None)
    hap = rows[-1]
    extra = {
        "machine": machine_info(args.device),
        "step_24": None if r24 is None else {"hz": r24["hz"], "target_hz": 1000.0, "met": r24["hz"] >= 1000.0},
        "haptic": {
            "n": hn,
            "force_hz": hap["hz"],
            "body_hz": hap["body_hz"],
            "target_hz": 1000.0,
            "met": hap["hz"] >= 990.0,
        },
    }
    if args.out:
        _plot(rows, args.out)
    emit("interaction", args, rows, COLUMNS, extra=extra)
    return 0


def _plot(rows, out_dir) -> None:
    fig, ax = axes(figsize=(6.5, 4.2))
    for engine, style in (("compiled", "-o"), ("eager", "--s")):
        pts = sorted((r["n"], r["hz"]) for r in rows if r["mode"] == "step" and r["engine"] == engine)
        if pts:
            ax.plot(*zip(*pts), style, label=f"step with contact, {engine}")
    hap = [r for r in rows if r["mode"] == "haptic"]
    for r in hap:
        ax.plot([r["n"]], [r["hz"]], "r*", ms=12, label=f"haptic force output, {r['n']}^3")
        ax.plot([r["n"]], [r["body_hz"]], "kx", ms=9, label=f"body steps behind it, {r['n']}^3")
    ax.axhline(1000, color="grey", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("n (n^3 nodes, 26 neighbours)")
    ax.set_ylabel("per second")
    ax.set_title("A sphere tool pressing in: steps/s and haptic rate")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_plot(fig, out_dir, "interaction.png")
