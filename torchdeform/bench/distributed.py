"""``torchdeform bench distributed``: a sweep and one large body on 1 and 2 ranks (``torchrun``, gloo).

**Rows.**

* ``sweep``: the whole command ``torchdeform sweep`` of a 64-point sweep (8 stiffnesses x 8
  dampings of a 4 x 4 x 5 cube, 26 neighbours, 200 symplectic steps each, batched 32 points per
  model), on one process and under ``torchrun --nproc-per-node N``: wall time from launch to the
  written table (process start and imports included, as a user waits for it).
* ``step``: one step of an ``n^3`` body (default 96^3, 26 neighbours, float32; the speed scene of
  :func:`~torchdeform.bench.common.speed_cube`) split into ``N`` slabs along D
  (:mod:`torchdeform.distributed.domain`): symplectic Euler, and implicit Euler with a fixed
  ``--cg-iters`` CG iterations. Milliseconds per step (median of ``--repeats`` timed runs of
  ``--steps`` steps after one warm-up step), the communication share of the step (time in halo
  exchanges and all-reduces over the step's time, the largest over ranks), halo exchanges per step
  and bytes each rank sends per exchange.

One rank runs with ``--threads`` threads (default: every core); each of ``N`` ranks with
``threads / N`` (at least 1), so the rows compare the same cores.

Example:
    torchdeform bench distributed --quick
    torchdeform bench distributed --ranks 1,2 --json --out bench-out
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ..errors import ConfigError
from ..options import integer, number
from ..outputs import axes, save_plot
from .common import add_common, emit, int_list, machine_info, progress

__all__ = ["COLUMNS", "SWEEP_SCENE", "add_arguments", "run", "worker"]

COLUMNS = [
    ("case", "case", None),
    ("ranks", "ranks", None),
    ("threads", "thr/rank", None),
    ("grid", "grid", None),
    ("wall_s", "wall s", "{:.2f}"),
    ("ms_per_step", "ms/step", "{:.1f}"),
    ("speedup", "speed-up", "{:.2f}x"),
    ("comm_share", "comm", "{:.0%}"),
    ("exchanges_per_step", "exch/step", "{:.0f}"),
    ("bytes_per_exchange", "bytes/exch", "{:,}"),
]

#: the sweep's scene (``{steps}`` filled in)
SWEEP_SCENE = """\
[grid]
shape = [4, 4, 5]
spacing = 0.01
topology = 26
[material]
stiffness = 50.0
damping = 0.05
[mass]
density = 1000.0
[boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]
[integrator]
name = "symplectic"
dt = 1e-4
steps = {steps}
"""


def add_arguments(p) -> None:
    """The options of ``torchdeform bench distributed``."""
    add_common(p)
    p.add_argument("--ranks", type=int_list("--ranks"), default=None, help="rank counts (default 1,2)")
    p.add_argument(
        "--n", type=integer(lo=2), default=None, help="body of n^3 nodes for the step rows (default 96; quick 24)"
    )
    p.add_argument("--steps", type=integer(lo=1), default=None, help="timed steps per run (default 5; quick 2)")
    p.add_argument("--repeats", type=integer(lo=1), default=None, help="timed runs, median kept (default 3; quick 1)")
    p.add_argument("--cg-iters", type=integer(lo=1), default=10, help="CG iterations of the implicit step (default 10)")
    p.add_argument("--points", type=integer(lo=1), default=None, help="sweep points, a square (default 64; quick 16)")
    p.add_argument(
        "--cases",
        default="sweep,explicit,implicit",
        help="rows to run, comma-separated: sweep, explicit, implicit (default all)",
    )
    p.add_argument(
        "--timeout", type=number(lo=0, lo_open=True), default=600, help="seconds each launch may take (default 600)"
    )


def _launch(ranks: int, threads: int, args: list, timeout: float) -> tuple:
    """Run ``python -m ARGS`` on one process or under torchrun; ``(wall seconds, completed process)``."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    cmd = (
        [sys.executable, "-m", *args]
        if ranks == 1
        else [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc-per-node",
            str(ranks),
            "-m",
            *args,
        ]
    )
    t = time.perf_counter()
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        raise ConfigError(
            "--timeout", f"more seconds: {' '.join(args[:2])} on {ranks} ranks took longer", got=timeout
        ) from None
    wall = time.perf_counter() - t
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
    return wall, done


def _sweep_row(ranks: int, threads: int, points: int, steps: int, timeout: float) -> dict:
    side = max(1, round(points**0.5))
    k = ",".join(f"{25 * 1.25**i:.6g}" for i in range(side))
    c = ",".join(f"{0.01 * 1.5**i:.6g}" for i in range(side))
    with tempfile.TemporaryDirectory(prefix="torchdeform-bench-sweep-") as tmp:
        scene = Path(tmp) / "cube.toml"
        scene.write_text(SWEEP_SCENE.format(steps=steps))
        wall, _ = _launch(
            ranks,
            threads,
            [
                "torchdeform",
                "sweep",
                str(scene),
                "--set",
                f"material.stiffness={k}",
                "--set",
                f"material.damping={c}",
                "--out",
                str(Path(tmp) / "out"),
                "--quiet",
            ],
            timeout,
        )
    return {
        "case": "sweep",
        "ranks": ranks,
        "threads": threads,
        "grid": f"{side * side} points x 4x4x5",
        "wall_s": wall,
    }


def _step_row(
    case: str, ranks: int, threads: int, n: int, steps: int, repeats: int, cg_iters: int, dtype: str, timeout: float
) -> dict:
    with tempfile.TemporaryDirectory(prefix="torchdeform-bench-domain-") as tmp:
        out = Path(tmp) / "step.json"
        wall, _ = _launch(
            ranks,
            threads,
            [
                "torchdeform.bench.distributed",
                str(out),
                case,
                str(n),
                str(steps),
                str(repeats),
                str(cg_iters),
                dtype,
                str(threads),
            ],
            timeout,
        )
        got = json.loads(out.read_text())
    return {"case": case, "ranks": ranks, "threads": threads, "grid": f"{n}^3", "wall_s": wall, **got}


def worker(out: str, case: str, n: str, steps: str, repeats: str, cg_iters: str, dtype: str, threads: str) -> None:
    """One ``step`` row on every rank of this launch; rank 0 writes its figures as JSON to ``out``."""
    import torch
    import torch.distributed as dist

    from ..distributed.domain import decomposed_simulate
    from ..sim.integrators import ImplicitEuler, SymplecticEuler
    from .common import speed_cube

    world = int(os.environ.get("WORLD_SIZE", 1))
    if world > 1:
        dist.init_process_group("gloo")
    torch.set_num_threads(int(threads))
    model, state, dt = speed_cube(int(n), 26, dtype=getattr(torch, dtype))
    integrator = SymplecticEuler() if case == "explicit" else ImplicitEuler(cg_iters=int(cg_iters), cg_tol=0.0)
    decomposed_simulate(model, state, dt, 1, integrator=integrator)  # warm-up: allocations
    runs = [decomposed_simulate(model, state, dt, int(steps), integrator=integrator) for _ in range(int(repeats))]
    mine = [(r.wall_s, r.comm_s, r.model.halo.exchanges, r.model.halo.bytes) for r in runs]
    parts = [mine]
    if world > 1:
        parts = [None] * world
        dist.all_gather_object(parts, mine)
    if int(os.environ.get("RANK", 0)) == 0:
        k = int(steps)
        walls = [max(p[i][0] for p in parts) for i in range(len(runs))]  # a step ends with its slowest rank
        shares = [max(p[i][1] / p[i][0] for p in parts) for i in range(len(runs))]
        exch = parts[0][0][2]
        Path(out).write_text(
            json.dumps(
                {
                    "ms_per_step": 1e3 * statistics.median(walls) / k,
                    "comm_share": statistics.median(shares),
                    "exchanges_per_step": exch / k,
                    "bytes_per_exchange": max(p[0][3] // p[0][2] if p[0][2] else 0 for p in parts),
                }
            )
        )
    if world > 1:
        dist.barrier()
        dist.destroy_process_group()


def run(args) -> int:
    """Run the bench: sweep rows, then explicit and implicit step rows, per rank count."""
    ranks = args.ranks or [1, 2]
    n = args.n or (24 if args.quick else 96)
    steps = args.steps or (2 if args.quick else 5)
    repeats = args.repeats or (1 if args.quick else 3)
    points = args.points or (16 if args.quick else 64)
    if min(ranks) < 1 or n < max(ranks) or steps < 1 or repeats < 1 or args.cg_iters < 1 or points < 1:
        raise ConfigError(
            "--ranks/--n/--steps/--repeats/--cg-iters/--points",
            "ranks >= 1, n >= the largest rank count, the others >= 1",
            got=(ranks, n, steps, repeats, args.cg_iters, points),
        )
    chosen = [c.strip() for c in args.cases.split(",") if c.strip()]
    if not chosen or set(chosen) - {"sweep", "explicit", "implicit"}:
        raise ConfigError("--cases", "a comma-separated choice of sweep, explicit, implicit", got=args.cases)
    if args.device != "cpu":
        raise ConfigError("--device", "cpu (the bench launches gloo ranks on this machine)", got=args.device)
    cores = args.threads or os.cpu_count() or 1
    rows = []
    cases = [(c, r) for c in ("sweep", "explicit", "implicit") if c in chosen for r in ranks]
    with progress(len(cases), "bench distributed") as bar:
        for case, r in cases:
            threads = max(1, cores // r)
            if case == "sweep":
                rows.append(_sweep_row(r, threads, points, 50 if args.quick else 200, args.timeout))
            else:
                rows.append(_step_row(case, r, threads, n, steps, repeats, args.cg_iters, args.dtype, args.timeout))
            bar.update(1)
    for row in rows:
        base = next(b for b in rows if b["case"] == row["case"] and b["ranks"] == min(ranks))
        key = "wall_s" if row["case"] == "sweep" else "ms_per_step"
        row["speedup"] = base[key] / row[key]
    extra = {
        "machine": machine_info("cpu"),
        "cores_used": cores,
        "n": n,
        "steps": steps,
        "repeats": repeats,
        "cg_iters": args.cg_iters,
        "dtype": args.dtype,
        "setup": (
            f"gloo on this machine; {cores} core(s) shared by the ranks (threads per rank = cores / ranks); "
            f"step rows: {n}^3, 26 neighbours, {args.dtype}, median of {repeats} run(s) of {steps} step(s)"
        ),
    }
    if args.out:
        _plot(rows, args.out)
    if not args.json:
        print("bench distributed: " + extra["setup"])
    emit("distributed", args, rows, COLUMNS, extra=extra)
    return 0


def _plot(rows, out_dir) -> None:
    fig, (left, right) = axes(figsize=(10, 4.2), ncols=2)
    for case, marker in (("explicit", "o"), ("implicit", "s")):
        sel = [r for r in rows if r["case"] == case]
        if not sel:
            continue
        left.plot([r["ranks"] for r in sel], [r["ms_per_step"] for r in sel], marker=marker, label=f"{case} step")
        left.bar(
            [r["ranks"] + (0.1 if case == "implicit" else -0.1) for r in sel],
            [r["ms_per_step"] * r["comm_share"] for r in sel],
            width=0.18,
            alpha=0.35,
            label=f"{case}: communication",
        )
    left.set_xlabel("ranks")
    left.set_ylabel("ms per step")
    left.set_title(f"one body split into slabs ({rows[-1]['grid']})" if rows[-1]["case"] != "sweep" else "")
    left.legend(fontsize=8)
    sweep = [r for r in rows if r["case"] == "sweep"]
    right.bar([str(r["ranks"]) for r in sweep], [r["wall_s"] for r in sweep], color="tab:green")
    right.set_xlabel("ranks")
    right.set_ylabel("wall time of the command (s)")
    right.set_title(f"sweep of {sweep[0]['grid']}" if sweep else "sweep")
    for ax in (left, right):
        ax.grid(True, alpha=0.3)
    save_plot(fig, out_dir, "distributed.png")


if __name__ == "__main__":
    worker(*sys.argv[1:])
