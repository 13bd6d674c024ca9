"""``torchdeform bench viewer``: frames per second of the browser viewer's page, as a user sees it.

**Set-up.** A viewer server (:class:`~torchdeform.view.server.Viewer`) runs an ``n^3`` cube of soft
tissue (:func:`viewer_cube`: 2 mm spacing, 26 neighbours, k = 5 N/m, dashpots 1e-4 N s/m,
1000 kg/m^3, bottom fixed, gravity along -D, global drag 20/s, symplectic Euler at 0.1 ms)
with ``--threads`` simulation threads (default: all cores but one, as ``torchdeform view``
does: the browser needs the other to draw). Debian's headless chromium
(:mod:`torchdeform.view.browser`; WebGL in software, SwiftShader, without a GPU) opens its page
on the same machine.

**Rows.** After ``--settle`` seconds (the page adapts its drawing resolution), the medians over
``--windows`` windows of ``--seconds`` each: ``fps`` (frames the page drew per second, its own
count), ``received`` (frames it received per second), ``sim_hz`` (simulation steps per second),
``resolution`` (the drawing resolution the page settled at, a fraction of the canvas). The
document's ``met`` says whether the page drew and received ``>= TARGET_FPS`` frames per second at
every size of at least :data:`TARGET_SIZE`^3 nodes. ``--busy`` runs the sizes again with a busy
process beside them (``busy`` column).

Needs ``apt-get install chromium chromium-driver`` and ``pip install selenium websockets``; a
missing piece is one line and exit status 2.

Example:
    torchdeform bench viewer --quick
    torchdeform bench viewer --sizes 16,32 --busy --json --out bench-out
"""

from __future__ import annotations

import contextlib
import tempfile

import torch

from ..errors import ConfigError
from ..options import integer, number
from ..outputs import axes, save_plot
from .common import add_common, busy_neighbour, emit, int_list, machine_info, progress

__all__ = ["COLUMNS", "TARGET_FPS", "TARGET_SIZE", "viewer_cube", "add_arguments", "run"]

#: the page's frame-rate target (frames drawn and received per second) ...
TARGET_FPS = 30.0
#: ... for bodies of this many nodes per side and more
TARGET_SIZE = 32
COLUMNS = [
    ("grid", "grid", None),
    ("vertices", "vertices", "{:,}"),
    ("busy", "busy", None),
    ("fps", "page fps", "{:.1f}"),
    ("received", "received/s", "{:.1f}"),
    ("resolution", "resolution", "{:.0%}"),
    ("sim_hz", "sim steps/s", "{:.0f}"),
    ("threads", "sim thr", None),
    ("build_s", "build s", "{:.1f}"),
]


def viewer_cube(n: int):
    """The bench's scene: an ``n^3`` cube of soft tissue (module docstring, "Set-up")."""
    from ..scene.mass_spring import Scene
    from ..sim.grid import Grid
    from ..sim.integrators import SymplecticEuler

    grid = Grid((n, n, n), spacing=0.002, topology=26)
    model_args = dict(
        stiffness=5.0, damping=1e-4, density=1000.0, fixed=grid.face("bottom"), decay=20.0, gravity=(-9.81, 0.0, 0.0)
    )
    return Scene(grid, model_args, integrator=SymplecticEuler(), dt=1e-4, steps=100, name=f"cube{n}")


def add_arguments(p) -> None:
    """The options of ``torchdeform bench viewer``."""
    add_common(p)
    p.add_argument(
        "--sizes",
        type=int_list("--sizes"),
        default=None,
        help="cube sizes n (n^3 nodes), comma-separated (default 16,32; quick 16)",
    )
    p.add_argument(
        "--windows", type=integer(lo=1), default=None, help="measuring windows, median kept (default 3; quick 1)"
    )
    p.add_argument("--seconds", type=number(lo=0, lo_open=True), default=2.0, help="length of a window (default 2 s)")
    p.add_argument(
        "--settle", type=number(lo=0), default=None, help="seconds before the first window (default 3; quick 1)"
    )
    p.add_argument("--busy", action="store_true", help="also measure with a busy process beside the viewer")


def _row(n: int, driver, *, windows, seconds, settle, busy) -> dict:
    import time

    from ..view import browser
    from ..view.server import Viewer
    from ..view.session import ViewerSession

    t = time.perf_counter()
    viewer = Viewer(ViewerSession(viewer_cube(n))).start()
    try:
        build = time.perf_counter() - t
        browser.open_page(driver, viewer.url)
        rates = browser.measured(driver, windows=windows, seconds=seconds, settle=settle)
        vertices = int(browser.js(driver, "window.viewerStats.vertices"))
    finally:
        viewer.stop()
    return {
        "grid": f"{n}^3",
        "n": n,
        "vertices": vertices,
        "busy": busy,
        **rates,
        "threads": torch.get_num_threads(),
        "build_s": build,
        "frames_posted": viewer.frames,
    }


def run(args) -> int:
    """Run the bench: one row per size (and per busy setting); returns the exit status."""
    from ..view import browser
    from ..view.commands import default_threads

    why = browser.missing()
    if why is not None:
        raise ConfigError("bench viewer", why, got="missing")
    try:
        import websockets  # noqa: F401
    except ImportError:
        raise ConfigError("bench viewer", "websockets: pip install websockets", got="missing") from None
    sizes = args.sizes or ([16] if args.quick else [16, 32])
    windows = args.windows or (1 if args.quick else 3)
    settle = args.settle if args.settle is not None else (1.0 if args.quick else 3.0)
    if min(sizes) < 2 or windows < 1 or not args.seconds > 0 or settle < 0:
        raise ConfigError(
            "--sizes/--windows/--seconds/--settle",
            "sizes >= 2, windows >= 1, seconds > 0, settle >= 0",
            got=(sizes, windows, args.seconds, settle),
        )
    if args.device != "cpu" or args.dtype != "float32":
        raise ConfigError(
            "--device/--dtype", "cpu and float32 (the viewer's simulation)", got=(args.device, args.dtype)
        )
    saved = torch.get_num_threads()
    torch.set_num_threads(args.threads or default_threads())
    rows = []
    cases = [(n, busy) for busy in ((False, True) if args.busy else (False,)) for n in sizes]
    try:
        with tempfile.TemporaryDirectory(prefix="torchdeform-chromium-") as profile:
            driver = browser.start(profile)
            try:
                with progress(len(cases), "bench viewer") as bar:
                    for n, busy in cases:
                        with busy_neighbour() if busy else contextlib.nullcontext():
                            rows.append(
                                _row(n, driver, windows=windows, seconds=args.seconds, settle=settle, busy=busy)
                            )
                        bar.update(1)
            finally:
                driver.quit()
        threads = torch.get_num_threads()
    finally:
        torch.set_num_threads(saved)
    judged = [r for r in rows if r["n"] >= TARGET_SIZE and not r["busy"]]
    extra = {
        "machine": dict(machine_info("cpu"), threads=threads),
        "target_fps": TARGET_FPS,
        "target_size": TARGET_SIZE,
        "met": (all(min(r["fps"], r["received"]) >= TARGET_FPS for r in judged) if judged else None),
        "target": f"the page draws and receives >= {TARGET_FPS:g} frames/s at every size >= {TARGET_SIZE}^3 "
        "(idle machine)",
        "setup": (
            f"headless chromium (software WebGL) and the viewer server on the same machine, "
            f"{threads} simulation thread{'s' if threads != 1 else ''}, {browser.WIDTH}x{browser.HEIGHT} "
            f"window; medians of {windows} window{'s' if windows != 1 else ''} of {args.seconds:g} s "
            f"after {settle:g} s"
        ),
    }
    if args.out:
        _plot(rows, args.out)
    if not args.json:
        print("the viewer's page in headless chromium: " + extra["setup"])
    emit("viewer", args, rows, COLUMNS, extra=extra)
    if not args.json and judged:
        print(f">= {TARGET_FPS:g} fps drawn and received at {TARGET_SIZE}^3 and up: {'yes' if extra['met'] else 'no'}")
    return 0


def _plot(rows, out_dir) -> None:
    fig, ax = axes(figsize=(6.5, 4.5))
    for busy, marker in ((False, "o"), (True, "^")):
        sel = [r for r in rows if r["busy"] == busy]
        if sel:
            label = " (busy process beside it)" if busy else ""
            ax.plot([r["vertices"] for r in sel], [r["fps"] for r in sel], marker=marker, label=f"page fps{label}")
            ax.plot(
                [r["vertices"] for r in sel],
                [r["received"] for r in sel],
                marker=marker,
                ls="--",
                label=f"frames received/s{label}",
            )
    ax.axhline(TARGET_FPS, color="grey", ls=":", label=f"{TARGET_FPS:g} fps target")
    ax.set_xscale("log")
    ax.set_xlabel("surface vertices")
    ax.set_ylabel("frames per second")
    ax.set_title("Browser viewer (headless chromium, software WebGL)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_plot(fig, out_dir, "viewer.png")
