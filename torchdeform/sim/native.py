"""Spring forces of the packed layout as a small C kernel, and a whole symplectic step as one.

``torch.compile`` turns the unrolled gather form of :meth:`~torchdeform.sim.packed.PackedModel.spring_forces`
into one fast vectorised loop, but building it takes inductor 20-60 s per grid shape on a 2-core
CPU (almost all of it in inductor's own Python code generation for a loop body of ~1,100
operations; the C++ compiler takes 3 s). Here the force sum is written out as C source with the
spring law of :func:`~torchdeform.sim.springs.spring_law` (Hooke); the system C compiler builds
it in 1-2 s, and it serves every grid shape (the stencil offsets are arguments). The compiled
step calls it through the custom op ``torchdeform::native_springs`` (inductor keeps it as one
external call and compiles the rest of the step, a few pointwise loops, in a few seconds); the
``"native"`` engine (:mod:`~torchdeform.sim.engine`) calls it, or :func:`symplectic_step`, without
``torch.compile`` at all.

Each kernel is specialised on what changes its loop body (:class:`Variant`): the number of
half-directions ``S``, float or double, the damping (none, projected, Radetzky's unprojected),
which of stiffness, rest length and damping are stored per spring, and whether it also makes
the symplectic Euler update. Hooke's law only: a strain-stiffening law (:mod:`torchdeform.sim.laws`)
keeps inductor's forms.

Built kernels are cached on disk (:func:`cache_dir`), keyed by their source, the compiler and the
CPU (they are built with ``-march=native``). Where no C compiler works, :func:`unavailable` says
why and the compiled step uses inductor's forms instead.

The loop (:func:`source`): every spring is evaluated once, at its first node, and its
coefficient is handed to its second node through a per-thread ring; the sums are those of the
gather form up to rounding (forward directions first, then backward ones). Threads split the
core range; each thread runs blocks of :data:`BLOCK_NODES` nodes, two ``#pragma omp simd`` loops
per block. The thread count is torch's when the kernel runs (the thread governor sets it).

Example:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.sim import native
    >>> from torchdeform.sim.packed import PackedModel
    >>> pm = PackedModel(td.Model(td.Grid((5, 6, 7), spacing=0.01, topology=26), stiffness=50.0, damping=0.1, mass=1e-3))
    >>> s = pm.rest_state()
    >>> x = s.x + 1e-4 * torch.randn_like(s.x)
    >>> f = native.spring_forces(pm, x, s.v) if native.supports(pm) is None else pm.spring_forces(x, s.v)
    >>> f.shape, bool(torch.allclose(f, pm.spring_forces(x, s.v), atol=1e-5))
    (torch.Size([1, 3, 508]), True)
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import hashlib
import math
import os
import platform
import shutil
import subprocess
import tempfile
from dataclasses import KW_ONLY, dataclass
from pathlib import Path

import torch

from . import native_cuda
from .springs import _needs_gate

__all__ = [
    "Variant",
    "source",
    "unavailable",
    "supports",
    "variant_of",
    "kernel",
    "spring_forces",
    "cache_dir",
    "NativeBuildError",
    "fused_blocker",
    "symplectic_step",
    "BLOCK_NODES",
    "name_of",
    "load_library",
    "unavailable_on",
]

#: bump when the generated source changes meaning (part of every cache key through the source)
KERNEL_VERSION = 3

_CTYPE = {torch.float32: "float", torch.float64: "double"}
#: the C type of each dtype the kernels take (their names)
CTYPE_NAMES = _CTYPE

#: nodes per block of the kernel's loops (see :func:`source`). Measured at 64^3, 26 neighbours,
#: float32, one and two threads: 32 nodes 17-21 and 10-13 ns per node, 128 about 15.5 and 8-11,
#: 256 about 15 and 10 (and 7.4 against 17.5 at 128^3): long loops amortise each block's set-up
BLOCK_NODES = 256


class NativeBuildError(RuntimeError):
    """The C kernel could not be built or loaded (the message has the compiler's words)."""


@dataclass(frozen=True)
class Variant:
    """What a spring-force kernel is specialised on.

    Attributes:
        S: half-directions of the stencil (3, 7, 9 or 13).
        dtype: ``"float"`` or ``"double"``.
        damping: 0 none, 1 projected (a dashpot along the spring), 2 unprojected (Radetzky).
        k_per_spring, l0_per_spring, c_per_spring: the field is stored per spring ``(Bp, S, P)``,
            not per direction ``(Bp, S, 1)``.
        gate: damping only where the stiffness is not zero (stiffness per spring, damping not:
            :func:`~torchdeform.sim.springs.gate_damping`).
        update: the kernel also makes the symplectic Euler update (:func:`symplectic_step`)
            instead of writing the forces.
        cell_term: the kernel also makes an Elastic body's cell term (:mod:`.native_volume`'s
            loop, in the same pass over the nodes) and adds its forces to the springs'.
        cells: stiffness from cells: the number of cells holding a spring along each direction
            (an Elastic body's springs, :func:`~torchdeform.sim.material.spring_stiffness`): the
            kernel reads the shear modulus of each cell (one node field) and makes each spring's
            stiffness ``k_s = kq[s] sum_cells mu_c`` instead of reading ``S`` per-spring fields;
            empty for stiffness per direction or per spring.
        cuda: the Triton kernel for CUDA tensors (:mod:`.native_cuda`) instead of the C one.
    """

    S: int
    dtype: str
    damping: int
    _: KW_ONLY
    k_per_spring: bool = False
    l0_per_spring: bool = False
    c_per_spring: bool = False
    gate: bool = False
    update: bool = False
    cell_term: bool = False
    cells: tuple = ()
    cuda: bool = False


def source(var: Variant) -> str:
    """The C source of the kernel ``var``: ``springs(x, v, f, inside, k, l0, c, off, B, P, G, kb, lb, cb, nt, tiny)``.

    ``x, v, f``: ``(B, 3, P)``; ``inside``: ``(P,)``; ``k, l0, c``: per direction ``(Bp, S)`` or per
    spring ``(Bp, S, P)`` with batch strides ``kb, lb, cb`` (0 when shared); ``off``: the ``S``
    linear offsets (all positive, at most ``G``); ``G``: the core range's margin; ``nt``: threads;
    ``tiny``: the clamp of ``|x_j - x_i|^2`` (a run-time value, so that the compiler does not fold
    ``sqrt(tiny)`` into a branch that stops it vectorising). Returns 0, or 1 when a thread could
    not allocate its ring.

    Every spring is evaluated once, at its first endpoint ``i`` (the ``S`` forward directions): its
    coefficient ``a`` (times both endpoints' ``inside``) is added as ``a (x_j - x_i)`` to ``i`` and
    kept in a per-thread ring of the last ``R >= G + 2 BLK`` nodes, from which its second endpoint
    ``j = i + o`` takes it, ``o`` nodes later, as ``a (x_i - x_j)``. Nodes go in blocks of
    :data:`BLOCK_NODES`: the forward pass of a block (one ``omp simd`` loop) before its backward
    pass (another), since a spring of offset 1 ends in the same block. A thread first runs the
    forward pass over the ``G`` nodes before its range (its ring's warm-up).

    Examples:
        >>> src = source(Variant(S=3, dtype="double", damping=1))
        >>> src.count("{ /* forward */"), src.count("{ /* backward */"), "sqrt(" in src
        (3, 3, True)
    """
    T, S, damp = var.dtype, var.S, var.damping
    sqrt = "sqrtf" if T == "float" else "sqrt"
    # the update's operands: new velocities U (F holds the new positions), 1 / m and m, g, dt, the drag factor
    upd = (
        (
            (
                f", {T}* restrict U, const {T}* restrict IM, const {T}* restrict MS, {T} g0, {T} g1, {T} g2, {T} dt, {T} keep"
            )
            if var.update
            else ""
        )
        + (
            f", const {T}* restrict KC, const {T}* restrict SC, int64_t sH, int64_t sD, {T} cta, {T} ctb"
            if var.cell_term
            else ""
        )
        + (f", const {T}* restrict MU, const int64_t* restrict coff" if var.cells else "")
    )
    rings = 2 if damp == 2 else 1  # a; and b (Radetzky's damping, per spring)
    lines = [
        f"/* torchdeform spring forces, kernel version {KERNEL_VERSION}: {var} */",
        *preamble(T),
        f"static __attribute__((noinline)) int core(const {T}* restrict X, const {T}* restrict V, "
        f"{T}* restrict F, const {T}* restrict inside,",
        f"    const {T}* restrict kq, const {T}* restrict lq, const {T}* restrict cq, "
        f"const int64_t* restrict off, int64_t P, int64_t G, int64_t lo, int64_t hi, {T} tiny{upd}) {{",
        f"  const {T} *X0 = X, *X1 = X + P, *X2 = X + 2 * P;",
        f"  {T} *F0 = F, *F1 = F + P, *F2 = F + 2 * P;",
    ]
    w = lines.append
    if damp or var.update:
        w(f"  const {T} *V0 = V, *V1 = V + P, *V2 = V + 2 * P;")
    if var.update:
        w(f"  {T} *U0 = U, *U1 = U + P, *U2 = U + 2 * P;")
    for s in range(S):
        w(f"  const int64_t o{s} = off[{s}];")
    cell_at = _cell_offset_lines(w, var.cells)
    w("  int64_t R = BLK;")
    w("  while (R < G + 2 * BLK) R <<= 1;")
    w("  const int64_t RS = R + BLK, M = R - 1;         /* a ring per direction, BLK mirrored at its end */")
    nq = 9 if var.cell_term else 0  # the cell term's 9 rings of Q after the springs' rings
    w(f"  {T}* restrict A = ring({rings * S + nq} * RS);")
    w("  if (!A) return 1;")
    if var.cell_term:
        w(f"  {T}* restrict Q = A + {rings * S} * RS;")
    if rings == 2:
        w(f"  {T}* restrict Bc = A + {S} * RS;")
    w(f"  {T} fa[BLK], fb[BLK], fc[BLK];")
    w("  const int64_t base = lo - G > 0 ? lo - G : 0;")
    w("  for (int64_t i0 = base; i0 < hi; i0 += BLK) {")
    w("    const int64_t n = hi - i0 < BLK ? hi - i0 : BLK, p0 = (i0 - base) & M;")
    w("    #pragma omp simd")
    w("    for (int64_t k = 0; k < n; k++) {")
    w("      const int64_t i = i0 + k;")
    w(f"      const {T} x0 = X0[i], x1 = X1[i], x2 = X2[i], own = inside[i];")
    if damp:
        w(f"      const {T} v0 = V0[i], v1 = V1[i], v2 = V2[i];")
    w(f"      {T} f0 = 0, f1 = 0, f2 = 0;")
    for s in range(S):
        w("      { /* forward */")
        w(f"        const int64_t j = i + o{s};")
        w(f"        const {T} ks = {_stiffness_expr(var, s, cell_at)};")
        w(f"        const {T} ls = " + (f"lq[{s} * P + i];" if var.l0_per_spring else f"lq[{s}];"))
        w(f"        const {T} d0 = X0[j] - x0, d1 = X1[j] - x1, d2 = X2[j] - x2;")
        w(f"        const {T} sq = d0 * d0 + d1 * d1 + d2 * d2;")
        w(f"        const {T} l = {sqrt}(sq > tiny ? sq : tiny);")
        w(f"        const {T} il = 1 / l, m = own * inside[j];")
        if damp:
            w(f"        {T} cs = " + (f"cq[{s} * P + i];" if var.c_per_spring else f"cq[{s}];"))
            if var.gate:
                w("        cs = ks != 0 ? cs : 0;")
            w(f"        const {T} w0 = V0[j] - v0, w1 = V1[j] - v1, w2 = V2[j] - v2;")
        if damp == 1:  # (k (l - l0) + c (d . w) / l) / l, masked
            w(f"        const {T} a = (ks * (l - ls) + cs * (d0 * w0 + d1 * w1 + d2 * w2) * il) * (il * m);")
        else:
            w(f"        const {T} a = ks * (l - ls) * (il * m);")
        w(f"        A[{s} * RS + p0 + k] = a;")
        if damp == 2:
            w(f"        const {T} b = cs * m;")
            w(f"        Bc[{s} * RS + p0 + k] = b;")
            w("        f0 += a * d0 + b * w0; f1 += a * d1 + b * w1; f2 += a * d2 + b * w2;")
        else:
            w("        f0 += a * d0; f1 += a * d1; f2 += a * d2;")
        w("      }")
    w("      fa[k] = f0; fb[k] = f1; fc[k] = f2;")
    w("    }")
    _cell_pass(w, T, var.cell_term)
    w("    if (p0 == 0) {                                 /* the ring's first block, mirrored past its end */")
    w(f"      for (int r = 0; r < {rings * S + nq}; r++) memcpy(A + r * RS + R, A + r * RS, n * sizeof({T}));")
    w("    }")
    w("    if (i0 + n <= lo) continue;                     /* warm-up: springs only */")
    w("    const int64_t k0 = lo > i0 ? lo - i0 : 0;")
    _cell_sums(w, T, var.cell_term)
    for s in range(S):
        w(f"    const int64_t q{s} = (i0 + k0 - o{s} - base) & M;")
    w("    #pragma omp simd")
    w("    for (int64_t k = k0; k < n; k++) {")
    w("      const int64_t i = i0 + k;")
    w(f"      const {T} x0 = X0[i], x1 = X1[i], x2 = X2[i];")
    if damp == 2:
        w(f"      const {T} v0 = V0[i], v1 = V1[i], v2 = V2[i];")
    w(f"      {T} f0 = fa[k], f1 = fb[k], f2 = fc[k];")
    for s in range(S):
        w("      { /* backward */")
        w(f"        const int64_t j = i - o{s}, r = q{s} + k - k0;")
        w(f"        const {T} a = A[{s} * RS + r];")
        if damp == 2:
            w(f"        const {T} b = Bc[{s} * RS + r];")
            w(
                "        f0 += a * (X0[j] - x0) + b * (V0[j] - v0); f1 += a * (X1[j] - x1) + b * (V1[j] - v1);"
                " f2 += a * (X2[j] - x2) + b * (V2[j] - v2);"
            )
        else:
            w("        f0 += a * (X0[j] - x0); f1 += a * (X1[j] - x1); f2 += a * (X2[j] - x2);")
        w("      }")
    w("      F0[i] = f0; F1[i] = f1; F2[i] = f2;") if not var.update else _update_lines(w, T, "      ")
    w("    }")
    w("  }")
    w("  return 0;")
    w("}")
    w("")
    cells_args = f", const {T}* mu, int64_t mub, const int64_t* coff" if var.cells else ""
    term_args = (
        f", const {T}* kc, const {T}* sc, int64_t kcb, int64_t sH, int64_t sD, {T} cta, {T} ctb"
        if var.cell_term
        else ""
    )
    w(f"int springs(const {T}* x, const {T}* v, {T}* f, const {T}* inside, const {T}* k, const {T}* l0,")
    w(f"    const {T}* c, const int64_t* off, int64_t B, int64_t P, int64_t G, int64_t kb, int64_t lb,")
    if var.update:
        w(
            f"    int64_t cb, int nt, {T} tiny, {T}* u, const {T}* im, const {T}* ms, int64_t mb, "
            f"{T} g0, {T} g1, {T} g2, {T} dt, {T} keep" + term_args + cells_args + ") {"
        )
    else:
        w(f"    int64_t cb, int nt, {T} tiny" + cells_args + ") {")
    w("  int failed = 0;")
    w("  for (int64_t b = 0; b < B; b++) {")
    w(f"    const {T}* X = x + b * 3 * P; const {T}* V = v + b * 3 * P; {T}* F = f + b * 3 * P;")
    if var.cells:
        w(f"    const {T}* MU = mu + b * mub;")
    w(f"    const {T}* kq = k + b * kb; const {T}* lq = l0 + b * lb; const {T}* cq = c + b * cb;")
    if var.update:
        w(f"    {T}* U = u + b * 3 * P; const {T}* IM = im + b * mb; const {T}* MS = ms + b * mb;")
        w(f"    const {T} *X0 = X, *X1 = X + P, *X2 = X + 2 * P, *V0 = V, *V1 = V + P, *V2 = V + 2 * P;")
        w(f"    {T} *F0 = F, *F1 = F + P, *F2 = F + 2 * P, *U0 = U, *U1 = U + P, *U2 = U + 2 * P;")
        if var.cell_term:
            w(f"    const {T}* KC = kc + b * kcb; const {T}* SC = sc + b * kcb;")
        w("    for (int part = 0; part < 2; part++) {            /* outside the core range: no springs */")
        w("      for (int64_t i = part ? P - G : 0; i < (part ? P : G); i++) {")
        w(f"        const {T} x0 = X0[i], x1 = X1[i], x2 = X2[i], f0 = 0, f1 = 0, f2 = 0;")
        _update_lines(w, T, "        ")
        w("      }")
        w("    }")
        extra = ", U, IM, MS, g0, g1, g2, dt, keep" + (", KC, SC, sH, sD, cta, ctb" if var.cell_term else "")
    else:
        w("    for (int a = 0; a < 3; a++) {                          /* zero outside the core range */")
        w(f"      memset(F + a * P, 0, G * sizeof({T})); memset(F + a * P + P - G, 0, G * sizeof({T}));")
        w("    }")
        extra = ""
    extra += ", MU, coff" if var.cells else ""
    core_over(w, "core(X, V, F, inside, kq, lq, cq, off, P, G, {lo}, {hi}, tiny" + extra + ")")
    w("  }")
    w("  return failed;")
    w("}")
    return "\n".join(lines) + "\n"


def core_over(w, call: str) -> None:
    """C lines running ``call`` (with ``{lo}``, ``{hi}``) over the core range ``[G, P - G)``.

    With ``nt > 1`` OpenMP threads each take a contiguous share (starts rounded down to 16 nodes)
    and ``continue`` the batch loop; otherwise one call covers the range. ``failed`` collects the
    calls' results.
    """
    w("#ifdef _OPENMP")
    w("    if (nt > 1) {")
    w("      #pragma omp parallel num_threads(nt) reduction(|:failed)")
    w("      {")
    w("        const int64_t n = P - 2 * G, t = omp_get_thread_num(), m = omp_get_num_threads();")
    w("        const int64_t lo = G + ((n * t / m) & ~(int64_t)15);")
    w("        const int64_t hi = t == m - 1 ? P - G : G + ((n * (t + 1) / m) & ~(int64_t)15);")
    w("        failed |= " + call.format(lo="lo", hi="hi") + ";")
    w("      }")
    w("      continue;")
    w("    }")
    w("#endif")
    w("    failed |= " + call.format(lo="G", hi="P - G") + ";")


def preamble(T: str) -> list:
    """The C lines every kernel starts with: headers, the block size and a per-thread ring buffer ``ring(n)``."""
    return [
        "#include <stdint.h>",
        "#include <stdlib.h>",
        "#include <string.h>",
        "#include <math.h>",
        "#ifdef _OPENMP",
        "#include <omp.h>",
        "#endif",
        f"#define BLK {BLOCK_NODES}",
        "",
        f"static __thread {T}* ring_buf = 0;",
        "static __thread int64_t ring_len = 0;",
        "",
        f"static {T}* ring(int64_t n) {{",
        "  if (n > ring_len) {",
        f"    free(ring_buf); ring_buf = ({T}*)malloc(n * sizeof({T})); ring_len = ring_buf ? n : 0;",
        "  }",
        "  return ring_buf;",
        "}",
        "",
    ]


_CORNERS = [(d, h, w) for d in (0, 1) for h in (0, 1) for w in (0, 1)]
_CORNER_OFFSET = {c: " + ".join(t for t, on in zip(("sD", "sH", "1"), c) if on) or "0" for c in _CORNERS}
_CORNER_NAME: dict[tuple, str] = {c: f"{c[0]}{c[1]}{c[2]}" for c in _CORNERS}


def cell_lines(w, T: str, ind: str, *, kappa: str, shear: str, a: str, b: str) -> None:
    """C lines making the cell term of the cell at node ``i`` into the ring ``Q[r * RS + p0 + k]``.

    The cell's corners are ``i + {0, 1} + {0, sH} + {0, sD}``; ``F`` from its four edges per axis
    (times ``a = 1 / (4 h)``), ``Q = b (kappa (J - 1) cof F + 2 mu' F E)`` with ``b = h^2 / 4``
    (:mod:`.native_volume`). ``kappa``, ``shear``: the names of the per-cell fields.
    """
    corners, off, name = _CORNERS, _CORNER_OFFSET, _CORNER_NAME
    for m in range(3):
        for c in corners:
            w(f"{ind}const {T} x{m}_{name[c]} = X{m}[i + {off[c]}];")
    for m in range(3):  # F[m][j]: d x_m / d X_j, j = 0 (D), 1 (H), 2 (W): the four edges along j
        for j in range(3):
            terms = []
            for c in corners:
                if c[j] == 0:
                    up = tuple(1 if q == j else c[q] for q in range(3))
                    terms.append(f"(x{m}_{name[up]} - x{m}_{name[c]})")
            w(f"{ind}const {T} F{m}{j} = {a} * ({' + '.join(terms)});")
    for i in range(3):
        for j in range(3):
            i1, i2, j1, j2 = (i + 1) % 3, (i + 2) % 3, (j + 1) % 3, (j + 2) % 3
            w(f"{ind}const {T} C{i}{j} = F{i1}{j1} * F{i2}{j2} - F{i1}{j2} * F{i2}{j1};")
    w(f"{ind}const {T} J = F00 * C00 + F01 * C01 + F02 * C02;")
    w(f"{ind}const {T} cs = {b} * {kappa}[i] * (J - 1), ct = {b} * 2 * {shear}[i];")
    for i in range(3):  # Green-Lagrange strain E = (F^T F - I) / 2, symmetric
        for j in range(i, 3):
            sq = " + ".join(f"F{m}{i} * F{m}{j}" for m in range(3))
            w(f"{ind}const {T} G{i}{j} = ({T})0.5 * ({sq}){' - (' + T + ')0.5' if i == j else ''};")
    e = {(i, j): f"G{min(i, j)}{max(i, j)}" for i in range(3) for j in range(3)}
    for r in range(9):
        i, j = divmod(r, 3)
        fe = " + ".join(f"F{i}{m} * {e[m, j]}" for m in range(3))
        w(f"{ind}Q[{r} * RS + p0 + k] = cs * C{i}{j} + ct * ({fe});")


def cell_ring_lines(w, ind: str) -> None:
    """C lines: where in the ring the node pass finds, for its first node, the cell of each of its 8 corners."""
    for c in _CORNERS:  # the cell whose corner c is the node: lowest corner at i - offset
        w(f"{ind}const int64_t qc{_CORNER_NAME[c]} = (i0 + k0 - ({_CORNER_OFFSET[c]}) - base) & M;")


def cell_gather_lines(w, ind: str) -> None:
    """C lines subtracting from ``f0..f2`` the forces of node ``i``'s 8 cells: ``f_k -= sum_j Q_kj s_j``."""
    for c in _CORNERS:
        w(f"{ind}{{")
        w(f"{ind}  const int64_t r = qc{_CORNER_NAME[c]} + k - k0;")
        for m in range(3):
            terms = "".join(f" {'+' if c[j] else '-'} Q[{3 * m + j} * RS + r]" for j in range(3))
            w(f"{ind}  f{m} -={terms};")
        w(f"{ind}}}")


def _cell_pass(w, T: str, on: bool) -> None:
    """The spring kernel's loop making the cells of a block into the ring (an Elastic body's cell term), if ``on``."""
    if not on:
        return
    w("    #pragma omp simd")
    w("    for (int64_t k = 0; k < n; k++) {                /* the cells at the block's nodes (lowest corners) */")
    w("      const int64_t i = i0 + k;")
    cell_lines(w, T, "      ", kappa="KC", shear="SC", a="cta", b="ctb")
    w("    }")


def _cell_sums(w, T: str, on: bool) -> None:
    """The spring kernel's loop adding each node's 8 cells to its sums ``fa, fb, fc``, if ``on``."""
    if not on:
        return
    cell_ring_lines(w, "    ")
    w("    #pragma omp simd")
    w("    for (int64_t k = k0; k < n; k++) {               /* each node: its 8 cells, into its sums */")
    w(f"      {T} f0 = 0, f1 = 0, f2 = 0;")
    cell_gather_lines(w, "      ")
    w("      fa[k] += f0; fb[k] += f1; fc[k] += f2;")
    w("    }")


def _cell_offset_lines(w, counts: tuple) -> list:
    """Declare the cells' offsets of each direction (``c{s}_{m} = coff[..]``); their names per direction."""
    names = []
    for s, n in enumerate(counts):
        names.append([f"c{s}_{m}" for m in range(n)])
        for m in range(n):
            w(f"  const int64_t c{s}_{m} = coff[{sum(counts[:s]) + m}];")
    return names


def _stiffness_expr(var: Variant, s: int, cell_at: list) -> str:
    """The C expression of direction ``s``'s stiffness at node ``i``: per direction, per spring or from cells."""
    if var.cells:  # the cells' shear moduli, summed in the order of material.spring_stiffness
        return f"({' + '.join(f'MU[i + {c}]' for c in cell_at[s])}) * kq[{s}]"
    return f"kq[{s} * P + i]" if var.k_per_spring else f"kq[{s}]"


def _update_lines(w, T: str, ind: str) -> None:
    """The symplectic Euler update of node ``i`` from its forces ``f0..f2``, in torch's order.

    ``a = (1/m) (f + m g)``, ``u = v + dt a``, ``x' = x + dt u`` (into ``F``), ``v' = keep u`` (into
    ``U``; ``keep`` the global drag's ``exp(-decay dt)``), as :class:`~torchdeform.sim.integrators.SymplecticEuler`.
    """
    w(f"{ind}const {T} im = IM[i], ms = MS[i];")
    w(
        f"{ind}const {T} u0 = V0[i] + dt * (im * (f0 + ms * g0)), u1 = V1[i] + dt * (im * (f1 + ms * g1)), "
        f"u2 = V2[i] + dt * (im * (f2 + ms * g2));"
    )
    w(f"{ind}F0[i] = x0 + dt * u0; F1[i] = x1 + dt * u1; F2[i] = x2 + dt * u2;")
    w(f"{ind}U0[i] = u0 * keep; U1[i] = u1 * keep; U2[i] = u2 * keep;")


# ------------------------------------------------------------------------------ building
def cache_dir() -> Path:
    """Where built kernels are kept: ``$TORCHDEFORM_CACHE_DIR/kernels``, else ``~/.cache/torchdeform/kernels``."""
    root = os.environ.get("TORCHDEFORM_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "torchdeform"
    )
    return Path(root) / "kernels"


#: compiler flags, tried in this order until one set works (GCC's RTL combiner spends 70% of a
#: 3 s build on the one long basic block of 2 S springs and changes nothing measurable: 1.3 s
#: without it; then no -march=native, then no OpenMP)
FLAG_SETS = (
    ["-O3", "-march=native", "-fno-math-errno", "-fopenmp", "-fdisable-rtl-combine"],
    ["-O3", "-march=native", "-fno-math-errno", "-fopenmp"],
    ["-O3", "-fno-math-errno", "-fopenmp"],
    ["-O3", "-fno-math-errno"],
)


@functools.cache
def _compiler() -> tuple:
    """``(command, version line, cpu identity)``; command None when there is no C compiler."""
    cmd = os.environ.get("CC") or next((c for c in ("cc", "gcc", "clang") if shutil.which(c)), None)
    if cmd is None or shutil.which(cmd) is None:
        return None, "", ""
    try:
        version = subprocess.run([cmd, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return None, "", ""
    cpu = platform.machine() + " " + platform.processor()
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            cpu += "".join(ln for ln in f if ln.startswith(("model name", "flags")))[:4000]
    except OSError:
        pass
    return cmd, version.splitlines()[0] if version else "", cpu


@functools.cache
def unavailable() -> str | None:
    """Why no kernel can be built here (no C compiler, not a POSIX system), or None."""
    if os.name != "posix":
        return f"native spring kernels need a POSIX system (this is {os.name})"
    if os.environ.get("TORCHDEFORM_NATIVE", "1") == "0":
        return "TORCHDEFORM_NATIVE=0"
    if _compiler()[0] is None:
        return "no C compiler found (set CC)"
    return None


_kernels: dict = {}  # loaded functions by the custom op's ``kernel`` argument (:func:`kernel`)


def _library_path(src: str, stem: str, flags) -> Path:
    """Where :func:`load_library` caches ``src`` built with ``flags``: keyed by source, compiler, CPU and flags."""
    cmd, version, cpu = _compiler()
    key = hashlib.sha256("\n".join([src, str(cmd), version, cpu, " ".join(flags)]).encode()).hexdigest()[:20]
    return cache_dir() / f"{stem}-{key}.so"


def load_library(src: str, stem: str) -> ctypes.CDLL:
    """Build C source ``src`` (or take it from the disk cache) and load it.

    Tries :data:`FLAG_SETS` in order; the library is cached as ``{stem}-{key}.so`` in
    :func:`cache_dir`, keyed by the source, the compiler, the CPU and the flags.

    Raises:
        NativeBuildError: no flag set built and loaded (the message has the compiler's words).
    """
    cmd, last = _compiler()[0], ""
    for flags in FLAG_SETS:
        so = _library_path(src, stem, flags)
        if not so.exists():
            so.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=so.parent) as tmp:
                c_file, out = Path(tmp) / f"{stem}.c", Path(tmp) / f"{stem}.so"
                c_file.write_text(src)
                r = subprocess.run(
                    [cmd, *flags, "-fPIC", "-shared", str(c_file), "-o", str(out), "-lm"],
                    capture_output=True,
                    text=True,
                )
                if r.returncode != 0:
                    last = f"{cmd} {' '.join(flags)}: {r.stderr.strip()[-800:]}"
                    continue
                os.replace(out, so)  # atomic: concurrent builders agree
        try:
            return ctypes.CDLL(str(so))
        except OSError as e:
            last = str(e)
    raise NativeBuildError(last)


def entry(src: str, stem: str, argtypes: list, *, what: str):
    """The function ``stem`` of C source ``src`` (built or taken from the disk cache), typed for ctypes.

    ``argtypes`` are its ctypes parameter types; it returns a C ``int`` (0: done).

    Raises:
        NativeBuildError: naming ``what`` (e.g. "the contact kernel (float)") and the compiler's words.
    """
    try:
        lib = load_library(src, stem)
    except NativeBuildError as e:
        raise NativeBuildError(f"could not build {what}: {e}") from None
    fn = getattr(lib, stem)
    fn.argtypes = argtypes
    fn.restype = ctypes.c_int
    return fn


def _build(var: Variant):
    T = ctypes.c_float if var.dtype == "float" else ctypes.c_double
    i64, ptr = ctypes.c_int64, ctypes.c_void_p
    argtypes = (
        ([ptr] * 8 + [i64] * 6 + [ctypes.c_int, T] + ([ptr] * 3 + [i64] + [T] * 5 if var.update else []))
        + ([ptr, ptr, i64, i64, i64, T, T] if var.cell_term else [])
        + ([ptr, i64, ptr] if var.cells else [])
    )
    return entry(source(var), "springs", argtypes, what=f"the spring kernel {var}")


def name_of(var: Variant) -> str:
    """The name of kernel ``var`` (the variant in short), as the custom op ``torchdeform::native_springs`` takes it.

    The same in every process, so a compiled graph names its kernel the same way everywhere; the
    kernel is built on its first call (:func:`kernel` builds it now).

    Examples:
        >>> name_of(Variant(S=13, dtype="float", damping=1))
        'S13-float-d1-k0-l0-c0-g0'
    """
    name = (
        f"S{var.S}-{var.dtype}-d{var.damping}-k{var.k_per_spring:d}-l{var.l0_per_spring:d}"
        f"-c{var.c_per_spring:d}-g{var.gate:d}"
        + ("-step" if var.update else "")
        + ("-cellterm" if var.cell_term else "")
        + ("-cells" if var.cells else "")
        + ("-cuda" if var.cuda else "")
    )
    _variants[name] = var
    return name


_variants: dict = {}


def kernel(var: Variant) -> str:
    """:func:`name_of` ``var``, the kernel built (or taken from the disk cache) and loaded now.

    Raises:
        NativeBuildError: no compiler, or the build failed.
    """
    name = name_of(var)
    if var.cuda:  # Triton builds it on its first launch
        why = native_cuda.unavailable()
        if why:
            raise NativeBuildError(why)
        return name
    _function(name)
    return name


def is_built(pm) -> bool:
    """Whether the spring kernel of packed model ``pm`` is loaded or in the disk cache (no build to wait for).

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> from torchdeform.sim.packed import PackedModel
        >>> pm = PackedModel(td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, mass=1e-3))
        >>> _ = kernel(variant_of(pm)) if unavailable() is None else None
        >>> is_built(pm) == (unavailable() is None)
        True
    """
    if _triton(pm.device):  # Triton keeps its own disk cache, not looked into here
        return False
    if unavailable() is not None:
        return False
    var = variant_of(pm)
    if name_of(var) in _kernels:
        return True
    src = source(var)
    return any(_library_path(src, "springs", flags).exists() for flags in FLAG_SETS)


def _function(name: str):
    if name not in _kernels:
        why = unavailable()
        if why:
            raise NativeBuildError(why)
        _kernels[name] = _build(_variants[name])
    return _kernels[name]


# ------------------------------------------------------------------------------ the model side
def _triton(device: torch.device) -> bool:
    """Whether tensors on ``device`` go to the Triton kernel (:mod:`.native_cuda`) rather than the C one."""
    return device.type == "cuda"


def _cells(pm):
    """The :class:`~torchdeform.sim.packed.CellSprings` a kernel makes the stiffness from, or None.

    None on a GPU: the Triton kernel reads an Elastic body's stored springs (faster there than
    summing its cells).
    """
    return None if _triton(pm.device) else getattr(pm, "cell_springs", None)


def unavailable_on(device) -> str | None:
    """Why no spring kernel runs on ``device`` (C on a CPU: :func:`unavailable`; Triton on CUDA), or None."""
    device = torch.device(device)
    if _triton(device):
        return native_cuda.unavailable()
    if device.type != "cpu":
        return f"the spring kernels run on the CPU or CUDA (not {device.type})"
    return unavailable()


def variant_of(pm) -> Variant:
    """The kernel :class:`Variant` of a :class:`~torchdeform.sim.packed.PackedModel`."""
    per = [p is not None and p.shape[-1] != 1 for p in (pm.stiffness, pm.rest_length, pm.damping)]
    damping = 0 if pm.damping is None else (1 if pm.projected else 2)
    gate = bool(damping) and _needs_gate(pm.stiffness, pm.damping)  # as spring_law gates it
    cells = _cells(pm)
    return Variant(
        S=len(pm.offsets),
        dtype=_CTYPE[pm.dtype],
        damping=damping,
        cells=() if cells is None else cells.counts,
        k_per_spring=per[0] and cells is None,
        l0_per_spring=per[1],
        c_per_spring=per[2] and bool(damping),
        gate=gate,
        cuda=_triton(pm.device),
    )


def supports(pm) -> str | None:
    """Why the kernel (C on the CPU, Triton on CUDA) cannot compute this packed model's forces, or None when it can."""
    if pm.law is not None:
        return f"the {type(pm.law).__name__} law runs in inductor's forms"
    if pm.dtype not in _CTYPE:
        return f"the spring kernels take float32 or float64 (the model is {pm.dtype})"
    return unavailable_on(pm.device)


def spring_forces(pm, x: torch.Tensor, v: torch.Tensor, *, name: str | None = None) -> torch.Tensor:
    """:meth:`~torchdeform.sim.packed.PackedModel.spring_forces` by the C kernel: ``(B, 3, P)``.

    No gradient (the kernel is not differentiable). ``name``: the kernel's name from :func:`kernel`
    (default: built or loaded here, which traced code must not do: a compiled step names it
    before tracing).
    """
    name = name or kernel(variant_of(pm))
    k, mu, coff = _stiffness_operands(pm)
    op = native_springs if torch.compiler.is_compiling() else _springs  # see native_springs
    return op(x, v, pm.inside, k, pm.rest_length, pm.damping, pm.offset_table, name, pm.G, mu, coff, pm.plane)


def _stiffness_operands(pm) -> tuple:
    """``(k, mu, cell offsets)`` of a kernel call: the stiffness, or the per-direction factors and the cells."""
    cells = _cells(pm)
    if cells is None:
        return pm.stiffness, None, None
    return cells.factors, cells.mu, cells.offsets


def _cell_args(mu: torch.Tensor | None, coff: torch.Tensor | None, G: int) -> tuple:
    """The trailing arguments of a kernel with stiffness from cells: ``mu`` (past its ``G`` leading zeros), its batch stride, the offsets."""
    if mu is None:
        return ()
    assert coff is not None and mu.is_contiguous()
    return (mu.data_ptr() + G * mu.element_size(), _batch_stride(mu), coff.data_ptr())


def fused_blocker(pm, integrator, *, loads=None) -> str | None:
    """Why :func:`symplectic_step` cannot make this packed step, or None.

    It makes the whole step of :class:`~torchdeform.sim.integrators.SymplecticEuler` for Hooke
    springs, an Elastic body's cell term, gravity, fixed nodes and the global drag; home springs, loads, drags along paths and
    interactions keep the step in torch around the force kernel.
    """
    from .integrators import SymplecticEuler

    if type(integrator) is not SymplecticEuler:
        return f"the {integrator.name} integrator"
    extras = [
        name
        for name, present in (
            ("home springs", pm.k_home is not None),
            ("loads", bool(pm.loads) or loads is not None),
            ("drags", bool(pm.drags)),
            ("interactions", bool(pm.interactions)),
        )
        if present
    ]
    if extras:
        return ", ".join(extras)
    if _triton(pm.device) and pm.volume is not None:
        return "an Elastic body's cell term (on CUDA the fused kernel makes the springs only)"
    return supports(pm)


def symplectic_step(pm, x: torch.Tensor, v: torch.Tensor, dt: float, *, name: str | None = None):
    """One :class:`~torchdeform.sim.integrators.SymplecticEuler` step of a packed model in one kernel.

    The springs, ``a = (f + m g) / m`` (zero at fixed nodes), ``v' = v + dt a``, ``x' = x + dt v'``
    and the global drag ``v' exp(-decay dt)``, in one pass over the nodes (:func:`fused_blocker`
    says where it applies). No gradient. ``name``: the kernel's name from :func:`kernel` (a variant
    with ``update``, and ``cell_term`` for an Elastic body's cell term), default built or loaded here.

    Returns:
        ``(x', v')``, each ``(B, 3, P)``.
    """
    name = name or kernel(fused_variant(pm))
    im, ms, scalars = _update_operands(pm, dt)
    if _triton(x.device):
        return native_cuda.symplectic_step(pm, x, v, _variants[name], im=im, ms=ms, scalars=scalars)
    x, v = x.contiguous(), v.contiguous()
    xo, vo = torch.empty_like(x), torch.empty_like(v)
    k, mu, coff = _stiffness_operands(pm)
    _call(
        name,
        x,
        v,
        xo,
        pm.inside,
        k,
        pm.rest_length,
        pm.damping,
        pm.offset_table,
        pm.G,
        vo.data_ptr(),
        im.data_ptr(),
        ms.data_ptr(),
        _batch_stride(im),
        *scalars,
        *_cell_term_args(pm, _variants[name]),
        *_cell_args(mu, coff, pm.G),
    )
    return xo, vo


def _update_operands(pm, dt: float) -> tuple:
    """``(1/m, m, (g0, g1, g2, dt, keep))`` of a fused step: the masses with one batch size, the scalars.

    ``keep`` is the global drag's ``exp(-decay dt)``. The gravity is read once per model (on a GPU
    a read is a wait for the device).
    """
    im, ms = pm.inv_mass.contiguous(), pm.mass.contiguous()
    if im.shape[0] != ms.shape[0]:
        im, ms = (t.expand(max(im.shape[0], ms.shape[0]), *t.shape[1:]).contiguous() for t in (im, ms))
    g = pm.__dict__.get("_gravity_values")
    if g is None:
        g = (0.0, 0.0, 0.0) if pm.gravity is None else tuple(float(a) for a in pm.gravity.flatten())
        pm.__dict__["_gravity_values"] = g
    keep = 1.0 if pm.decay is None else math.exp(-pm.decay * dt)
    return im, ms, (*g, dt, keep)


def fused_variant(pm) -> Variant:
    """The :class:`Variant` of :func:`symplectic_step` for a packed model (its cell term made in the kernel)."""
    return dataclasses.replace(variant_of(pm), update=True, cell_term=pm.volume is not None)


def _cell_term_args(pm, var: Variant) -> tuple:
    """The trailing arguments of a kernel making the cell term: kappa, shear, their batch stride, s_H, s_D, 1/(4h), h^2/4."""
    if not var.cell_term:
        return ()
    kappa, shear = pm.volume_kappa, pm.volume_shear.expand_as(pm.volume_kappa)
    assert kappa.is_contiguous() and shear.is_contiguous()
    row = pm.grid.shape[2] + 2
    h = float(pm.volume_h)
    return (kappa.data_ptr(), shear.data_ptr(), _batch_stride(kappa), row, pm.G - row - 1, 1.0 / (4.0 * h), h * h / 4.0)


def _batch_stride(p: torch.Tensor) -> int:
    return 0 if p.shape[0] == 1 else p.stride(0)


def _call(name: str, x, v, out, inside, k, l0, c, offsets, G: int, *update) -> None:
    """Run kernel ``name`` into ``out`` (the spring operands made contiguous; ``update``: the fused step's)."""
    x, v, inside, k, l0 = (t.contiguous() for t in (x, v, inside, k, l0))
    c = k if c is None else c.contiguous()  # not read by an undamped kernel
    B, _, P = x.shape
    ptr = [t.data_ptr() for t in (x, v, out, inside, k, l0, c, offsets)]
    if _function(name)(
        *ptr,
        B,
        P,
        G,
        _batch_stride(k),
        _batch_stride(l0),
        _batch_stride(c),
        torch.get_num_threads(),
        torch.finfo(x.dtype).tiny,
        *update,
    ):
        raise MemoryError(f"native spring kernel {name}: a thread could not allocate its ring of springs")


def _springs(
    x: torch.Tensor,
    v: torch.Tensor,
    inside: torch.Tensor,
    k: torch.Tensor,
    l0: torch.Tensor,
    c: torch.Tensor | None,
    offsets: torch.Tensor,
    kernel: str,
    G: int,
    mu: torch.Tensor | None = None,
    coff: torch.Tensor | None = None,
    plane: int = 0,
) -> torch.Tensor:
    """Spring forces ``(B, 3, P)`` by the loaded C kernel named ``kernel`` (see :func:`spring_forces`).

    ``mu``, ``coff``: a kernel with stiffness from cells (``k`` then holds the per-direction factors).
    CUDA tensors go to the Triton kernel (:mod:`.native_cuda`), which walks ``plane`` nodes at a time.
    """
    if _triton(x.device):
        return native_cuda.spring_forces(x, v, inside, k, l0, c, offsets, _variants[kernel], G=G, plane=plane or G)
    x = x.contiguous()
    f = torch.empty_like(x)
    _call(kernel, x, v, f, inside, k, l0, c, offsets, G, *_cell_args(mu, coff, G))
    return f


#: :func:`_springs` as the custom op ``torchdeform::native_springs``, for compiled graphs. Eager code
#: calls :func:`_springs` itself: the op's first call imports ``torch._dynamo`` (1.2 s of every run
#: that does not compile, on 2 cores), which the plain function never needs.
native_springs = torch.library.custom_op("torchdeform::native_springs", mutates_args=())(_springs)


@native_springs.register_fake
def _(x, v, inside, k, l0, c, offsets, kernel, G, mu=None, coff=None, plane=0):
    return torch.empty_like(x)
