"""Learn stiffness from a few snapshots: Radetzky's balloon experiment, synthetically.

A closed surface from trimesh (an icosphere by default, or --mesh FILE) is voxelised into a
grid body and inflated by a pressure that rises linearly over the run, applied along the
vertex normals at the surface nodes. Only --snapshots snapshots (default 5), --interval
seconds apart (default 1 s), are observed, while the simulation steps at --dt (default
0.02 s, so 50 steps between snapshots). As Radetzky did, only the stiffness is learned (mass
and viscosity known) from a random initial value, with teacher forcing at every snapshot.

Window starts: positions from the snapshot, velocities carried over from the simulation
(--velocity carry, default) or zero (--velocity zero, the quasi-static assumption). The loss
is not convex in the stiffness (a much stiffer body barely moves and the loss flattens), so
the script scans --scan log-spaced values between 1/10 and 10 x the initial value first and
refines the best with L-BFGS.

Examples:
    python training/fit_sparse.py --out runs/balloon
    python training/fit_sparse.py --noise 0.01 --velocity zero --out runs/balloon-noise
    torchrun --standalone --nproc-per-node 2 training/fit_sparse.py --velocity zero --out runs/balloon-2ranks

Under ``torchrun`` the windows (one per snapshot interval) are shared out over the ranks and rank 0
writes the results. With ``--velocity carry`` the windows run in sequence, so every rank still
simulates the whole series (same result, no speed-up); ``--velocity zero`` divides the work.

Writes DIR/result.json (true, initial and learned stiffness, relative error, equilibrium
volume error, loss history, wall and CPU time), DIR/loss.png and DIR/scan.png.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from torchdeform import learn
from torchdeform.distributed import data_parallel
from torchdeform.options import Parser, integer, number


def parse_args(argv=None):
    p = Parser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__[__doc__.index("Examples") :],
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--mesh", default=None, help="closed mesh file (default: icosphere)")
    p.add_argument("--subdivisions", type=integer(lo=0, hi=6), default=1, help="icosphere subdivisions (default 1)")
    p.add_argument(
        "--radius", type=number(lo=0, lo_open=True, unit="m"), default=0.05, help="icosphere radius, m (default 0.05)"
    )
    p.add_argument(
        "--spacing", type=number(lo=0, lo_open=True, unit="m"), default=None, help="grid spacing, m (default radius/2)"
    )
    p.add_argument("--snapshots", type=integer(lo=2), default=5)
    p.add_argument(
        "--interval", type=number(lo=0, lo_open=True, unit="s"), default=1.0, help="seconds between snapshots"
    )
    p.add_argument("--dt", type=number(lo=0, lo_open=True, unit="s"), default=0.02)
    p.add_argument("--noise", type=number(lo=0), default=0.0, help="relative observation noise")
    p.add_argument("--seed", type=integer(lo=0), default=0, help="seed of the random initial value and the noise")
    p.add_argument(
        "--init", type=number(lo=0, lo_open=True), default=None, help="initial stiffness (default: U[0.2, 5] x truth)"
    )
    p.add_argument("--scan", type=integer(lo=0), default=13, help="scan points before refining (0 = off)")
    p.add_argument("--velocity", default="carry", choices=["carry", "zero"])
    p.add_argument("--iterations", type=integer(lo=1), default=15)
    p.add_argument("--threads", type=integer(lo=1), default=1)
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def volume(points: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    return float(ConvexHull(points).volume)


def main(argv=None) -> int:
    args = parse_args(argv)
    with data_parallel.process_group():  # under torchrun: gloo over the ranks; else nothing
        return learn.run_script("fit_sparse.py", args, fit, summary)


def fit(args, out) -> dict:
    series = learn.balloon_series(
        subdivisions=args.subdivisions,
        radius=args.radius,
        spacing=args.spacing,
        snapshots=args.snapshots,
        interval=args.interval,
        dt=args.dt,
        noise=args.noise,
        seed=args.seed,
        mesh=args.mesh,
    )
    kt = series.meta["truth"]["stiffness"]
    g = np.random.default_rng(args.seed + 1)
    init = args.init if args.init is not None else kt * float(np.exp(g.uniform(np.log(0.2), np.log(5.0))))
    k = learn.SpringParameter.like(series, init=init)
    params = learn.Parameters(series, k, series.truth["damping"], series.truth["mass"])
    loss = data_parallel.parallel_loss(learn.WindowLoss(series, window=1, velocity=args.velocity))
    main = data_parallel.is_main()
    result = {
        "series": {key: v for key, v in series.meta.items() if key != "loads"},
        "nodes": series.grid.num_nodes,
        "springs": series.grid.num_springs,
        "true": {"stiffness": kt},
        "initial": {"stiffness": init},
        "velocity": args.velocity,
    }
    start = init
    if args.scan:
        values = init * np.logspace(-1, 1, args.scan)
        losses = []
        with torch.no_grad():
            for v in values:
                k.value.raw.fill_(float(np.log(v)))
                losses.append(float(loss(params)))
        start = float(values[int(np.nanargmin(losses))])
        k.value.raw.data.fill_(float(np.log(start)))
        result["scan"] = {"values": values.tolist(), "losses": losses, "best": start}
        if main:
            learn.plot_scan(
                values,
                losses,
                kt,
                out / "scan.png",
                xlabel="stiffness (N/m)",
                marker="true stiffness",
                title="stiffness scan",
                logx=True,
            )
    with torch.no_grad():
        first = float(loss(params))
    trainer = learn.Trainer(
        params,
        loss,
        optimizer="lbfgs",
        iterations=args.iterations,
        patience=4,
        tol=1e-26,
        progress=not args.quiet and main,
    )
    trainer.run()
    got = params.summary()["stiffness"]
    # equilibrium check (Radetzky: volume within 5 %): final snapshot volume, learned vs true model
    with torch.no_grad():
        learned_model = params.model()
        x_true = series.simulate(series.true_model())[-1, 0]
        x_learn = series.simulate(learned_model)[-1, 0]
    nodes = series.grid.nodes()
    vt = volume(x_true[:, nodes].T.numpy())
    vl = volume(x_learn[:, nodes].T.numpy())
    result.update(
        {
            "start": {"stiffness": start},
            "learned": {"stiffness": got},
            "relative_error": {"stiffness": learn.relative_error(got, kt)},
            "final_volume": {"true": vt, "learned": vl, "relative_error": abs(vl - vt) / vt},
            "initial_loss": first,
            "final_loss": trainer.final_loss(),
            "iterations": trainer.iteration,
            "stopped": trainer.stopped or "iteration limit",
            "history": learn.history_dicts(trainer.history),
        }
    )
    if main:
        learn.plot_history(trainer.history, out / "loss.png", title="balloon: stiffness from 5 snapshots")
    return result


def summary(result) -> str:
    return (
        f"balloon ({result['nodes']} nodes, {result['springs']} springs, {result['series']['snapshots']} "
        f"snapshots): stiffness {result['learned']['stiffness']:.6g} (true {result['true']['stiffness']:.6g}, "
        f"initial {result['initial']['stiffness']:.4g}, rel err {result['relative_error']['stiffness']:.2e}); "
        f"final volume rel err {result['final_volume']['relative_error']:.2e}; "
        f"{result['wall_seconds']:.1f} s wall, {result['cpu_seconds']:.1f} s CPU"
    )


if __name__ == "__main__":
    sys.exit(main())
