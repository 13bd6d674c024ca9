"""The fast renderer: axis views through node offsets as plain tensor code, eager or compiled.

:func:`~torchdeform.volume.render` with ``engine="eager"`` or ``"compiled"`` takes this path for
an axis view through ``offsets`` (batch 1, linear offsets, ``inverse_iters=0``, no gradient;
anything else runs on ``grid_sample`` in :mod:`.rendering`). It computes the same samples
written out by hand, per chunk of ``S`` slabs:

1. the offsets on the image plane: the node layers ``(3, n_a, n_b, n_c)`` interpolated over the
   two image axes once per render, ``ctr`` ``(3, n_a, h, w)`` (two small matrix products with
   the separable linear weights); per slab, linear interpolation between two node layers;
2. the sample points ``X = p - u(p)`` [voxels] and trilinear interpolation by hand: eight
   indexed loads from the flat volume ``(D * H * W,)`` (:func:`trilinear_flat`, the numbers of
   ``grid_sample`` with ``align_corners=True``);
3. ``mip`` / ``average``: a running maximum / a length-weighted sum; ``dvr``: the
   transfer-function lookup in the flat table ``(resolution * 4,)`` and front-to-back
   compositing over the ``S`` slabs, unrolled (pointwise per pixel).

Under ``torch.compile`` (``engine="compiled"``) each chunk is one fused loop, compiled once per
shape, view and mode (the chunk's start is a 0-d tensor, so it never recompiles), with the eager
code as fallback and one :class:`RenderCompileWarning`. ``dvr`` skips chunks whose samples can
only read values of zero extinction (the largest voxel of the slabs within the offsets' reach
below the table's first non-zero extinction) and stops once every transmittance is below
``stop``.

Example:
    >>> import torch
    >>> from torchdeform.volume import render
    >>> vol = torch.zeros(16, 16, 16); vol[8, 8, 4] = 1000.0
    >>> offsets = torch.zeros(3, 3, 3, 3); offsets[2] = 2.0
    >>> fast = render(vol, mode="mip", view="d", offsets=offsets, engine="eager")
    >>> ref = render(vol, mode="mip", view="d", offsets=offsets)
    >>> divmod(int(fast[0, 0].argmax()), 16), float((fast - ref).abs().max()) < 1e-3   # float32 rounding
    ((8, 6), True)
"""

from __future__ import annotations

import math

import torch

from .deform import axis_weights_at
from .plan import AXIS_VIEWS, RenderPlan

__all__ = ["trilinear_flat", "RenderCompileWarning", "FAST_INDUCTOR_OPTIONS"]

#: Inductor options of the compiled renderer: indices are clamped in the code, so the bounds
#: asserts go; the realisation thresholds keep the sample coordinates in registers (one fused
#: loop per chunk instead of stored intermediates), as in :mod:`torchdeform.sim.compiled`.
FAST_INDUCTOR_OPTIONS = {
    "assert_indirect_indexing": False,
    "realize_opcount_threshold": 10_000,
    "realize_reads_threshold": 1_000,
    "realize_acc_reads_threshold": 1_000,
}

_FAST_CACHE: dict = {}
_fast_warned: set = set()


class RenderCompileWarning(UserWarning):
    """``torch.compile`` is unavailable or failed for the fast renderer; the eager code runs instead."""


def _axis_terms(pos, N: int, padding: str):
    """Per-axis trilinear terms at voxel coordinates ``pos``.

    Corner indices ``(j0, j1)`` (int32, inside ``[0, N - 1]``) and weights ``(w0, w1)``; ``zeros``
    padding zeroes the weight of a corner outside the volume (grid_sample ``align_corners=True``
    semantics).
    """
    if N == 1:
        zero = torch.zeros_like(pos, dtype=torch.int32)
        if padding == "border":
            one = torch.ones_like(pos)
            return zero, zero, one, one * 0
        inside = ((pos > -1) & (pos < 1)).to(pos.dtype)
        return zero, zero, (1 - pos.abs()).clamp(min=0) * inside, pos * 0
    if padding == "border":
        x = pos.clamp(0, N - 1)
        i0 = x.floor().clamp(max=N - 2)
        f = x - i0
        j0 = i0.to(torch.int32)
        return j0, j0 + 1, 1 - f, f
    x = pos.clamp(-2.0, N + 1.0)
    i0 = x.floor()
    f = x - i0
    w0 = (1 - f) * ((i0 >= 0) & (i0 <= N - 1)).to(pos.dtype)
    w1 = f * ((i0 >= -1) & (i0 <= N - 2)).to(pos.dtype)
    return i0.clamp(0, N - 1).to(torch.int32), (i0 + 1).clamp(0, N - 1).to(torch.int32), w0, w1


def trilinear_flat(v: torch.Tensor, X, shape, *, padding: str = "border", fill: float = 0.0) -> torch.Tensor:
    """Trilinear samples of a volume by hand: eight indexed loads from its flat view.

    The same numbers as :func:`~torchdeform.volume.sample` (``grid_sample``, ``align_corners=True``)
    written as plain tensor code, so that ``torch.compile`` fuses it into one loop with indirect
    loads.

    Args:
        v: the volume's flat contiguous view ``(D * H * W,)``.
        X: three broadcastable tensors, voxel coordinates along ``D``, ``H``, ``W``.
        shape: ``(D, H, W)``.
        padding: ``"border"`` (clamp) or ``"zeros"`` (``fill`` outside).
        fill: the value outside the volume with ``padding="zeros"``.

    Returns:
        the samples, shape of ``X[0] + X[1] + X[2]``.

    Example:
        >>> import torch
        >>> from torchdeform.volume import trilinear_flat
        >>> vol = torch.arange(27.0).reshape(3, 3, 3)
        >>> X = [torch.tensor([1.0]), torch.tensor([0.5]), torch.tensor([2.0])]
        >>> float(trilinear_flat(vol.reshape(-1), X, (3, 3, 3)))
        12.5
    """
    D, H, W = (int(s) for s in shape)
    (a0, a1, wa0, wa1), (b0, b1, wb0, wb1), (c0, c1, wc0, wc1) = (
        _axis_terms(x, N, padding) for x, N in zip(X, (D, H, W))
    )
    rows = [(a0 * (H * W), wa0), (a1 * (H * W), wa1)]
    cols = [(b0 * W, wb0), (b1 * W, wb1)]
    out = 0.0
    for ra, wa in rows:
        for cb, wb in cols:
            base = ra + cb
            pair = wc0 * torch.gather(v, 0, (base + c0).long().reshape(-1)).view(
                (base + c0).shape
            ) + wc1 * torch.gather(v, 0, (base + c1).long().reshape(-1)).view((base + c1).shape)
            out = out + (wa * wb) * pair
    if padding == "zeros" and fill:
        out = out + fill * (1 - (wa0 + wa1) * (wb0 + wb1) * (wc0 + wc1))
    return out


class _FastAxis:
    """Everything fixed about one fast axis-view render; :meth:`chunk` is the per-chunk code."""

    def __init__(self, *, shape, node_shape, view, mode, img_shape, n, dt, S, padding, fill, cell_centred, resolution):
        self.shape, self.node_shape, self.mode = tuple(shape), tuple(node_shape), mode
        self.axis = "dhw".index(view[-1])
        self.reverse = view.startswith("-")
        self.others = [a for a in range(3) if a != self.axis]
        self.img_shape, self.n, self.dt, self.S = tuple(img_shape), int(n), float(dt), int(S)
        self.padding, self.fill, self.cell_centred, self.resolution = padding, float(fill), cell_centred, resolution

    def slab_nodes(self, z):
        """Ray-axis node index ``a0`` (long) and weight ``fa`` of slab coordinates ``z`` ``(S,)``."""
        na, N = self.node_shape[self.axis], self.shape[self.axis]
        if na == 1:
            return torch.zeros_like(z, dtype=torch.long), z * 0
        t = (z + 0.5) * (na / N) - 0.5 if self.cell_centred else z * ((na - 1) / max(N - 1, 1))
        t = t.clamp(0, na - 1)
        a0 = t.floor().clamp(max=na - 2)
        return a0.long(), t - a0

    def chunk(self, v, ctr, pix_b, pix_c, start, state, table, lohi):
        """One chunk of ``S`` slabs starting at ray sample ``start`` (0-d tensor); returns the new state.

        ``ctr`` ``(3, n_axis, h, w)``: the offsets interpolated over the image plane (per ray-axis
        node layer); ``pix_b`` ``(h, 1)``, ``pix_c`` ``(1, w)``: pixel centres in voxels.
        """
        S, n = self.S, self.n
        k = start + torch.arange(S, dtype=v.dtype, device=v.device)  # (S,)
        valid = k < n
        kk = (n - 1 - k) if self.reverse else k
        z = -0.5 + (kk + 0.5) * self.dt
        a0, fa = self.slab_nodes(z)
        na = self.node_shape[self.axis]
        u0 = ctr[:, a0]  # (3, S, h, w)
        u = u0 + fa.view(1, S, 1, 1) * (ctr[:, (a0 + 1).clamp(max=na - 1)] - u0) if na > 1 else u0
        p = [None, None, None]
        p[self.axis], p[self.others[0]], p[self.others[1]] = z.view(S, 1, 1), pix_b, pix_c
        X = [p[c] - u[c] for c in range(3)]
        val = trilinear_flat(v, X, self.shape, padding=self.padding, fill=self.fill)  # (S, h, w)
        vmask = valid.view(S, 1, 1)
        if self.mode == "mip":
            (M,) = state
            return (torch.maximum(M, torch.where(vmask, val, torch.full_like(val, -math.inf)).amax(0)),)
        if self.mode == "average":
            Ssum, L = state
            w = vmask.to(val.dtype) * self.dt
            return (Ssum + (val * w).sum(0), L + w.sum(0).expand_as(L))
        C, T = state
        R = self.resolution
        if torch.compiler.is_compiling():
            # store the samples: every compositing term reads them (inlined, the trilinear
            # interpolation would be recomputed per term)
            from .._compile import realize

            val = realize(val)
        x = ((val - lohi[0]) * ((R - 1) / (lohi[1] - lohi[0]))).clamp(0, R - 1)
        i0 = x.floor().clamp(max=R - 2)
        f = x - i0
        i0 = i0.to(torch.int32) * 4
        e = []
        for ch in range(4):
            lo_e = torch.gather(table, 0, (i0 + ch).long().reshape(-1)).view(i0.shape)
            hi_e = torch.gather(table, 0, (i0 + (ch + 4)).long().reshape(-1)).view(i0.shape)
            e.append(lo_e + f * (hi_e - lo_e))
        tau = e[3] * (self.dt * vmask.to(val.dtype))  # (S, h, w)
        if torch.compiler.is_compiling():
            from .._compile import realize

            tau = realize(tau)
        # front to back through the S slabs, unrolled: pointwise per pixel (no scan), so it fuses
        # into one loop; exp(-acc) is the transmittance since the chunk's start
        acc = torch.zeros_like(T)
        rgb = [C[0], C[1], C[2]]
        for s in range(S):
            w = T * torch.exp(-acc) * -torch.expm1(-tau[s])
            for c in range(3):
                rgb[c] = rgb[c] + w * e[c][s]
            acc = acc + tau[s]
        return (torch.stack(rgb), T * torch.exp(-acc))


def _fast_chunk_fn(spec: _FastAxis, engine: str):
    """The chunk function of ``spec``: eager, or compiled once.

    Cached per spec; eager fallback with one warning line when compilation is unavailable.
    """
    if engine == "eager":
        return spec.chunk
    from .._compile import fresh, inductor_options

    threads = torch.get_num_threads()
    key = tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in sorted(vars(spec).items())) + (threads,)
    fn = _FAST_CACHE.get(key)
    if fn is None:

        def chunk(*args):
            return spec.chunk(*args)

        try:
            # inductor_options: the thread count goes into inductor's cache key (see there)
            compiled = torch.compile(
                fresh(chunk), dynamic=False, options=inductor_options(options=FAST_INDUCTOR_OPTIONS)
            )
        except Exception as e:  # pragma: no cover
            compiled, reason = None, f"{type(e).__name__}: {e}".splitlines()[0]
        state = {"fn": compiled}

        def fn(*args):
            if state["fn"] is not None:
                try:
                    return state["fn"](*args)
                except Exception as e:  # pragma: no cover
                    _warn_fast(f"{type(e).__name__}: {e}".splitlines()[0])
                    state["fn"] = None
            return spec.chunk(*args)

        if compiled is None:  # pragma: no cover
            _warn_fast(reason)
        _FAST_CACHE[key] = fn
    return fn


def _warn_fast(reason: str) -> None:
    import warnings

    if reason not in _fast_warned:
        _fast_warned.add(reason)
        warnings.warn(
            f"torchdeform: torch.compile unavailable for the fast renderer ({reason[:200]}); using the eager code",
            RenderCompileWarning,
            stacklevel=4,
        )


def _fast_supported(plan: RenderPlan) -> bool:
    """Whether ``plan`` can take the fast path: an axis view through linear offsets, batch 1, no gradient."""
    vol, field = plan.volume, plan.field
    return (
        field is not None
        and isinstance(plan.view, str)
        and plan.view in AXIS_VIEWS
        and plan.batch == 1
        and vol.shape[0] == 1
        and field.order == "linear"
        and not plan.inverse_iters
        and vol.dtype in (torch.float32, torch.float64)
        and not (torch.is_grad_enabled() and (vol.requires_grad or field.nodes.requires_grad))
    )


def _transparent_below(table: torch.Tensor, lo: float, hi: float) -> float:
    """Largest value ``t`` such that every value ``<= t`` has zero extinction in ``table``."""
    opaque = (table[:, 3] > 0).to(torch.uint8)
    i, found = torch.stack([opaque.argmax(), opaque.amax().long()]).tolist()  # the first opaque entry; one sync
    if not found:
        return math.inf
    if i == 0:
        return -math.inf
    return lo + (i - 1) * (hi - lo) / (table.shape[0] - 1)


_SLAB_MAX: dict = {}


def _slab_max(v: torch.Tensor, others) -> list:
    """Largest voxel value of each slab across ``others``, as Python floats ``(N,)``.

    On the host, so that the per-chunk tests of :func:`_empty_chunks` never sync with the device.
    Cached for the last volume: a frame loop renders one volume many times; the key includes the
    tensor's device and version counter.
    """
    key = (v.data_ptr(), v.device, v._version, tuple(v.shape), v.dtype, tuple(others))
    if key not in _SLAB_MAX:
        _SLAB_MAX.clear()
        _SLAB_MAX[key] = v.amax(dim=tuple(others)).tolist()
    return _SLAB_MAX[key]


def _empty_chunks(plan: RenderPlan, lat, S: int):
    """``dvr`` empty-space skipping: which chunks can only read values with zero extinction.

    A test ``start -> bool``, or None when no value is transparent (or the mode is not ``dvr``).
    """
    if plan.mode != "dvr":
        return None
    skip_below = _transparent_below(plan.table, plan.lo, plan.hi)
    if not math.isfinite(skip_below):
        return None
    n, dt, N = lat.n, lat.dt, plan.shape[lat.axis]
    slab_max = _slab_max(plan.volume[0, 0], lat.others)  # (N,) floats on the host
    if plan.padding == "zeros":
        fill = torch.tensor(plan.fill, dtype=plan.dtype).item()  # rounded to the volume's dtype, on the host
        slab_max = [max(m, fill) for m in slab_max]
    reach = math.ceil(float(plan.field.nodes[:, lat.axis].abs().max())) + 1  # one host sync per render

    def empty(start: int) -> bool:
        ks = [start, min(n, start + S) - 1]
        zs = [-0.5 + ((n - 1 - k if lat.reverse else k) + 0.5) * dt for k in ks]
        a = min(N - 1, max(0, math.floor(min(zs)) - reach))
        b = max(a + 1, min(N, math.ceil(max(zs)) + reach + 1))
        return a >= b or max(slab_max[a:b]) <= skip_below

    return empty


def _initial_state(mode: str, h: int, w: int, dtype, device) -> tuple:
    """The chunk state before the first slab: ``mip`` ``(M,)``, ``average`` ``(sum, length)``, ``dvr`` ``(C, T)``."""
    if mode == "mip":
        return (torch.full((h, w), -math.inf, dtype=dtype, device=device),)
    if mode == "average":
        return (torch.zeros(h, w, dtype=dtype, device=device), torch.zeros(h, w, dtype=dtype, device=device))
    return (torch.zeros(3, h, w, dtype=dtype, device=device), torch.ones(h, w, dtype=dtype, device=device))


def _final_image(mode: str, state: tuple) -> torch.Tensor:
    """The image ``(1, C, h, w)`` of the last chunk state (rays that read nothing are 0)."""
    if mode == "mip":
        M = state[0]
        return torch.where(torch.isfinite(M), M, torch.zeros_like(M))[None, None]
    if mode == "average":
        Ssum, L = state
        return torch.where(L > 0, Ssum / L.clamp(min=1e-12), torch.zeros_like(Ssum))[None, None]
    C, T = state
    return torch.cat([C, (1 - T)[None]], 0)[None]


def _render_axis_fast(plan: RenderPlan):
    """:func:`~torchdeform.volume.render` of an axis view through the offsets, by :class:`_FastAxis` chunks.

    ``plan.engine`` is ``"eager"`` or ``"compiled"``; returns ``(image, info)`` with ``info`` the chunks
    run/skipped.
    """
    vol, field, mode, table, lo, hi = plan.volume, plan.field, plan.mode, plan.table, plan.lo, plan.hi
    shape, dtype, device = plan.shape, plan.dtype, plan.device
    lat = plan.axis_samples()
    axis, others, n, pix = lat.axis, lat.others, lat.n, lat.pix
    h, w = lat.img_shape
    S = min(n, plan.slabs_per_chunk(h * w), 32 if mode == "dvr" else n)
    cc = field.cell_centred
    Wb = axis_weights_at(pix[0], field.node_shape[others[0]], shape[others[0]], order="linear", cell_centred=cc).to(
        dtype
    )
    Wc = axis_weights_at(pix[1], field.node_shape[others[1]], shape[others[1]], order="linear", cell_centred=cc).to(
        dtype
    )
    nodes_p = field.nodes[0].to(dtype).permute(0, 1 + axis, 1 + others[0], 1 + others[1])
    ctr = torch.einsum("caij,Hi,Wj->caHW", nodes_p, Wb, Wc).contiguous()  # (3, n_axis, h, w)
    spec = _FastAxis(
        shape=shape,
        node_shape=field.node_shape,
        view=plan.view,
        mode=mode,
        img_shape=lat.img_shape,
        n=n,
        dt=lat.dt,
        S=S,
        padding=plan.padding,
        fill=plan.fill,
        cell_centred=cc,
        resolution=table.shape[0] if table is not None else 0,
    )
    fn = _fast_chunk_fn(spec, plan.engine)
    v = vol.reshape(-1).contiguous()
    state = _initial_state(mode, h, w, dtype, device)
    tab = table.reshape(-1).contiguous() if table is not None else torch.zeros(8, dtype=dtype, device=device)
    lohi = torch.tensor([lo if lo is not None else 0.0, hi if hi is not None else 1.0], dtype=dtype, device=device)
    empty = _empty_chunks(plan, lat, S)
    pix_b, pix_c = pix[0].view(h, 1), pix[1].view(1, w)
    run = skipped = 0
    for start in range(0, n, S):
        if empty is not None and empty(start):
            skipped += 1
            continue
        # torch.full: a fill on the device, where torch.tensor would copy from the host and sync
        state = fn(v, ctr, pix_b, pix_c, torch.full((), float(start), dtype=dtype, device=device), state, tab, lohi)
        run += 1
        if mode == "dvr" and plan.stop > 0 and float(state[1].max()) < plan.stop:
            break
    return _final_image(mode, state), {"chunks": run, "skipped": skipped, "slabs_per_chunk": S}
