"""Neuro-fuzzy fit: learn the fuzzy inputs (slider values) or the membership functions so that
the fuzzy-derived stiffness and viscosity reproduce an observed series.

Radetzky's shape modeler sets spring constant and viscosity from a Mamdani system (e.g.
SUSILAP-G: consistency -> spring_const, viscosity). Here the series is Radetzky's cube
(70 springs, lower 9 nodes fixed, constant force on the top-centre node) simulated with the
values the system gives at the target slider value; training starts from another value.

  --learn inputs       learn the slider (kept inside the input range by a sigmoid). The
                       fuzzy map has plateaus (trapezoid shoulders) where the gradient is 0,
                       so the script first scans the slider range (--scan points) and then
                       refines the best value with L-BFGS.
  --learn membership   keep the slider at --init and learn the membership-function corners of
                       the outputs, so that the system gives the observed stiffness/viscosity
                       at that slider value (a recalibrated rule base).

Examples:
    python training/fit_fuzzy.py --out runs/fuzzy                         # slider, SUSILAP-G
    python training/fit_fuzzy.py --learn membership --init 7.0 --out runs/fuzzy-mf
    torchrun --standalone --nproc-per-node 2 training/fit_fuzzy.py --out runs/fuzzy-2ranks

Under ``torchrun`` the cube's teacher-forcing windows are shared out over the ranks (data-parallel)
and rank 0 writes the results.

Writes DIR/result.json (target and learned stiffness/viscosity, slider values, relative errors,
loss history, wall and CPU time) and DIR/loss.png, DIR/scan.png.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

import torchdeform as td
from torchdeform import fuzzy, learn
from torchdeform.distributed import data_parallel
from torchdeform.options import Parser, integer, number


def parse_args(argv=None):
    p = Parser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__[__doc__.index("  --learn") :],
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--preset", default="susilap_g", help="fuzzy preset with one input (default susilap_g)")
    p.add_argument("--learn", default="inputs", choices=["inputs", "membership"])
    p.add_argument(
        "--target",
        type=number(),
        default=5.5,
        help="slider value that produced the data (default 5.5, the Fallopian tube)",
    )
    p.add_argument("--init", type=number(), default=7.0, help="initial slider value (default 7.0, the bowel)")
    p.add_argument(
        "--scan", type=integer(lo=0), default=61, help="slider scan points before refining (inputs; 0 = off)"
    )
    p.add_argument(
        "--mass", type=number(lo=0, lo_open=True, unit="kg"), default=0.2, help="node mass (kg; default 0.2)"
    )
    p.add_argument(
        "--iterations",
        type=integer(lo=1),
        default=None,
        help="iterations (default 20 L-BFGS for inputs, 600 Adam for membership)",
    )
    p.add_argument(
        "--lr",
        type=number(lo=0, lo_open=True),
        default=0.05,
        help="Adam learning rate of membership corners (default 0.05)",
    )
    p.add_argument("--threads", type=integer(lo=1), default=1)
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    with data_parallel.process_group():  # under torchrun: gloo over the ranks; else nothing
        return learn.run_script("fit_fuzzy.py", args, fit, summary)


def fit(args, out) -> dict:
    ref = fuzzy.load_preset(args.preset).double()
    if len(ref.inputs) != 1:
        raise td.ConfigError("--preset", "a fuzzy system with one input (the slider)", got=args.preset)
    name = ref.input_names()[0]
    target = {k: float(v) for k, v in ref.evaluate({name: args.target}).items()}
    kt, ct = target["spring_const"], target["viscosity"]
    series = learn.radetzky_cube(springs=70, stiffness=kt, damping=ct, mass=args.mass)
    fs = learn.FuzzySprings(
        fuzzy.load_preset(args.preset),
        {name: args.init},
        grid=series.grid,
        spring_mask=series.spring_mask_tensor(),
        learn=args.learn,
    )
    params = learn.Parameters(series, fs.part("stiffness"), fs.part("damping"), series.truth["mass"])
    loss = data_parallel.parallel_loss(learn.WindowLoss(series, window=10))
    main = data_parallel.is_main()
    result = {
        "preset": args.preset,
        "learn": args.learn,
        "input": name,
        "target_slider": args.target,
        "initial_slider": args.init,
        "target": {"stiffness": kt, "damping": ct},
        "initial": {k: float(v.detach()) for k, v in fs().items()},
    }
    its = args.iterations or (20 if args.learn == "inputs" else 600)
    starts = [args.init]
    if args.learn == "inputs" and args.scan:
        lo, hi = (float(v) for v in ref.inputs[0].range)
        grid = np.linspace(lo, hi, args.scan + 2)[1:-1]
        with torch.no_grad():
            losses = []
            for g in grid:
                set_slider(fs, g)
                losses.append(float(loss(params)))
        ls = np.asarray(losses)
        minima = [i for i in range(len(ls)) if ls[i] <= ls[max(i - 1, 0)] and ls[i] <= ls[min(i + 1, len(ls) - 1)]]
        starts = [float(grid[i]) for i in sorted(minima, key=lambda i: ls[i])[:3]]
        result["scan"] = {"values": grid.tolist(), "losses": losses, "starts": starts}
        if main:
            learn.plot_scan(
                grid, losses, args.target, out / "scan.png", xlabel=name, marker="target", title="slider scan"
            )
    best = None
    for start in starts:  # refine each start; keep the lowest loss
        set_slider(fs, start)
        with torch.no_grad():
            first = float(loss(params))
        if args.learn == "inputs":
            trainer = learn.Trainer(
                params, loss, optimizer="lbfgs", iterations=its, patience=5, tol=1e-26, progress=not args.quiet and main
            )
        else:  # small Adam steps: big quasi-Newton steps collapse trapezoids (zero gradient)
            trainer = learn.Trainer(
                params,
                loss,
                optimizer="adam",
                lr=args.lr,
                iterations=its,
                patience=50,
                tol=1e-26,
                clip=None,
                progress=not args.quiet and main,
            )
        trainer.run()
        final = trainer.final_loss()
        if best is None or final < best[0]:
            best = (final, first, trainer, [p.detach().clone() for p in params.parameters()])
    final, first, trainer, values = best
    with torch.no_grad():
        for p, v in zip(params.parameters(), values):
            p.copy_(v)
    got = {k: float(v.detach()) for k, v in fs().items()}
    result.update(
        {
            "learned": got,
            "learned_slider": float(fs.inputs()[0].detach()),
            "relative_error": {
                "stiffness": learn.relative_error(got["stiffness"], kt),
                "damping": learn.relative_error(got["damping"], ct),
            },
            "initial_loss": first,
            "final_loss": final,
            "iterations": trainer.iteration,
            "stopped": trainer.stopped or "iteration limit",
            "history": learn.history_dicts(trainer.history),
        }
    )
    if args.learn == "membership":
        result["membership"] = {
            v.name: {t: [float(x) for x in mf.params.detach()] for t, mf in v.terms.items()} for v in fs.fis.outputs
        }
    if main:
        learn.plot_history(trainer.history, out / "loss.png", title=f"fuzzy fit ({args.learn})")
    return result


def summary(result) -> str:
    got, want, err = result["learned"], result["target"], result["relative_error"]
    return (
        f"{result['learn']}: slider {result['learned_slider']:.6g} (target {result['target_slider']}); "
        f"stiffness {got['stiffness']:.6g} (target {want['stiffness']:.6g}, rel err {err['stiffness']:.2e}); "
        f"viscosity {got['damping']:.6g} (target {want['damping']:.6g}, rel err {err['damping']:.2e}); "
        f"{result['wall_seconds']:.1f} s wall, {result['cpu_seconds']:.1f} s CPU"
    )


def set_slider(fs, value):
    """Put the (single) slider of ``fs`` at ``value``."""
    lo, hi = float(fs.lo[0]), float(fs.hi[0])
    u = (float(value) - lo) / (hi - lo)
    with torch.no_grad():
        fs.raw_inputs.fill_(float(np.log(u / (1 - u))))


if __name__ == "__main__":
    sys.exit(main())
