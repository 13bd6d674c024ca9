"""``torchdeform bench endoscope``: virtual-endoscopy frame rates against Radetzky's Table 3.1.

Radetzky's SGI Onyx2 (2 CPUs, OpenGL Volumizer, REFERENCE.md section 12) rendered a 256 x 256 x 128
CT of 2-byte voxels into a 700 x 600 window at: 15 fps for the whole volume (``overview``), 8 fps
for an endoscopic view without a volume of interest (``endoscope``), 10 fps with a VOI 64 voxels
deep (``endoscope_voi``), 8 fps and 3 fps for the overview and the endoscopic view of a deforming
volume (``overview_deforming``, ``endoscope_deforming``; his figures include the physics).

Here: the procedural CT phantom (:func:`~torchdeform.volume.phantom`) at 128 x 256 x 256 voxels
``(D, H, W)``, with its winding air-filled lumen (``lumen=True``: a bowel-like tube of radius 12.8
voxels, 128 voxels long, carved through the abdomen); an image of 600 x 700 pixels ``(h, w)``; samples every ``--step`` voxels (default 0.5: Nyquist), early ray termination at
``T < 1e-3``, empty-space leaping; every frame by the native kernel
(:mod:`torchdeform.volume.native_march`) with the headlight (ambient 0.2, diffuse 0.8):

=======================  =======================================================================
``overview``             an :class:`~torchdeform.volume.EndoscopeCamera` outside the volume
                         (``inside="allow"``, no mask, 40 degrees), 1.6 volume diagonals from the
                         centre, orbiting 1 degree per frame; ``ct-bone`` transfer function
``endoscope``            the camera inside the lumen on its centre line looking along it (100
                         degrees, round image, ``far = inf``: the whole depth), advancing half a
                         voxel per frame; a transfer function with the air clear and the wall
                         opaque (the ``ct-lumen`` preset)
``endoscope_voi``        the same with ``far = 64`` voxels (Radetzky's VOI)
``*_deforming``          the same views through node offsets ``(3, 9, 17, 17)`` that change every
                         frame (a travelling wave of ``--amplitude`` voxels, default 3); each
                         frame makes its offsets, and the kernel pulls every sample back through
                         them (``X = p - u(p)``)
=======================  =======================================================================

A frame is what an interactive viewer does per frame: the camera's pose, its rays (the
camera-frame ray table of :meth:`~torchdeform.volume.EndoscopeCamera.rays`, made once, turned
into the new pose by a 3 x 3 rotation), the offsets (deforming rows), and the kernel (which clips
the rays to the box and near/far). ``fps`` is 1 / the median wall time over ``--frames`` frames after one
warm-up frame; ``ratio`` = fps / Radetzky's; ``cpu_ms`` the process CPU time per frame (all
threads: on a loaded machine ``cpu_ms / threads`` estimates the quiet wall time). ``api_fps`` times the same frame through
:func:`~torchdeform.volume.render_endoscope` (``engine="auto"``), whose camera makes its rays
from scratch every call (skipped with ``--no-api``).

Example:
    torchdeform bench endoscope --quick
    torchdeform bench endoscope --json --threads 2 --out bench-out
"""

from __future__ import annotations

import math
import statistics
import time

import torch

from ..errors import ConfigError
from ..options import integer, number
from ..outputs import axes, save_plot
from ..volume.phantoms import lumen_centre
from .common import add_common, emit, machine_info, progress

__all__ = ["COLUMNS", "RADETZKY_FPS", "VIEWS", "add_arguments", "run"]

#: Radetzky's Table 3.1 (frames per second on the SGI Onyx2 IR, 2 CPUs)
RADETZKY_FPS = {
    "overview": 15.0,
    "endoscope": 8.0,
    "endoscope_voi": 10.0,
    "overview_deforming": 8.0,
    "endoscope_deforming": 3.0,
}
VIEWS = tuple(RADETZKY_FPS)
COLUMNS = [
    ("view", "view", None),
    ("volume", "volume", None),
    ("image", "image", None),
    ("threads", "thr", None),
    ("ms_per_frame", "ms/frame", "{:.1f}"),
    ("cpu_ms", "cpu ms", "{:.0f}"),
    ("fps", "fps", "{:.1f}"),
    ("radetzky_fps", "Radetzky fps", "{:.0f}"),
    ("ratio", "x Radetzky", "{:.2f}"),
    ("api_fps", "render_endoscope fps", "{:.1f}"),
    ("coverage", "alpha>0.5", "{:.2f}"),
]
FULL_VOLUME, FULL_IMAGE, FULL_NODES = (128, 256, 256), (600, 700), (9, 17, 17)
QUICK_VOLUME, QUICK_IMAGE, QUICK_NODES = (32, 64, 64), (120, 140), (5, 9, 9)
VOI_DEPTH = 64.0


def add_arguments(p) -> None:
    """The options of ``torchdeform bench endoscope``."""
    add_common(p)
    p.add_argument(
        "--frames", type=integer(lo=1), default=None, help="timed frames per view, median kept (default 9; quick 3)"
    )
    p.add_argument("--step", type=number(lo=0, lo_open=True), default=0.5, help="sample spacing in voxels (0.5)")
    p.add_argument(
        "--amplitude", type=number(lo=0), default=3.0, help="largest node offset of the deforming rows (voxels, 3)"
    )
    p.add_argument("--views", default=None, help="comma list of " + ", ".join(VIEWS) + " (default all)")
    p.add_argument("--no-api", action="store_true", help="leave out the render_endoscope timing (api_fps)")
    p.add_argument(
        "--overview-tf",
        choices=("ct-bone", "ct-soft", "ct-liver", "ct-lumen"),
        default="ct-bone",
        help="the overview's transfer function (default ct-bone; ct-soft: semi-transparent tissue, longer rays)",
    )


# ------------------------------------------------------------------ the scene
def _tangent(s: float, shape) -> tuple:
    a, b = lumen_centre(s - 1e-3, shape), lumen_centre(s + 1e-3, shape)
    return tuple(y - x for x, y in zip(a, b))


def _offsets(frame: int, nodes, amplitude: float) -> torch.Tensor:
    """Node offsets ``(3, *nodes)`` of frame ``frame``: a smooth travelling wave, at most ``amplitude`` voxels."""
    axes_ = [torch.linspace(0, 1, n) for n in nodes]
    z, y, x = torch.meshgrid(*axes_, indexing="ij")
    ph = 0.35 * frame
    return amplitude * torch.stack(
        [
            torch.sin(2 * math.pi * (x + 0.5 * y) + ph),
            torch.sin(2 * math.pi * (z + 0.7 * x) + 1.3 * ph + 1.0),
            torch.sin(2 * math.pi * (y - 0.6 * z) + 0.8 * ph + 2.0),
        ]
    )


class _View:
    """A view of the bench: its camera per frame, rays from a camera-frame table, and the renderer's arguments."""

    def __init__(self, name: str, shape, image, step: float, amplitude: float, nodes, overview_tf: str = "ct-bone"):
        from ..volume import EndoscopeCamera, preset

        self.name, self.shape, self.image, self.step = name, shape, image, step
        self.deforming = name.endswith("_deforming")
        self.overview = name.startswith("overview")
        self.far = VOI_DEPTH if name == "endoscope_voi" else math.inf
        self.tf = preset(overview_tf) if self.overview else preset("ct-lumen")
        self.amplitude, self.nodes = amplitude, nodes
        self.kw = (
            dict(fov=40.0, size=image, mask=False, inside="allow")
            if self.overview
            else dict(fov=100.0, size=image, mask=True, far=self.far)
        )
        self.EndoscopeCamera = EndoscopeCamera

    def pose(self, frame: int):
        if self.overview:
            D, H, W = self.shape
            centre = torch.tensor([(n - 1) / 2 for n in self.shape], dtype=torch.float64)
            diag = math.sqrt(D * D + H * H + W * W)
            az, el = math.radians(30.0 + frame), math.radians(20.0)
            fwd = torch.tensor([-math.sin(el), math.cos(el) * math.cos(az), math.cos(el) * math.sin(az)])
            return (centre - fwd * 1.6 * diag).tolist(), fwd.tolist()
        s = 0.12 + 0.004 * frame * (FULL_VOLUME[2] / self.shape[2])  # half a voxel per frame
        return list(lumen_centre(s, self.shape)), list(_tangent(s, self.shape))

    def camera(self, frame: int):
        from ..volume import EndoscopeCamera

        pos, fwd = self.pose(frame)
        return EndoscopeCamera(position=pos, direction=fwd, up=(1.0, 0.0, 0.0), **self.kw)

    def frame(self, vol, frame: int):
        """One frame by the kernel: ``(image (1, 4, h, w), offsets or None)``."""
        from ..volume import native_march

        cam = self.camera(frame)
        eye, dirs, valid = cam.rays(self.shape)  # the image's camera-frame rays, rotated to the pose
        u = _offsets(frame, self.nodes, self.amplitude) if self.deforming else None
        lo, hi = self.tf.range()
        img, _ = native_march.render(
            vol, self.table, lo, hi, eye, dirs, valid=valid, near=cam.near, far=cam.far, step=self.step, offsets=u
        )
        return img, u

    def api_frame(self, vol, frame: int):
        """The same frame through :func:`~torchdeform.volume.render_endoscope` (``engine="auto"``)."""
        from ..volume import render_endoscope

        u = _offsets(frame, self.nodes, self.amplitude) if self.deforming else None
        with torch.no_grad():
            return render_endoscope(vol, self.camera(frame), tf=self.tf, offsets=u, step=self.step, engine="auto")

    @property
    def table(self):
        if not hasattr(self, "_table"):
            self._table = self.tf.table()
        return self._table


def _median_time(fn, frames: int) -> tuple:
    """``(median wall s, median process CPU s)`` per frame over ``frames`` frames after a warm-up frame."""
    fn(0)  # warm-up: builds or loads the kernel, the volume's copy and its leap distances
    walls, cpus = [], []
    for k in range(1, frames + 1):
        t0, c0 = time.perf_counter(), time.process_time()
        fn(k)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus)


def run(args) -> int:
    """Run the bench: one row per view; returns the exit status."""
    from ..volume import native_march

    why = native_march.unavailable()
    if why:
        raise ConfigError("bench endoscope", "a C compiler for the native ray marcher", got=why, show_got=True)
    if args.device != "cpu" or args.dtype != "float32":
        raise ConfigError("--device/--dtype", "cpu and float32 (the native kernel)", got=(args.device, args.dtype))
    views = [v.strip() for v in (args.views or ",".join(VIEWS)).split(",") if v.strip()]
    for v in views:
        if v not in VIEWS:
            raise ConfigError("--views", "a comma list of " + ", ".join(VIEWS), got=args.views)
    shape = QUICK_VOLUME if args.quick else FULL_VOLUME
    image = QUICK_IMAGE if args.quick else FULL_IMAGE
    nodes = QUICK_NODES if args.quick else FULL_NODES
    frames = args.frames or (3 if args.quick else 9)
    amplitude = args.amplitude * (shape[2] / FULL_VOLUME[2])
    saved = torch.get_num_threads()
    if args.threads:
        torch.set_num_threads(args.threads)
    rows = []
    try:
        from ..volume import phantom

        t_setup = time.perf_counter()
        vol = phantom(shape=shape, lumen=True)
        setup_s = time.perf_counter() - t_setup
        with torch.no_grad(), progress(len(views), "bench endoscope") as bar:
            for name in views:
                view = _View(name, shape, image, args.step, amplitude, nodes, args.overview_tf)
                last = {}

                def fn(k, view=view, last=last):
                    last["img"] = view.frame(vol, k)[0]

                wall, cpu = _median_time(fn, frames)
                api = None
                if not args.no_api:
                    api = _median_time(lambda k, view=view: view.api_frame(vol, k), max(1, min(frames, 3)))[0]
                img = last["img"]
                valid = view.camera(0).rays(shape)[2]
                rows.append(
                    dict(
                        view=name,
                        fps=1.0 / wall,
                        radetzky_fps=RADETZKY_FPS[name],
                        ratio=(1.0 / wall) / RADETZKY_FPS[name],
                        ms_per_frame=wall * 1e3,
                        cpu_ms=cpu * 1e3,
                        api_fps=None if api is None else 1.0 / api,
                        coverage=float((img[0, 3][valid] > 0.5).float().mean()),
                        volume="x".join(str(n) for n in shape),
                        image=f"{image[1]}x{image[0]}",
                        far=None if math.isinf(view.far) else view.far,
                        nodes=list(nodes) if view.deforming else None,
                        step=args.step,
                        frames=frames,
                        threads=torch.get_num_threads(),
                        quick=bool(args.quick),
                    )
                )
                bar.update(1)
    finally:
        torch.set_num_threads(saved)
    extra = {
        "machine": machine_info("cpu"),
        "quick": bool(args.quick),
        "setup_s": setup_s,
        "setup": (
            f"phantom {'x'.join(map(str, shape))} (D, H, W) with an air lumen, image {image[1]}x{image[0]} (w x h), "
            f"step {args.step:g} voxel, early termination at T < 1e-3, empty-space leaping, headlight; "
            f"overview {args.overview_tf}, endoscope ct-lumen; deforming: {'x'.join(map(str, nodes))} nodes, "
            f"{amplitude:g} voxels, new every frame"
        ),
        "radetzky": "SGI Onyx2 IR, 2 CPUs, 256x256x128 voxels, 700x600 window (Table 3.1)",
        "met": all(r["ratio"] >= 1.0 for r in rows) if not args.quick else None,
    }
    if args.out:
        _plot(rows, args.out)
    if not args.json:
        print("virtual endoscopy, " + extra["setup"])
    emit("endoscope", args, rows, COLUMNS, extra=extra)
    return 0


def _plot(rows, out_dir) -> None:
    fig, ax = axes(figsize=(7.5, 4.2))
    names = [r["view"] for r in rows]
    x = list(range(len(rows)))
    ax.bar([i - 0.2 for i in x], [r["fps"] for r in rows], width=0.4, label="torchdeform (native kernel)")
    ax.bar([i + 0.2 for i in x], [r["radetzky_fps"] for r in rows], width=0.4, label="Radetzky, Onyx2 (Table 3.1)")
    ax.set_xticks(x)
    ax.set_xticklabels([n.replace("_", "\n") for n in names], fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("frames per second")
    threads = rows[0]["threads"] if rows else "?"
    size = f"{rows[0]['volume']} voxels, {rows[0]['image']} image" if rows else ""
    ax.set_title(f"Virtual endoscopy: {size}, {threads} thread(s)", fontsize=9)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_plot(fig, out_dir, "endoscope.png")
