"""Helpers every benchmark shares.

The common options, machine information, progress bars, the output conventions (a table on
stdout, or exactly one JSON document with ``--json``; ``--out DIR`` writes ``<name>.csv``), and
the speed scene that :mod:`.speed`, :mod:`.batch` and :mod:`.warp_baseline` time, and the device's
copy bandwidth that :mod:`.speed` compares its steps with.
"""

from __future__ import annotations

import csv
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from .. import options
from ..options import integer
from ..outputs import atomic_path
from ..sim.grid import Grid
from ..sim.material import Elastic
from ..sim.model import Model, State

__all__ = [
    "int_list",
    "add_common",
    "machine_info",
    "device_sync",
    "copy_bandwidth",
    "progress",
    "emit",
    "format_table",
    "speed_cube",
    "busy_neighbour",
]


class busy_neighbour:
    """A context: another process spinning on a core (``python -c "while True: pass"``) while it is open.

    What a user's machine often has beside a simulation: a browser, a build, another job. The
    process starts on entry (after a short pause, so that it is running) and is killed on exit.
    """

    def __enter__(self):
        import subprocess
        import time

        self.proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        time.sleep(0.2)
        return self

    def __exit__(self, *exc):
        self.proc.kill()
        self.proc.wait()
        return False


def int_list(key, *, lo: int = 1):
    """An ``argparse`` type: comma-separated integers >= ``lo`` (argparse names the option ``key``)."""
    return options.int_list(lo=lo)


def add_common(p) -> None:
    """Options every benchmark takes."""
    p.add_argument("--quick", action="store_true", help="tiny sizes, few steps: a smoke run in seconds")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout, nothing else")
    p.add_argument("--out", default=None, help="folder for the CSV and the plot")
    p.add_argument("--threads", type=integer(lo=1), default=None, help="CPU threads (default: torch's current)")
    p.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")


def machine_info(device: str) -> dict:
    """Torch and Python versions, thread and CPU counts, the device (and the GPU's name)."""
    info = {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "threads": torch.get_num_threads(),
        "device": device,
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
    }
    if device.startswith("cuda") and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    return info


def device_sync(device: str):
    """A function that waits for the device (CUDA) to finish; a no-op on the CPU."""
    if device.startswith("cuda"):
        return torch.cuda.synchronize
    return lambda: None


def copy_bandwidth(device, *, nbytes: int | None = None, repeats: int = 7) -> float:
    """The device's copy bandwidth in GB/s (1e9 bytes per second): bytes read plus bytes written.

    The median over ``repeats`` timings of ``dst.copy_(src)`` between two float32 buffers of
    ``nbytes`` bytes each on ``device`` (default 256 MiB on a CPU, 1 GiB on CUDA: far larger than
    the caches), after two warm-up copies, the device synchronised (:func:`device_sync`) around
    each timing. A CUDA timing is of 10 copies back to back (one 1 GiB copy takes under a
    millisecond). Both buffers are written first, so that their pages exist before the timing.
    Each copy moves ``2 * nbytes`` bytes; the buffers are freed (on CUDA released from torch's
    cache) before it returns.
    """
    dev = torch.device(device)
    cuda = dev.type == "cuda"
    nbytes = int(nbytes or (2**30 if cuda else 2**28))
    n = max(1, nbytes // 4)
    src = torch.empty(n, dtype=torch.float32, device=dev).fill_(1.0)
    dst = torch.empty_like(src).fill_(0.0)
    sync, inner = device_sync(str(dev)), 10 if cuda else 1
    for _ in range(2):
        dst.copy_(src)
    times = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        for _ in range(inner):
            dst.copy_(src)
        sync()
        times.append((time.perf_counter() - t0) / inner)
    del src, dst
    if cuda:
        torch.cuda.empty_cache()  # the 2 GiB go back to the device before the rows
    return 2 * n * 4 / statistics.median(times) / 1e9


def progress(total: int, desc: str):
    """A tqdm bar on stderr (so stdout keeps exactly the table or the JSON document)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="row", file=sys.stderr, disable=None, leave=False)


def emit(name: str, args, rows: list, columns: list, *, extra: dict | None = None, display=None) -> None:
    """Write ``--out DIR/<name>.csv`` and print the JSON document (``--json``) or the table.

    The table shows the ``display`` rows (default ``rows``).
    """
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        with atomic_path(out / f"{name}.csv") as tmp, open(tmp, "w", newline="") as fh:
            keys = list(dict.fromkeys(k for r in rows for k in r)) or [c[0] for c in columns]
            w = csv.DictWriter(fh, fieldnames=keys)  # rows may differ (compile_s ...)
            w.writeheader()
            w.writerows(rows)
    if args.json:
        doc = {"bench": name, **(extra or {}), "rows": rows}
        sys.stdout.write(json.dumps(doc, indent=1) + "\n")
        sys.stdout.flush()
    else:
        print(format_table(rows if display is None else display, columns))


def format_table(rows: list, columns: list) -> str:
    """``columns``: ``(key, header, format)``; ``None`` values print as ``-``."""
    cells = [[h for _, h, _ in columns]]
    for r in rows:
        cells.append(["-" if r.get(k) is None else (fmt.format(r[k]) if fmt else str(r[k])) for k, _, fmt in columns])
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(row, widths)) for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def speed_cube(n: int, topology: int, *, dtype=torch.float32, device="cpu", seed: int = 0, material: str = "springs"):
    """The speed scene: an ``n^3`` damped cube, slightly perturbed from rest.

    1 cm spacing, c = 0.05 N s/m, 1 g per node, no gravity; ``material`` ``"springs"``: k = 100 N/m;
    ``"elastic"``: ``td.Elastic(10 kPa, 0.45)`` (springs from the cells plus the cell term).
    Returns ``(model, state, dt)``.
    """
    grid = Grid((n, n, n), spacing=0.01, topology=topology)
    stiffness = 100.0 if material == "springs" else Elastic(1e4, 0.45)
    model = Model(grid, stiffness, damping=0.05, mass=1e-3, dtype=dtype, device=device)
    g = torch.Generator().manual_seed(seed)
    x = model.X + (1e-4 * torch.randn(model.X.shape, generator=g, dtype=torch.float64)).to(dtype=dtype, device=device)
    v = (1e-3 * torch.randn(model.X.shape, generator=g, dtype=torch.float64)).to(dtype=dtype, device=device)
    return model, State(x, v, t=0.0), 1e-4  # dt well below the bound (~8e-4 s for 26 neighbours)
