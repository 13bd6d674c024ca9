r"""The volume term of an :class:`~torchdeform.sim.material.Elastic` body as a C kernel on the packed layout.

:func:`~torchdeform.sim.material.volume_forces` makes the per-cell force of
:math:`W_c = \tfrac12 \kappa_c h^3 (J_c - 1)^2` in about thirty passes of torch operations over the
cells (13 ms per call at 64^3 in float32 on 2 cores, five times a native spring step). Here it is one
loop over the nodes of the packed layout (:mod:`~torchdeform.sim.packed`), built by the system C
compiler as the spring kernel is (:func:`~torchdeform.sim.native.load_library`, same flags and disk
cache).

The loop: a cell is stored at its lowest corner ``i`` (its corners are ``i + a`` for the 8 offsets
``a = a_D s_D + a_H s_H + a_W``, ``s_D = (H+2)(W+2)``, ``s_H = W+2``, ``a_* in {0, 1}``) with
``kappa_i`` its modulus (0 where there is no cell: the halo, the last layer of each axis, cells
outside the body). For each block of :data:`~torchdeform.sim.native.BLOCK_NODES` nodes one
``omp simd`` loop makes the cells of the block: ``F`` from the four edge differences per axis,
``J = det F``, ``cof F`` and ``Q = (h^2 / 4) kappa (J - 1) cof F`` (9 values), kept in a per-thread
ring; a second loop gives each node the forces of its 8 cells,
``f_k = -sum_cells sum_j Q_kj s_j`` (``s_j = +1`` where the node is the cell's upper corner along
``j``, else ``-1``), which is :func:`~torchdeform.sim.material.volume_forces` up to rounding. A
cell is made once per thread; a thread first makes the cells of the ``G`` nodes before its range.

Example:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.sim import native_volume
    >>> from torchdeform.sim.packed import PackedModel
    >>> pm = PackedModel(td.Model(td.Grid((4, 5, 6), spacing=0.01, topology=26), td.Elastic(5e3, 0.45), mass=1e-3))
    >>> x = pm.X + 1e-4 * torch.randn_like(pm.X)
    >>> f = native_volume.volume_forces(pm, x) if native_volume.supports(pm) is None else pm.volume_forces(x, impl="torch")
    >>> bool(torch.allclose(f, pm.volume_forces(x, impl="torch"), atol=1e-6))
    True
"""

from __future__ import annotations

import ctypes
import functools

import torch

from . import native

__all__ = ["source", "supports", "volume_forces", "native_volume", "kernel"]


def source(dtype: str) -> str:
    """C source of ``volume(x, out, kappa, B, P, sH, sD, G, kb, nt, a, b)`` for ``dtype`` (``"float"``/``"double"``).

    ``x, out``: ``(B, 3, P)``; ``kappa``: ``(Bk, P)`` per cell at its lowest corner, batch stride
    ``kb`` (0 when shared); ``a = 1 / (4 h)``, ``b = h^2 / 4``. ``out`` gets the forces in the core
    range ``[G, P - G)`` and zero outside. Returns 0, or 1 when a thread could not allocate its ring.

    Examples:
        >>> src = source("double")
        >>> "volume(" in src, src.count("#pragma omp simd")
        (True, 2)
    """
    T = dtype
    lines = [
        "/* torchdeform volume term (Elastic), packed layout */",
        *native.preamble(T),
        f"static __attribute__((noinline)) int core(const {T}* restrict X, {T}* restrict F, const {T}* restrict K,",
        f"    const {T}* restrict MU,",
        f"    int64_t P, int64_t sH, int64_t sD, int64_t G, int64_t lo, int64_t hi, {T} a, {T} b) {{",
        f"  const {T} *X0 = X, *X1 = X + P, *X2 = X + 2 * P;",
        f"  {T} *F0 = F, *F1 = F + P, *F2 = F + 2 * P;",
        "  int64_t R = BLK;",
        "  while (R < G + 2 * BLK) R <<= 1;",
        "  const int64_t RS = R + BLK, M = R - 1;           /* 9 rings of Q, BLK mirrored at each end */",
        f"  {T}* restrict Q = ring(9 * RS);",
        "  if (!Q) return 1;",
        "  const int64_t base = lo - G > 0 ? lo - G : 0;",
        "  for (int64_t i0 = base; i0 < hi; i0 += BLK) {",
        "    const int64_t n = hi - i0 < BLK ? hi - i0 : BLK, p0 = (i0 - base) & M;",
        "    #pragma omp simd",
        "    for (int64_t k = 0; k < n; k++) {                /* the cells at the nodes of the block */",
        "      const int64_t i = i0 + k;",
    ]
    w = lines.append
    native.cell_lines(w, T, "      ", kappa="K", shear="MU", a="a", b="b")
    w("    }")
    w("    if (p0 == 0) {                                   /* the ring's first block, mirrored past its end */")
    w(f"      for (int r = 0; r < 9; r++) memcpy(Q + r * RS + R, Q + r * RS, n * sizeof({T}));")
    w("    }")
    w("    if (i0 + n <= lo) continue;                       /* warm-up: cells only */")
    w("    const int64_t k0 = lo > i0 ? lo - i0 : 0;")
    native.cell_ring_lines(w, "    ")
    w("    #pragma omp simd")
    w("    for (int64_t k = k0; k < n; k++) {               /* each node: its 8 cells */")
    w("      const int64_t i = i0 + k;")
    w(f"      {T} f0 = 0, f1 = 0, f2 = 0;")
    native.cell_gather_lines(w, "      ")
    w("      F0[i] = f0; F1[i] = f1; F2[i] = f2;")
    w("    }")
    w("  }")
    w("  return 0;")
    w("}")
    w("")
    w(f"int volume(const {T}* x, {T}* out, const {T}* kappa, const {T}* shear, int64_t B, int64_t P, int64_t sH,")
    w(f"    int64_t sD, int64_t G, int64_t kb, int nt, {T} a, {T} b) {{")
    w("  int failed = 0;")
    w("  for (int64_t bi = 0; bi < B; bi++) {")
    w(f"    const {T}* X = x + bi * 3 * P; {T}* F = out + bi * 3 * P;")
    w(f"    const {T}* K = kappa + bi * kb; const {T}* MU = shear + bi * kb;")
    w("    for (int c = 0; c < 3; c++) {                           /* zero outside the core range */")
    w(f"      memset(F + c * P, 0, G * sizeof({T})); memset(F + c * P + P - G, 0, G * sizeof({T}));")
    w("    }")
    native.core_over(w, "core(X, F, K, MU, P, sH, sD, G, {lo}, {hi}, a, b)")
    w("  }")
    w("  return failed;")
    w("}")
    return "\n".join(lines) + "\n"


@functools.cache
def _function(dtype: str):
    T = ctypes.c_float if dtype == "float" else ctypes.c_double
    i64, ptr = ctypes.c_int64, ctypes.c_void_p
    argtypes = [ptr] * 4 + [i64] * 6 + [ctypes.c_int, T, T]
    return native.entry(source(dtype), "volume", argtypes, what=f"the volume kernel ({dtype})")


def kernel(dtype: torch.dtype) -> str:
    """Build (or load) the kernel for ``dtype`` now; its name as :func:`native_volume` takes it.

    Raises:
        NativeBuildError: no compiler, or the build failed.
    """
    why = native.unavailable()
    if why:
        raise native.NativeBuildError(why)
    name = native.CTYPE_NAMES[dtype]
    _function(name)
    return name


def supports(pm) -> str | None:
    """Why the C kernel cannot make this packed model's volume term, or None when it can."""
    if pm.device.type != "cpu":
        return f"the C kernel runs on the CPU (the model is on {pm.device.type})"
    if pm.dtype not in native.CTYPE_NAMES:
        return f"the C kernel takes float32 or float64 (the model is {pm.dtype})"
    return native.unavailable()


def volume_forces(pm, x: torch.Tensor, *, name: str | None = None) -> torch.Tensor:
    """The volume term's forces of a packed model (N), ``(B, 3, P)``, by the C kernel (no gradient)."""
    name = name or kernel(pm.dtype)
    W = pm.grid.shape[2]
    op = native_volume if torch.compiler.is_compiling() else _volume  # eager: no torch._dynamo import
    return op(x, pm.volume_kappa, pm.volume_shear, name, W + 2, pm.G, pm.volume_h)


def _volume(
    x: torch.Tensor, kappa: torch.Tensor, shear: torch.Tensor, kernel: str, row: int, G: int, h: float
) -> torch.Tensor:
    """Cell-term forces ``(B, 3, P)`` of positions ``x`` ``(B, 3, P)``, per-cell ``kappa`` and ``shear`` ``(Bk, 1, P)``.

    ``row``: ``W + 2`` (the packed layout's row length; a plane is ``row * (H + 2)``, found from ``G``).
    """
    x, kappa = x.contiguous(), kappa.contiguous()
    shear = shear.expand_as(kappa).contiguous()
    out = torch.empty_like(x)
    B, _, P = x.shape
    sH = row
    sD = G - sH - 1
    kb = 0 if kappa.shape[0] == 1 else kappa.stride(0)
    if _function(kernel)(
        x.data_ptr(),
        out.data_ptr(),
        kappa.data_ptr(),
        shear.data_ptr(),
        B,
        P,
        sH,
        sD,
        G,
        kb,
        torch.get_num_threads(),
        1.0 / (4.0 * h),
        h * h / 4.0,
    ):
        raise MemoryError("native volume kernel: a thread could not allocate its ring of cells")
    return out


#: :func:`_volume` as the custom op ``torchdeform::native_volume``, for compiled graphs (eager code
#: calls :func:`_volume`: the op's first call imports ``torch._dynamo``, see ``native.native_springs``).
native_volume = torch.library.custom_op("torchdeform::native_volume", mutates_args=())(_volume)


@native_volume.register_fake
def _(x, kappa, shear, kernel, row, G, h):
    return torch.empty_like(x)
