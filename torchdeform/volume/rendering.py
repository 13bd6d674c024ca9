"""Volume rendering: :func:`render`, compositing along rays, through a displacement field or a cut.

Rendering modes
---------------
``dvr``      emission-absorption, front to back: ``alpha_k = 1 - exp(-sigma(v_k) dt_k)``,
             ``C += T alpha_k c_k``, ``T *= 1 - alpha_k``; ``dt`` (voxels) is in the formula, so
             the result does not depend on the number of samples (a homogeneous slab of length
             ``L`` transmits exactly ``exp(-sigma L)``). Early termination once every ray's
             transmittance is below ``stop``. Output ``(B, 4, h, w)``: premultiplied RGB and alpha.
             ``sigma`` and ``c`` come from a transfer function (:mod:`.transfer`).
``mip``      maximum intensity along each ray, ``(B, 1, h, w)`` in volume units.
``average``  length-weighted mean along each ray, ``(B, 1, h, w)``.

Views (:mod:`.cameras`): an axis view (``"d"``, ``"-h"``, ...) marches slab by slab, ``n``
slabs of ``dt`` voxels; an :class:`~torchdeform.volume.OrbitCamera` marches perspective rays
clipped to the volume's box in segments of ``step`` voxels (the last one shorter). Voxels are
unit cubes (coordinates in voxels, the volume occupies ``[-0.5, N - 0.5]`` per axis), so
``sigma`` is an extinction per voxel length.

:func:`render` checks its arguments once and resolves them into a
:class:`~torchdeform.volume.plan.RenderPlan`; the axis-view path, the orbit path (here) and the
fast path (:mod:`.fastpath`) each take the plan.

Through the displacement field: with ``offsets`` (node offsets in voxels, see
:mod:`torchdeform.volume`) each sample point ``p`` reads the volume at ``p - u(p)`` (or the
fixed-point inverse); for an axis view ``u`` on a slab is two small matrix products of the
node grid (separable interpolation weights), so the warped volume is never built.
Everything is differentiable with respect to the offsets and the transfer function.

Through a cut (``pieces=[(offsets_1, material_1), ...]``): a body cut into pieces has one
displacement field per piece (each extended over the whole node grid, e.g. by
:func:`torchdeform.topology.cut_pieces`) and a material region per piece in rest space (a node
mask, read by trilinear interpolation). A sample ``p`` is mapped back through every piece,
``X_i = p - u_i(p)``; it shows ``V(X_i)`` of the piece whose material ``m_i(X_i)`` is largest,
provided that is at least 1/2 (inside that piece's region), and ``fill`` otherwise. So the gap
between two sides that moved apart is empty, where one interpolated field would smear the
tissue across it. With every offset zero and pieces that cover the body, this is the plain render.

Example:
    >>> import torch
    >>> from torchdeform.volume import render
    >>> vol = torch.zeros(8, 8, 8); vol[4, 4, 4] = 1000.0
    >>> img = render(vol, mode="mip", view="d")
    >>> tuple(img.shape), float(img.max())
    ((1, 1, 8, 8), 1000.0)
"""

from __future__ import annotations

import math

import torch

from ..errors import ConfigError
from .cameras import OrbitCamera, _check_size
from .deform import DisplacementField, as_offsets, as_volume, axis_weights_at, sample
from .fastpath import _fast_supported, _render_axis_fast
from .plan import AXIS_VIEWS, ENGINES, RENDER_MODES, RenderPlan
from .transfer import get_tf

__all__ = ["render"]


class _Accumulator:
    """Front-to-back compositing state of one render (its plan's mode) for images ``shape`` ``(h, w)``."""

    def __init__(self, plan: RenderPlan, shape):
        mode, dtype, device, B = plan.mode, plan.dtype, plan.device, plan.batch
        self.mode, self.tf, self.lo, self.hi, self.table = mode, plan.tf, plan.lo, plan.hi, plan.table
        if mode == "dvr":
            self.C = torch.zeros(B, 3, *shape, dtype=dtype, device=device)
            self.T = torch.ones(B, *shape, dtype=dtype, device=device)
        elif mode == "mip":
            self.M = torch.full((B, *shape), -math.inf, dtype=dtype, device=device)
        else:
            self.S = torch.zeros(B, *shape, dtype=dtype, device=device)
            self.L = torch.zeros(B, *shape, dtype=dtype, device=device)

    def add(self, v: torch.Tensor, dt: torch.Tensor):
        """Samples ``v`` ``(B, S, *img)`` front to back with segment lengths ``dt`` (broadcastable)."""
        if self.mode == "dvr":
            e = self.tf.lookup(v, self.lo, self.hi, table=self.table)  # (4, B, S, *img)
            alpha = -torch.expm1(-e[3] * dt)
            trans = torch.cumprod(1 - alpha, dim=1)
            excl = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], 1) * self.T.unsqueeze(1)
            w = excl * alpha  # (B, S, *img)
            self.C = self.C + torch.einsum("cbs...,bs...->bc...", e[:3], w)
            self.T = self.T * trans[:, -1]
        elif self.mode == "mip":
            vv = (
                v if not torch.is_tensor(dt) or dt.dim() == 0 else torch.where(dt > 0, v, torch.full_like(v, -math.inf))
            )
            self.M = torch.maximum(self.M, vv.amax(dim=1))
        else:
            dtb = dt.expand_as(v) if torch.is_tensor(dt) else torch.full_like(v, dt)
            self.S = self.S + (v * dtb).sum(1)
            self.L = self.L + dtb.sum(1)

    def done(self, stop: float) -> bool:
        """Whether every ray's transmittance is below ``stop`` (``dvr``; one host sync per call)."""
        return self.mode == "dvr" and stop > 0 and float(self.T.detach().max()) < stop

    def result(self, background=0.0) -> torch.Tensor:
        """The image; ``mip``/``average`` pixels whose ray misses the volume get ``background``.

        ``background``: a number, or a 0-d tensor of the image's dtype and device (no host sync).
        """
        if self.mode == "dvr":
            return torch.cat([self.C, (1 - self.T).unsqueeze(1)], 1)
        if self.mode == "mip":
            return torch.where(torch.isfinite(self.M), self.M, background).unsqueeze(1)
        hit = self.L > 0
        return torch.where(hit, self.S / self.L.clamp(min=1e-12), background).unsqueeze(1)


def render(
    volume,
    *,
    tf=None,
    mode: str = "dvr",
    view="d",
    offsets=None,
    warp_mode: str = "deform",
    inverse_iters: int = 0,
    order: str = "linear",
    padding: str = "border",
    fill: float = 0.0,
    step: float = 1.0,
    size=None,
    stop: float = 1e-3,
    chunk_points: int = 1 << 20,
    window=None,
    engine: str = "grid_sample",
    pieces=None,
) -> torch.Tensor:
    """Render a volume, optionally through a displacement field (without building the warped volume).

    Args:
        volume: ``(D, H, W)`` or ``(B, C=1, D, H, W)``.
        tf: :class:`TransferFunction`, a preset name or a file (``dvr`` only; default ``"grey"``).
        mode: ``"dvr"``, ``"mip"`` or ``"average"``.
        view: an axis view (``"d"``, ``"-h"``, ...) or an :class:`OrbitCamera`.
        offsets: node offsets ``(3, n_d, n_h, n_w)`` / ``(B, 3, ...)`` in voxels, or None.
        warp_mode: ``"deform"`` or ``"knoche"`` lookup of the offsets.
        inverse_iters: fixed-point inverse iterations (0: first order ``p - u(p)``).
        order: ``"linear"`` or ``"bspline"`` offset texture.
        padding: volume lookups outside the volume, ``"border"`` or ``"zeros"`` (as
            :func:`~torchdeform.volume.warp`).
        fill: the value outside the volume with ``padding="zeros"``.
        step: sample spacing along the rays in voxels (axis views: rounded so that a whole
            number of samples covers the volume).
        size: image ``(h, w)`` for axis views (default: the volume's own two axes).
        stop: early ray termination once every transmittance is below this (0: never).
        chunk_points: samples per batch of slabs (memory and cache use).
        window: unused by the renderer; accepted for symmetry with :func:`to_image`.
        engine: how an axis view through ``offsets`` samples the volume: ``"grid_sample"``
            (default; differentiable, every option), ``"eager"`` or ``"compiled"`` (the fast
            path: trilinear by hand from the node grid and the flat volume, compositing fused
            per chunk of slabs, skipping chunks that can only read fully transparent values;
            ``"compiled"`` runs it under ``torch.compile``, compiling once per shape and view,
            20-60 s, with the eager code as fallback). The fast path takes batch 1, linear
            offsets, ``inverse_iters=0`` and no gradient; anything else uses ``grid_sample``.
            Same image either way up to rounding. ``"native"``: the C ray marcher
            (:mod:`~torchdeform.volume.native_march`; ``dvr`` of a float32 CPU volume, directly or
            through linear offsets, ``padding="border"``, no gradient; else a ConfigError saying
            why); ``"auto"``: native where it applies, else ``grid_sample``. The kernel stops each
            ray at ``stop`` (the others a chunk of slabs once every ray is below it): alpha within
            ``stop`` of theirs, the same with ``stop=0`` up to float32 rounding.
        pieces: instead of ``offsets``, a cut body: a list of ``(offsets, material)`` pairs, one per
            piece, with node offsets ``(3, n_d, n_h, n_w)`` / ``(B, 3, ...)`` in voxels (extended
            over the whole node grid) and the piece's rest-space material ``(n_d, n_h, n_w)`` (1 at
            its nodes, 0 elsewhere); samples outside every piece read ``fill`` (module docstring,
            "Through a cut"). Always the ``grid_sample`` engine.

    Returns:
        ``dvr``: ``(B, 4, h, w)`` premultiplied RGB + alpha; ``mip``/``average``: ``(B, 1, h, w)``.

    Example:
        >>> import math
        >>> import torch
        >>> from torchdeform.volume import TransferFunction, render
        >>> vol = torch.full((10, 4, 4), 500.0)
        >>> tf = TransferFunction([0, 1000], [[1, 1, 1], [1, 1, 1]], [0.1, 0.1])
        >>> img = render(vol, tf=tf, mode="dvr", view="d", stop=0)
        >>> abs(float(img[0, 3, 0, 0]) - (1 - math.exp(-0.1 * 10))) < 1e-5
        True

        Through node offsets: a bright voxel moved 2 voxels along +W shows up 2 pixels further on.

        >>> vol = torch.zeros(16, 16, 16); vol[8, 8, 4] = 1000.0
        >>> offsets = torch.zeros(3, 3, 3, 3); offsets[2] = 2.0
        >>> img = render(vol, mode="mip", view="d", offsets=offsets)
        >>> divmod(int(img[0, 0].argmax()), 16)
        (8, 6)
    """
    vol, _ = as_volume(volume)
    _check_options(vol, mode, warp_mode, step, engine)
    size = _check_size(size)
    shape = tuple(vol.shape[2:])
    knoche = warp_mode == "knoche"
    field = None
    if pieces is not None:
        if offsets is not None:
            raise ConfigError("pieces", "either offsets or pieces, not both", got="both given", show_got=True)
        pieces = _Pieces(pieces, shape, order, knoche, vol.dtype, vol.device)
        if vol.shape[0] != pieces.batch and 1 not in (vol.shape[0], pieces.batch):
            raise ConfigError("pieces", f"offsets with a batch of 1 or {vol.shape[0]} (the volume's)", got=pieces.batch)
        if knoche:
            inverse_iters, padding = 0, "border"
    if offsets is not None:
        u = as_offsets(offsets, volume_shape=shape, dtype=vol.dtype, device=vol.device)
        if vol.shape[0] != u.shape[0] and 1 not in (vol.shape[0], u.shape[0]):
            raise ConfigError("offsets", f"a batch of 1 or {vol.shape[0]} (the volume's)", got=u.shape[0])
        field = DisplacementField(u, shape, order=order, cell_centred=knoche)
        if knoche:
            inverse_iters, padding = 0, "border"
    tf = get_tf(tf) if mode == "dvr" else None
    lo = hi = table = None
    if tf is not None:
        lo, hi = tf.range(volume=vol)
        table = tf.table(dtype=vol.dtype, device=vol.device)
    B = vol.shape[0] if field is None else max(vol.shape[0], field.nodes.shape[0])
    B = B if pieces is None else max(B, pieces.batch)
    plan = RenderPlan(
        volume=vol,
        mode=mode,
        view=view,
        batch=B,
        field=field,
        pieces=pieces,
        tf=tf,
        lo=lo,
        hi=hi,
        table=table,
        inverse_iters=inverse_iters,
        padding=padding,
        fill=fill,
        step=step,
        size=size,
        stop=stop,
        chunk_points=chunk_points,
        engine=engine,
    )
    if isinstance(view, OrbitCamera):
        return _render_orbit(plan)
    if view not in AXIS_VIEWS:
        raise ConfigError("view", "an axis (" + ", ".join(AXIS_VIEWS) + ") or an OrbitCamera", got=view)
    if engine in ("native", "auto"):
        from . import native_march  # a C build on first use: only when asked for

        why = native_march.axis_blocker(plan)
        if why is None:
            return native_march.render_axis_native(plan).to(plan.dtype)
        if engine == "native":
            raise ConfigError("engine", "a plan the C kernel renders (or engine='auto')", got=f"native: {why}")
        return _render_axis(plan)
    if engine != "grid_sample" and _fast_supported(plan):
        return _render_axis_fast(plan)[0]
    return _render_axis(plan)


def _check_options(vol: torch.Tensor, mode: str, warp_mode: str, step, engine: str) -> None:
    """:func:`render`'s checks of the volume's channels and the named options (one ConfigError each)."""
    if vol.shape[1] != 1:
        raise ConfigError("volume", "a single-channel volume (B, 1, D, H, W)", got=tuple(vol.shape))
    if mode not in RENDER_MODES:
        raise ConfigError("mode", "one of " + ", ".join(RENDER_MODES), got=mode)
    if warp_mode not in ("deform", "knoche"):
        raise ConfigError("warp_mode", '"deform" or "knoche" when rendering through offsets', got=warp_mode)
    if not (isinstance(step, (int, float)) and step > 0 and math.isfinite(step)):
        raise ConfigError("step", "a positive number of voxels", got=step)
    if engine not in ENGINES:
        raise ConfigError("engine", "one of " + ", ".join(ENGINES), got=engine)


def _render_axis(plan: RenderPlan) -> torch.Tensor:
    """An axis view on ``grid_sample``: chunks of slabs front to back (voxel slices where samples sit on voxels)."""
    vol, field, pieces = plan.volume, plan.field, plan.pieces
    shape, dtype, device, B = plan.shape, plan.dtype, plan.device, plan.batch
    lat = plan.axis_samples()
    axis, others, n, dt, img_shape, pix = lat.axis, lat.others, lat.n, lat.dt, lat.img_shape, lat.pix
    N = shape[axis]
    native = plan.size is None or tuple(plan.size) == tuple(shape[a] for a in others)
    direct = field is None and pieces is None and native and n == N  # samples on voxel centres: read slices
    acc = _Accumulator(plan, img_shape)
    S = plan.slabs_per_chunk(img_shape[0] * img_shape[1])
    dt_t = torch.full((), dt, dtype=dtype, device=device)  # made once: no host-to-device copy per chunk
    if field is not None:
        nodes = field.nodes  # (Bn, 3, nd, nh, nw)
        cc = field.cell_centred
        Wb = axis_weights_at(pix[0], field.node_shape[others[0]], shape[others[0]], order=field.order, cell_centred=cc)
        Wc = axis_weights_at(pix[1], field.node_shape[others[1]], shape[others[1]], order=field.order, cell_centred=cc)
        perm = [0, 1, 2 + axis, 2 + others[0], 2 + others[1]]
        nodes_p = nodes.permute(*perm)  # (Bn, 3, na, nb, nc)
        ctr = torch.einsum("bcaij,Hi,Wj->bcaHW", nodes_p, Wb, Wc) if field.order == "linear" else None
    for start in range(0, n, S):
        kk = torch.arange(start, min(n, start + S), dtype=dtype, device=device)  # slab indices, front to back
        kk = (n - 1) - kk if lat.reverse else kk
        z = -0.5 + (kk + 0.5) * dt  # (S,)
        if direct:
            idx = kk.long()
            v = vol.index_select(2 + axis, idx).movedim(2 + axis, 2)[:, 0]  # (B, S, img...)
            v = v.expand(B, *v.shape[1:])
        else:
            # sample points p in (D, H, W) voxel coordinates, (1, 3, S, h, w)
            grids = torch.meshgrid(z, pix[0], pix[1], indexing="ij")
            p = [None, None, None]
            p[axis], p[others[0]], p[others[1]] = grids
            p = torch.stack(p)[None]
            if field is not None:
                Wa = axis_weights_at(z, field.node_shape[axis], N, order=field.order, cell_centred=cc)
                if ctr is not None:  # linear: reuse the (b, c) products
                    u_perm = torch.einsum("sa,bcaHW->bcsHW", Wa, ctr)
                else:
                    u_perm = torch.einsum("sa,bcaij,Hi,Wj->bcsHW", Wa, nodes_p, Wb, Wc)
                X = p - u_perm
                if plan.inverse_iters:
                    X, _ = _refine(field, p, X, plan.inverse_iters)
            else:
                X = p
            if pieces is not None:
                v = pieces.sample(p, plan)[:, 0]
            else:
                v = sample(vol, X, padding=plan.padding, fill=plan.fill)[:, 0]  # (B, S, h, w)
        acc.add(v, dt_t)
        if acc.done(plan.stop):
            break
    return acc.result()


def _refine(field, p, X, iters, tol=1e-4):
    info = None
    for _ in range(int(iters)):
        X_new = p - field.at(X)
        upd = float((X_new - X).detach().abs().max())
        X = X_new
        if upd <= tol:
            break
    return X, info


def _render_orbit(plan: RenderPlan) -> torch.Tensor:
    """An :class:`~torchdeform.volume.OrbitCamera` view: rays clipped to the volume's box, segments of ``step`` voxels."""
    vol, field, pieces, step = plan.volume, plan.field, plan.pieces, plan.step
    shape, dtype, device = plan.shape, plan.dtype, plan.device
    eye, d = plan.view.rays(shape, dtype=dtype, device=device)  # (3,), (3, h, w)
    lo_b = torch.full((3, 1, 1), -0.5, dtype=dtype, device=device)
    hi_b = torch.tensor([n - 0.5 for n in shape], dtype=dtype, device=device).view(3, 1, 1)
    inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0 = (lo_b - eye.view(3, 1, 1)) * inv
    t1 = (hi_b - eye.view(3, 1, 1)) * inv
    t_near = torch.minimum(t0, t1).amax(0).clamp(min=0)
    t_far = torch.maximum(t0, t1).amin(0)
    length = (t_far - t_near).clamp(min=0)  # (h, w)
    n = math.ceil(float(length.max()) / step) if float(length.max()) > 0 else 0
    img = tuple(d.shape[1:])
    acc = _Accumulator(plan, img)
    S = plan.slabs_per_chunk(img[0] * img[1])
    for start in range(0, n, S):
        k = torch.arange(start, min(n, start + S), dtype=dtype, device=device).view(-1, 1, 1)
        seg0 = k * step
        seglen = (length.unsqueeze(0) - seg0).clamp(0, step)  # (S, h, w)
        t = t_near.unsqueeze(0) + seg0 + seglen / 2
        p = (eye.view(3, 1, 1, 1) + d.unsqueeze(1) * t.unsqueeze(0))[None]  # (1, 3, S, h, w)
        X = p
        if field is not None:
            X = p - field.at(p)
            if plan.inverse_iters:
                X, _ = _refine(field, p, X, plan.inverse_iters)
        if pieces is not None:
            v = pieces.sample(p, plan)[:, 0]
        else:
            v = sample(vol, X, padding=plan.padding, fill=plan.fill)[:, 0]
        acc.add(v, seglen.unsqueeze(0))
        if acc.done(plan.stop):
            break
    return acc.result(vol.detach().amin())  # background of the rays that miss: a 0-d tensor, no host sync


class _Pieces:
    """The pieces of a cut body for :func:`render`: per piece a displacement field and its rest-space material.

    Args:
        pieces: a non-empty list of ``(offsets, material)``: node offsets ``(3, n_d, n_h, n_w)`` or
            ``(B, 3, ...)`` (voxels) and material ``(n_d, n_h, n_w)`` in ``[0, 1]``, on one node grid.
        shape: the volume ``(D, H, W)``.
        order, cell_centred: as :class:`~torchdeform.volume.DisplacementField`.
    """

    #: A sample belongs to a piece when its material there is at least this (1/2, less rounding).
    INSIDE = 0.5 - 1e-6

    def __init__(self, pieces, shape, order, cell_centred, dtype, device):
        expected = "a non-empty list of (offsets (3, n_d, n_h, n_w), material (n_d, n_h, n_w)) pairs"
        if (
            not isinstance(pieces, (list, tuple))
            or not pieces
            or not all(isinstance(pc, (list, tuple)) and len(pc) == 2 for pc in pieces)
        ):
            raise ConfigError("pieces", expected, got=type(pieces).__name__)
        self.fields, self.materials = [], []
        for u, m in pieces:
            u = as_offsets(u, volume_shape=shape, key="pieces offsets", dtype=dtype, device=device)
            field = DisplacementField(u, shape, order=order, cell_centred=cell_centred)
            m = torch.as_tensor(m).to(dtype=dtype, device=device)
            if tuple(m.shape) != field.node_shape:
                raise ConfigError(
                    "pieces material", f"a node array {field.node_shape} (the offsets' node grid)", got=tuple(m.shape)
                )
            if not bool(torch.isfinite(m).all()) or bool((m < 0).any()) or bool((m > 1).any()):
                raise ConfigError("pieces material", "values in [0, 1]", got="values outside", show_got=True)
            if self.fields and field.node_shape != self.fields[0].node_shape:
                raise ConfigError(
                    "pieces offsets", f"one node grid {self.fields[0].node_shape} for every piece", got=field.node_shape
                )
            self.fields.append(field)
            self.materials.append(m[None, None])
        batches = {f.nodes.shape[0] for f in self.fields} - {1}
        if len(batches) > 1:
            raise ConfigError("pieces offsets", "one batch size (or 1) for every piece", got=sorted(batches))
        self.batch = batches.pop() if batches else 1

    def sample(self, p, plan: RenderPlan):
        """Samples ``(B, 1, *S)`` of the plan's volume at the points ``p`` ``(1, 3, *S)`` through the pieces.

        Its ``padding`` outside the volume, its ``fill`` in the gaps, its ``inverse_iters``.
        """
        vol, padding, fill, inverse_iters = plan.volume, plan.padding, plan.fill, plan.inverse_iters
        best_w = best_v = None
        for field, m in zip(self.fields, self.materials):
            X = p - field.at(p)
            if inverse_iters:
                X, _ = _refine(field, p, X, inverse_iters)
            w = sample(m, field.to_node_coords(X), padding="border")  # (B, 1, *S)
            v = sample(vol, X, padding=padding, fill=fill)
            if best_w is None:
                best_w, best_v = w, v
            else:
                better = w > best_w
                best_v = torch.where(better, v, best_v)
                best_w = torch.maximum(w, best_w)
        return torch.where(best_w >= self.INSIDE, best_v, torch.full_like(best_v, fill))
