"""``torchdeform bench frame``: interactive frames per second against Punak's GPU pipeline.

**A frame** is what Punak's pipeline does per displayed image (REFERENCE §6.3: Verlet,
relaxation, collision, marching cubes): one time step of a 26-neighbour mass-spring body and the
extraction of its deformed surface, with per-vertex normals a renderer needs; with ``--volume``
also a volume render of the phantom deformed with the body (optional row data, not part of the
target).

**Body.** Punak's grid sizes (node counts) 16^3, 32^3, 40 x 60 x 20, 64^3 and 100^3, 1 cm
spacing, k = 100 N/m per spring, 1 g per node, the bottom face (``d-``) fixed, gravity along -D,
slightly perturbed from rest. Punak's integrator, :class:`~torchdeform.sim.integrators.DampedVerlet`
(``kd`` = :data:`KD`, no spring dashpots), at 0.9 times the Gershgorin bound of
:func:`~torchdeform.sim.stability.suggest_dt`.

**Step.** The compiled fast path (:func:`~torchdeform.sim.compiled.compiled_step`) on a packed
state, packed once before the timed loop; ``--no-compile`` (and ``--quick``) use the same code
eagerly. The first call's wall time is ``compile_s``; ``engine`` says ``eager`` when the
wrapper fell back.

**Surface** (:class:`~torchdeform.topology.surfaces.FrameSurface`). :func:`~torchdeform.topology.surfaces.surface_map` is built
once at rest (not timed); per frame the vertices are ``rest + W (x - X)`` (a sparse CSR product
over the surface nodes only, read straight from the packed state: nothing else is unpacked), then
the area-weighted face normals summed per vertex and normalised (compiled with the step: each
vertex gathers its incident faces' normals; eager: ``index_add_``). The same vertices as the slow
reference :func:`~torchdeform.topology.cut_surfaces`, which runs marching tetrahedra every call.
The normals' first call is ``surface_compile_s`` (2-3 s per shape).

**Rows.** Medians over ``--repeats`` runs of several frames each: ``step_ms``, ``surface_ms``
(``vertices_ms`` + ``normals_ms``) and ``volume_ms`` (``--volume``);
``fps = 1000 / (step_ms + surface_ms [+ volume_ms])`` and ``ratio = fps / punak_fps`` (Punak's
rates on a GeForce 8800 GTS: 90, 28, 21, 6.1 and 2.0 fps); ``surface_fps`` and ``surface_ratio``
leave the volume render out (the same as ``fps`` and ``ratio`` without ``--volume``). The
document's ``met`` says whether ``surface_ratio >= target_ratio`` (2) at every size that has a
Punak rate. ``cpu_ms`` is the process CPU time per frame (all threads): on a busy host, wall times
with several threads include waits for a descheduled thread, and ``cpu_ms`` shows it.

Example:
    torchdeform bench frame --quick
    torchdeform bench frame --threads 2 --json --out bench-out
    torchdeform bench frame --sizes 32,40x60x20 --volume
"""

from __future__ import annotations

import math
import statistics
import time

import torch

from ..errors import ConfigError
from ..options import integer
from ..outputs import axes, save_plot
from ..topology.surfaces import FrameSurface
from .common import add_common, device_sync, emit, machine_info, progress

__all__ = [
    "COLUMNS",
    "PUNAK",
    "KD",
    "TARGET_RATIO",
    "FrameSurface",
    "parse_sizes",
    "frame_body",
    "add_arguments",
    "run",
]

#: Punak's frame rates (REFERENCE §6.3, Fig. 5-2; GeForce 8800 GTS): grid shape -> fps
PUNAK = {(16, 16, 16): 90.0, (32, 32, 32): 28.0, (40, 60, 20): 21.0, (64, 64, 64): 6.1, (100, 100, 100): 2.0}
#: Verlet damping per step (Punak eq. 4-1)
KD = 0.01
TARGET_RATIO = 2.0
SPACING = 0.01
COLUMNS = [
    ("grid", "grid", None),
    ("nodes", "nodes", "{:,}"),
    ("vertices", "vertices", "{:,}"),
    ("faces", "faces", "{:,}"),
    ("step_ms", "step ms", "{:.2f}"),
    ("vertices_ms", "vert ms", "{:.2f}"),
    ("normals_ms", "norm ms", "{:.2f}"),
    ("surface_ms", "surface ms", "{:.2f}"),
    ("volume_ms", "volume ms", "{:.1f}"),
    ("cpu_ms", "cpu ms", "{:.1f}"),
    ("fps", "fps", "{:.1f}"),
    ("punak_fps", "Punak fps", "{:g}"),
    ("ratio", "x Punak", "{:.1f}"),
    ("engine", "engine", None),
    ("compile_s", "compile s", "{:.1f}"),
    ("threads", "thr", None),
]


def parse_sizes(text) -> list:
    """``--sizes``: comma-separated ``n`` (an ``n^3`` grid) or ``DxHxW`` entries -> list of shapes."""
    shapes = []
    for item in str(text).split(","):
        item = item.strip().lower()
        if not item:
            continue
        try:
            dims = [int(v) for v in item.split("x")]
        except ValueError:
            raise ConfigError("--sizes", "comma-separated n or DxHxW, e.g. 16,32,40x60x20", got=text) from None
        if len(dims) == 1:
            dims = dims * 3
        if len(dims) != 3 or min(dims) < 2:
            raise ConfigError("--sizes", "n or DxHxW with every count >= 2, e.g. 16,40x60x20", got=text)
        shapes.append(tuple(dims))
    if not shapes:
        raise ConfigError("--sizes", "at least one grid size", got=text)
    return shapes


def _name(shape) -> str:
    return f"{shape[0]}^3" if len(set(shape)) == 1 else "x".join(map(str, shape))


def frame_body(shape, *, dtype=torch.float32, device="cpu", seed: int = 0):
    """The bench's body: ``(model, state, dt)`` (module docstring, "Body"); ``state`` in the grid layout."""
    from ..sim.grid import Grid
    from ..sim.model import Model, State
    from ..sim.stability import suggest_dt

    grid = Grid(tuple(shape), spacing=SPACING, topology=26)
    model = Model(
        grid,
        stiffness=100.0,
        mass=1e-3,
        fixed=grid.face("bottom"),
        gravity=(-9.81, 0.0, 0.0),
        dtype=dtype,
        device=device,
    )
    dt = suggest_dt(model, integrator="verlet", safety=0.9, method="gershgorin")
    g = torch.Generator().manual_seed(seed)
    x = model.X + (1e-4 * torch.randn(model.X.shape, generator=g, dtype=torch.float64)).to(dtype=dtype, device=device)
    x = torch.where(grid.face("bottom").to(device), model.X, x)
    return model, State(x, torch.zeros_like(x), t=0.0), dt


def add_arguments(p) -> None:
    """The options of ``torchdeform bench frame``."""
    add_common(p)
    p.add_argument(
        "--sizes",
        type=parse_sizes,
        default=None,
        help="grids, n (n^3 nodes) or DxHxW, comma-separated (default Punak's 16,32,40x60x20,64,100; quick 16,32)",
    )
    p.add_argument(
        "--repeats",
        type=integer(lo=1),
        default=None,
        help="timed runs of --frames frames, median kept (default 5; quick 2)",
    )
    p.add_argument(
        "--frames", type=integer(lo=1), default=None, help="frames per timed run (default: about 0.3 s; quick 2)"
    )
    p.add_argument(
        "--volume",
        action="store_true",
        help="also render the phantom deformed with the body (volume_ms; not part of the target)",
    )
    p.add_argument(
        "--volume-size",
        type=integer(lo=8),
        default=128,
        help="--volume: phantom side in voxels = image side (default 128)",
    )
    p.add_argument(
        "--no-compile", action="store_true", help="eager step and normals (no torch.compile; --quick implies it)"
    )


def _volume_fn(model, packed, size, compiled, dtype, device):
    """``frame(x_packed)``: node offsets from the frame's positions, then a DVR image (``size^2``)."""
    from ..volume import node_offsets, preset, render
    from .volume import bench_volume

    vol, _ = bench_volume(size, dtype=dtype)
    vol, tf = vol.to(device), preset("ct-bone")
    shape = (size,) * 3

    def frame(x):
        xg = packed.unpack(x)
        off = node_offsets(xg, model.X, model.grid.spacing, shape)[0]
        return render(
            vol, tf=tf, mode="dvr", view="h", offsets=off, stop=1e-3, engine="compiled" if compiled else "eager"
        )

    return frame


def _frame_row(shape, *, repeats, frames, compiled, volume_size, dtype, device, target_s=0.3) -> dict:
    from ..sim.compiled import compiled_step
    from ..sim.integrators import DampedVerlet

    sync = device_sync(device)
    model, state, dt = frame_body(shape, dtype=dtype, device=device)
    with torch.no_grad():
        step = compiled_step(DampedVerlet(kd=KD), model, dt, enable=compiled)
        ps = step.packed.pack_state(state)  # packed once, outside the timing
        t0 = time.perf_counter()
        ps = step.step_packed(ps)  # compiles (once per shape)
        sync()
        first_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        surf = FrameSurface(model.grid, packed=step.packed, dtype=dtype, device=device, compile=compiled)
        setup_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        surf(ps.x)  # compiles the normals (once per shape)
        sync()
        surface_first_s = time.perf_counter() - t0
        render_ = None
        volume_compile_s = None
        if volume_size:
            render_ = _volume_fn(model, step.packed, volume_size, compiled, dtype, device)
            t0 = time.perf_counter()
            render_(ps.x)
            volume_compile_s = time.perf_counter() - t0 if compiled else None
        # warm-up frame, also sizes the runs
        t0 = time.perf_counter()
        ps = step.step_packed(ps)
        v, n = surf(ps.x)
        if render_ is not None:
            render_(ps.x)
        sync()
        warm = max(time.perf_counter() - t0, 1e-6)
        if frames is None:
            frames = int(min(50, max(2, math.ceil(target_s / warm))))
        step_t, vert_t, norm_t, vol_t, cpu_t = [], [], [], [], []
        for _ in range(repeats):
            ts = tv = tn = tr = 0.0
            c0 = time.process_time()
            for _ in range(frames):
                t0 = time.perf_counter()
                ps = step.step_packed(ps)
                sync()
                t1 = time.perf_counter()
                v = surf.vertices(ps.x)
                sync()
                t2 = time.perf_counter()
                n = surf.normals(v)
                sync()
                t3 = time.perf_counter()
                if render_ is not None:
                    render_(ps.x)
                    sync()
                t4 = time.perf_counter()
                ts, tv, tn, tr = ts + t1 - t0, tv + t2 - t1, tn + t3 - t2, tr + t4 - t3
            step_t.append(ts / frames)
            vert_t.append(tv / frames)
            norm_t.append(tn / frames)
            vol_t.append(tr / frames)
            cpu_t.append((time.process_time() - c0) / frames)
        if not bool(torch.isfinite(v).all() and torch.isfinite(n).all()):
            raise RuntimeError(f"bench frame {_name(shape)}: non-finite surface (the step diverged at dt = {dt:.3g} s)")
    med = lambda t: 1e3 * statistics.median(t)
    step_ms, vertices_ms, normals_ms = med(step_t), med(vert_t), med(norm_t)
    surface_ms = med([a + b for a, b in zip(vert_t, norm_t)])
    volume_ms = med(vol_t) if render_ is not None else None
    fps = 1e3 / (step_ms + surface_ms + (volume_ms or 0.0))
    surface_fps = 1e3 / (step_ms + surface_ms)  # the target's frame (no volume)
    punak = PUNAK.get(tuple(shape))
    engine = "compiled" if step.compiled else "eager"
    row = dict(
        grid=_name(shape),
        shape=list(shape),
        nodes=model.grid.num_nodes,
        springs=model.grid.num_springs,
        vertices=surf.num_vertices,
        faces=int(surf.faces.shape[0]),
        step_ms=step_ms,
        vertices_ms=vertices_ms,
        normals_ms=normals_ms,
        surface_ms=surface_ms,
        fps=fps,
        punak_fps=punak,
        ratio=None if punak is None else fps / punak,
        surface_fps=surface_fps,
        surface_ratio=None if punak is None else surface_fps / punak,
        engine=engine,
        cpu_ms=med(cpu_t),
        compile_s=first_s if compiled and step.compiled else None,
        first_step_s=first_s,
        surface_compile_s=surface_first_s if surf._compiled is not None else None,
        surface_setup_s=setup_s,
        threads=torch.get_num_threads(),
        dt=dt,
        kd=KD,
        frames=frames,
        repeats=repeats,
        dtype=str(dtype).replace("torch.", ""),
        device=str(device),
    )
    if render_ is not None:
        row.update(
            volume_ms=volume_ms, volume=f"{volume_size}^3", image=f"{volume_size}^2", volume_compile_s=volume_compile_s
        )
    if compiled and not step.compiled:
        row["compile_error"] = step.compile_error
    if surf.compile_error:
        row["surface_compile_error"] = surf.compile_error
    return row


def run(args) -> int:
    """Run the bench: one row per grid size; returns the exit status."""
    shapes = args.sizes or ([(16, 16, 16), (32, 32, 32)] if args.quick else list(PUNAK))
    repeats = args.repeats or (2 if args.quick else 5)
    frames = args.frames or (2 if args.quick else None)
    if repeats < 1 or (frames is not None and frames < 1):
        raise ConfigError("--repeats/--frames", "at least 1", got=(repeats, frames))
    if args.volume and args.volume_size < 8:
        raise ConfigError("--volume-size", "a volume side of at least 8 voxels", got=args.volume_size)
    compiled = not (args.no_compile or args.quick)
    dtype = getattr(torch, args.dtype)
    saved = torch.get_num_threads()
    if args.threads:
        torch.set_num_threads(args.threads)
    rows = []
    try:
        with progress(len(shapes), "bench frame") as bar:
            for shape in shapes:
                rows.append(
                    _frame_row(
                        shape,
                        repeats=repeats,
                        frames=frames,
                        compiled=compiled,
                        volume_size=args.volume_size if args.volume else None,
                        dtype=dtype,
                        device=args.device,
                    )
                )
                bar.update(1)
        threads = torch.get_num_threads()
    finally:
        torch.set_num_threads(saved)
    judged = [r for r in rows if r["surface_ratio"] is not None]
    extra = {
        "machine": dict(machine_info(args.device), threads=threads),
        "target_ratio": TARGET_RATIO,
        "met": bool(judged) and all(r["surface_ratio"] >= TARGET_RATIO for r in judged),
        "worst_ratio": min((r["surface_ratio"] for r in judged), default=None),
        "target": "step + surface frame rate >= target_ratio x Punak's at every size with a Punak rate "
        "(surface_ratio; the volume render of --volume is not part of it)",
        "punak": {_name(s): f for s, f in PUNAK.items()},
        "setup": (
            f"one frame = one DampedVerlet step (kd {KD}, 26 neighbours, 1 cm, k 100 N/m, 1 g/node, bottom "
            f"fixed, gravity) + surface vertices and normals"
            + (f" + DVR of a {args.volume_size}^3 phantom to {args.volume_size}^2" if args.volume else "")
            + f"; {threads} thread{'s' if threads != 1 else ''}, {args.dtype}, {args.device}; "
            f"Punak: GeForce 8800 GTS"
        ),
    }
    if args.out:
        _plot(rows, args.out, threads)
    if not args.json:
        engines = ", ".join(sorted({r["engine"] for r in rows}))
        print(f"frames per second ({engines} step, {threads} thread{'s' if threads != 1 else ''}); " + extra["setup"])
    emit("frame", args, rows, COLUMNS, extra=extra)
    if not args.json and judged:
        print(
            f"step + surface >= {TARGET_RATIO:g}x Punak at every size: {'yes' if extra['met'] else 'no'} "
            f"(worst {extra['worst_ratio']:.2f}x)"
        )
    return 0


def _plot(rows, out_dir, threads) -> None:
    fig, ax = axes(figsize=(6.5, 4.5))
    xs = list(range(len(rows)))
    what = f"{threads} CPU thread{'s' if threads != 1 else ''}"
    ax.plot(xs, [r["surface_fps"] for r in rows], marker="o", label=f"torchdeform, step + surface ({what})")
    if any(r.get("volume_ms") is not None for r in rows):
        ax.plot(xs, [r["fps"] for r in rows], marker="^", label=f"torchdeform, + volume render ({what})")
    pk = [(i, r["punak_fps"]) for i, r in enumerate(rows) if r["punak_fps"]]
    if pk:
        ax.plot(*zip(*pk), marker="s", ls="--", label="Punak, GeForce 8800 GTS")
        ax.plot(
            [i for i, _ in pk],
            [TARGET_RATIO * f for _, f in pk],
            ls=":",
            color="grey",
            label=f"{TARGET_RATIO:g}x Punak (target)",
        )
    ax.set_xticks(xs, [f"{r['grid']}\n{r['nodes']:,}" for r in rows], fontsize=8)
    ax.set_yscale("log")
    ax.set_xlabel("grid (nodes)")
    ax.set_ylabel("frames per second")
    ax.set_title("One step + deformed surface per frame, against Punak's GPU")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_plot(fig, out_dir, "frame.png")
