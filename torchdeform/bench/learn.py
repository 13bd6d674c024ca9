"""``torchdeform bench learn``: a training iteration eager and compiled, and whether they agree.

**Run.** Radetzky's per-spring run (``training/fit_cube.py --runs 2``): the 3 x 3 x 3 cube with
70 springs, 250 steps, every spring's stiffness and damping learned from a start at
``U[0.2, 5]`` x truth (:func:`~torchdeform.learn.per_spring_start`), teacher forcing every 10
observations (25 windows in one batch), L-BFGS with a strong-Wolfe line search (one iteration is
up to 20 loss and gradient evaluations), float64.

**Engines.** :class:`~torchdeform.learn.WindowLoss` with ``engine="eager"`` (the reference) and
``engine="compiled"`` (each step of the rollout one ``torch.compile`` graph, forward and backward).
``compile_s`` is the compiled engine's first loss and gradient evaluation (it compiles there; less
when inductor's on-disk cache already holds the graphs); ``s_per_iteration`` is the median over
the iterations after the first; ``speedup`` is eager over compiled, both timed in this run.

**Agreement.** The loss and gradient at the start, compiled against eager (relative); then,
after every iteration, the largest relative difference of the learned values. A third trainer
runs eagerly from the start multiplied by ``1 + 1e-15``: how far rounding alone moves this run.
The per-spring problem is ill-determined (Radetzky's lesson), so its L-BFGS path amplifies any
difference in the last bit about 30-fold per iteration; the comparison that can hold to 1e-10 is
one training iteration (``met`` asks for it and for ``speedup >= 3``).

Example:
    torchdeform bench learn --quick
    torchdeform bench learn --iterations 10 --json --out bench-out
"""

from __future__ import annotations

import statistics
import sys
import time

import torch

from ..errors import ConfigError
from ..options import integer
from ..outputs import axes, save_plot
from .common import add_common, emit, machine_info

__all__ = ["COLUMNS", "TARGET_SPEEDUP", "TOLERANCE", "PERTURBATION", "add_arguments", "run"]

#: the compiled training iteration's speed-up over the eager one that the bench asks for
TARGET_SPEEDUP = 3.0
#: largest relative difference, compiled against eager, of one iteration's loss, gradient and result
TOLERANCE = 1e-10
#: relative perturbation of the start of the sensitivity trainer
PERTURBATION = 1e-15

COLUMNS = [
    ("engine", "engine", None),
    ("threads", "threads", None),
    ("compile_s", "compile s", "{:.1f}"),
    ("s_per_iteration", "s / iteration", "{:.3f}"),
    ("speedup", "speed-up", "{:.2f}x"),
    ("final_loss", "loss after", "{:.4e}"),
]


def add_arguments(p) -> None:
    """The options of ``bench learn``."""
    add_common(p)
    p.add_argument("--iterations", type=integer(lo=1), default=None, help="L-BFGS iterations (default 10; --quick: 2)")
    p.add_argument("--seed", type=integer(lo=0), default=0, help="seed of the per-spring start (default 0)")
    p.add_argument("--no-compile", action="store_true", help="the eager engine only (as --quick)")


def _values(params) -> torch.Tensor:
    return torch.cat([m.values().detach().reshape(-1) for m in params.learned.values()])


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(((a - b).abs() / b.abs().clamp_min(1e-300)).max())


def _loss_and_grad(loss, params):
    for p in params.parameters():
        p.grad = None
    t0 = time.perf_counter()
    value = loss(params)
    value.backward()
    seconds = time.perf_counter() - t0
    return value.detach(), torch.cat([p.grad.reshape(-1) for p in params.parameters()]), seconds


def run(args) -> int:
    """Run the bench; returns the exit status."""
    from .. import learn

    iterations = args.iterations or (2 if args.quick else 10)
    if iterations < 2:
        raise ConfigError(
            "--iterations", "at least 2 (the first compiled iteration includes the compile)", got=iterations
        )
    device = str(torch.device(args.device))
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("--device", "cpu, or cuda on a machine with CUDA", got=args.device)
    compiled = not (args.no_compile or args.quick)
    saved = torch.get_num_threads()
    torch.set_num_threads(args.threads or 1)  # a 27-node body: one thread is fastest
    try:
        threads = torch.get_num_threads()
        series = learn.radetzky_cube(springs=70)
        engines = ["eager", "compiled"] if compiled else ["eager"]
        runs = {}
        for name in engines + ["perturbed"]:
            params, _ = learn.per_spring_start(series, seed=args.seed)
            params = params.to(device)  # the rollouts run where the parameters are
            if name == "perturbed":
                with torch.no_grad():
                    for p in params.parameters():
                        p.add_(torch.log1p(torch.tensor(PERTURBATION, dtype=p.dtype)))  # values x (1 + eps)
            loss = learn.WindowLoss(series, window=10, engine="compiled" if name == "compiled" else "eager")
            runs[name] = {
                "params": params,
                "loss": loss,
                "trainer": learn.Trainer(
                    params,
                    loss,
                    optimizer="lbfgs",
                    iterations=iterations,
                    patience=iterations,
                    tol=1e-26,
                    progress=False,
                ),
            }
        first = {name: _loss_and_grad(r["loss"], r["params"]) for name, r in runs.items() if name in engines}
        check = {}
        if compiled:
            (le, ge, _), (lc, gc, compile_s) = first["eager"], first["compiled"]
            check = {"loss_rel": _rel(lc.reshape(1), le.reshape(1)), "grad_rel": float((gc - ge).norm() / ge.norm())}
        agreement, seconds = [], {name: [] for name in runs}
        from tqdm.auto import tqdm

        for it in tqdm(
            range(1, iterations + 1), desc="bench learn", unit="it", file=sys.stderr, disable=None, leave=False
        ):
            for name, r in runs.items():
                before = r["trainer"].seconds
                r["trainer"].run(iterations=it)
                seconds[name].append(r["trainer"].seconds - before)
            ref = _values(runs["eager"]["params"])
            agreement.append(
                {
                    "iteration": it,
                    "compiled_vs_eager": _rel(_values(runs["compiled"]["params"]), ref) if compiled else None,
                    "perturbed_vs_eager": _rel(_values(runs["perturbed"]["params"]), ref),
                }
            )
    finally:
        torch.set_num_threads(saved)
    eager_s = statistics.median(seconds["eager"])
    rows = []
    for name in engines:
        per_it = statistics.median(seconds[name][1:])
        rows.append(
            {
                "engine": name,
                "threads": threads,
                "iterations": iterations,
                "compile_s": compile_s if name == "compiled" else None,
                "s_per_iteration": per_it,
                "first_iteration_s": seconds[name][0],
                "speedup": eager_s / per_it if name == "compiled" else 1.0,
                "final_loss": runs[name]["trainer"].history[-1].loss,
            }
        )
    one = agreement[0]["compiled_vs_eager"]
    met = None
    if compiled:
        met = bool(rows[1]["speedup"] >= TARGET_SPEEDUP and max(check.values()) <= TOLERANCE and one <= TOLERANCE)
    extra = {
        "machine": dict(machine_info(device), threads=threads),
        "target_speedup": TARGET_SPEEDUP,
        "tolerance": TOLERANCE,
        "met": met,
        "start_check": check,
        "agreement": agreement,
        "perturbation": PERTURBATION,
        "setup": f"Radetzky's cube, 70 springs learned per spring (fit_cube.py --runs 2), 25 windows of 10 "
        f"steps, L-BFGS, float64, {device}, {threads} thread{'s' if threads != 1 else ''}",
    }
    if args.out:
        _plot(rows, agreement, args.out, threads)
    if not args.json:
        print("training iterations, " + extra["setup"])
    emit("learn", args, rows, COLUMNS, extra=extra)
    if not args.json:
        if compiled:
            print(f"start: loss {check['loss_rel']:.1e}, gradient {check['grad_rel']:.1e} relative (compiled vs eager)")
        for a in agreement:
            c = "-" if a["compiled_vs_eager"] is None else f"{a['compiled_vs_eager']:.1e}"
            print(
                f"after iteration {a['iteration']:>2}: learned values differ by {c} (compiled vs eager), "
                f"{a['perturbed_vs_eager']:.1e} (eager from a start x (1 + {PERTURBATION:g}))"
            )
        if compiled:
            print(
                f">= {TARGET_SPEEDUP:g}x faster and one iteration the same to {TOLERANCE:g}: "
                f"{'yes' if met else 'no'} ({rows[1]['speedup']:.2f}x, {one:.1e})"
            )
    return 0


def _plot(rows, agreement, out_dir, threads) -> None:
    fig, (a1, a2) = axes(figsize=(10, 4), ncols=2)
    a1.bar([r["engine"] for r in rows], [r["s_per_iteration"] for r in rows], color=["C0", "C1"][: len(rows)])
    a1.set_ylabel("seconds per L-BFGS iteration")
    a1.set_title(f"Per-spring run, {threads} thread{'s' if threads != 1 else ''}")
    its = [a["iteration"] for a in agreement]
    if agreement[0]["compiled_vs_eager"] is not None:
        a2.semilogy(its, [max(a["compiled_vs_eager"], 1e-17) for a in agreement], marker="o", label="compiled vs eager")
    a2.semilogy(
        its,
        [max(a["perturbed_vs_eager"], 1e-17) for a in agreement],
        marker="s",
        ls="--",
        label=f"eager from start x (1 + {PERTURBATION:g}) vs eager",
    )
    a2.axhline(TOLERANCE, color="grey", ls=":", label=f"{TOLERANCE:g}")
    a2.set_xlabel("L-BFGS iteration")
    a2.set_ylabel("largest relative difference of learned values")
    a2.set_title("Rounding grows along the ill-determined run")
    a2.grid(True, which="both", alpha=0.3)
    a2.legend(fontsize=8)
    save_plot(fig, out_dir, "learn.png")
