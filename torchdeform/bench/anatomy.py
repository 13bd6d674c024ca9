"""``torchdeform bench anatomy``: label volumes to bodies, and embedded surfaces per frame.

Three rows, each the median of ``--repeats`` timings, each also timed with a busy process beside
it with ``--contention`` (``busy/idle``):

* ``labels -> body``: a synthetic ``n^3`` label volume at 1 mm (an ellipsoidal organ with a
  stiffer spherical tumour, a slab of fixed bone, air around them) made into a ready lattice body
  at ``n / 64`` mm spacing (about 64^3 nodes at ``n = 256``):
  :func:`~torchdeform.anatomy.body_from_labels` and its model. Target: at most 3 s for 256^3.
* ``label surfaces``: the organ's and the tumour's smooth surfaces at image resolution
  (:func:`~torchdeform.mesh.embed.label_surfaces`: marching cubes, Taubin smoothing, decimation
  to 20,000 triangles each); no target, for the record.
* ``surface update``: a surface of about 100,000 triangles (a UV sphere) embedded in a 40^3
  lattice, its positions and normals on a deformed lattice (:meth:`~torchdeform.mesh.embed.
  EmbeddedSurface.update`), float32. Target: at most 5 ms per frame.

It runs on 2 CPU threads unless ``--threads`` says otherwise (the targets are stated for 2 cores).
``--out DIR`` writes ``anatomy.csv`` and ``anatomy.png`` (each row's time against its target).

Example:
    torchdeform bench anatomy --quick
    torchdeform bench anatomy --contention --json --out bench-out
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch

from ..options import integer
from ..outputs import axes, save_plot
from .common import add_common, busy_neighbour, emit, machine_info

__all__ = ["COLUMNS", "add_arguments", "run", "label_phantom", "TARGETS_MS"]

COLUMNS = [
    ("row", "row", None),
    ("size", "size", None),
    ("threads", "thr", None),
    ("ms", "ms (median)", "{:,.1f}"),
    ("target_ms", "target ms", "{:,.0f}"),
    ("met", "met", None),
    ("busy_ms", "busy ms", "{:,.1f}"),
    ("busy_over_idle", "busy/idle", "{:.2f}"),
]

#: the targets (ms) of the rows that have one, at the full sizes
TARGETS_MS = {"labels -> body": 3000.0, "surface update": 5.0}


def add_arguments(p) -> None:
    """The options of ``torchdeform bench anatomy``."""
    add_common(p)
    p.add_argument("--size", type=integer(lo=16), default=None, help="label volume side n (default 256; quick 64)")
    p.add_argument("--triangles", type=integer(lo=100), default=None, help="surface triangles (default 100,000)")
    p.add_argument("--repeats", type=integer(lo=1), default=None, help="timed repeats (default 5; quick 2)")
    p.add_argument("--contention", action="store_true", help="time each row again beside a busy process")


def label_phantom(n: int) -> np.ndarray:
    """A ``(n, n, n)`` uint8 label volume: organ 1, tumour 2 inside it, bone 3 beside it, air 0."""
    c = (np.arange(n, dtype=np.float32) + 0.5) / n
    i, j, k = np.meshgrid(c, c, c, indexing="ij", sparse=True)
    lab = np.zeros((n, n, n), np.uint8)
    lab[((i - 0.5) / 0.42) ** 2 + ((j - 0.45) / 0.36) ** 2 + ((k - 0.5) / 0.46) ** 2 < 1] = 1
    lab[((i - 0.58) ** 2 + (j - 0.4) ** 2 + (k - 0.5) ** 2) < 0.11**2] = 2
    bone = np.broadcast_to((j > 0.86) & (i > 0.15) & (i < 0.85), (n, n, n)) & (lab == 0)
    lab[bone] = 3
    return lab


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def _cases(args) -> list:
    """``[(row, size text, fn, repeats, calls per timing)]``: the timed calls, built (and warmed up) once."""
    import trimesh

    import torchdeform as td

    from ..anatomy import Image, body_from_labels
    from ..mesh.embed import EmbeddedSurface, label_surfaces

    n = args.size or (64 if args.quick else 256)
    repeats = args.repeats or (2 if args.quick else 5)
    lab = label_phantom(n)
    image = Image(lab, np.diag([0.001, 0.001, 0.001, 1.0]), f"phantom {n}^3")
    spacing = n / (16 if args.quick else 64) * 0.001  # a body of about 64^3 nodes (quick: 16^3)
    tissues = {1: "liver", 2: {"youngs_modulus": 2e4, "poisson_ratio": 0.45}}

    def body():
        return body_from_labels(image, spacing, tissues=tissues, fixed=[3]).model()

    shape = body().grid.shape
    tri = args.triangles or (10_000 if args.quick else 100_000)
    count = max(8, round((tri / 3.07) ** 0.5))  # trimesh's UV sphere of count [c, c] has about 3.07 c^2 triangles
    sphere = trimesh.creation.uv_sphere(radius=0.017, count=[count, count])
    grid = td.Grid((40, 40, 40), spacing=0.001)
    surf = EmbeddedSurface(sphere.vertices + 0.0195, sphere.faces, grid)
    x = grid.rest_positions(dtype=torch.float32)[0]
    x = x + 0.001 * torch.sin(x * 200.0)  # a deformed lattice

    def update():
        with torch.no_grad():
            surf.update(x)

    update()
    frames = 50 if not args.quick else 10

    def surfaces():
        label_surfaces(lab, image.affine, which=[1, 2], smooth=10, faces=20_000)

    return [
        ("labels -> body", f"{n}^3 -> {shape[0]}x{shape[1]}x{shape[2]}", body, repeats, 1),
        ("label surfaces", f"{n}^3, labels 1, 2", surfaces, max(1, repeats // 2), 1),
        ("surface update", f"{surf.num_faces:,} triangles", lambda: [update() for _ in range(frames)], repeats, frames),
    ]


def run(args) -> int:
    """Run ``torchdeform bench anatomy``."""
    torch.set_num_threads(args.threads or 2)
    threads = torch.get_num_threads()
    rows = []
    for name, size, fn, repeats, per in _cases(args):
        ms = _median_ms(fn, repeats) / per
        target = TARGETS_MS.get(name) if not args.quick else None
        row = dict(row=name, size=size, threads=threads, ms=ms, target_ms=target)
        row["met"] = None if target is None else ("met" if ms <= target else "missed")
        if args.contention:
            with busy_neighbour():
                busy = _median_ms(fn, repeats) / per
            row.update(busy_ms=busy, busy_over_idle=ms / busy)
        rows.append(row)
    extra = {"machine": machine_info("cpu"), "targets_ms": TARGETS_MS}
    emit("anatomy", args, rows, COLUMNS, extra=extra)
    if args.out:
        _plot(rows, args.out)
    return 0


def _plot(rows, out_dir) -> None:
    fig, ax = axes(figsize=(6.5, 3.8))
    y = np.arange(len(rows))
    ax.barh(y, [r["ms"] for r in rows], 0.35, label="idle")
    if any("busy_ms" in r for r in rows):
        ax.barh(y + 0.35, [r.get("busy_ms", 0.0) for r in rows], 0.35, label="busy process beside")
    for k, r in enumerate(rows):
        if r["target_ms"]:
            ax.plot([r["target_ms"]] * 2, [k - 0.3, k + 0.6], color="black", lw=1.2)
    ax.set_yticks(y + 0.17, [f"{r['row']}\n{r['size']}" for r in rows], fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel(f"ms (median; black: target), {rows[0]['threads']} threads")
    ax.set_title("Bodies from label volumes, embedded surfaces")
    ax.grid(True, which="both", axis="x", alpha=0.3)
    ax.legend(fontsize=8)
    save_plot(fig, out_dir, "anatomy.png")
