"""Volume deformation through an offset texture (Knoche 2008), on ``grid_sample``.

A deformation model only has to deliver node offsets; a CT/MR volume is then deformed by
sampling it at the material point that moved to each output point.

Conventions (fixed here, once)
------------------------------
* A volume is ``(D, H, W)`` or ``(B, C, D, H, W)``; voxel ``(i, j, k)`` has its centre at
  *voxel coordinate* ``(i, j, k)``; the volume occupies ``[-0.5, D - 0.5] x ...``.
* Node offsets are ``(B, 3, n_d, n_h, n_w)`` (or ``(3, n_d, n_h, n_w)``) **in voxel units of
  the volume**, channel ``c`` along axis ``c`` of ``(D, H, W)``.
* The node grid spans the volume corner to corner: node ``a`` of ``n`` along an axis of ``N``
  voxels sits at voxel coordinate ``a (N - 1) / (n - 1)`` (``align_corners=True``). Node values
  are then exact at voxels when ``n - 1`` divides ``N - 1`` (65 voxels, 9 nodes).
* **A -> B rule.** If material moves from A to B (offset ``d = B - A``), B shows A's content:
  the output is ``V(p - u)``; a uniform offset ``d`` gives ``V'(p) = V(p - d)``.
* Volume samples use trilinear interpolation with ``padding="border"`` (clamp to the edge
  voxels, default) or ``"zeros"`` (a constant ``fill`` outside, interpolated across the last
  half voxel like ``scipy.ndimage.map_coordinates(..., mode="grid-constant")``).
* :func:`to_grid_sample` is the one place where ``(D, H, W)`` voxel coordinates become
  ``grid_sample``'s normalised ``(x, y, z) = (W, H, D)`` order.

Modes of :func:`warp`
---------------------
``deform``  ``V(X)`` with ``X = p - u(p)`` (first order: the forward node offsets used as the
            inverse map), or with ``inverse_iters > 0`` the fixed-point inverse
            ``X <- p - u(X)`` (solves ``X + u(X) = p``; converges while ``|grad u| < 1``).
``carve``   values unchanged, material removed: ``fill + m (V(p) - fill)`` with the
            material ``m(X)`` (default: 1 inside the node grid's box) carried by the offsets
            (Radetzky's fragmentation: texture coordinates follow the geometry).
``knoche``  Knoche's shader: offsets looked up cell-centred (node ``a`` at voxel coordinate
            ``(a + 0.5) N / n - 0.5``) with border clamping, volume sampled at ``p - u`` with
            border clamping. Knoche's texture offsets are ``u / N`` in texture units. His
            ``mod`` wrap at ``uvw.y = 1`` is replaced by clamping.

Example:
    >>> import torch
    >>> from torchdeform.volume import warp
    >>> vol = torch.arange(4 * 5 * 6, dtype=torch.float32).reshape(4, 5, 6)
    >>> offsets = torch.zeros(3, 3, 3, 3)
    >>> offsets[2] = 1.0                       # everything moves one voxel along +W
    >>> out = warp(vol, offsets)
    >>> torch.allclose(out[:, :, 1:], vol[:, :, :-1])
    True
"""

from __future__ import annotations

import math
import warnings

import torch
import torch.nn.functional as F

from ..errors import ConfigError

MODES = ("deform", "carve", "knoche")
ORDERS = ("linear", "bspline")
PADDINGS = ("border", "zeros")


class FoldingWarning(UserWarning):
    """The deformation folds: ``det(I + grad u) <= 0`` somewhere (``fraction`` of samples)."""


# ------------------------------------------------------------------ checks
def _tensor(value, key: str, kinds: str, expected: str) -> torch.Tensor:
    """``value`` as a tensor; a non-tensor must convert to a numpy array of dtype kind in ``kinds``."""
    if torch.is_tensor(value):
        return value
    try:
        import numpy as np

        arr = np.asarray(value)
        if arr.dtype.kind not in kinds:
            raise TypeError
        return torch.as_tensor(arr)
    except (TypeError, ValueError, RuntimeError):
        raise ConfigError(key, expected, got=type(value).__name__) from None


def as_volume(volume, *, key: str = "volume", dtype=None) -> tuple[torch.Tensor, bool]:
    """``volume`` as a floating ``(B, C, D, H, W)`` tensor, and whether it was given as ``(D, H, W)``.

    Raises:
        ConfigError: not 3-D or 5-D, not a real numeric dtype, an empty axis, or NaN/inf voxels.
    """
    volume = _tensor(volume, key, "biuf", "a numeric array (D, H, W) or (B, C, D, H, W)")
    if volume.is_complex():
        raise ConfigError(key, "a real-valued array", got=str(volume.dtype))
    if volume.dim() not in (3, 5):
        raise ConfigError(key, "an array of shape (D, H, W) or (B, C, D, H, W)", got=tuple(volume.shape))
    if min(volume.shape) < 1:
        raise ConfigError(key, "a non-empty array", got=tuple(volume.shape))
    plain = volume.dim() == 3
    if not volume.is_floating_point():
        volume = volume.to(dtype or torch.float32)
    elif dtype is not None:
        volume = volume.to(dtype)
    lo, hi = torch.aminmax(volume)  # one pass, NaN propagates (10x cheaper than isfinite().all())
    if not bool(torch.isfinite(lo) & torch.isfinite(hi)):  # one host sync
        bad = int((~torch.isfinite(volume)).sum())
        raise ConfigError(key, "finite voxel values (no NaN or inf)", got=f"{bad} non-finite voxels")
    return (volume[None, None] if plain else volume), plain


def as_offsets(offsets, *, volume_shape=None, key: str = "offsets", dtype=None, device=None) -> torch.Tensor:
    """Node offsets as a floating ``(B, 3, n_d, n_h, n_w)`` tensor (voxel units).

    Raises:
        ConfigError: wrong shape (channel count other than 3), a node count < 1, a non-float
            dtype that cannot be converted, non-finite values.
    """
    offsets = _tensor(offsets, key, "iuf", "a numeric array of shape (3, n_d, n_h, n_w)")
    if offsets.is_complex() or offsets.dtype == torch.bool:
        raise ConfigError(key, "a real-valued array of node offsets in voxels", got=str(offsets.dtype))
    if offsets.dim() == 4:
        offsets = offsets[None]
    if offsets.dim() != 5 or offsets.shape[1] != 3 or min(offsets.shape) < 1:
        raise ConfigError(
            key,
            "an array of shape (3, n_d, n_h, n_w) or (B, 3, n_d, n_h, n_w), channel order (D, H, W)",
            got=tuple(offsets.shape),
        )
    if not offsets.is_floating_point():
        offsets = offsets.to(torch.float32)
    offsets = offsets.to(dtype=dtype or offsets.dtype, device=device)
    if not bool(torch.isfinite(offsets).all()):
        raise ConfigError(key, "finite offsets (no NaN or inf)", got="non-finite values", show_got=True)
    if volume_shape is not None:
        for n, N, ax in zip(offsets.shape[2:], volume_shape, "DHW"):
            if n > N:
                raise ConfigError(
                    key,
                    f"a node grid no finer than the volume {tuple(volume_shape)} (axis {ax}: {n} nodes for {N} voxels)",
                    got=tuple(offsets.shape[1:]),
                )
    return offsets


def _choice(value, key, allowed):
    if value not in allowed:
        raise ConfigError(key, "one of " + ", ".join(allowed), got=value)
    return value


# ------------------------------------------------------------------ coordinates
def to_grid_sample(points: torch.Tensor, shape, *, align_corners: bool = True) -> torch.Tensor:
    """Voxel coordinates ``(B, 3, ...)`` in ``(D, H, W)`` order -> ``grid_sample`` grid ``(B, ..., 3)``.

    The one axis flip of the library: the last axis of the result is ``(x, y, z) = (W, H, D)``,
    normalised to ``[-1, 1]`` for ``align_corners`` (True: ``2 p / (N - 1) - 1``; False:
    ``(2 p + 1) / N - 1``). An axis of size 1 maps to 0.

    Args:
        points: ``(B, 3, *S)`` coordinates in voxels (channel c along axis c of ``shape``).
        shape: ``(D, H, W)`` of the sampled array.
        align_corners: ``grid_sample``'s convention (True: voxel centres ``0`` and ``N - 1`` map
            to -1 and 1; False: the outer voxel faces do).

    Returns:
        ``(B, *S, 3)``.

    Example:
        >>> import torch
        >>> from torchdeform.volume import to_grid_sample
        >>> p = torch.tensor([[0.0, 2.0, 4.0]]).view(1, 3, 1)
        >>> to_grid_sample(p, (3, 3, 5)).view(3).tolist()
        [1.0, 1.0, -1.0]
    """
    parts = []
    for c in (2, 1, 0):
        n = int(shape[c])
        p = points[:, c]
        if align_corners:
            parts.append(p * (2.0 / (n - 1)) - 1.0 if n > 1 else p * 0.0)
        else:
            parts.append((2.0 * p + 1.0) / n - 1.0)
    return torch.stack(parts, dim=-1)


def identity_points(shape, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Voxel coordinates of every voxel centre, ``(1, 3, D, H, W)``."""
    axes = [torch.arange(int(n), dtype=dtype, device=device) for n in shape]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"))[None]


def sample(
    volume: torch.Tensor,
    points: torch.Tensor,
    *,
    padding: str = "border",
    fill: float = 0.0,
    align_corners: bool = True,
) -> torch.Tensor:
    """Trilinear samples of ``volume`` at voxel coordinates.

    Args:
        volume: ``(B, C, D, H, W)``.
        points: ``(B or 1, 3, *S)`` voxel coordinates (``*S`` = one to three axes).
        padding: ``"border"`` (clamp to the edge voxels) or ``"zeros"`` (``fill`` outside).
        fill: the value outside the volume with ``padding="zeros"``.
        align_corners: as in :func:`to_grid_sample` (voxel centres at the voxel coordinates: True).

    Returns:
        ``(B, C, *S)``.
    """
    B = max(volume.shape[0], points.shape[0])
    S = points.shape[2:]
    pts = points.reshape(points.shape[0], 3, -1, 1, 1) if len(S) != 3 else points
    grid = to_grid_sample(pts, volume.shape[2:], align_corners=align_corners)
    vol = volume - fill if (padding == "zeros" and fill) else volume
    out = F.grid_sample(
        vol.expand(B, *vol.shape[1:]),
        grid.expand(B, *grid.shape[1:]),
        mode="bilinear",
        padding_mode="border" if padding == "border" else "zeros",
        align_corners=align_corners,
    )
    if padding == "zeros" and fill:
        out = out + fill
    return out.reshape(B, volume.shape[1], *S)


# ------------------------------------------------------------------ offset texture
def _bspline(t: torch.Tensor) -> torch.Tensor:
    """Cubic B-spline kernel."""
    a = t.abs()
    return torch.where(a < 1, (4 - 6 * a**2 + 3 * a**3) / 6, torch.where(a < 2, (2 - a) ** 3 / 6, torch.zeros_like(a)))


def axis_weights_at(pos, n: int, N: int, *, order: str = "linear", cell_centred: bool = False) -> torch.Tensor:
    """Interpolation weights ``(P, n)`` of ``n`` nodes at voxel positions ``pos`` ``(P,)`` along one axis.

    The axis has ``N`` voxels. ``linear``: hat functions with node ``a`` at voxel
    ``a (N - 1) / (n - 1)`` (or, with ``cell_centred``, at ``(a + 0.5) N / n - 0.5``), positions
    clamped to the node range; ``bspline``: cubic B-spline with the nodes as control points, the
    ends extended by repeating the edge nodes (smoother; reproduces constants, does not
    interpolate). Rows sum to 1; differentiable in ``pos``.
    """
    if n == 1:
        return torch.ones(pos.shape[0], 1, dtype=pos.dtype, device=pos.device)
    t = (pos + 0.5) * n / N - 0.5 if cell_centred else pos * ((n - 1) / max(N - 1, 1))
    t = t.clamp(0, n - 1)
    if order == "linear":
        a = torch.arange(n, dtype=pos.dtype, device=pos.device)
        return (1 - (t[:, None] - a[None]).abs()).clamp(min=0)
    ext = torch.arange(-2, n + 2, dtype=pos.dtype, device=pos.device)
    w = _bspline(t[:, None] - ext[None])  # (P, n + 4)
    Wm = torch.zeros(pos.shape[0], n, dtype=pos.dtype, device=pos.device)
    return Wm.index_add(1, ext.clamp(0, n - 1).long(), w)


def axis_weights(
    n: int, N: int, *, order: str = "linear", dtype=torch.float64, device=None, cell_centred: bool = False
) -> torch.Tensor:
    """Interpolation matrix ``(N, n)`` from ``n`` nodes to the ``N`` voxel centres of an axis.

    :func:`axis_weights_at` at ``0, 1, ..., N - 1``.
    """
    pos = torch.arange(N, dtype=torch.float64)
    return axis_weights_at(pos, n, N, order=order, cell_centred=cell_centred).to(dtype=dtype, device=device)


def offset_texture(offsets, volume_shape, *, order: str = "linear") -> torch.Tensor:
    """Dense displacement field at every voxel from node offsets (Knoche's offset texture).

    Args:
        offsets: ``(B, 3, n_d, n_h, n_w)`` or ``(3, n_d, n_h, n_w)``, voxel units.
        volume_shape: ``(D, H, W)``.
        order: ``"linear"`` (trilinear, ``align_corners=True``) or ``"bspline"`` (cubic B-spline).

    Returns:
        ``(B, 3, D, H, W)``, same dtype as ``offsets``.

    Example:
        >>> import torch
        >>> from torchdeform.volume import offset_texture
        >>> u = offset_texture(torch.ones(3, 2, 2, 2), (4, 5, 6))
        >>> tuple(u.shape), float(u.min()), float(u.max())
        ((1, 3, 4, 5, 6), 1.0, 1.0)
    """
    volume_shape = tuple(int(n) for n in volume_shape)
    u = as_offsets(offsets, volume_shape=volume_shape)
    _choice(order, "order", ORDERS)
    if order == "linear" and all(n > 1 for n in u.shape[2:]) and all(N > 1 for N in volume_shape):
        return F.interpolate(u, size=volume_shape, mode="trilinear", align_corners=True)
    Wd, Wh, Ww = (
        axis_weights(n, N, order=order, dtype=u.dtype, device=u.device) for n, N in zip(u.shape[2:], volume_shape)
    )
    return torch.einsum("bcijk,Di,Hj,Wk->bcDHW", u, Wd, Wh, Ww)


class DisplacementField:
    """A continuous displacement field ``u(p)`` (voxel units) defined by node offsets.

    Args:
        offsets: ``(B, 3, n_d, n_h, n_w)`` or ``(3, n_d, n_h, n_w)``, voxel units.
        volume_shape: ``(D, H, W)`` of the volume the nodes span.
        order: ``"linear"`` or ``"bspline"``.
        cell_centred: Knoche's node placement (see the module docstring).

    Example:
        >>> import torch
        >>> from torchdeform.volume import DisplacementField
        >>> f = DisplacementField(torch.ones(3, 3, 3, 3), (9, 9, 9))
        >>> f.at(torch.zeros(1, 3, 2)).tolist()
        [[[1.0, 1.0], [1.0, 1.0], [1.0, 1.0]]]
    """

    def __init__(self, offsets, volume_shape, *, order: str = "linear", cell_centred: bool = False):
        self.volume_shape = tuple(int(n) for n in volume_shape)
        self.nodes = as_offsets(offsets, volume_shape=self.volume_shape)
        self.order = _choice(order, "order", ORDERS)
        self.cell_centred = cell_centred
        self._dense = None

    @property
    def node_shape(self) -> tuple:
        """The node grid ``(n_d, n_h, n_w)``."""
        return tuple(self.nodes.shape[2:])

    def dense(self) -> torch.Tensor:
        """The field at every voxel centre, ``(B, 3, D, H, W)`` (built once)."""
        if self._dense is None:
            if self.cell_centred:
                W = [
                    axis_weights(
                        n, N, order="linear", dtype=self.nodes.dtype, device=self.nodes.device, cell_centred=True
                    )
                    for n, N in zip(self.node_shape, self.volume_shape)
                ]
                self._dense = torch.einsum("bcijk,Di,Hj,Wk->bcDHW", self.nodes, *W)
            else:
                self._dense = offset_texture(self.nodes, self.volume_shape, order=self.order)
        return self._dense

    def to_node_coords(self, points: torch.Tensor) -> torch.Tensor:
        """Voxel coordinates ``(B, 3, ...)`` -> node coordinates (fractional node indices)."""
        # per channel with Python numbers: no host-to-device copy (this runs per chunk of a render)
        pairs = zip(self.node_shape, self.volume_shape)
        if self.cell_centred:
            return torch.stack([(points[:, c] + 0.5) * n / N - 0.5 for c, (n, N) in enumerate(pairs)], 1)
        return torch.stack([points[:, c] * (n - 1) / max(N - 1, 1) for c, (n, N) in enumerate(pairs)], 1)

    def at(self, points: torch.Tensor) -> torch.Tensor:
        """``u`` at voxel coordinates ``points`` ``(B or 1, 3, *S)``; returns ``(B, 3, *S)``.

        Linear fields are evaluated exactly from the nodes (clamped to the node box); B-spline
        fields trilinearly from :meth:`dense`.
        """
        if self.order == "bspline" and not self.cell_centred:
            return sample(self.dense(), points, padding="border")
        q = self.to_node_coords(points)
        return sample(self.nodes, q, padding="border")


# ------------------------------------------------------------------ inverse map
def inverse_points(field: DisplacementField, points: torch.Tensor, *, iters: int = 0, tol: float = 1e-4):
    """Material points ``X`` that moved to ``points``: ``X + u(X) = p``.

    ``iters = 0``: first order, ``X = p - u(p)``. Otherwise the fixed-point iteration
    ``X <- p - u(X)`` from ``X = p - u(p)``, at most ``iters`` more times, stopping once the
    largest update is below ``tol`` voxels. One field lookup per iteration.

    Args:
        field: the :class:`DisplacementField`.
        points: ``(B or 1, 3, *S)`` voxel coordinates.
        iters: at most this many fixed-point iterations after the first-order guess (0: none).
        tol: stop once the largest update is below this (voxels).

    Returns:
        ``(X (B, 3, *S), info)`` with ``info = {"iterations": k, "update": last max update}``.
    """
    if isinstance(iters, bool) or int(iters) != iters or iters < 0:
        raise ConfigError("inverse_iters", "an integer >= 0", got=iters)
    if not (tol >= 0):
        raise ConfigError("tol", "a number >= 0 (voxels)", got=tol)
    X = points - field.at(points)
    k, update = 0, None
    while k < int(iters):
        k += 1
        X_new = points - field.at(X)
        update = float((X_new - X).detach().abs().max()) if X.numel() else 0.0
        X = X_new
        if update <= tol:
            break
    return X, {"iterations": k, "update": update}


def inverse_residual(field: DisplacementField, X: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``|X + u(X) - p|`` per point (voxels), ``(B, *S)``: how far ``X`` is from the true inverse."""
    return (X + field.at(X) - points).norm(dim=1)


# ------------------------------------------------------------------ folding
def jacobian_determinant(field: torch.Tensor, *, spacing=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """``det(I + grad u)`` of a dense displacement field by finite differences.

    Central differences inside, one-sided at the faces (``torch.gradient``), as VoxelMorph's
    ``jacobian_determinant``.

    Args:
        field: ``(B, 3, D, H, W)`` displacement (same unit as ``spacing``), each axis >= 2.
        spacing: sample spacing along ``(D, H, W)``.

    Returns:
        ``(B, D, H, W)``.

    Example:
        >>> import torch
        >>> from torchdeform.volume import identity_points, jacobian_determinant
        >>> A = torch.tensor([[0.1, 0, 0], [0, -0.2, 0], [0, 0, 0.0]])
        >>> p = identity_points((4, 4, 4))
        >>> u = torch.einsum("ij,bjdhw->bidhw", A, p)
        >>> round(float(jacobian_determinant(u).mean()), 6)
        0.88
    """
    if field.dim() != 5 or field.shape[1] != 3 or min(field.shape[2:]) < 2:
        raise ConfigError("field", "a displacement field (B, 3, D, H, W) with every axis >= 2", got=tuple(field.shape))
    grads = [torch.gradient(field[:, c], spacing=tuple(float(s) for s in spacing), dim=(1, 2, 3)) for c in range(3)]
    J = [[grads[i][j] + (1.0 if i == j else 0.0) for j in range(3)] for i in range(3)]
    return (
        J[0][0] * (J[1][1] * J[2][2] - J[1][2] * J[2][1])
        - J[0][1] * (J[1][0] * J[2][2] - J[1][2] * J[2][0])
        + J[0][2] * (J[1][0] * J[2][1] - J[1][1] * J[2][0])
    )


def folding_fraction(offsets, volume_shape, *, order: str = "linear", samples=None) -> float:
    """Fraction of samples with ``det(I + grad u) <= 0`` (folded).

    The field is evaluated on a lattice of ``samples`` points per axis spanning the volume
    (default: the volume's own size, at most ``4 (n - 1) + 1`` per axis, enough for a
    trilinear field), and differentiated there.

    Example:
        >>> import torch
        >>> from torchdeform.volume import folding_fraction
        >>> folding_fraction(torch.zeros(3, 5, 5, 5), (32, 32, 32))
        0.0
    """
    volume_shape = tuple(int(n) for n in volume_shape)
    u = as_offsets(offsets, volume_shape=volume_shape)
    if samples is None:
        samples = tuple(max(2, min(N, 4 * (n - 1) + 1)) for n, N in zip(u.shape[2:], volume_shape))
    samples = tuple(int(s) for s in samples)
    dense = (
        offset_texture(u, samples, order=order)
        if samples != volume_shape
        else offset_texture(u, volume_shape, order=order)
    )
    spacing = tuple((N - 1) / max(s - 1, 1) for N, s in zip(volume_shape, samples))
    det = jacobian_determinant(dense.detach(), spacing=spacing)
    return float((det <= 0).double().mean())


def check_folding(offsets, volume_shape, *, order: str = "linear", stacklevel: int = 2) -> float:
    """:func:`folding_fraction`, warning (:class:`FoldingWarning`) when it is above zero."""
    frac = folding_fraction(offsets, volume_shape, order=order)
    if frac > 0:
        warnings.warn(
            f"the deformation folds: det(I + grad u) <= 0 at {frac:.2%} of the samples; node offsets "
            f"above about half the node spacing turn the volume inside out there",
            FoldingWarning,
            stacklevel=stacklevel + 1,
        )
    return frac


# ------------------------------------------------------------------ warping
def sample_points(
    offsets,
    volume_shape,
    *,
    mode: str = "deform",
    inverse_iters: int = 0,
    tol: float = 1e-4,
    order: str = "linear",
    points: torch.Tensor | None = None,
):
    """Where :func:`warp` samples the volume: ``(X (B, 3, *S), info)``.

    ``points`` (voxel coordinates ``(B or 1, 3, *S)``) default to every voxel centre.
    """
    _choice(mode, "mode", MODES)
    volume_shape = tuple(int(n) for n in volume_shape)
    field = DisplacementField(offsets, volume_shape, order=order, cell_centred=(mode == "knoche"))
    if points is None:
        points = identity_points(volume_shape, dtype=field.nodes.dtype, device=field.nodes.device)
    iters = 0 if mode == "knoche" else inverse_iters
    X, info = inverse_points(field, points, iters=iters, tol=tol)
    return X, info


def warp(
    volume,
    offsets,
    *,
    mode: str = "deform",
    inverse_iters: int = 0,
    tol: float = 1e-4,
    order: str = "linear",
    padding: str = "border",
    fill: float = 0.0,
    material=None,
    check: bool = True,
    return_info: bool = False,
):
    """Deform a volume by node offsets.

    Args:
        volume: ``(D, H, W)`` or ``(B, C, D, H, W)``; integer volumes become float32.
        offsets: ``(3, n_d, n_h, n_w)`` or ``(B, 3, n_d, n_h, n_w)`` in voxels, channels ``(D, H, W)``.
        mode: ``"deform"``, ``"carve"`` or ``"knoche"`` (module docstring).
        inverse_iters: fixed-point inverse iterations (``deform`` and ``carve``; 0: first order).
        tol: stopping tolerance of the inverse iterations, in voxels.
        order: ``"linear"`` or ``"bspline"`` offset texture (``deform``, ``carve``).
        padding: ``"border"`` or ``"zeros"`` (value ``fill`` outside the volume).
        fill: background value (also what ``carve`` leaves where material was removed).
        material: ``carve`` only: material present (1) or removed (0), at the nodes
            ``(n_d, n_h, n_w)`` or the voxels ``(D, H, W)`` (optionally with leading ``(B, 1)``);
            default: 1 inside the node box, 0 outside.
        check: warn (:class:`FoldingWarning`) when the deformation folds.
        return_info: also return ``{"iterations", "update", "folded"}``.

    Returns:
        the warped volume, in the layout of ``volume`` (``(B, C, D, H, W)`` when the offsets
        carry a batch ``B > 1`` for a plain volume).

    Raises:
        ConfigError: bad shapes, dtypes, NaN voxels, node grids finer than the volume, unknown
            mode, order or padding.

    Example:
        >>> import torch
        >>> from torchdeform.volume import warp
        >>> vol = torch.zeros(9, 9, 9); vol[2, 4, 4] = 1.0
        >>> offsets = torch.zeros(3, 3, 3, 3); offsets[0] = 3.0      # move 3 voxels along +D
        >>> int(warp(vol, offsets).argmax()) == 5 * 81 + 4 * 9 + 4
        True
    """
    vol, plain = as_volume(volume)
    _choice(mode, "mode", MODES)
    _choice(padding, "padding", PADDINGS)
    _choice(order, "order", ORDERS)
    if not isinstance(fill, (int, float)) or not math.isfinite(fill):
        raise ConfigError("fill", "a finite number", got=fill)
    shape = tuple(vol.shape[2:])
    u = as_offsets(offsets, volume_shape=shape, dtype=vol.dtype, device=vol.device)
    if vol.shape[0] != u.shape[0] and 1 not in (vol.shape[0], u.shape[0]):
        raise ConfigError("offsets", f"a batch of 1 or {vol.shape[0]} (the volume's)", got=u.shape[0])
    folded = check_folding(u, shape, order=order, stacklevel=2) if check and mode != "carve" else None
    if not bool(u.any()) and not u.requires_grad:
        # zero offsets: X = p exactly; read the voxels instead of interpolating (exact identity)
        inverse_points(
            DisplacementField(u, shape, order=order),
            identity_points((1, 1, 1), dtype=u.dtype, device=u.device),
            iters=inverse_iters,
            tol=tol,
        )
        B = max(vol.shape[0], u.shape[0])
        out = vol.expand(B, *vol.shape[1:]).clone()
        if mode == "carve" and material is not None:
            out = fill + _material(material, u, shape, vol) * (out - fill)
        if plain and out.shape[:2] == (1, 1):
            out = out[0, 0]
        return (out, {"iterations": 0, "update": 0.0, "folded": folded}) if return_info else out
    X, info = sample_points(u, shape, mode=mode, inverse_iters=inverse_iters, tol=tol, order=order)
    if mode == "carve":
        m = _material(material, u, shape, vol)
        keep = sample(m, X, padding="zeros")
        out = fill + keep * (vol - fill)
    else:
        out = sample(vol, X, padding="border" if mode == "knoche" else padding, fill=fill)
    if plain and out.shape[:2] == (1, 1):
        out = out[0, 0]
    if return_info:
        return out, dict(info, folded=folded)
    return out


def _material(material, u, shape, vol) -> torch.Tensor:
    """Material as ``(B, 1, *grid)`` in voxel coordinates of the volume (upsampled from nodes)."""
    if material is None:
        return torch.ones(1, 1, *shape, dtype=vol.dtype, device=vol.device)
    m = torch.as_tensor(material).to(dtype=vol.dtype, device=vol.device)
    if m.dim() == 3:
        m = m[None, None]
    node_shape = tuple(u.shape[2:])
    if m.dim() != 5 or m.shape[1] != 1 or tuple(m.shape[2:]) not in (node_shape, shape):
        raise ConfigError(
            "material", f"an array of the node grid {node_shape} or the volume {shape}", got=tuple(m.shape)
        )
    if not bool(torch.isfinite(m).all()):
        raise ConfigError("material", "finite values in [0, 1]", got="non-finite values", show_got=True)
    if tuple(m.shape[2:]) == node_shape and node_shape != shape:
        m = offset_texture(m.expand(m.shape[0], 3, *node_shape), shape)[:, :1]
    return m


def node_offsets(x: torch.Tensor, X: torch.Tensor, spacing, volume_shape) -> torch.Tensor:
    """Node displacements of a simulation (metres) -> node offsets in voxels of a volume.

    The volume is taken to fill the node grid's bounding box: node ``(0, 0, 0)`` at voxel
    centre ``(0, 0, 0)``, the last node at the last voxel centre.

    Args:
        x: deformed positions ``(B, 3, n_d, n_h, n_w)`` (m).
        X: rest positions ``(B, 3, n_d, n_h, n_w)`` (m).
        spacing: node spacing ``(sd, sh, sw)`` (m).
        volume_shape: ``(D, H, W)`` voxels.

    Returns:
        ``(B, 3, n_d, n_h, n_w)`` offsets in voxels.
    """
    n = x.shape[2:]
    scale = [(N - 1) / (s * max(k - 1, 1)) for N, s, k in zip(volume_shape, spacing, n)]
    return torch.stack([(x[:, c] - X[:, c]) * scale[c] for c in range(3)], 1)  # no host-to-device copy


__all__ = [
    "FoldingWarning",
    "DisplacementField",
    "MODES",
    "as_volume",
    "as_offsets",
    "to_grid_sample",
    "identity_points",
    "sample",
    "axis_weights",
    "axis_weights_at",
    "offset_texture",
    "inverse_points",
    "inverse_residual",
    "jacobian_determinant",
    "folding_fraction",
    "check_folding",
    "sample_points",
    "warp",
    "node_offsets",
]
