"""``torchdeform bench bodies``: what contact between two deformable bodies costs a step.

The scene (:func:`stacked_blocks`): two ``n^3`` blocks on 26-neighbour grids (1 cm spacing,
k = 400 N/m, 1 g per node, gravity -9.81 m/s^2 along D, global decay 50 1/s, Coulomb friction 0.5
between them), stepped by :meth:`~torchdeform.interact.bodies.Bodies.step` with symplectic Euler
at ``dt = td.suggest_dt(model)`` (0.9 times the stability bound, about 0.68 ms). The lower block's
base (``"bottom"``) is fixed; the upper one is free, in two placements:

* ``contact``: resting on the lower block, 0.05 spacings above its top and shifted half a spacing
  along H and W (so its nodes fall between the lower block's). The pair first settles for
  ``--settle`` steps (default 300), so that the contact set is steady, before any timing; the
  ``"lower/upper.contacts"`` reading must then be > 0;
* ``apart``: the same two bodies with the upper one 1 m above the lower one's top: each step
  still asks whether they touch (their bounding boxes do not overlap), and the reading is 0.

For every ``n`` (``--sizes``, default 16, 24, 32; quick 16) a row carries ``steps_per_s_contact``
and ``steps_per_s_apart`` (medians over ``--repeats`` timed runs of ``--steps`` steps, the two
scenes interleaved run by run so a drift of the machine reads the same on both),
``contact_ratio`` = apart / contact (how many times slower contact makes the step), ``contacts``
(nodes of either body inside the other at the end of the last contact run; ``contacts_min`` and
``contacts_max`` over the runs), ``contacts_apart`` (0), ``penetration_m`` (the deepest, before
the projection), ``dt_s`` and ``threads``.

Target (the multi-body contact issue): contact between two 24^3 bodies costs at most as much
again as the two bodies' steps alone, ``contact_ratio <= 2`` at ``n = 24``.

It runs on one CPU thread unless ``--threads`` says otherwise: the eager multi-body step on
bodies this small is a chain of short operations (the contact search indexes a few thousand
nodes), and a second thread on a 2-core machine mostly waits at OpenMP barriers (n = 24 on the
2-core CI machine, 2026-11-27: 89 steps/s in contact and 256 apart on 1 thread, 65 and 145 on 2).

Example:
    torchdeform bench bodies --quick
    torchdeform bench bodies --json --out bench-out
"""

from __future__ import annotations

import statistics
import time

import torch

from ..errors import ConfigError, DivergenceError
from ..options import integer
from ..outputs import axes, save_plot
from .common import add_common, device_sync, emit, int_list, machine_info, progress

__all__ = ["COLUMNS", "add_arguments", "run", "stacked_blocks"]

COLUMNS = [
    ("n", "n", None),
    ("steps_per_s_contact", "steps/s contact", "{:,.1f}"),
    ("steps_per_s_apart", "steps/s apart", "{:,.1f}"),
    ("contact_ratio", "apart/contact", "{:.2f}"),
    ("contacts", "contacts", None),
    ("contacts_apart", "contacts apart", None),
    ("penetration_m", "penetration m", "{:.2e}"),
    ("threads", "threads", None),
]
SPACING = 0.01
GAP_APART = 1.0  # m between the blocks when apart: the upper one falls < 0.2 m/s (g / decay)
TARGET_N, TARGET_RATIO = 24, 2.0
PAIR = "lower/upper"


def stacked_blocks(n: int, *, apart: bool = False, dtype=torch.float32, device="cpu"):
    """The bench scene: ``(Bodies, dt)``, two ``n^3`` blocks, the upper resting on the lower (or 1 m above it).

    26 neighbours, 1 cm spacing, k = 400 N/m, 1 g per node, gravity -9.81 m/s^2 along D, decay
    50 1/s, friction 0.5; the lower block's bottom face fixed. ``dt`` is :func:`td.suggest_dt` of
    the lower block (0.9 times its symplectic bound; the two blocks have the same bound).
    """
    from ..interact.bodies import Bodies, Body
    from ..sim.grid import Grid
    from ..sim.model import Model
    from ..sim.stability import suggest_dt

    def block(origin, fixed):
        grid = Grid((n, n, n), spacing=SPACING, topology=26, origin=origin)
        return Model(
            grid,
            stiffness=400.0,
            mass=1e-3,
            fixed=fixed,
            gravity=(-9.81, 0.0, 0.0),
            decay=50.0,
            dtype=dtype,
            device=device,
        )

    top = (n - 1) * SPACING
    lift = GAP_APART if apart else 0.05 * SPACING
    lower = block((0.0, 0.0, 0.0), "bottom")
    upper = block((top + lift, 0.5 * SPACING, 0.5 * SPACING), None)
    return Bodies([Body("lower", lower), Body("upper", upper)], friction=0.5), suggest_dt(lower)


def add_arguments(p) -> None:
    """The options of ``torchdeform bench bodies``."""
    add_common(p)
    for action in p._actions:  # the bench's own default and why
        if "--threads" in action.option_strings:
            action.help = (
                "CPU threads (default 1: the eager multi-body step on bodies this small is fastest on one "
                "thread on a 2-core machine; a second one mostly waits at OpenMP barriers)"
            )
    p.add_argument("--sizes", type=int_list("--sizes"), default=None, help="n (n^3 nodes; default 16,24,32; quick 16)")
    p.add_argument("--steps", type=integer(lo=1), default=None, help="steps per timed run (default 100; quick 10)")
    p.add_argument("--repeats", type=integer(lo=1), default=None, help="timed runs of each case (default 5; quick 3)")
    p.add_argument(
        "--settle",
        type=integer(lo=0),
        default=None,
        help="untimed steps before the timing, so the contact set is steady (default 300; quick 60)",
    )


def _run(scene, states, dt, steps, sync):
    """``steps`` steps; returns ``(seconds, states)``."""
    t0 = time.perf_counter()
    for _ in range(steps):
        states = scene.step(states, dt)
    sync()
    return time.perf_counter() - t0, states


def _check(states, step, dt, n):
    for s in states:
        if not bool(torch.isfinite(s.x).all()):
            raise DivergenceError(step, "position", float("nan"), dt=dt, safe_dt=None, cause=f"the {n}^3 stack")


def _contacts(states) -> int:
    return int(states[0].readings[f"{PAIR}.contacts"][0])


def _row(n, steps, repeats, settle, dtype, device):
    sync = device_sync(device)
    contact, dt = stacked_blocks(n, dtype=dtype, device=device)
    apart, _ = stacked_blocks(n, apart=True, dtype=dtype, device=device)
    sc = contact.rest_states()
    sa = apart.rest_states()
    contact.check_apart(sc)
    _, sc = _run(contact, sc, dt, max(settle, 1), sync)  # the contact set settles
    _, sa = _run(apart, sa, dt, max(1, min(settle, 20)), sync)  # warm-up
    _check(sc + sa, settle, dt, n)
    times_c, times_a, counts = [], [], []
    for _ in range(repeats):  # interleaved: a drift of the machine reads the same on both
        t, sc = _run(contact, sc, dt, steps, sync)
        times_c.append(t)
        counts.append(_contacts(sc))
        t, sa = _run(apart, sa, dt, steps, sync)
        times_a.append(t)
    _check(sc + sa, settle + repeats * steps, dt, n)
    rate_c = steps / statistics.median(times_c)
    rate_a = steps / statistics.median(times_a)
    return dict(
        n=n,
        steps_per_s_contact=rate_c,
        steps_per_s_apart=rate_a,
        contact_ratio=rate_a / rate_c,
        contacts=counts[-1],
        contacts_min=min(counts),
        contacts_max=max(counts),
        contacts_apart=_contacts(sa),
        penetration_m=float(sc[0].readings[f"{PAIR}.penetration"][0]),
        ms_per_step_contact=1e3 / rate_c,
        ms_per_step_apart=1e3 / rate_a,
        nodes=2 * n**3,
        dt_s=dt,
        steps=steps,
        repeats=repeats,
        settle=settle,
        threads=torch.get_num_threads(),
    )


def run(args) -> int:
    """Run the bench; returns the exit status."""
    torch.set_num_threads(args.threads or 1)
    sizes = args.sizes or ([16] if args.quick else [16, 24, 32])
    steps = args.steps or (10 if args.quick else 100)
    repeats = args.repeats or (3 if args.quick else 5)
    settle = args.settle if args.settle is not None else (60 if args.quick else 300)
    if min(sizes) < 4:
        raise ConfigError("--sizes", "sizes n >= 4 (n^3 nodes per body)", got=sizes)
    dtype = getattr(torch, args.dtype)
    rows = []
    bar = progress(len(sizes), "bench bodies")
    for n in sizes:
        rows.append(_row(n, steps, repeats, settle, dtype, args.device))
        bar.update(1)
    bar.close()
    at = next((r for r in rows if r["n"] == TARGET_N), None)
    extra = {
        "machine": machine_info(args.device),
        "targets": {"n": TARGET_N, "contact_ratio_max": TARGET_RATIO},
        "met": {
            "contact": all(r["contacts_min"] > 0 and r["contacts_apart"] == 0 for r in rows),
            "contact_ratio_24": None if at is None else bool(at["contact_ratio"] <= TARGET_RATIO),
        },
    }
    if args.out:
        _plot(rows, args.out)
    emit("bodies", args, rows, COLUMNS, extra=extra)
    return 0


def _plot(rows, out_dir) -> None:
    fig, ax = axes(figsize=(6.5, 4.2))
    pts = sorted((r["n"], r["steps_per_s_contact"], r["steps_per_s_apart"]) for r in rows)
    ns = [p[0] for p in pts]
    ax.plot(ns, [p[2] for p in pts], "-o", label="apart (no contact)")
    ax.plot(ns, [p[1] for p in pts], "-s", label="resting in contact")
    ax.plot(ns, [p[2] / TARGET_RATIO for p in pts], ":", color="grey", label="target: apart / 2")
    ax.set_yscale("log")
    ax.set_xticks(ns)
    ax.set_xlabel("n (two n^3 bodies, 26 neighbours)")
    ax.set_ylabel("Bodies.step per second")
    threads = rows[0]["threads"] if rows else "?"
    ax.set_title(f"Two bodies, one on the other vs apart ({threads} thread{'s' if threads != 1 else ''})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_plot(fig, out_dir, "bodies.png")
