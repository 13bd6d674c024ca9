"""Radetzky's cube experiment: learn spring constants, viscosities and masses from a time series.

Three runs (thesis §2.3, EUFIT'99), on a 3 x 3 x 3 cube with its lower 9 nodes fixed and a
constant force on the top-centre node for 250 steps:

  run 1: per-spring stiffness and damping and per-node masses, initialised at U[0.2, 5] x truth
  run 2: per-spring stiffness and damping (masses known), same initialisation
  run 3: shared stiffness and damping, initialised at offset x truth (default 3x and 1/2.5x)

Radetzky's lesson: one load case cannot identify per-spring values, shared values can. The
per-spring runs print the identifiability report (spread of learned/true ratios, Hessian
eigenvalues).

Examples:
    python training/fit_cube.py --out runs/cube                    # all three runs
    python training/fit_cube.py --runs 3 --noise 0.01 --out runs/cube-noise
    python training/fit_cube.py --long 2000 --checkpoint 100 --out runs/long   # BPTT memory
    python training/fit_cube.py --runs 2 --engine compiled --out runs/cube-compiled
    python training/fit_cube.py --integrator implicit --runs 3 --out runs/cube-stiff   # stiff cube, dt 50x bound
    torchrun --standalone --nproc-per-node 2 training/fit_cube.py --runs 3 --out runs/cube-2ranks

Under ``torchrun`` the teacher-forcing windows are shared out over the ranks (data-parallel,
gloo; torchdeform.distributed.data_parallel): each rank simulates its block of windows, losses
and gradients are summed over the ranks, and the fit equals the one-process fit to rounding.
Rank 0 writes the results and plots. Without torchrun the script is one process.

With ``--integrator implicit`` the cube is 1000x stiffer (k = 1e4 N/m, d = 3.16 N s/m: the same
damping ratio) and stepped by implicit Euler at ``--dt-factor`` (default 50) times the explicit
(symplectic Euler) stability bound, CG to 1e-12, for the truth and the fit alike; the gradient
goes through the adjoint solves (``--gradient``, see ``ImplicitEuler``).

Writes DIR/result.json (learned and true values, relative errors, loss histories, wall and
CPU time) and DIR/run<k>_loss.png, DIR/run<k>_spread_*.png.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time

import numpy as np
import torch

import torchdeform as td
from torchdeform import learn
from torchdeform.distributed import data_parallel
from torchdeform.options import Parser, integer, number, number_list


def parse_args(argv=None):
    p = Parser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__[__doc__.index("Examples") :],
    )
    p.add_argument("--out", required=True, help="output folder (result.json, plots)")
    p.add_argument("--runs", default="1,2,3", help="comma-separated runs to do (default 1,2,3)")
    p.add_argument("--data", default=None, help="a series file (.npz) instead of generating Radetzky's cube")
    p.add_argument("--springs", type=int, default=70, choices=sorted(learn.SPRING_SETS), help="spring set (default 70)")
    p.add_argument("--noise", type=number(lo=0), default=0.0, help="relative observation noise (0.01 = 1%%)")
    p.add_argument("--seed", type=integer(lo=0), default=0, help="seed of the noise and of random initial values")
    p.add_argument(
        "--offset",
        type=number_list(count=2, lo=0, lo_open=True),
        default=[3.0, 0.4],
        help="run 3 initial factors for stiffness,damping (default 3,0.4)",
    )
    p.add_argument("--optimizer", default="lbfgs", choices=["lbfgs", "adam"])
    p.add_argument(
        "--iterations",
        type=integer(lo=1),
        default=None,
        help="iterations (default: 30 L-BFGS / 400 Adam for run 3, 10 / 300 per-spring)",
    )
    p.add_argument(
        "--lr", type=number(lo=0, lo_open=True), default=None, help="learning rate (default 1 L-BFGS, 0.05 Adam)"
    )
    p.add_argument(
        "--window",
        type=integer(lo=0),
        default=None,
        help="teacher forcing every k observations (default 10, Radetzky; 50 with noise); 0 = full BPTT",
    )
    p.add_argument(
        "--smooth",
        type=integer(lo=0),
        default=None,
        help="half-width of the start-state smoothing (default 0; 10 with noise)",
    )
    p.add_argument("--checkpoint", type=integer(lo=0), default=0, help="gradient checkpoint segment in steps (0 = off)")
    p.add_argument(
        "--long",
        type=integer(lo=0),
        default=0,
        help="instead of the runs: train shared k, d on one full rollout of this many steps "
        "(a 4^3 cube under a sinusoidal drag) and report memory",
    )
    p.add_argument("--no-curvature", action="store_true", help="skip the Hessian eigenvalues of per-spring runs")
    p.add_argument(
        "--engine",
        default="eager",
        choices=learn.LOSS_ENGINES,
        help="rollouts eager (the reference) or compiled (each step one torch.compile graph, "
        "forward and backward; ~35 s to compile once, then ~5x faster per iteration)",
    )
    p.add_argument(
        "--integrator",
        default="symplectic",
        choices=["symplectic", "implicit"],
        help="symplectic: Radetzky's cube as published; implicit: a 1000x stiffer cube stepped by "
        "implicit Euler far above the explicit bound",
    )
    p.add_argument(
        "--dt-factor",
        type=number(lo=0, lo_open=True),
        default=50.0,
        help="implicit: the time step over the explicit stability bound (default 50)",
    )
    p.add_argument(
        "--gradient",
        default="adjoint",
        choices=["adjoint", "unrolled"],
        help="implicit: gradients by adjoint solves (default) or through every CG iteration",
    )
    p.add_argument(
        "--threads", type=integer(lo=1), default=1, help="torch threads (default 1: fastest for tiny bodies)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p.parse_args(argv)


def rss_mb() -> float:
    """Peak resident set size of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def current_rss_mb() -> float:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * resource.getpagesize() / 2**20
    except OSError:
        return float("nan")


def train(params, loss, args, iterations, name, out):
    t0, c0 = time.perf_counter(), time.process_time()
    with torch.no_grad():
        first = float(loss(params))
    it = iterations if args.iterations is None else args.iterations
    trainer = learn.Trainer(
        params,
        loss,
        optimizer=args.optimizer,
        lr=args.lr,
        iterations=it,
        patience=5 if args.optimizer == "lbfgs" else 50,
        tol=1e-26,
        progress=progress(args),
    )
    trainer.run()
    final = trainer.final_loss()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    if data_parallel.is_main():
        learn.plot_history(trainer.history, out / f"{name}_loss.png", title=f"{name}: loss")
    return {
        "initial_loss": first,
        "final_loss": final,
        "loss_drop": first / max(final, 1e-300),
        "iterations": trainer.iteration,
        "stopped": trainer.stopped or "iteration limit",
        "wall_seconds": wall,
        "cpu_seconds": cpu,
        "history": learn.history_dicts(trainer.history),
    }


def shared_run(series, args, out) -> dict:
    kt, ct = series.meta["truth"]["stiffness"], series.meta["truth"]["damping"]
    if not all(isinstance(v, (int, float)) for v in (kt, ct)):
        raise td.ConfigError(
            "--runs",
            "1,2 for a series whose truth is not one shared stiffness and damping "
            f"(run 3 fits one of each; {args.data or 'this series'} has per-region values "
            f"stiffness {kt}, damping {ct})",
            got=args.runs,
        )
    fk, fc = args.offset
    params = learn.Parameters(
        series,
        learn.SpringParameter.like(series, init=kt * fk),
        learn.SpringParameter.like(series, init=ct * fc),
        series.truth["mass"],
    )
    loss = make_loss(series, args)
    res = train(params, loss, args, 30 if args.optimizer == "lbfgs" else 400, "run3", out)
    got = params.summary()
    res.update(
        {
            "learned": got,
            "true": {"stiffness": kt, "damping": ct},
            "initial": {"stiffness": kt * fk, "damping": ct * fc},
            "relative_error": {
                "stiffness": learn.relative_error(got["stiffness"], kt),
                "damping": learn.relative_error(got["damping"], ct),
            },
        }
    )
    return res


#: the stiff cube of ``--integrator implicit``: 1000x Radetzky's stiffness, the same damping ratio
STIFF = {"stiffness": 1e4, "damping": 0.1 * 1000**0.5}


def implicit_integrator(args):
    """Implicit Euler of the truth and the fit (tight CG, so both are the same function)."""
    return td.ImplicitEuler(cg_iters=300, cg_tol=1e-12, gradient=args.gradient)


def stiff_cube(args):
    """Radetzky's cube 1000x stiffer, stepped by implicit Euler at ``args.dt_factor`` x the explicit bound."""
    probe = learn.radetzky_cube(springs=args.springs, steps=1, **STIFF)
    bound = td.time_step_bound(probe.true_model(), integrator="symplectic")
    series = learn.radetzky_cube(
        springs=args.springs,
        noise=args.noise,
        seed=args.seed,
        dt=args.dt_factor * bound,
        integrator=implicit_integrator(args),
        **STIFF,
    )
    series.meta.update(explicit_bound=bound, dt_over_bound=args.dt_factor)
    return series


def progress(args) -> bool:
    """Progress bars: unless --quiet, and on rank 0 only."""
    return not args.quiet and data_parallel.is_main()


def make_loss(series, args):
    """The window loss of the fit, shared out over the ranks under torchrun."""
    noisy = series.meta.get("noise", 0.0) > 0
    window = args.window if args.window is not None else (50 if noisy else 10)
    smooth = args.smooth if args.smooth is not None else (10 if noisy else 0)
    integrator = implicit_integrator(args) if args.integrator == "implicit" else None
    return data_parallel.parallel_loss(
        learn.WindowLoss(
            series,
            window=None if window == 0 else window,
            smooth=smooth,
            checkpoint=args.checkpoint or None,
            engine=args.engine,
            integrator=integrator,
        )
    )


def per_spring_run(series, args, out, with_mass: bool) -> dict:
    params, truth = learn.per_spring_start(series, seed=args.seed, with_mass=with_mass)
    k, c = params.learned["stiffness"], params.learned["damping"]
    tk, tc = truth["stiffness"], truth["damping"]
    n = len(tk)
    loss = make_loss(series, args)
    name = "run1" if with_mass else "run2"
    res = train(params, loss, args, 10 if args.optimizer == "lbfgs" else 300, name, out)
    active = learn.active_springs(series)[k.mask]
    spread = {}
    for key, mod, true in (("stiffness", k, tk), ("damping", c, tc)):
        v = mod.values().detach()
        spread[key] = learn.spread_report(v[active], true[active])
        if data_parallel.is_main():
            learn.plot_spread(v[active], true[active], out / f"{name}_spread_{key}.png", title=f"{name}: {key}")
    if with_mass:
        free = torch.as_tensor(~series.constrained())[series.grid.nodes()]
        v, tm = params.learned["mass"].values().detach(), truth["mass"]
        spread["mass"] = learn.spread_report(v[free], tm[free])
        if data_parallel.is_main():
            learn.plot_spread(v[free], tm[free], out / f"{name}_spread_mass.png", title=f"{name}: mass (free nodes)")
    res.update(
        {
            "spread": spread,
            "springs": n,
            "inactive_springs": int((~active).sum()),
            "note": "springs between two fixed nodes never move and are left out of the spread",
        }
    )
    if not args.no_curvature:
        res["curvature"] = learn.curvature_report(params, loss)
        if "eigenvalues" in res["curvature"]:  # (skipped for many parameters: a reason instead)
            res["curvature"]["eigenvalues"] = [float(f"{e:.4g}") for e in res["curvature"]["eigenvalues"]]
    res["learned"] = params.summary()
    return res


def long_run(args, out) -> dict:
    """Full BPTT over one long rollout: shared k, d of a 4^3 cube dragged sinusoidally."""
    series = learn.cube_series(n=4, topology=26, load="sine", steps=args.long, dt=0.005, period=1.0)
    kt, ct = series.meta["truth"]["stiffness"], series.meta["truth"]["damping"]
    params = learn.Parameters(
        series,
        learn.SpringParameter.like(series, init=kt * 2.0),
        learn.SpringParameter.like(series, init=ct * 0.5),
        series.truth["mass"],
    )
    loss = data_parallel.parallel_loss(
        learn.WindowLoss(series, window=None, checkpoint=args.checkpoint or None, engine=args.engine)
    )  # one window: rank 0 runs it
    before = current_rss_mb()
    t0, c0 = time.perf_counter(), time.process_time()
    trainer = learn.Trainer(
        params,
        loss,
        optimizer="adam",
        lr=args.lr or 0.05,
        iterations=args.iterations or 3,
        patience=100,
        progress=progress(args),
    )
    trainer.run()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    losses = [r.loss for r in trainer.history]
    return {
        "steps": args.long,
        "nodes": series.grid.num_nodes,
        "springs": series.grid.num_springs,
        "checkpoint_segment": args.checkpoint or None,
        "iterations": trainer.iteration,
        "losses": losses,
        "finite": bool(np.isfinite(losses).all()),
        "learned": params.summary(),
        "true": {"stiffness": kt, "damping": ct},
        "rss_before_mb": before,
        "peak_rss_mb": rss_mb(),
        "peak_growth_mb": rss_mb() - before,
        "wall_seconds": wall,
        "cpu_seconds": cpu,
    }


def main(argv=None) -> int:
    args = parse_args(argv)
    with data_parallel.process_group():  # under torchrun: gloo over the ranks; else nothing
        return learn.run_script("fit_cube.py", args, fit, summary)


def check_truth(series, path) -> None:
    """Refuse a series without the true values a fit starts from and is scored against (one line)."""
    missing = [f"true_{k}" for k in ("stiffness", "damping", "mass") if k not in series.truth]
    truth = series.meta.get("truth")
    if not (isinstance(truth, dict) and "stiffness" in truth and "damping" in truth):
        missing.append("meta truth {stiffness, damping}")
    if missing:
        raise td.ConfigError(
            "--data",
            "a series with its true values, as torchdeform data cube writes them (this script starts "
            f"from and scores against them); missing {', '.join(missing)}",
            got=str(path),
        )


def fit(args, out) -> dict:
    if args.long:
        result = {"long_rollout": long_run(args, out)}
    else:
        if args.data:
            series = learn.load_series(args.data)
            check_truth(series, args.data)
        elif args.integrator == "implicit":
            series = stiff_cube(args)
        else:
            series = learn.radetzky_cube(springs=args.springs, noise=args.noise, seed=args.seed)
        try:
            runs = [int(r) for r in args.runs.split(",") if r.strip()]
        except ValueError:
            runs = [0]
        if not runs or any(r not in (1, 2, 3) for r in runs):
            raise td.ConfigError("--runs", "comma-separated runs among 1, 2, 3", got=args.runs)
        result = {
            "series": {k: v for k, v in series.meta.items() if k != "loads"},
            "optimizer": args.optimizer,
            "runs": {},
        }
        for r in runs:
            if data_parallel.is_main():
                print(f"run {r} ...", file=sys.stderr)
            result["runs"][str(r)] = (
                shared_run(series, args, out) if r == 3 else per_spring_run(series, args, out, with_mass=(r == 1))
            )
    return result


def summary(result) -> str:
    lines = []
    if "long_rollout" in result:
        r = result["long_rollout"]
        return (
            f"long rollout: {r['steps']} steps, checkpoint {r['checkpoint_segment']}, losses {r['losses']}, "
            f"peak RSS {r['peak_rss_mb']:.0f} MB (before training {r['rss_before_mb']:.0f} MB), "
            f"{r['wall_seconds']:.1f} s wall, {r['cpu_seconds']:.1f} s CPU"
        )
    for name, r in result["runs"].items():
        line = (
            f"run {name}: loss {r['initial_loss']:.3e} -> {r['final_loss']:.3e} "
            f"({r['loss_drop']:.3g}-fold) in {r['iterations']} it, {r['wall_seconds']:.1f} s wall, "
            f"{r['cpu_seconds']:.1f} s CPU"
        )
        if "relative_error" in r:
            line += "; " + ", ".join(
                f"{k} {r['learned'][k]:.6g} (true {r['true'][k]:.6g}, rel err {e:.2e})"
                for k, e in r["relative_error"].items()
            )
        if "spread" in r:
            for k, s in r["spread"].items():
                q = s["ratio"]
                line += (
                    f"\n   {k}: learned/true p05 {q['p05']:.3f} median {q['median']:.3f} p95 {q['p95']:.3f}, "
                    f"{100 * s['within_10pct']:.0f}% within 10% -> {s['verdict']}"
                )
            if "curvature" in r and "undetermined" in r["curvature"]:
                c = r["curvature"]
                line += f"\n   Hessian: {c['undetermined']} of {c['n']} directions undetermined (< {c['threshold']:g} x max)"
        lines.append(line)
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
