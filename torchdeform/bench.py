"""Benchmarks: ``torchdeform bench <name>``.

=========  ================================================================================
speed      spring-step throughput of symplectic Euler on a damped cube: Msprings/s,
           node-steps/s and ms/step for n^3 grids, topologies, eager and compiled
=========  ================================================================================

Each benchmark is one entry of :data:`BENCHES`: a help line, a function that adds its
options to an ``argparse`` parser and a function ``run(args) -> int``. A new benchmark
(accuracy, ChainMail, implicit beam ...) is one more entry.

Output conventions shared by every benchmark: the table goes to stdout; with ``--json``
stdout carries exactly one JSON document and nothing else (progress, warnings and compiler
chatter go to stderr); ``--out DIR`` writes ``<name>.csv`` and ``<name>.png``.

Example:
    torchdeform bench speed --quick
    torchdeform bench speed --sizes 16,32,64 --topologies 6,26 --threads 2 --out bench-out
"""
from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from .errors import ConfigError

# ----------------------------------------------------------------- registry


def add_arguments(parser) -> None:
    """Add one sub-command per benchmark of :data:`BENCHES` to the ``bench`` parser."""
    sub = parser.add_subparsers(dest="bench", required=True, metavar="BENCH")
    for name, (help_, add, run) in BENCHES.items():
        p = sub.add_parser(name, help=help_, description=help_)
        add(p)
        p.set_defaults(bench_main=run)


def main(args) -> int:
    """Run the benchmark chosen on the command line; returns the exit status."""
    return args.bench_main(args)


def _int_list(key):
    def parse(text):
        try:
            values = [int(v) for v in str(text).split(",") if v.strip()]
        except ValueError:
            raise ConfigError(key, "comma-separated integers, e.g. 16,32,64", text) from None
        if not values:
            raise ConfigError(key, "at least one integer", text)
        return values
    return parse


def add_common(p) -> None:
    """Options every benchmark takes."""
    p.add_argument("--quick", action="store_true", help="tiny sizes, few steps: a smoke run in seconds")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout, nothing else")
    p.add_argument("--out", default=None, help="folder for the CSV and the plot")
    p.add_argument("--threads", type=int, default=None, help="CPU threads (default: torch's current)")
    p.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")


def machine_info(device: str) -> dict:
    info = {"torch": torch.__version__, "python": platform.python_version(), "threads": torch.get_num_threads(),
            "device": device, "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count()}
    if device.startswith("cuda") and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    return info


def _sync(device: str):
    if device.startswith("cuda"):
        return torch.cuda.synchronize
    return lambda: None


def _progress(total: int, desc: str):
    from tqdm.auto import tqdm
    return tqdm(total=total, desc=desc, unit="row", file=sys.stderr, disable=None, leave=False)


def emit(name: str, args, rows: list, columns: list, extra: dict | None = None, display=None) -> None:
    """Write ``--out DIR/<name>.csv`` and print the JSON document (``--json``) or the table of
    ``display`` rows (default ``rows``)."""
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        with open(out / f"{name}.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else [c[0] for c in columns])
            w.writeheader()
            w.writerows(rows)
    if args.json:
        doc = {"bench": name, **(extra or {}), "rows": rows}
        sys.stdout.write(json.dumps(doc, indent=1) + "\n")
        sys.stdout.flush()
    else:
        print(format_table(rows if display is None else display, columns))


def format_table(rows: list, columns: list) -> str:
    """``columns``: ``(key, header, format)``; ``None`` values print as ``-``."""
    cells = [[h for _, h, _ in columns]]
    for r in rows:
        cells.append(["-" if r.get(k) is None else (fmt.format(r[k]) if fmt else str(r[k]))
                      for k, _, fmt in columns])
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(row, widths)) for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


# -------------------------------------------------------------------- speed

SPEED_COLUMNS = [("grid", "grid", None), ("topology", "topo", None), ("mode", "mode", None),
                 ("springs", "springs", "{:,}"), ("steps", "steps", None), ("ms_per_step", "ms/step", "{:.3f}"),
                 ("msprings_per_s", "Msprings/s", "{:.1f}"), ("node_steps_per_s", "Mnode-steps/s", None),
                 ("compile_s", "compile s", "{:.1f}"), ("max_abs_diff", "max|diff|", "{:.1e}")]


def _add_speed(p) -> None:
    add_common(p)
    p.add_argument("--sizes", type=_int_list("--sizes"), default=None,
                   help="grid sizes n (n^3 nodes), comma-separated (default 16,32,48,64; quick 8,12)")
    p.add_argument("--topologies", type=_int_list("--topologies"), default=[6, 26],
                   help="neighbour counts, comma-separated (default 6,26)")
    p.add_argument("--no-compile", action="store_true", help="eager rows only")
    p.add_argument("--steps", type=int, default=None,
                   help="steps per timed repeat (default: enough for ~0.2 s, 3..200)")
    p.add_argument("--repeats", type=int, default=None, help="timed repeats, the median is kept (default 5; quick 3)")


def speed_cube(n: int, topology: int, dtype=torch.float32, device="cpu", seed: int = 0):
    """The speed scene: an ``n^3`` damped cube (1 cm spacing, k = 100 N/m, c = 0.05 N s/m,
    1 g per node, no gravity), slightly perturbed from rest. Returns ``(model, state, dt)``."""
    from .grid import Grid
    from .model import Model, State
    grid = Grid((n, n, n), spacing=0.01, topology=topology)
    model = Model(grid, stiffness=100.0, damping=0.05, mass=1e-3, dtype=dtype, device=device)
    g = torch.Generator().manual_seed(seed)
    x = model.X + (1e-4 * torch.randn(model.X.shape, generator=g, dtype=torch.float64)).to(dtype=dtype, device=device)
    v = (1e-3 * torch.randn(model.X.shape, generator=g, dtype=torch.float64)).to(dtype=dtype, device=device)
    return model, State(x, v, 0.0), 1e-4       # dt well below the bound (~8e-4 s for 26 neighbours)


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


def speed_row(n: int, topology: int, mode: str, *, dtype=torch.float32, device="cpu", steps=None,
              repeats: int = 5, target_s: float = 0.2, reference=None) -> dict:
    """Time symplectic Euler steps on :func:`speed_cube`; one row of the speed table.

    ``mode`` is ``"eager"`` (``SymplecticEuler.step``) or ``"compiled"``
    (:func:`~torchdeform.compiled.compiled_step`). ``reference``: the eager state after one step,
    to report ``max_abs_diff`` of the compiled step. The warm-up (and compilation) is excluded
    from the timing; the compile time is the first call's wall time.
    """
    from .compiled import compiled_step
    from .integrators import SymplecticEuler
    model, state, dt = speed_cube(n, topology, dtype, device)
    integ = SymplecticEuler()
    sync = _sync(device)
    row = {"grid": f"{n}^3", "n": n, "topology": topology, "mode": mode, "dtype": str(dtype).replace("torch.", ""),
           "threads": torch.get_num_threads(), "device": device, "nodes": model.grid.num_nodes,
           "springs": model.grid.num_springs}
    with torch.no_grad():
        compile_s, fallback = None, False
        if mode == "eager":
            def step(s):
                return integ.step(model, s, dt)
        else:
            step = compiled_step(integ, model, dt)
            t0 = time.perf_counter()
            step(state)
            sync()
            compile_s = time.perf_counter() - t0
            fallback = not step.compiled
        first = step(state)
        diff = None
        if reference is not None:
            diff = max(float((first.x - reference.x).abs().max()), float((first.v - reference.v).abs().max()))
        sync()
        t0 = time.perf_counter()                       # second warm-up call, also sizes the run
        step(state)
        sync()
        warm = max(time.perf_counter() - t0, 1e-7)
        if steps is None:
            steps = int(min(200, max(3, math.ceil(target_s / warm))))
        sec = _time_steps(step, state, steps, repeats, sync)
    row.update(steps=steps, repeats=repeats, ms_per_step=sec * 1e3,
               msprings_per_s=row["springs"] / sec / 1e6, node_steps_per_s=row["nodes"] / sec,
               compile_s=compile_s, max_abs_diff=diff, fallback=fallback)
    row["_first"] = first
    return row


def _speed(args) -> int:
    if args.threads is not None:
        if args.threads < 1:
            raise ConfigError("--threads", "an integer >= 1", args.threads)
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    device = str(torch.device(args.device))
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("--device", "cpu, or cuda on a machine with CUDA", args.device)
    sizes = args.sizes or ([8, 12] if args.quick else [16, 32, 48, 64])
    if min(sizes) < 2:
        raise ConfigError("--sizes", "grid sizes >= 2", sizes)
    for t in args.topologies:
        if t not in (6, 14, 18, 26):
            raise ConfigError("--topologies", "6, 14, 18 or 26", t)
    if args.steps is not None and args.steps < 1:
        raise ConfigError("--steps", "an integer >= 1", args.steps)
    repeats = args.repeats or (3 if args.quick else 5)
    modes = ["eager"] if args.no_compile else ["eager", "compiled"]
    # --quick compiles one shape only (the smallest grid, first topology): compilation costs
    # 10-30 s per shape on 2 cores, the smoke run must stay well under a minute.
    tasks = [(n, t, m) for t in args.topologies for n in sizes for m in modes
             if not (m == "compiled" and args.quick and (n, t) != (min(sizes), args.topologies[0]))]

    rows, refs = [], {}
    redirect = contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext()
    with redirect, _progress(len(tasks), "bench speed") as bar:
        for n, t, m in tasks:
            bar.set_postfix_str(f"{n}^3 {t}-nbr {m}")
            row = speed_row(n, t, m, dtype=dtype, device=device, steps=args.steps, repeats=repeats,
                            target_s=0.02 if args.quick else 0.2, reference=refs.get((n, t)))
            first = row.pop("_first")
            if m == "eager":
                refs[(n, t)] = first
            rows.append(row)
            bar.update(1)
    for r in rows:
        r["node_steps_per_s"] = float(r["node_steps_per_s"])
    display = [dict(r, node_steps_per_s=f"{r['node_steps_per_s'] / 1e6:.2f}",
                    mode=r["mode"] + (" (eager fallback)" if r["fallback"] else "")) for r in rows]
    machine = machine_info(device)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        _speed_plot(rows, Path(args.out) / "speed.png", machine)
    if not args.json:
        print(f"symplectic Euler on a damped n^3 cube, {args.dtype}, {device}, "
              f"{machine['threads']} threads, torch {machine['torch']}")
    emit("speed", args, rows, SPEED_COLUMNS, {"machine": machine, "scene": _SCENE}, display)
    if not args.json and args.out:
        print(f"wrote {Path(args.out) / 'speed.csv'} and {Path(args.out) / 'speed.png'}")
    return 0


_SCENE = ("symplectic Euler, dt 1e-4 s, damped cube (1 cm spacing, k 100 N/m, c 0.05 N s/m, 1 g nodes), "
          "no gravity; msprings_per_s = springs / (s per step) / 1e6, median over repeats, warm-up excluded")


def _speed_plot(rows, path: Path, machine: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for key in sorted({(r["topology"], r["mode"]) for r in rows}):
        pts = sorted((r["nodes"], r["msprings_per_s"]) for r in rows if (r["topology"], r["mode"]) == key)
        ax.plot(*zip(*pts), marker="o", ls="-" if key[1] == "compiled" else "--",
                label=f"{key[0]} neighbours, {key[1]}")
    ax.set_xscale("log")
    ax.set_xlabel("nodes")
    ax.set_ylabel("Msprings/s")
    ax.set_title(f"spring step throughput ({machine['threads']} threads, {machine['device']})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


#: name -> (help line, add_arguments(parser), run(args) -> int)
BENCHES = {
    "speed": ("spring-step throughput (Msprings/s, node-steps/s), eager and compiled", _add_speed, _speed),
}

__all__ = ["BENCHES", "add_arguments", "main", "speed_cube", "speed_row", "format_table", "machine_info"]
