"""Command-line code of learning.

``torchdeform data cube|balloon`` (synthetic series) and :func:`run_script`, the frame every
training script in ``training/`` shares.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

from ..errors import ConfigError, TorchdeformError
from .synthetic import balloon_series, cube_grid, cube_series, inclusion_regions, layered_regions, radetzky_cube

__all__ = ["add_arguments", "command", "run_script"]


def add_arguments(parser) -> None:
    """``torchdeform data cube|balloon --out FILE.npz [options]``."""
    sub = parser.add_subparsers(dest="data_command", required=True)
    c = sub.add_parser("cube", help="a cube series: Radetzky's cube (--springs) or an n^3 cube (--n)")
    c.add_argument("--out", required=True, help="output file (.npz)")
    c.add_argument("--springs", type=int, default=None, help="Radetzky's cube with 54, 70, 86 or 126 springs")
    c.add_argument("--n", type=int, default=None, help="nodes per edge of an n^3 cube (instead of --springs)")
    c.add_argument("--topology", type=int, default=26, help="neighbours of the n^3 cube (6, 14, 18, 26)")
    c.add_argument("--load", default="constant", help="n^3 cube load: constant, ramp, sine, indent")
    c.add_argument("--amplitude", type=float, default=None, help="force (N) or displacement (m) of the load")
    c.add_argument("--regions", default=None, help="heterogeneous material: 'layers' or 'inclusion' (n^3 cube)")
    c.add_argument("--stiffness", default="10", help="true stiffness N/m; comma-separated per region")
    c.add_argument("--damping", default="0.1", help="true damping N s/m; comma-separated per region")
    c.add_argument("--mass", type=float, default=0.01, help="node mass, kg")
    c.add_argument("--steps", type=int, default=250)
    c.add_argument("--dt", type=float, default=0.005)
    c.add_argument("--noise", type=float, default=0.0, help="relative observation noise (0.01 = 1%%)")
    c.add_argument("--every", type=int, default=1, help="observe every k-th step")
    c.add_argument("--seed", type=int, default=0)
    b = sub.add_parser("balloon", help="a voxelised icosphere inflated by pressure, seen in a few snapshots")
    b.add_argument("--out", required=True, help="output file (.npz)")
    b.add_argument("--snapshots", type=int, default=5)
    b.add_argument("--interval", type=float, default=1.0)
    b.add_argument("--dt", type=float, default=0.02)
    b.add_argument("--noise", type=float, default=0.0)
    b.add_argument("--seed", type=int, default=0)


def _numbers(text, key):
    try:
        vals = [float(v) for v in str(text).split(",")]
    except ValueError:
        raise ConfigError(key, "a number or comma-separated numbers", text) from None
    return vals[0] if len(vals) == 1 else vals


def command(args) -> int:
    """Run ``torchdeform data ...``; prints a one-line summary."""
    if args.data_command == "balloon":
        s = balloon_series(snapshots=args.snapshots, interval=args.interval, dt=args.dt, noise=args.noise,
                           seed=args.seed)
    else:
        k, c = _numbers(args.stiffness, "--stiffness"), _numbers(args.damping, "--damping")
        if args.n is None:
            s = radetzky_cube(springs=70 if args.springs is None else args.springs, stiffness=k, damping=c,
                              mass=args.mass, steps=args.steps, dt=args.dt, noise=args.noise, every=args.every,
                              seed=args.seed)
        else:
            if args.springs is not None:
                raise ConfigError("--springs", "not together with --n (Radetzky's sets are 3 x 3 x 3)", args.springs)
            regions = None
            if args.regions is not None:
                g, _ = cube_grid(args.n, 0.01, None, args.topology)
                if args.regions not in ("layers", "inclusion"):
                    raise ConfigError("--regions", "layers or inclusion", args.regions)
                regions = layered_regions(g) if args.regions == "layers" else inclusion_regions(g, args.n / 4)
            s = cube_series(n=args.n, topology=args.topology, load=args.load, amplitude=args.amplitude,
                            stiffness=k, damping=c, mass=args.mass, regions=regions, steps=args.steps, dt=args.dt,
                            noise=args.noise, every=args.every, seed=args.seed)
    path = s.save(args.out)
    print(f"{path}: {s.meta['description']}; {len(s.steps)} observations of {s.grid.num_nodes} nodes, "
          f"dt = {s.dt:g} s, {s.grid.num_springs if s.spring_mask is None else int(s.spring_mask.sum())} springs")
    return 0


def run_script(name: str, args, fit, summary) -> int:
    """The frame every training script shares.

    ``args.threads`` torch threads, the ``args.out`` folder, wall and CPU time, ``result.json``,
    and one line on stderr (exit status 2) for a :class:`~torchdeform.errors.TorchdeformError`.

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
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        result = fit(args, out)
    except TorchdeformError as e:
        if main:
            print(f"{name}: {e}", file=sys.stderr)
        return 2
    result.update(wall_seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0, threads=args.threads,
                  ranks=dist.get_world_size() if joined else 1)
    if main:
        (out / "result.json").write_text(json.dumps(result, indent=1))
        print(summary(result))
    return 0
