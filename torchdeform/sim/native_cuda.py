"""Spring forces of the packed layout, and a whole symplectic step, as one Triton kernel (CUDA).

The GPU counterpart of the C kernel (:mod:`.native`): the same kernel variants (:class:`~.native.Variant`: the
number of half-directions, float or double, the damping, which spring fields are stored per
spring, the gate, the fused update), the same spring law (:func:`~torchdeform.sim.springs.spring_law`,
Hooke) and the same update (:func:`~torchdeform.sim.native.symplectic_step`: ``a = (f + m g) / m``,
``v' = v + dt a``, ``x' = x + dt v'``, the global drag). An Elastic body's springs are read as
stored per spring (the GPU reads them faster than it sums cells); its cell term stays in torch.
:func:`~torchdeform.sim.native.spring_forces` and :func:`~torchdeform.sim.native.symplectic_step`
call it for CUDA tensors, so the ``"native"`` engine, the compiled step's ``"native"`` force form
and the fused step run it unchanged.

**The loop.** Every node gathers all its ``2 S`` springs (each spring is evaluated from both
ends: twice the arithmetic, no scatter, no atomics). A program takes ``BLOCK`` consecutive
nodes of one ``(H+2)(W+2)`` plane of the packed layout and walks ``DC`` planes down the ``D``
axis with that footprint, so the neighbours it reads in planes ``d - 1`` and ``d`` were read a
moment ago by itself (in L1) and each value comes from the card's memory about once per step:
a step moves little more than x and v read and written once (a plane smaller than a block is
walked as blocks of consecutive nodes instead, so small bodies keep every lane busy). The grid is
``(plane chunks, plane slabs, bodies)``; the whole packed range, halo and end padding included,
is written (halo nodes have no springs and no free degree of freedom).

**Tuning.** The block size, the planes per program and the warps are chosen per kernel and
shape on the first call by timing :data:`CONFIGS` (Triton compiles each shape once per kernel;
the choice is kept for the process in :data:`chosen`), for steps of at least
:data:`TUNE_NODES` nodes; smaller ones take the first. :func:`unavailable` says why the kernel cannot run (no CUDA, no
Triton).

Example (on a CUDA machine with Triton):
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.sim import native, native_cuda
    >>> from torchdeform.sim.packed import PackedModel
    >>> if native_cuda.unavailable() is None:
    ...     model = td.Model(td.Grid((8, 8, 8), spacing=0.01, topology=26), 50.0, damping=0.1, mass=1e-3, device="cuda")
    ...     pm = PackedModel(model)
    ...     s = pm.rest_state()
    ...     x = s.x + 1e-4 * torch.randn_like(s.x)
    ...     f = native.spring_forces(pm, x, s.v)         # this kernel, for CUDA tensors
    ...     assert torch.allclose(f, pm.spring_forces(x, s.v), atol=1e-5)
"""

from __future__ import annotations

import functools
import os
import time
from typing import NamedTuple

import torch

__all__ = [
    "CONFIGS",
    "TUNE_NODES",
    "Config",
    "chosen",
    "neighbour_bits",
    "unavailable",
    "spring_forces",
    "symplectic_step",
    "launch",
    "timings",
]


class Config(NamedTuple):
    """One launch shape: ``block`` nodes per program (a power of two), ``planes`` walked, ``warps``.

    ``bits``: read which springs exist from one 32-bit word per node (:func:`neighbour_bits`)
    instead of the node mask at both ends of every spring (27 loads per node).
    """

    block: int
    planes: int
    warps: int
    bits: bool = False


#: the launch shapes timed on a kernel's first call for a shape (Triton compiles each, ~10 s per
#: shape on the GPU machine's host). Measured at 256^3, 26 neighbours, float32, damped (H200):
#: blocks of 1024 nodes walking 8 planes 1.52 ms, of 512 nodes 1.76 ms (1.67 with the bit
#: words), walking 32 planes 2.08 ms, one plane per program 29.6 ms
CONFIGS = (
    Config(1024, 8, 8),
    Config(1024, 8, 8, True),
    Config(1024, 16, 8, True),
)

#: the least nodes (bodies times packed nodes) for which the launch shapes are timed: smaller
#: steps take the first (their time is the launch's; timing would only compile the other shapes)
TUNE_NODES = 2**20

#: the launch shape chosen per ``(variant name, P, plane, batch)`` (see :func:`launch`)
chosen: dict = {}
#: the times of every config on the first call per key: ``{key: [(Config, ms), ...]}``
timings: dict = {}


@functools.cache
def unavailable() -> str | None:
    """Why the Triton kernel cannot run here (no CUDA device, Triton missing), or None."""
    if os.environ.get("TRITON_INTERPRET") != "1" and not torch.cuda.is_available():
        return "no CUDA device"
    try:
        import triton  # noqa: F401  # pyright: ignore[reportMissingImports]
    except ImportError as e:
        return f"Triton is not installed ({e})"
    return None


@functools.cache
def _kernel():
    """The ``@triton.jit`` kernel (built here: Triton is imported only where a CUDA step runs)."""
    import triton  # pyright: ignore[reportMissingImports]
    import triton.language as tl  # pyright: ignore[reportMissingImports]

    @triton.jit
    def springs_kernel(
        X,
        V,
        XO,
        VO,
        INSIDE,
        NB,
        KQ,
        LQ,
        CQ,
        OFF,
        IM,
        MS,
        SC,
        P,
        G,
        plane,
        kb,
        lb,
        cb,
        mb,
        S: tl.constexpr,
        DAMP: tl.constexpr,
        KPS: tl.constexpr,
        LPS: tl.constexpr,
        CPS: tl.constexpr,
        GATE: tl.constexpr,
        UPDATE: tl.constexpr,
        BLOCK: tl.constexpr,
        DC: tl.constexpr,
        BITS: tl.constexpr,
        FAST: tl.constexpr,
    ):
        chunk = tl.program_id(0)
        slab = tl.program_id(1)
        b = tl.program_id(2).to(tl.int64)
        r = chunk * BLOCK + tl.arange(0, BLOCK)
        in_plane = r < plane
        xb = X + b * 3 * P
        vb = V + b * 3 * P
        ob = XO + b * 3 * P
        kq = KQ + b * kb
        lq = LQ + b * lb
        cq = CQ + b * cb
        tiny = tl.load(SC + 5)
        for dd in range(DC):
            i = (slab * DC + dd) * plane + r
            m = in_plane & (i < P)
            core = m & (i >= G) & (i < P - G)
            x0 = tl.load(xb + i, mask=m, other=0.0)
            x1 = tl.load(xb + P + i, mask=m, other=0.0)
            x2 = tl.load(xb + 2 * P + i, mask=m, other=0.0)
            if BITS:
                nb = tl.load(NB + i, mask=core, other=0)
            else:
                own = tl.load(INSIDE + i, mask=core, other=0.0)
            v0 = x0
            v1 = x1
            v2 = x2
            if DAMP or UPDATE:
                v0 = tl.load(vb + i, mask=m, other=0.0)
                v1 = tl.load(vb + P + i, mask=m, other=0.0)
                v2 = tl.load(vb + 2 * P + i, mask=m, other=0.0)
            f0 = tl.zeros_like(x0)
            f1 = tl.zeros_like(x0)
            f2 = tl.zeros_like(x0)
            for s in tl.static_range(S):
                o = tl.load(OFF + s).to(tl.int32)
                for sign in tl.static_range(2):
                    # the spring along +d_s is stored at its node i, the one along -d_s at j = i - o
                    if sign == 0:
                        j = i + o
                        at = i
                    else:
                        j = i - o
                        at = j
                    if KPS:  # noqa: SIM108 (Triton: a compile-time branch)
                        ks = tl.load(kq + s * P + at, mask=core, other=0.0)
                    else:
                        ks = tl.load(kq + s)
                    if LPS:  # noqa: SIM108
                        ls = tl.load(lq + s * P + at, mask=core, other=0.0)
                    else:
                        ls = tl.load(lq + s)
                    d0 = tl.load(xb + j, mask=core, other=0.0) - x0
                    d1 = tl.load(xb + P + j, mask=core, other=0.0) - x1
                    d2 = tl.load(xb + 2 * P + j, mask=core, other=0.0) - x2
                    if BITS:
                        mm = ((nb >> (2 * s + sign)) & 1).to(x0.dtype)
                    else:
                        mm = own * tl.load(INSIDE + j, mask=core, other=0.0)
                    sq = d0 * d0 + d1 * d1 + d2 * d2
                    sq = tl.where(sq > tiny, sq, tiny)
                    if FAST:  # float32: one reciprocal square root (the hardware's, within 2 ulp)
                        il = tl.rsqrt(sq)
                        ln = sq * il
                    else:
                        ln = tl.sqrt(sq)
                        il = 1.0 / ln
                    if DAMP:
                        if CPS:  # noqa: SIM108
                            cs = tl.load(cq + s * P + at, mask=core, other=0.0)
                        else:
                            cs = tl.load(cq + s)
                        if GATE:
                            cs = tl.where(ks != 0.0, cs, 0.0)
                        w0 = tl.load(vb + j, mask=core, other=0.0) - v0
                        w1 = tl.load(vb + P + j, mask=core, other=0.0) - v1
                        w2 = tl.load(vb + 2 * P + j, mask=core, other=0.0) - v2
                        if DAMP == 1:
                            a = (ks * (ln - ls) + cs * (d0 * w0 + d1 * w1 + d2 * w2) * il) * (il * mm)
                            f0 += a * d0
                            f1 += a * d1
                            f2 += a * d2
                        else:
                            a = ks * (ln - ls) * (il * mm)
                            bc = cs * mm
                            f0 += a * d0 + bc * w0
                            f1 += a * d1 + bc * w1
                            f2 += a * d2 + bc * w2
                    else:
                        a = ks * (ln - ls) * (il * mm)
                        f0 += a * d0
                        f1 += a * d1
                        f2 += a * d2
            if UPDATE:
                im = tl.load(IM + b * mb + i, mask=m, other=0.0)
                ms = tl.load(MS + b * mb + i, mask=m, other=0.0)
                dt = tl.load(SC + 3)
                keep = tl.load(SC + 4)
                u0 = v0 + dt * (im * (f0 + ms * tl.load(SC + 0)))
                u1 = v1 + dt * (im * (f1 + ms * tl.load(SC + 1)))
                u2 = v2 + dt * (im * (f2 + ms * tl.load(SC + 2)))
                tl.store(ob + i, x0 + dt * u0, mask=m)
                tl.store(ob + P + i, x1 + dt * u1, mask=m)
                tl.store(ob + 2 * P + i, x2 + dt * u2, mask=m)
                ub = VO + b * 3 * P
                tl.store(ub + i, u0 * keep, mask=m)
                tl.store(ub + P + i, u1 * keep, mask=m)
                tl.store(ub + 2 * P + i, u2 * keep, mask=m)
            else:
                tl.store(ob + i, f0, mask=m)
                tl.store(ob + P + i, f1, mask=m)
                tl.store(ob + 2 * P + i, f2, mask=m)

    return springs_kernel


def _stride(t: torch.Tensor) -> int:
    return 0 if t.shape[0] == 1 else t.stride(0)


@functools.cache
def _on_device(values: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """A small constant tensor on ``device`` (the offsets, the update's scalars), made once."""
    return torch.tensor(values, dtype=dtype, device=device)


def neighbour_bits(inside: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """``(P,)`` int32: bit ``2 s`` set where the spring along ``+d_s`` from a node exists, bit ``2 s + 1`` along ``-d_s``.

    A spring exists where both its ends are inside (``inside`` ``(P,)``, 1 or 0; ``offsets`` the
    ``S <= 13`` linear offsets). Nodes whose neighbours fall outside ``[0, P)`` (the halo) get no
    bits. Made once per node mask and kept on it.
    """
    key = tuple(int(o) for o in offsets.tolist())
    kept = getattr(inside, "_neighbour_bits", None)
    if kept is not None and kept[0] == key:
        return kept[1]
    P = inside.shape[-1]
    on = inside > 0
    bits = torch.zeros(P, dtype=torch.int32, device=inside.device)
    for s, o in enumerate(key):
        both = on[: P - o] & on[o:]  # the spring from node i to node i + o
        bits[: P - o] |= both.to(torch.int32) << (2 * s)
        bits[o:] |= both.to(torch.int32) << (2 * s + 1)
    inside._neighbour_bits = (key, bits)  # pyright: ignore[reportAttributeAccessIssue]
    return bits


def launch(var, x, v, out, vout, inside, k, l0, c, offsets, im, ms, *, G: int, plane: int, scalars=(), config=None):
    """Run the kernel of variant ``var`` on packed ``x``, ``v`` ``(B, 3, P)`` into ``out`` (and ``vout``).

    ``inside`` ``(P,)``; ``k, l0, c`` ``(Bp, S, 1|P)`` (``c`` any of them when undamped);
    ``offsets``: the ``S`` linear offsets (a CPU tensor); ``G``: the core range's margin;
    ``plane``: ``(H + 2)(W + 2)``, the span a program walks by (any positive value gives the same
    sums; the plane keeps a program's neighbours in its cache). With ``var.update``, ``out`` gets
    the new positions and ``vout`` the new velocities of one step, ``im, ms`` ``(B|1, 1, P)`` are
    1/m and m, and ``scalars`` are ``(g0, g1, g2, dt, keep)``; else ``out`` gets the spring forces
    (N). ``config``: the launch shape, default the one chosen for this kernel and shape (timed on
    its first call, :data:`CONFIGS`).
    """
    B, _, P = x.shape
    dev, dtype = x.device, x.dtype
    k, l0, c = (t.contiguous() for t in (k, l0, c))
    sc = _on_device((*(scalars or (0.0, 0.0, 0.0, 0.0, 1.0)), torch.finfo(dtype).tiny), dtype, dev)
    off = _on_device(tuple(int(o) for o in offsets.tolist()), torch.int64, dev)
    mb = _stride(im) if var.update else 0
    head = (x, v, out, out if vout is None else vout, inside)
    tail = (k, l0, c, off, im, ms, sc, P, G)
    strides = (_stride(k), _stride(l0), _stride(c), mb)
    flags = dict(
        S=var.S,
        DAMP=var.damping,
        KPS=var.k_per_spring,
        LPS=var.l0_per_spring,
        CPS=var.c_per_spring,
        GATE=var.gate,
        UPDATE=var.update,
    )
    kern = _kernel()

    def run(cfg: Config) -> None:
        # a plane smaller than a block (small bodies, batches of them): programs walk blocks of
        # consecutive nodes instead, every lane busy (the sums do not depend on the span)
        span = max(plane, cfg.block)
        planes = -(-P // span)
        grid = (-(-span // cfg.block), -(-planes // cfg.planes), B)
        nb = neighbour_bits(inside, offsets) if cfg.bits else inside
        kern[grid](  # pyright: ignore[reportIndexIssue]
            *head,
            nb,
            *tail,
            span,
            *strides,
            **flags,
            BLOCK=cfg.block,
            DC=cfg.planes,
            BITS=cfg.bits,
            FAST=dtype == torch.float32,
            num_warps=cfg.warps,
        )

    if config is not None:
        run(config)
        return
    key = (str(var), P, plane, B)
    if key not in chosen:
        # the interpreter (tests on a CPU) and small steps take the first shape
        chosen[key] = _tune(run, key, dev) if B * P >= TUNE_NODES and dev.type == "cuda" else CONFIGS[0]
    run(chosen[key])


def _tune(run, key, device) -> Config:
    """The fastest of :data:`CONFIGS` for ``run`` (each compiled, warmed and timed over 5 launches).

    A launch shape that fails to build or launch here (registers or shared memory another card
    lacks) is left out, its time None in :data:`timings`; when every one fails, the last error is raised.
    """
    times, errors = [], []
    for cfg in CONFIGS:
        try:
            run(cfg)  # Triton compiles it
        except Exception as e:  # the other shapes may run
            errors.append(e)
            times.append((cfg, None))
            continue
        times.append((cfg, _ms(run, cfg, device)))
    timings[key] = times
    ok = [(cfg, ms) for cfg, ms in times if ms is not None]
    if not ok:
        raise errors[-1]
    return min(ok, key=lambda t: t[1])[0]


def _ms(run, cfg: Config, device: torch.device, repeats: int = 5) -> float:
    """Milliseconds per launch of ``cfg`` (CUDA events on a GPU, the clock elsewhere)."""
    if device.type != "cuda":
        t0 = time.perf_counter()
        for _ in range(repeats):
            run(cfg)
        return (time.perf_counter() - t0) * 1e3 / repeats
    start, stop = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    for _ in range(repeats):
        run(cfg)
    stop.record()
    stop.synchronize()
    return start.elapsed_time(stop) / repeats


def spring_forces(x, v, inside, k, l0, c, offsets, var, *, G: int, plane: int) -> torch.Tensor:
    """The spring forces ``(B, 3, P)`` (N) of packed ``x``, ``v`` by the kernel of ``var`` (see :func:`launch`)."""
    x, v = x.contiguous(), v.contiguous()
    f = torch.empty_like(x)
    launch(var, x, v, f, None, inside, k, l0, k if c is None else c, offsets, x, x, G=G, plane=plane)
    return f


def symplectic_step(pm, x: torch.Tensor, v: torch.Tensor, var, *, im, ms, scalars):
    """One symplectic Euler step of packed model ``pm`` from ``x``, ``v`` ``(B, 3, P)`` in one kernel: ``(x', v')``.

    ``im``, ``ms``: 1/m and m ``(B|1, 1, P)``; ``scalars``: ``(g0, g1, g2, dt, keep)`` (see :func:`launch`).
    """
    x, v = x.contiguous(), v.contiguous()
    xo, vo = torch.empty_like(x), torch.empty_like(v)
    c = pm.stiffness if pm.damping is None else pm.damping
    launch(
        var,
        x,
        v,
        xo,
        vo,
        pm.inside,
        pm.stiffness,
        pm.rest_length,
        c,
        pm.offset_table,
        im,
        ms,
        G=pm.G,
        plane=pm.plane,
        scalars=scalars,
    )
    return xo, vo
