"""``torchdeform bench texture``: node colouring and triangle interiors against Chen & He's GPU times.

**Meshes.** Four closed meshes with the vertex and face counts of Chen & He's liver models A-D
(REFERENCE §7.2): the convex hull of ``V`` random points on an ellipsoid (semi-axes 1 : 0.8 :
0.6) is a closed triangulated surface with exactly ``V`` vertices and ``2V - 4`` faces (seeded),
which gives A-C exactly (1,323 / 1,537 / 2,687 vertices; 2,642 / 3,070 / 5,370 faces). Model D's
14,663 vertices and 18,676 faces cannot both hold for a closed surface (``F = 2V - 4``); its
faces are kept (9,340 vertices, 18,676 faces) and the row says so.

**Scale.** Each mesh fills the texture box Chen & He's launch grid implies, 4 x 4 x 3 blocks of
64 voxels (256 x 256 x 192 voxels: the ellipsoid's axes span 250, 200 and 150 voxels), textured
by a 128^3 procedural liver exemplar in 64^3 blocks: triangles of a few voxels to a few dozen.

**Timings** (median of ``--repeats``): ``node_ms`` colours every vertex (Chen & He's node
colouring); ``triangle_ms`` samples every triangle's interior at about one sample per voxel and
colours the samples (their triangle-interior step; ``samples`` counts them). Speedups are against
Chen & He's GPU times (GeForce GT 540M, Table 2 and 3: nodes 0.236-0.302 s, triangles
1.33-2.687 s). A last row, ``cut face``, times texturing the surfaces a fresh cut opens: a
16^3-node block cut through its middle, the two new faces' triangles sampled and coloured (target
< 8 ms, Dong et al.'s lazy synthesis for new cut surfaces).

**Seams** (a second table; ``seams`` in the JSON): the 128^3 exemplar in 64^3 blocks over a box
of ``--seam-blocks`` blocks (default 2 x 2 x 2, i.e. 128^3 voxels with seams normal to every
axis; ``4,4,3`` is Chen & He's whole box), materialised, then blended by the 3-D Poisson blend and
by Chen & He's per-slice 2-D blend (slices normal to D): the seam measure
(:func:`~torchdeform.texture.seams.seam_jump`, the mean gradient jump across block faces over the
exemplar's mean gradient), its reduction, the Wasserstein-1 distance of the colour histograms to
the exemplar's (colour units), CG iterations and seconds. The exemplar's own value (its faces
placed at the same planes) is the floor. With ``--out``, ``texture_seams.png`` shows a slice of
each.

It runs on 2 CPU threads unless ``--threads`` says otherwise (its target is stated for 2 cores).

Example:
    torchdeform bench texture --quick
    torchdeform bench texture --json --out bench-out
    torchdeform bench texture --seam-blocks 4,4,3
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch

from ..options import integer
from ..outputs import axes, save_plot
from .common import add_common, emit, format_table, machine_info, progress

__all__ = ["COLUMNS", "add_arguments", "run", "MODELS", "hull_mesh"]

#: Chen & He's models: (name, vertices, faces, node GPU s, triangle GPU s) (REFERENCE §7.2)
MODELS = [
    ("A", 1323, 2642, 0.236, 1.33),
    ("B", 1537, 3070, 0.254, 1.362),
    ("C", 2687, 5370, 0.285, 1.425),
    ("D", 14663, 18676, 0.302, 2.687),
]
COLUMNS = [
    ("model", "model", None),
    ("vertices", "vertices", "{:,}"),
    ("faces", "faces", "{:,}"),
    ("samples", "samples", "{:,}"),
    ("node_ms", "node ms", "{:.2f}"),
    ("triangle_ms", "triangle ms", "{:.1f}"),
    ("speedup_nodes", "x nodes", "{:.0f}"),
    ("speedup_triangles", "x triangles", "{:.0f}"),
    ("threads", "threads", None),
]
BOX = (256, 256, 192)  # texture voxels: Chen & He's 4 x 4 x 3 blocks of 64
SEAM_COLUMNS = [
    ("method", "seams", None),
    ("seam_jump", "seam measure", "{:.2f}"),
    ("reduction", "reduction", "{:.1f}x"),
    ("histogram_w1", "histogram W1", "{:.4f}"),
    ("iterations", "CG iterations", None),
    ("seconds", "seconds", "{:.1f}"),
]


def add_arguments(p) -> None:
    """The options of ``torchdeform bench texture``."""
    add_common(p)
    p.add_argument("--repeats", type=integer(lo=1), default=None, help="timing repeats (default 7; quick 3)")
    p.add_argument(
        "--seam-blocks",
        default="2,2,2",
        help="blocks of 64 per axis (D,H,W) of the seam test box (default 2,2,2; Chen & He's box is 4,4,3)",
    )


def hull_mesh(vertices: int, *, seed: int = 0):
    """A closed mesh with exactly ``vertices`` vertices and ``2 vertices - 4`` faces (see the module docstring).

    Returns ``(V (n, 3) float64 in texture voxels, F (2n - 4, 3) int64)``.

    Examples:
        >>> v, f = hull_mesh(100)
        >>> v.shape, f.shape
        ((100, 3), (196, 3))
    """
    from scipy.spatial import ConvexHull

    rng = np.random.default_rng(seed)
    p = rng.normal(size=(vertices, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    p = p * np.array([125.0, 100.0, 75.0]) + np.array(BOX) / 2
    hull = ConvexHull(p)
    faces = hull.simplices.astype(np.int64)
    # outward winding (the hull's facets are not oriented)
    normals = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    flip = (normals * (p[faces].mean(1) - p.mean(0))).sum(1) < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return p, faces


def _median_ms(fn, repeats):
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def _rows(repeats):
    from ..texture import SolidTexture, liver_exemplar, sample_triangles

    tex = SolidTexture(liver_exemplar(size=128, seed=0), block=64, extent=BOX, seed=0)
    rows = []
    for name, nv, nf, gpu_nodes, gpu_triangles in MODELS:
        v_count = (nf + 4) // 2  # closed: F = 2V - 4
        v, f = hull_mesh(v_count, seed=ord(name))
        X = torch.from_numpy(v).float()
        node_ms = _median_ms(lambda X=X: tex.colour(X), repeats)
        count = []
        triangle_ms = _median_ms(lambda v=v, f=f, count=count: count.append(sample_triangles(v, f, tex).count), repeats)
        rows.append(
            dict(
                model=name,
                vertices=v_count,
                faces=len(f),
                samples=count[-1],
                node_ms=node_ms,
                triangle_ms=triangle_ms,
                speedup_nodes=gpu_nodes * 1e3 / node_ms,
                speedup_triangles=gpu_triangles * 1e3 / triangle_ms,
                gpu_node_s=gpu_nodes,
                gpu_triangle_s=gpu_triangles,
                paper_vertices=nv,
                threads=torch.get_num_threads(),
                note=None
                if v_count == nv
                else f"paper: {nv} vertices, impossible with {nf} faces on a closed surface (F = 2V - 4); faces kept",
            )
        )
    return rows, tex


def _cut_face_row(tex, repeats):
    """Texture the two faces a fresh full cut opens in a 16^3 block (their triangles' interiors)."""
    import torchdeform as td

    from ..texture import SolidTexture, sample_triangles
    from ..topology import Blade, cut, cut_surfaces

    n, h = 16, 0.0025
    grid = td.Grid((n, n, n), spacing=h, topology=26)
    model = td.Model(grid, stiffness=10.0, mass=1e-3, dtype=torch.float64)
    cut(model, model.X, Blade(((n / 2 - 0.5) * h, -h, -h), (0, (n + 1) * h, 0), (0, 0, (n + 1) * h)))
    side = (model.X[0, 0] > (n / 2 - 0.5) * h).long()
    pieces = cut_surfaces(grid, model.X, side)
    plane = (n / 2 - 0.5) * h
    faces, rest = [], []
    for p in pieces:  # the triangles on the cut (within half a cell of it)
        on = np.abs(p.rest[p.faces].mean(1)[:, 0] - plane) < 0.5 * h
        faces.append(p.faces[on] + sum(len(r) for r in rest))
        rest.append(p.rest)
    f, r = np.concatenate(faces), np.concatenate(rest)  # material coordinates (m)
    fine = SolidTexture(tex.exemplar, block=64, extent=(96, 96, 96), seed=1, voxel=0.0005)  # 0.5 mm voxels
    count = []
    ms = _median_ms(lambda: count.append(sample_triangles(r, f, fine).count), repeats)
    return dict(
        model="cut face",
        vertices=len(r),
        faces=len(f),
        samples=count[-1],
        node_ms=None,
        triangle_ms=ms,
        speedup_nodes=None,
        speedup_triangles=None,
        threads=torch.get_num_threads(),
        target_ms=8.0,
        note="a full cut through a 16^3 block (4 cm, 0.5 mm texture voxels): both new faces",
    )


def _seam_rows(blocks, ex):
    """Seam measure and histogram distance of the tiled texture, its 3-D and per-slice blends of exemplar ``ex``."""
    from ..texture import SolidTexture
    from ..texture.seams import histogram_distance, seam_jump

    extent = tuple(64 * n for n in blocks)
    rows, slices = [], {}
    for method, name in (("none", "tiled"), ("3d", "3-D Poisson"), ("slices", "per-slice 2-D (D)")):
        tex = SolidTexture(ex, block=64, extent=extent, seed=0)
        r = tex.blend(method=method)  # "none": the tiled texture, after = before
        rows.append(
            dict(
                method=name,
                seam_jump=r["seam_after"],
                reduction=r["seam_before"] / r["seam_after"],
                histogram_w1=r["histogram_after"],
                iterations=r["iterations"] if method != "none" else None,
                seconds=r["seconds"] if method != "none" else None,
            )
        )
        slices[name] = tex.materialise()[:, :, extent[1] // 2 + 7].permute(1, 2, 0)
    floor = seam_jump(ex, 64, reference=ex)
    rows.append(
        dict(
            method="exemplar (floor)",
            seam_jump=floor,
            reduction=rows[0]["seam_jump"] / floor,
            histogram_w1=histogram_distance(ex, ex),
            iterations=None,
            seconds=None,
        )
    )
    for r in rows:
        r.update(box=list(extent), block=64, exemplar=128, threads=torch.get_num_threads())
    return rows, slices


def run(args) -> int:
    """Run the bench; returns the exit status."""
    from ..errors import ConfigError

    torch.set_num_threads(args.threads or 2)
    repeats = args.repeats or (3 if args.quick else 7)
    try:
        blocks = tuple(int(n) for n in args.seam_blocks.split(","))
        assert len(blocks) == 3 and min(blocks) >= 1 and max(blocks) >= 2
    except (ValueError, AssertionError):
        raise ConfigError(
            "--seam-blocks", "three block counts D,H,W, at least one of them >= 2", got=args.seam_blocks
        ) from None
    bar = progress(3, "bench texture")
    rows, tex = _rows(repeats)
    bar.update(1)
    rows.append(_cut_face_row(tex, repeats))
    bar.update(1)
    seams, slices = _seam_rows(blocks, tex.exemplar)  # the rows' 128^3 exemplar
    bar.update(1)
    bar.close()
    models = [r for r in rows if r["model"] != "cut face"]
    extra = {
        "machine": machine_info(args.device),
        "target_speedup": 30.0,
        "met": {
            "nodes": all(r["speedup_nodes"] >= 30 for r in models),
            "triangles": all(r["speedup_triangles"] >= 30 for r in models),
            "cut_face": rows[-1]["triangle_ms"] < 8.0,
            "seams_3d_5x": seams[1]["reduction"] >= 5.0,
        },
        "seams": seams,
    }
    if args.out:
        _plot(models, args.out)
        _plot_seams(seams, slices, args.out)
    emit("texture", args, rows, COLUMNS, extra=extra)
    if not args.json:
        print()
        print(format_table(seams, SEAM_COLUMNS))
    return 0


def _plot_seams(rows, slices, out_dir) -> None:
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 3, figsize=(10.5, 3.9))
    jump = {r["method"]: r["seam_jump"] for r in rows}
    for ax, name in zip(axs, ("tiled", "3-D Poisson", "per-slice 2-D (D)")):
        ax.imshow(slices[name].clamp(0, 1).numpy(), origin="lower")
        ax.set_title(f"{name}: seam measure {jump[name]:.2f}", fontsize=9)
        ax.set_xlabel("W (voxels)")
        ax.set_ylabel("D (voxels)")
    fig.suptitle("Block seams of a 64^3-block solid texture (slice normal to H)", fontsize=10)
    save_plot(fig, out_dir, "texture_seams.png")


def _plot(rows, out_dir) -> None:
    fig, ax = axes(figsize=(6.5, 4.2))
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["speedup_nodes"] for r in rows], 0.4, label="node colouring")
    ax.bar(x + 0.2, [r["speedup_triangles"] for r in rows], 0.4, label="triangle interiors")
    ax.axhline(30, color="grey", lw=0.8)
    ax.set_xticks(x, [f"{r['model']} ({r['faces']:,} faces)" for r in rows])
    ax.set_yscale("log")
    ax.set_ylabel("speedup over Chen & He's GPU times")
    ax.set_title("Solid texture on Chen & He's model sizes")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_plot(fig, out_dir, "texture.png")
