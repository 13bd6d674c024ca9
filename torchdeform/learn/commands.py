"""Command-line code of learning.

``torchdeform data cube|balloon`` (synthetic series) and :func:`run_script`, the frame every
training script in ``training/`` shares.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import torch

from ..errors import ConfigError
from ..options import guarded, integer, number
from ..outputs import NonFiniteOutputError, atomic_path, non_finite_keys
from .synthetic import balloon_series, cube_grid, cube_series, inclusion_regions, layered_regions, radetzky_cube

__all__ = ["add_arguments", "command", "run_script"]


def add_arguments(parser):
    """``torchdeform data cube|balloon --out FILE.npz [options]``; returns the sub-parsers, for other ``data`` commands."""
    sub = parser.add_subparsers(dest="data_command", required=True)
    c = sub.add_parser("cube", help="a cube series: Radetzky's cube (--springs) or an n^3 cube (--n)")
    c.add_argument("--out", required=True, help="output file (.npz)")
    c.add_argument("--springs", type=integer(), default=None, help="Radetzky's cube with 54, 70, 86 or 126 springs")
    c.add_argument("--n", type=integer(lo=2), default=None, help="nodes per edge of an n^3 cube (instead of --springs)")
    c.add_argument("--topology", type=integer(), default=26, help="neighbours of the n^3 cube (6, 14, 18, 26)")
    c.add_argument("--load", default="constant", help="n^3 cube load: constant, ramp, sine, indent")
    c.add_argument("--amplitude", type=number(), default=None, help="force (N) or displacement (m) of the load")
    c.add_argument("--regions", default=None, help="heterogeneous material: 'layers' or 'inclusion' (n^3 cube)")
    c.add_argument("--stiffness", default="10", help="true stiffness N/m; comma-separated per region")
    c.add_argument("--damping", default="0.1", help="true damping N s/m; comma-separated per region")
    c.add_argument("--mass", type=number(lo=0, lo_open=True, unit="kg"), default=0.01, help="node mass, kg")
    c.add_argument("--steps", type=integer(lo=1), default=250)
    c.add_argument("--dt", type=number(lo=0, lo_open=True, unit="s"), default=0.005)
    c.add_argument("--noise", type=number(lo=0), default=0.0, help="relative observation noise (0.01 = 1%%)")
    c.add_argument("--every", type=integer(lo=1), default=1, help="observe every k-th step")
    c.add_argument("--seed", type=integer(lo=0), default=0)
    b = sub.add_parser("balloon", help="a voxelised icosphere inflated by pressure, seen in a few snapshots")
    b.add_argument("--out", required=True, help="output file (.npz)")
    b.add_argument("--snapshots", type=integer(lo=1), default=5)
    b.add_argument("--interval", type=number(lo=0, lo_open=True, unit="s"), default=1.0)
    b.add_argument("--dt", type=number(lo=0, lo_open=True, unit="s"), default=0.02)
    b.add_argument("--noise", type=number(lo=0), default=0.0)
    b.add_argument("--seed", type=integer(lo=0), default=0)
    return sub


def _numbers(text, key):
    try:
        vals = [float(v) for v in str(text).split(",")]
    except ValueError:
        raise ConfigError(key, "a number or comma-separated numbers", got=text) from None
    if not all(math.isfinite(v) and v >= 0 for v in vals):
        raise ConfigError(key, "finite numbers >= 0", got=text)
    return vals[0] if len(vals) == 1 else vals


def _check_cube_memory(args) -> None:
    """Refuse an ``--n`` cube whose simulation and series cannot fit in memory, before allocating anything."""
    from ..checks import check_grid, check_memory

    n = args.n
    check_grid("--n", (n, n, n), topology=args.topology, itemsize=8)
    frames = args.steps + 1  # the true run keeps every step (float64), then the observed copy
    check_memory(
        "--n",
        float(n) ** 3 * 3 * 8 * (frames + (args.steps // args.every + 1)),
        f"a series of {frames} steps of {n}^3 nodes",
        got=n,
    )


def command(args) -> int:
    """Run ``torchdeform data ...``; prints a one-line summary."""
    if args.data_command == "balloon":
        s = balloon_series(
            snapshots=args.snapshots, interval=args.interval, dt=args.dt, noise=args.noise, seed=args.seed
        )
    else:
        k, c = _numbers(args.stiffness, "--stiffness"), _numbers(args.damping, "--damping")
        if args.n is None:
            s = radetzky_cube(
                springs=70 if args.springs is None else args.springs,
                stiffness=k,
                damping=c,
                mass=args.mass,
                steps=args.steps,
                dt=args.dt,
                noise=args.noise,
                every=args.every,
                seed=args.seed,
            )
        else:
            if args.springs is not None:
                raise ConfigError(
                    "--springs", "not together with --n (Radetzky's sets are 3 x 3 x 3)", got=args.springs
                )
            _check_cube_memory(args)
            regions = None
            if args.regions is not None:
                g, _ = cube_grid(n=args.n, spacing=0.01, springs=None, topology=args.topology)
                if args.regions not in ("layers", "inclusion"):
                    raise ConfigError("--regions", "layers or inclusion", got=args.regions)
                regions = layered_regions(g) if args.regions == "layers" else inclusion_regions(g, args.n / 4)
            s = cube_series(
                n=args.n,
                topology=args.topology,
                load=args.load,
                amplitude=args.amplitude,
                stiffness=k,
                damping=c,
                mass=args.mass,
                regions=regions,
                steps=args.steps,
                dt=args.dt,
                noise=args.noise,
                every=args.every,
                seed=args.seed,
            )
    path = s.save(args.out)
    print(
        f"{path}: {s.meta['description']}; {len(s.steps)} observations of {s.grid.num_nodes} nodes, "
        f"dt = {s.dt:g} s, {s.grid.num_springs if s.spring_mask is None else int(s.spring_mask.sum())} springs"
    )
    return 0


def run_script(name: str, args, fit, summary) -> int:
    """The frame every training script shares.

    ``args.threads`` torch threads, the ``args.out`` folder, wall and CPU time, ``result.json``
    (written whole, and refused if it would hold NaN or inf), and the exit statuses of
    :func:`torchdeform.options.guarded`: one line on stderr and status 2 for a user's problem.

    ``fit(args, out) -> dict`` does the work and returns the result; ``summary(result) -> str``
    is printed at the end (the result then also holds ``wall_seconds``, ``cpu_seconds`` (this
    process's), ``threads`` and ``ranks``). Returns the exit status.

    In a ``torch.distributed`` process group (a script under ``torchrun``, see
    :func:`torchdeform.distributed.data_parallel.process_group`) every rank runs ``fit``; rank 0
    alone writes ``result.json`` and prints.
    """
    import torch.distributed as dist

    joined = dist.is_available() and dist.is_initialized()
    main = not joined or dist.get_rank() == 0

    def work() -> int:
        torch.set_num_threads(args.threads)
        out = Path(args.out)
        if out.exists() and not out.is_dir():
            raise ConfigError("--out", "a folder (this path is a file)", got=str(out))
        out.mkdir(parents=True, exist_ok=True)
        t0, c0 = time.perf_counter(), time.process_time()
        result = fit(args, out)
        result.update(
            wall_seconds=time.perf_counter() - t0,
            cpu_seconds=time.process_time() - c0,
            threads=args.threads,
            ranks=dist.get_world_size() if joined else 1,
        )
        if main:
            try:
                text = json.dumps(result, indent=1, allow_nan=False)
            except ValueError:
                raise NonFiniteOutputError(
                    f"refusing to write {out / 'result.json'}: it would hold NaN or inf "
                    f"({', '.join(non_finite_keys(result))})"
                ) from None
            with atomic_path(out / "result.json") as tmp:
                tmp.write_text(text)
            print(summary(result))
        return 0

    return guarded(name, work, echo=main)
