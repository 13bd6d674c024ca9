"""``torchdeform bench chainmail``: time of a local pull against grid size and moved elements.

A cube of ``n^3`` elements 1 mm apart (limits 0.8 / 1.2 / 0.2 of the spacing) has its centre
element pulled by ``(p, p/2, 0)``; the pull sizes are chosen so that about 200, 1,300 and 9,000
elements move (the same on every grid: ChainMail is local). Each row is the median over
``--repeats`` pulls from rest (the reset is not timed) of one variant:

=========  =======================================================================
gibson     :class:`~torchdeform.chainmail.ChainMail`, six lists (sequential)
enhanced   the same with one priority queue per coordinate (sequential)
tensor     :func:`~torchdeform.chainmail.tensor_chainmail`, sponsor-front Jacobi sweeps over
           the active region only (the bounding box of the moved elements plus one hop,
           grown as the front advances; torch, ``--device``); also reports sweeps and
           propagation depth
=========  =======================================================================

Rows carry ``grid``, ``moved``, ``variant`` and ``ms``; ``checked`` is the number of elements
visited (sequential: elements examined; tensor: the sum over sweeps of the active box's volume,
far below ``n^3`` per sweep). The document also gives the 100^3 pull that moves about 1,300
elements, sequential (``pull_100``) and tensor (``tensor_pull_100``), each against the 50 ms
target, and the ratio of the same pull on 128^3 and 32^3 (locality: about 1). The figure plots
ms against moved elements per variant and grid with the 50 ms line. The sequential variants
work in float64; the tensor rows in ``--dtype`` (default float32, where rounding moves some
elements by an ulp: about 1,560 moved instead of the 1,304 of ``--dtype float64``).

Example:
    torchdeform bench chainmail --quick
    torchdeform bench chainmail --json --out bench-out
"""

from __future__ import annotations

import statistics
import time

import torch

from ..errors import ConfigError
from ..options import integer
from ..outputs import axes, save_plot
from .common import add_common, emit, int_list, machine_info, progress

__all__ = ["COLUMNS", "SPACING", "PULLS", "add_arguments", "run"]

COLUMNS = [
    ("grid", "grid", None),
    ("variant", "variant", None),
    ("pull_mm", "pull mm", "{:.1f}"),
    ("moved", "moved", "{:,}"),
    ("checked", "checked", "{:,}"),
    ("ms", "ms (median)", "{:.2f}"),
    ("us_per_moved", "us/moved", "{:.2f}"),
    ("sweeps", "sweeps", None),
    ("depth", "depth", None),
    ("max_violation_m", "max excess m", "{:.1e}"),
]
SPACING = 1e-3
#: pull sizes (metres along d; half that along h): about 200, 1,300 and 9,000 moved elements
PULLS = (1e-3, 2e-3, 4e-3)


def add_arguments(p) -> None:
    """The options of ``torchdeform bench chainmail``."""
    add_common(p)
    p.add_argument(
        "--sizes",
        type=int_list("--sizes"),
        default=None,
        help="grid sizes n (n^3 elements), comma-separated (default 32,64,100,128; quick 16,24)",
    )
    p.add_argument(
        "--tensor-sizes",
        type=int_list("--tensor-sizes"),
        default=None,
        help="sizes that also get tensor rows, for the middle pull (default 32,64,100; quick 16,24)",
    )
    p.add_argument(
        "--repeats", type=integer(lo=1), default=None, help="timed pulls per row, the median is kept (default 5)"
    )


def _median_ms(fn, reset, repeats):
    fn()  # warm-up (first touch of the arrays)
    reset()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
        reset()
    return 1e3 * statistics.median(times), out


def run(args) -> int:
    """Run the bench: one row per grid size, pull and variant; returns the exit status."""
    from ..chainmail import ChainMail, Limits, limit_violation, tensor_chainmail
    from ..sim.grid import Grid

    if args.threads:
        torch.set_num_threads(args.threads)
    sizes = args.sizes or ([16, 24] if args.quick else [32, 64, 100, 128])
    tsizes = args.tensor_sizes or ([16, 24] if args.quick else [32, 64, 100])
    repeats = args.repeats or (2 if args.quick else 5)
    if repeats < 1 or min(sizes + tsizes) < 3:
        raise ConfigError("--repeats/--sizes", "at least 1 repeat and sizes >= 3", got=(repeats, sizes))
    pulls = PULLS[:2] if args.quick else PULLS
    dtype = getattr(torch, args.dtype)
    rows = []
    bar = progress(len(sizes) * len(pulls) * 2 + len(tsizes), "bench chainmail")
    for n in sizes:
        grid = Grid((n, n, n), spacing=SPACING)
        lim = Limits.from_material(grid, compression=0.8, stretch=1.2, shear=0.2)
        centre = (n // 2, n // 2, n // 2)
        for variant in ("gibson", "enhanced"):
            cm = ChainMail(grid, lim, method=variant)
            for pull in pulls:
                if pull / (0.2 * SPACING) > n // 2 - 1:  # the pull would reach the border
                    bar.update(1)
                    continue
                ms, r = _median_ms(
                    lambda cm=cm, pull=pull, centre=centre: cm.move([centre], (pull, pull / 2, 0.0)), cm.reset, repeats
                )
                cm.move([centre], (pull, pull / 2, 0.0))
                worst = float(limit_violation(cm.positions(), grid, lim)[0])
                cm.reset()
                rows.append(
                    dict(
                        grid=f"{n}^3",
                        n=n,
                        variant=variant,
                        pull_mm=pull * 1e3,
                        moved=r.moved,
                        checked=r.checked,
                        ms=ms,
                        us_per_moved=1e3 * ms / r.moved,
                        sweeps=None,
                        depth=None,
                        max_violation_m=worst,
                        repeats=repeats,
                    )
                )
                bar.update(1)
    pull = pulls[1]
    for n in tsizes:
        grid = Grid((n, n, n), spacing=SPACING)
        lim = Limits.from_material(grid, compression=0.8, stretch=1.2, shear=0.2)
        if pull / (0.2 * SPACING) > n // 2 - 1:
            bar.update(1)
            continue
        x = grid.rest_positions(dtype=dtype, device=args.device)
        pick = torch.zeros(grid.shape, dtype=torch.bool)
        pick[n // 2, n // 2, n // 2] = True
        d = torch.tensor([pull, pull / 2, 0.0], dtype=dtype)
        sync = torch.cuda.synchronize if str(args.device).startswith("cuda") else (lambda: None)

        def once(x=x, grid=grid, lim=lim, pick=pick, d=d, sync=sync):
            r = tensor_chainmail(x, grid, lim, pick, d)
            sync()
            return r

        ms, r = _median_ms(once, lambda: None, repeats)
        moved = int(r.moved.sum())
        rows.append(
            dict(
                grid=f"{n}^3",
                n=n,
                variant="tensor",
                pull_mm=pull * 1e3,
                moved=moved,
                checked=r.checked,
                ms=ms,
                us_per_moved=1e3 * ms / moved,
                sweeps=r.sweeps,
                depth=int(r.depth[0]),
                max_violation_m=float(r.violation[0]),
                repeats=repeats,
                device=str(args.device),
            )
        )
        bar.update(1)
    bar.close()

    def find(n, variant, pull_mm):
        return next(
            (r for r in rows if r["n"] == n and r["variant"] == variant and abs(r["pull_mm"] - pull_mm) < 1e-9), None
        )

    extra = {"machine": machine_info(args.device), "spacing_m": SPACING, "limits": [0.8, 1.2, 0.2]}
    for key, variant in (("pull_100", "gibson"), ("tensor_pull_100", "tensor")):
        r100 = find(100, variant, 2.0)
        extra[key] = (
            None
            if r100 is None
            else {"moved": r100["moved"], "ms": r100["ms"], "target_ms": 50.0, "met": r100["ms"] < 50.0}
        )
    small, large = find(32, "gibson", 2.0), find(128, "gibson", 2.0)
    extra["locality_128_vs_32"] = (
        None
        if not (small and large)
        else {
            "moved": [small["moved"], large["moved"]],
            "ms": [small["ms"], large["ms"]],
            "ratio": large["ms"] / small["ms"],
        }
    )
    if args.out:
        _plot(rows, args.out)
    emit("chainmail", args, rows, COLUMNS, extra=extra)
    return 0


def _plot(rows, out_dir) -> None:
    fig, ax = axes(figsize=(6.5, 4.5))
    styles = {"gibson": "-", "enhanced": "--", "tensor": ":"}
    for variant in ("gibson", "enhanced", "tensor"):
        for n in sorted({r["n"] for r in rows if r["variant"] == variant}):
            pts = sorted((r["moved"], r["ms"]) for r in rows if r["variant"] == variant and r["n"] == n)
            ax.plot(*zip(*pts), marker="o", ls=styles[variant], label=f"{variant} {n}^3")
    ax.axhline(50, color="grey", lw=0.8)
    ax.text(ax.get_xlim()[0], 52, " 50 ms", color="grey", fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("elements moved by the pull")
    ax.set_ylabel("ms per pull (median)")
    ax.set_title("ChainMail: a local pull, cost against moved elements and grid size")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    save_plot(fig, out_dir, "chainmail.png")
