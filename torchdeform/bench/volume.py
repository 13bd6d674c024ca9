"""``torchdeform bench volume``: deform and render a volume, frames per second.

A phantom (:mod:`torchdeform.volume.phantoms`, generated at half size and upsampled) of ``--size``^3
voxels is deformed by smooth random node offsets (``--nodes``^3 nodes, up to ``--amplitude``
voxels) and rendered along axis H to a ``size x size`` image, one sample per voxel, in two ways:

``naive``        build the warped volume (:func:`~torchdeform.volume.warp`: dense offset texture +
                 ``grid_sample`` of every voxel), then composite its slices;
``grid_sample``  render through the displacement field (:func:`~torchdeform.volume.rendering.render` with
                 ``offsets``): slab by slab, the offsets at the slab from the node grid by separable
                 weights, one ``grid_sample`` per batch of slabs. The warped volume is never built;
``eager``        the fast path (``engine="eager"``): trilinear interpolation by hand (offsets from
                 the node grid, eight indexed loads from the flat volume), compositing per chunk of
                 slabs, chunks that can only read fully transparent values skipped (``dvr``);
``compiled``     the same code under ``torch.compile`` (one fused loop per chunk); the first call
                 compiles (``compile_s`` in the rows and the JSON ``extra``);
``native``       the C ray marcher (``engine="native"``, :mod:`torchdeform.volume.native_march`):
                 parallel rays, the same slab samples, empty-space leaping, per-ray early
                 termination (``dvr`` of a float32 volume on the CPU only: no row otherwise).

Modes ``mip`` and ``dvr`` (``ct-bone`` transfer function). Each row: median wall seconds per
frame over ``--repeats`` after a warm-up, ``fps`` = 1 / that, ``cpu_ms`` (process CPU time per
frame, all threads: on a loaded machine ``cpu_ms / threads`` estimates the quiet wall time) and
the largest difference from the naive image. No gradients. ``--paths`` picks the paths
(``--no-compile`` drops ``compiled``).

Example:
    torchdeform bench volume --quick
    torchdeform bench volume --json --threads 2
"""

from __future__ import annotations

import statistics
import time

import torch

from ..errors import ConfigError
from ..options import integer, number
from .common import add_common, device_sync, emit, machine_info, progress

__all__ = ["COLUMNS", "PATHS", "add_arguments", "bench_volume", "run"]

COLUMNS = [
    ("size", "volume", None),
    ("image", "image", None),
    ("mode", "mode", None),
    ("path", "path", None),
    ("threads", "thr", None),
    ("ms_per_frame", "ms/frame", "{:.0f}"),
    ("fps", "fps", "{:.2f}"),
    ("cpu_ms", "cpu ms", "{:.0f}"),
    ("speedup", "x naive", "{:.2f}"),
    ("max_abs_diff", "max|diff|", "{:.1e}"),
    ("compile_s", "compile s", "{:.0f}"),
]
PATHS = ("naive", "grid_sample", "eager", "compiled", "native")


def add_arguments(p) -> None:
    """The options of ``torchdeform bench volume``."""
    add_common(p)
    p.add_argument("--size", type=integer(lo=2), default=None, help="volume side in voxels (default 256; quick 64)")
    p.add_argument("--nodes", type=integer(lo=2), default=9, help="node grid side (default 9)")
    p.add_argument("--amplitude", type=number(lo=0), default=3.0, help="largest node offset in voxels (default 3)")
    p.add_argument(
        "--repeats", type=integer(lo=1), default=None, help="timed repeats, median kept (default 5; quick 2)"
    )
    p.add_argument("--modes", default="mip,dvr", help="render modes (default mip,dvr)")
    p.add_argument(
        "--paths", default=None, help="comma list of " + ", ".join(PATHS) + " (default all; quick: no compiled)"
    )
    p.add_argument("--no-compile", action="store_true", help="leave out the compiled path")


def bench_volume(size: int, *, nodes: int = 9, amplitude: float = 3.0, dtype=torch.float32, device="cpu"):
    """The bench's volume ``(size,)*3`` (HU) and node offsets ``(3, nodes, nodes, nodes)`` in voxels.

    The phantom is generated on the CPU at half the size (at most 128^3) and upsampled
    trilinearly on ``device``; both tensors are on ``device``.
    """
    import torch.nn.functional as F

    from ..volume import phantom

    half = max(8, min(size // 2, 128))
    vol = phantom(shape=(half,) * 3, dtype=dtype).to(device)
    vol = F.interpolate(vol[None, None], size=(size,) * 3, mode="trilinear", align_corners=True)[0, 0]
    g = torch.Generator().manual_seed(0)
    offsets = (torch.rand(3, nodes, nodes, nodes, generator=g, dtype=torch.float64) * 2 - 1) * amplitude
    return vol.contiguous(), offsets.to(device, dtype)


def _time(fn, repeats, sync=lambda: None):
    """``(median wall s, median process CPU s, first result)``; the first call is a warm-up.

    ``sync`` waits for the device (:func:`~.common.device_sync`) before each clock is read.
    """
    out = fn()
    sync()
    walls, cpus = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        sync()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus), out


def run(args) -> int:
    """Run the bench: one row per mode and path; returns the exit status."""
    from ..volume import preset, render, warp

    size = args.size or (64 if args.quick else 256)
    repeats = args.repeats or (2 if args.quick else 5)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if size < 8 or args.nodes < 2 or args.nodes > size or repeats < 1:
        raise ConfigError(
            "--size", "a volume side >= 8, 2 <= --nodes <= size, --repeats >= 1", got=(size, args.nodes, repeats)
        )
    for m in modes:
        if m not in ("mip", "dvr", "average"):
            raise ConfigError("--modes", "mip, dvr and/or average", got=args.modes)
    saved = torch.get_num_threads()
    if args.threads:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    paths = [
        q.strip()
        for q in (args.paths or ("naive,grid_sample,eager,native" if args.quick else ",".join(PATHS))).split(",")
        if q.strip()
    ]
    if args.no_compile:
        paths = [q for q in paths if q != "compiled"]
    for q in paths:
        if q not in PATHS:
            raise ConfigError("--paths", "a comma list of " + ", ".join(PATHS), got=args.paths)
    if "naive" not in paths:
        paths = ["naive"] + paths
    rows, compile_times = [], {}
    try:
        device = str(torch.device(args.device))
        if device.startswith("cuda") and not torch.cuda.is_available():
            raise ConfigError("--device", "cpu, or cuda on a machine with CUDA", got=args.device)
        sync = device_sync(device)
        vol, offsets = bench_volume(size, nodes=args.nodes, amplitude=args.amplitude, dtype=dtype, device=device)
        tf = preset("ct-bone")
        with torch.no_grad(), progress(len(paths) * len(modes), "bench volume") as bar:
            for mode in modes:
                t = tf if mode == "dvr" else None
                base = dict(
                    size=f"{size}^3",
                    image=f"{size}^2",
                    mode=mode,
                    nodes=args.nodes,
                    dtype=args.dtype,
                    threads=torch.get_num_threads(),
                    amplitude_vox=args.amplitude,
                )
                ref = naive_s = None
                for path in paths:
                    compile_s = None
                    if path == "naive":
                        fn = lambda t=t, mode=mode: render(
                            warp(vol, offsets, check=False), tf=t, mode=mode, view="h", stop=1e-3
                        )
                    else:
                        fn = lambda e=path, t=t, mode=mode: render(
                            vol, tf=t, mode=mode, view="h", offsets=offsets, stop=1e-3, engine=e
                        )
                    if path == "native":
                        try:
                            fn()  # loads the kernel; the renderer says when it does not apply
                        except ConfigError:  # (dvr of a float32 CPU volume only): no row
                            bar.update(1)
                            continue
                    if path == "compiled":
                        t0 = time.perf_counter()
                        fn()  # compiles (once per shape, view and mode)
                        sync()
                        compile_s = time.perf_counter() - t0
                        compile_times[mode] = compile_s
                    wall, cpu, img = _time(fn, repeats, sync)
                    bar.update(1)
                    if path == "naive":
                        ref, naive_s = img, wall
                    rows.append(
                        dict(
                            base,
                            path=path,
                            seconds=wall,
                            ms_per_frame=wall * 1e3,
                            fps=1 / wall,
                            cpu_ms=cpu * 1e3,
                            speedup=naive_s / wall,
                            max_abs_diff=float((img - ref).abs().max()),
                            compile_s=compile_s,
                        )
                    )
    finally:
        torch.set_num_threads(saved)
    extra = {
        "machine": machine_info(device),
        "compile_s": compile_times,
        "setup": (
            f"phantom {size}^3 (HU), {args.nodes}^3 node offsets up to {args.amplitude:g} voxels, axis view "
            f"H, one sample per voxel, image {size}x{size}; dvr: ct-bone, early termination at T < 1e-3"
        ),
    }
    if not args.json:
        print("deform + render, " + extra["setup"])
    emit("volume", args, rows, COLUMNS, extra=extra)
    return 0
