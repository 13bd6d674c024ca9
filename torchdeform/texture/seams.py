r"""Seams of a block-tiled solid texture: a measure, 3-D and per-slice Poisson blending, histograms.

A solid texture tiled from blocks of ``b`` voxels copied at random exemplar offsets
(REFERENCE.md section 7, Chen & He 2015) is smooth inside each block and jumps on the block
faces: between voxel planes ``k b - 1`` and ``k b`` along each axis, for ``0 < k b < n``.
Blocks start at voxel 0; the last block along an axis may be shorter.

Notation
--------
A volume ``v`` has shape ``(3, D, H, W)`` (RGB first; any channel count ``C`` works). An *edge*
``(i, j = i + e_a)`` joins two 6-neighbours along axis ``a``; it is stored at ``i``, as every
spring of :mod:`torchdeform.sim.springs` is. ``D`` is the grid difference operator of the
6-neighbour :class:`~torchdeform.sim.grid.Grid`, ``(D v)_{ij} = v_j - v_i``, and ``L = D^T D``
the 6-neighbour graph Laplacian (natural Neumann condition on the outer boundary: a boundary
voxel simply has fewer edges). ``F`` is the set of *face edges* (``i`` in plane ``k b - 1``,
``j`` in plane ``k b``), all other in-grid edges are *in-block edges*.

Seam measure
------------
:func:`seam_measure` is

    s = mean_{(i,j) in F, c} |v_j - v_i|  /  mean_{(i,j) not in F, c} |v_j - v_i|

(means over edges and channels; the numerator over the faces normal to one axis if ``axis`` is
given; the denominator over a ``reference`` volume's edges, all of them, if one is given). A
texture without seams has ``s ~ 1``; a tiled smooth texture has ``s >> 1``.

Guided Poisson blending (Perez, Gangnet & Blake 2003)
-----------------------------------------------------
Per channel, find ``u`` minimising

    E(u) = sum_{edges (i,j)} (u_j - u_i - g_ij)^2 = |D u - g|^2

with the guidance ``g = D v`` on in-block edges and, on face edges, either (``guide="mean"``, the
default) the mean of the in-block differences along the same axis just before and just after
the face, ``g_ij = (g_{i-e_a, i} + g_{j, j+e_a}) / 2`` (one side where only one exists, 0 where
none does), a smooth estimate of the gradient the texture would have had, or (``guide="zero"``)
``g_ij = 0``. Writing ``u = v + w`` and ``r = g - D v`` (non-zero only on face edges), the
normal equations are

    L w = D^T r.

The right-hand side sums to zero over each channel (it is in the range of ``D^T``), so the
Neumann problem is consistent. Its solution is unique up to a constant:

- ``region="all"``: every voxel is unknown. Conjugate gradients from ``w = 0`` stay in the range
  of ``L`` (the zero-mean fields), and the final ``w`` is made exactly zero-mean, so each
  channel keeps its mean colour.
- ``region="seams"``: only voxels within ``margin`` voxels of an interior block face are
  unknown (the band ``U``); the others keep their colour (``w = 0``) and act as Dirichlet
  anchors, so ``L_UU w_U = (D^T r)_U`` is symmetric positive definite. Cheaper; the mean colour
  is kept only approximately (a face's correction is antisymmetric about it only in the mean).
  If the band covers every voxel this falls back to ``"all"``.

The solve is matrix free: ``L w`` is one call of the project's one spring operator
(:func:`~torchdeform.sim.springs.accumulate` with the identity spring law, ``-accumulate = D^T D``),
``g`` comes from :func:`~torchdeform.sim.springs.difference` and ``D^T r`` from
:func:`~torchdeform.sim.springs.adjoint`, and the solver is
:func:`~torchdeform.sim.integrators.conjugate_gradient` with each channel (and each slice) a
batch entry, so every one converges independently with its own step lengths.

Chen & He's per-slice blend
---------------------------
:func:`poisson_blend_slices` solves the same problem in 2-D in every slice normal to ``axis``
(forward differences, ``u_xx + u_yy = phi`` with ``phi = div g``, eq. 3 of Chen & He): the slices
become batch entries of a grid of thickness 1 along ``axis``, which has no edges along that
axis. It cannot remove the seams between blocks stacked along ``axis``: no slice contains an
edge across them.

Histogram distance
------------------
:func:`histogram_distance` is the mean over channels of the 1-D Wasserstein-1 (earth mover's)
distance between the two channels' histograms, ``W1 = sum_k |P_k - Q_k| * dx`` for the
cumulative histograms ``P, Q`` over ``bins`` bins of width ``dx`` spanning both volumes' range of
that channel, in colour units (``metric="l1"``: the mean L1 distance ``sum_k |p_k - q_k|``
between the normalised histograms, in ``[0, 2]``).

Shapes: volumes ``(C, D, H, W)``, float32 or float64, any device. Nothing here is learnt, but
everything is plain tensor algebra and therefore differentiable in the volume.
"""

from __future__ import annotations

import torch

from ..errors import ConfigError
from ..sim.grid import Grid
from ..sim.integrators import conjugate_gradient
from ..sim.springs import accumulate, adjoint, difference

__all__ = [
    "seam_measure",
    "seam_jump",
    "poisson_blend_3d",
    "poisson_blend_slices",
    "histogram_distance",
    "face_edges",
    "seam_band",
]

GUIDES = ("mean", "zero")
REGIONS = ("seams", "all")


# ---------------------------------------------------------------------------- helpers
def _check_volume(volume, key="volume") -> torch.Tensor:
    if not torch.is_tensor(volume) or volume.dim() != 4 or not volume.is_floating_point():
        got = tuple(volume.shape) if torch.is_tensor(volume) else type(volume).__name__
        raise ConfigError(key, "a float tensor (C, D, H, W)", got=got)
    return volume


def _blocks(block, ndim: int = 3) -> tuple:
    """Block size per axis; one int for all axes, or one per axis (``None``: no faces on that axis)."""
    sizes = (block,) * ndim if block is None or isinstance(block, int) else tuple(block)
    if len(sizes) != ndim or not all(b is None or (isinstance(b, int) and b >= 1) for b in sizes):
        raise ConfigError("block", f"a block size >= 1 or {ndim} of them", got=block)
    return sizes


def face_edges(shape, block) -> torch.Tensor:
    """Bool ``(3, D, H, W)``: the 6-neighbour edge stored at ``i`` along axis ``a`` crosses a block face.

    Entry ``[a, i]`` is True when ``(i_a + 1) % b_a == 0`` and ``i_a + 1 < n_a``, i.e. the edge joins
    planes ``k b - 1`` and ``k b`` of an interior face. The axis order is that of
    ``Grid(shape, topology=6).directions``.

    Args:
        shape: ``(D, H, W)``.
        block: block size, one int or one per axis (``None``: that axis has no faces).

    Returns:
        bool ``(3, D, H, W)``.

    Example:
        >>> from torchdeform.texture.seams import face_edges
        >>> m = face_edges((4, 1, 1), 2)
        >>> m[0, :, 0, 0].tolist(), int(m[1:].sum())
        ([False, True, False, False], 0)
    """
    shape = tuple(int(n) for n in shape)
    sizes = _blocks(block)
    out = torch.zeros((3,) + shape, dtype=torch.bool)
    for a, (n, b) in enumerate(zip(shape, sizes)):
        if b is None:
            continue
        i = torch.arange(n)
        hit = ((i + 1) % b == 0) & (i + 1 < n)
        out[a] = hit.view([-1 if k == a else 1 for k in range(3)]).expand(shape)
    return out


def seam_band(shape, block, margin: int) -> torch.Tensor:
    """Bool ``(D, H, W)``: voxels within ``margin`` voxels of an interior block face.

    Along axis ``a``, voxel index ``i`` is in the band of the face between planes ``p - 1`` and ``p``
    when ``p - margin <= i < p + margin``; a voxel is in the band if it is along any axis.

    Args:
        shape: ``(D, H, W)``.
        block: block size, one int or one per axis (``None``: that axis has no faces).
        margin: half-width in voxels, >= 1.

    Returns:
        bool ``(D, H, W)``.

    Example:
        >>> from torchdeform.texture.seams import seam_band
        >>> seam_band((8, 1, 1), 4, margin=2)[:, 0, 0].int().tolist()
        [0, 0, 1, 1, 1, 1, 0, 0]
    """
    if not isinstance(margin, int) or margin < 1:
        raise ConfigError("margin", "an integer >= 1 (voxels)", got=margin)
    shape = tuple(int(n) for n in shape)
    sizes = _blocks(block)
    out = torch.zeros(shape, dtype=torch.bool)
    for a, (n, b) in enumerate(zip(shape, sizes)):
        if b is None:
            continue
        i = torch.arange(n)
        near = torch.zeros(n, dtype=torch.bool)
        for p in range(b, n, b):
            near |= (i >= p - margin) & (i < p + margin)
        out |= near.view([-1 if k == a else 1 for k in range(3)])
    return out


def _guidance(x: torch.Tensor, grid: Grid, faces: torch.Tensor, guide: str) -> torch.Tensor:
    """Guidance field ``(B, 3, C, D, H, W)``: ``D x`` in blocks, the face rule on face edges."""
    d = difference(x, grid)  # (B, S=3, C, D, H, W), 0 off the grid
    faces = faces.to(x.device)[None, :, None]  # (1, 3, 1, D, H, W)
    if guide == "zero":
        return torch.where(faces, torch.zeros((), dtype=x.dtype, device=x.device), d)
    inblock = (grid.in_grid_mask(device=x.device)[None, :, None] & ~faces).to(x.dtype)
    d_in = d * inblock
    num = torch.zeros_like(d)
    den = torch.zeros_like(inblock)
    for a in range(3):  # the edges before and after, same axis
        # torch.roll wraps around, but what wraps in is never an in-block edge where it is used:
        # shifting by +1 brings the off-grid edge n-1 to index 0; index n-1 is never a face edge.
        for shift in (1, -1):
            num[:, a] += torch.roll(d_in[:, a], shift, 2 + a)  # spatial dim of axis a in (B, C, D, H, W)
            den[:, a] += torch.roll(inblock[:, a], shift, 2 + a)
    est = num / den.clamp_min(1.0)
    return torch.where(faces, est, d)


def _laplacian(grid: Grid):
    """``w -> L w = D^T D w`` through the one spring operator (identity spring law)."""

    def apply_L(w):
        return -accumulate(grid, lambda s, src, dw: dw, w)

    return apply_L


def _blend(x: torch.Tensor, grid: Grid, block, *, guide, region, margin, iters, tol):
    """Guided Poisson blend of node fields ``x`` ``(B, 1, D, H, W)`` on ``grid``; see the module notes."""
    if guide not in GUIDES:
        raise ConfigError("guide", "one of " + ", ".join(map(repr, GUIDES)), got=guide)
    if region not in REGIONS:
        raise ConfigError("region", "one of " + ", ".join(map(repr, REGIONS)), got=region)
    if not isinstance(iters, int) or iters < 1:
        raise ConfigError("iters", "an integer >= 1", got=iters)
    faces = face_edges(grid.shape, block)
    if not bool(faces.any()):  # one block: nothing to blend
        return x, 0, 0.0
    g = _guidance(x, grid, faces, guide)
    rhs = adjoint(g - difference(x, grid), grid)  # D^T r, (B, 1, D, H, W)
    mask = None
    if region == "seams":
        band = seam_band(grid.shape, block, margin)
        if not bool(band.all()):
            mask = band.to(device=x.device, dtype=x.dtype)[None, None]
    w, used, rel = conjugate_gradient(_laplacian(grid), rhs, mask=mask, iters=iters, tol=tol)
    if mask is None:  # Neumann: fix the mean colour
        w = w - w.mean(dim=(1, 2, 3, 4), keepdim=True)
    return x + w, used, rel


# ---------------------------------------------------------------------------- public API
def seam_measure(
    volume: torch.Tensor, block, *, axis: int | None = None, reference: torch.Tensor | None = None
) -> float:
    """How visible the block seams are: face differences over in-block differences.

    ``s = mean |v_j - v_i|`` over face edges (planes ``k b - 1`` and ``k b``, every interior face along
    every axis, or only those normal to ``axis``) and channels, divided by the mean ``|v_j - v_i|`` over
    the in-block 6-neighbour edges of ``volume`` and channels, or, with ``reference``, over all
    6-neighbour edges of ``reference`` (e.g. the exemplar). About 1 for a seamless texture.

    Args:
        volume: ``(C, D, H, W)`` float.
        block: block size, one int or one per axis.
        axis: 0, 1 or 2 to count only faces normal to that axis; None (default) for all.
        reference: optional ``(C, d, h, w)`` volume whose mean gradient is the denominator.

    Returns:
        the ratio, a Python float.

    Raises:
        ConfigError: when the volume has no interior face (one block), so the ratio is undefined.

    Example:
        >>> import torch
        >>> from torchdeform.texture.seams import seam_measure
        >>> i, j, k = torch.meshgrid(*[torch.arange(8.0)] * 3, indexing="ij")
        >>> v = (i + j + k).expand(3, 8, 8, 8).clone()             # a ramp: every difference is 1
        >>> seam_measure(v, 4)                                     # no seam
        1.0
        >>> v[:, 4:] += 3.0                                        # a step on the face at D = 4
        >>> seam_measure(v, 4, axis=0), seam_measure(v, 4)         # faces normal to D; all faces
        (4.0, 2.0)
    """
    volume = _check_volume(volume)
    faces = face_edges(volume.shape[1:], block)
    if axis is not None:
        if axis not in (0, 1, 2):
            raise ConfigError("axis", "0, 1, 2 or None", got=axis)
        faces[[a for a in range(3) if a != axis]] = False
    if not bool(faces.any()):
        raise ConfigError(
            "block", f"a block size that puts a face inside the volume {tuple(volume.shape[1:])}", got=block
        )
    grid = Grid(tuple(volume.shape[1:]), spacing=1.0, topology=6)
    d = difference(volume[None], grid)[0].abs()  # (3, C, D, H, W)
    faces = faces.to(volume.device)[:, None].expand_as(d)
    num = d[faces].mean()
    if reference is None:
        inblock = (
            grid.in_grid_mask(device=volume.device)[:, None]
            & ~face_edges(volume.shape[1:], block).to(volume.device)[:, None]
        ).expand_as(d)
        den = d[inblock].mean()
    else:
        reference = _check_volume(reference, "reference")
        rgrid = Grid(tuple(reference.shape[1:]), spacing=1.0, topology=6)
        dr = difference(reference[None], rgrid)[0].abs()
        den = dr[rgrid.in_grid_mask(device=reference.device)[:, None].expand_as(dr)].mean()
    return float(num / den.clamp_min(torch.finfo(den.dtype).tiny))


def seam_jump(volume: torch.Tensor, block, *, reference: torch.Tensor | None = None) -> float:
    """How much the colour gradient jumps across block faces, relative to the mean gradient.

    For every face edge (planes ``k b - 1`` and ``k b`` along an axis) the step across the face is
    compared with the mean of the steps just before and after it along the same axis:
    ``J = mean |d_face - (d_before + d_after) / 2|`` over face edges and channels, divided by the
    mean ``|d|`` over the 6-neighbour edges of ``reference`` (e.g. the exemplar), or of the
    in-block edges of ``volume``. A seamless texture scores its own second-difference level (about
    0.25 for the procedural liver, 0 for a linear ramp), a seam adds its jump: unlike
    :func:`seam_measure`, whose floor is 1, it can fall as far as the seams can be removed.

    Args:
        volume: ``(C, D, H, W)`` float.
        block: block size, one int or one per axis.
        reference: optional ``(C, d, h, w)`` volume whose mean gradient is the denominator.

    Returns:
        the ratio, a Python float.

    Example:
        >>> import torch
        >>> from torchdeform.texture.seams import seam_jump
        >>> i, j, k = torch.meshgrid(*[torch.arange(8.0)] * 3, indexing="ij")
        >>> v = (i + j + k).expand(3, 8, 8, 8).clone()             # a ramp: no jump anywhere
        >>> seam_jump(v, 4)
        0.0
        >>> v[:, 4:] += 3.0                                        # a step of 3 on the face at D = 4
        >>> seam_jump(v, 4)                                        # 3 on a third of the face edges
        1.0
    """
    volume = _check_volume(volume)
    shape = tuple(volume.shape[1:])
    faces = face_edges(shape, block).to(volume.device)
    grid = Grid(shape, spacing=1.0, topology=6)
    d = difference(volume[None], grid)[0]  # (3, C, D, H, W), signed
    total, count = d.new_zeros(()), 0
    for a in range(3):
        n = shape[a]
        ok = faces[a].clone()
        idx = torch.arange(n, device=volume.device).view([-1 if b == a else 1 for b in range(3)])
        ok &= (idx >= 1) & (idx + 2 <= n - 1)  # steps before and after exist
        if not bool(ok.any()):
            continue
        da = d[a]  # (C, D, H, W)
        before, after = torch.roll(da, 1, 1 + a), torch.roll(da, -1, 1 + a)
        jump = (da - (before + after) / 2).abs()[:, ok]
        total, count = total + jump.sum(), count + jump.numel()
    if count == 0:
        raise ConfigError("block", f"a block size that puts a face inside the volume {shape}", got=block)
    if reference is None:
        inblock = (grid.in_grid_mask(device=volume.device) & ~faces)[:, None].expand_as(d)
        den = d.abs()[inblock].mean()
    else:
        reference = _check_volume(reference, "reference")
        rgrid = Grid(tuple(reference.shape[1:]), spacing=1.0, topology=6)
        dr = difference(reference[None], rgrid)[0].abs()
        den = dr[rgrid.in_grid_mask(device=reference.device)[:, None].expand_as(dr)].mean()
    return float(total / count / den.clamp_min(torch.finfo(den.dtype).tiny))


def poisson_blend_3d(
    volume: torch.Tensor,
    block,
    *,
    iters: int = 2000,
    tol: float = 1e-6,
    region: str = "seams",
    margin: int = 4,
    guide: str = "mean",
    return_info: bool = False,
):
    """Blend block seams by 3-D guided Poisson editing, each channel on its own.

    Minimises ``|D u - g|^2`` over the 6-neighbour edges (see the module notes): ``g`` is the volume's
    forward difference inside blocks and, across block faces, the mean of the neighbouring in-block
    differences (``guide="mean"``) or 0 (``guide="zero"``); Neumann outer boundary. Solved by
    conjugate gradients on ``L = D^T D`` (the project's spring operator), one CG per channel.

    Args:
        volume: ``(C, D, H, W)`` float (RGB: ``C = 3``).
        block: block size of the tiling, one int or one per axis (faces at every multiple).
        iters: maximum CG iterations.
        tol: CG stops when ``|r| <= tol |b|`` for every channel.
        region: ``"seams"`` (default): only voxels within ``margin`` of a face change, the others
            anchor the solution; ``"all"``: every voxel changes and each channel keeps its mean exactly.
        margin: half-width of the band of unknowns in voxels (``region="seams"``).
        guide: ``"mean"`` or ``"zero"``, the guidance across faces.
        return_info: also return ``(iterations, relative residual)``.

    Returns:
        the blended volume ``(C, D, H, W)`` (same dtype and device), and with ``return_info`` the CG
        iteration count and final relative residual. A volume with no interior face is returned as is.

    Example:
        >>> import torch
        >>> from torchdeform.texture.seams import poisson_blend_3d, seam_measure
        >>> i, j, k = torch.meshgrid(*[torch.arange(8.0)] * 3, indexing="ij")
        >>> v = (i + j + k).expand(3, 8, 8, 8).clone()
        >>> v[:, 4:] += 5.0                                           # a seam on the face at D = 4
        >>> u = poisson_blend_3d(v, 4, region="all")
        >>> round(seam_measure(v, 4, axis=0), 3), round(seam_measure(u, 4, axis=0), 3)
        (6.0, 1.0)
        >>> bool(torch.allclose(u.mean(), v.mean()))                  # colour level kept
        True
    """
    volume = _check_volume(volume)
    C = volume.shape[0]
    grid = Grid(tuple(volume.shape[1:]), spacing=1.0, topology=6)
    x = volume.reshape(C, 1, *volume.shape[1:])  # one batch entry per channel
    u, used, rel = _blend(x, grid, block, guide=guide, region=region, margin=margin, iters=iters, tol=tol)
    u = u.reshape(volume.shape)
    return (u, used, rel) if return_info else u


def poisson_blend_slices(
    volume: torch.Tensor,
    block,
    *,
    axis: int = 0,
    iters: int = 2000,
    tol: float = 1e-6,
    region: str = "seams",
    margin: int = 4,
    guide: str = "mean",
    return_info: bool = False,
):
    """Chen & He's per-slice 2-D Poisson blend: every slice normal to ``axis`` on its own.

    The same guided problem as :func:`poisson_blend_3d` restricted to the 4-neighbour edges inside
    each slice (``u_xx + u_yy = div g``, forward differences), solved for all slices and channels at
    once as batch entries of one CG over a grid of thickness 1 along ``axis``. Seams between blocks
    stacked along ``axis`` stay: no slice has an edge across them.

    Args:
        volume: ``(C, D, H, W)`` float.
        block: block size, one int or one per axis.
        axis: the slicing axis (0, 1 or 2 for D, H, W); slices are normal to it.
        iters: maximum CG iterations.
        tol: CG stops when ``|r| <= tol |b|`` for every slice and channel.
        region: ``"seams"`` (default) or ``"all"``, as in :func:`poisson_blend_3d`; with ``"all"``
            each slice keeps its mean colour per channel exactly.
        margin: half-width of the band of unknowns in voxels (``region="seams"``).
        guide: ``"mean"`` or ``"zero"``, the guidance across faces.
        return_info: also return ``(iterations, relative residual)``.

    Returns:
        the blended volume ``(C, D, H, W)``, and with ``return_info`` ``(iterations, relative residual)``.

    Example:
        >>> import torch
        >>> from torchdeform.texture.seams import poisson_blend_slices, seam_measure
        >>> k = torch.arange(8.0)
        >>> v = (k + 3.0 * (k >= 4)).expand(3, 8, 8, 8).clone()       # a ramp along W, a seam normal to W
        >>> v[:, 4:] += 1.0                                           # and one normal to D
        >>> u = poisson_blend_slices(v, 4, axis=0, region="all")      # slices normal to D
        >>> round(seam_measure(v, 4, axis=2), 3), round(seam_measure(u, 4, axis=2), 3)
        (12.0, 3.0)
        >>> bool(torch.allclose(u[:, 4:] - u[:, :4], v[:, 4:] - v[:, :4]))   # the D seam stays
        True
    """
    volume = _check_volume(volume)
    if axis not in (0, 1, 2):
        raise ConfigError("axis", "0, 1 or 2", got=axis)
    C = volume.shape[0]
    sizes = list(_blocks(block))
    sizes[axis] = None
    shape = list(volume.shape[1:])
    n = shape[axis]
    shape[axis] = 1
    grid = Grid(tuple(shape), spacing=1.0, topology=6)
    # (C, D, H, W) -> (n, C, ...) with the slicing axis of size 1 -> one batch entry per slice and channel
    x = volume.movedim(axis + 1, 0).unsqueeze(axis + 2).reshape(n * C, 1, *shape)
    u, used, rel = _blend(x, grid, tuple(sizes), guide=guide, region=region, margin=margin, iters=iters, tol=tol)
    u = u.reshape(n, C, *shape).squeeze(axis + 2).movedim(0, axis + 1)
    return (u, used, rel) if return_info else u


def histogram_distance(a: torch.Tensor, b: torch.Tensor, *, bins: int = 32, metric: str = "wasserstein") -> float:
    """Distance between the per-channel colour histograms of two volumes.

    For each channel, both volumes are binned into ``bins`` equal bins over the union of their value
    ranges and normalised to sum 1 (``p``, ``q``). ``metric="wasserstein"`` (default) gives the 1-D
    Wasserstein-1 distance ``sum_k |P_k - Q_k| dx`` of the cumulative histograms (colour units;
    the exact distance of the binned values, within about one bin width ``dx`` of the unbinned one); ``metric="l1"`` gives ``sum_k |p_k - q_k|`` (in ``[0, 2]``).
    The result is the mean over channels.

    Args:
        a: ``(C, ...)`` float, any number of voxels.
        b: ``(C, ...)`` float, same ``C``.
        bins: number of bins.
        metric: ``"wasserstein"`` or ``"l1"``.

    Returns:
        the distance, a Python float.

    Example:
        >>> import torch
        >>> from torchdeform.texture.seams import histogram_distance
        >>> a = torch.zeros(3, 4, 4, 4)
        >>> a[:, 2:] = 1.0
        >>> histogram_distance(a, a), round(histogram_distance(a, a + 0.5, bins=64), 2)   # a shift by 0.5
        (0.0, 0.49)
        >>> histogram_distance(a, torch.ones(3, 8), metric="l1")
        1.0
    """
    if metric not in ("wasserstein", "l1"):
        raise ConfigError("metric", "'wasserstein' or 'l1'", got=metric)
    if not isinstance(bins, int) or bins < 1:
        raise ConfigError("bins", "an integer >= 1", got=bins)
    if a.shape[0] != b.shape[0]:
        raise ConfigError("b", f"a volume with {a.shape[0]} channels like a", got=tuple(b.shape))
    a = a.reshape(a.shape[0], -1).double()
    b = b.reshape(b.shape[0], -1).double()
    total = 0.0
    for ac, bc in zip(a, b):
        lo = float(torch.minimum(ac.min(), bc.min()))
        hi = float(torch.maximum(ac.max(), bc.max()))
        if hi <= lo:
            hi = lo + 1.0
        p = torch.histc(ac, bins, lo, hi)
        q = torch.histc(bc, bins, lo, hi)
        p, q = p / p.sum(), q / q.sum()
        if metric == "l1":
            total += float((p - q).abs().sum())
        else:
            total += float((p.cumsum(0) - q.cumsum(0)).abs().sum()) * (hi - lo) / bins
    return total / a.shape[0]
