"""Constants and small factories shared by the test modules (the fixtures wrapping them live in ``conftest.py``).

``make_grid`` and ``make_model`` build the small bodies most unit tests start from: a cube of 4^3
nodes, 1 cm apart, 26 neighbours, float64 (the accuracy dtype), on the CPU unless ``device`` says
otherwise. The ``make_model`` fixture is the same factory bound to the device of the run
(``pytest --device cuda``).
"""

from __future__ import annotations

import contextlib
import io

import torch

import torchdeform as td

F32 = torch.float32
F64 = torch.float64
#: both dtypes every code path runs in (float32 by default, float64 for accuracy)
DTYPES = (F32, F64)


def make_grid(shape=(4, 4, 4), spacing=0.01, topology=26, **kw) -> td.Grid:
    """A :class:`td.Grid` of ``shape`` (an int gives a cube) with ``spacing`` [m] and ``topology`` neighbours."""
    shape = (shape,) * 3 if isinstance(shape, int) else tuple(shape)
    return td.Grid(shape, spacing=spacing, topology=topology, **kw)


def make_model(grid=None, *, stiffness=50.0, mass=1e-3, dtype=F64, device=None, **kw) -> td.Model:
    """A :class:`td.Model` on ``grid`` (default :func:`make_grid`): 50 N/m springs, 1 g nodes, float64.

    Further keywords (``damping``, ``gravity``, ``fixed``, ``density``, ...) go to :class:`td.Model`;
    ``density`` replaces the default ``mass``.
    """
    grid = make_grid() if grid is None else grid
    if "density" in kw:
        mass = None
    return td.Model(grid, stiffness=stiffness, mass=mass, dtype=dtype, device=device, **kw)


def cg_solve(op, b, *, tol=1e-12, iters=20000):
    """Plain conjugate gradients on ``op u = b`` (``op`` symmetric positive semi-definite, ``b`` in its
    range): the test's own small-strain solver, independent of :func:`td.conjugate_gradient`."""
    u, r = torch.zeros_like(b), b.clone()
    p, rr = r.clone(), (r * r).sum()
    for _ in range(iters):
        Ap = op(p)
        a = rr / (p * Ap).sum()
        u, r = u + a * p, r - a * Ap
        rn = (r * r).sum()
        if rn.sqrt() < tol * b.norm():
            break
        p, rr = r + rn / rr * p, rn
    return u


@contextlib.contextmanager
def no_host_wait(device):
    """Inside, on CUDA, any wait of the host for the device raises (torch's sync debug mode); elsewhere nothing."""
    if device.type != "cuda":
        yield
        return
    torch.cuda.synchronize(device)
    torch.cuda.set_sync_debug_mode("error")
    try:
        yield
    finally:
        torch.cuda.set_sync_debug_mode("default")


def cli_call(argv) -> tuple[int, str, str]:
    """``torchdeform ARGV`` in-process: (exit status, stdout, stderr); argparse's exits are statuses too."""
    from torchdeform import cli

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = cli.main(argv=[str(a) for a in argv])
        except SystemExit as e:  # argparse: usage errors, --help, --version
            status = e.code
    return status, out.getvalue(), err.getvalue()
