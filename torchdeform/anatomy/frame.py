r"""Images and lattices in one physical frame: voxel look-ups at lattice points, images resampled onto lattice axes.

An image's affine ``A`` (4 x 4) maps a voxel index ``(i, j, k, 1)`` to the LPS position of the
voxel's centre in metres; a lattice's node ``(d, h, w)`` rests at ``origin + (d, h, w) * spacing``
with its axes (D, H, W) along LPS (x, y, z). A lattice point ``p`` lies in the voxel whose index is
``round(A^-1 p)`` (nearest voxel centre): :func:`voxel_indices`. Because both maps are affine, the
fractional voxel index of a regular set of lattice points is one base point plus integer steps
along three columns (:func:`lattice_to_voxel`), so look-ups run slab by slab without building the
points.

Shapes: a lattice of ``(D, H, W)`` points; an image array ``(I, J, K)``; affines ``(4, 4)``.

Example:
    >>> import numpy as np
    >>> A = np.diag([0.002, 0.002, 0.004, 1.0])            # 2 x 2 x 4 mm voxels, origin 0
    >>> M, q0 = lattice_to_voxel(A, origin=(0.0, 0.0, 0.0), spacing=(0.004,) * 3)
    >>> (q0 + M @ np.array([1, 1, 1])).tolist()             # the lattice point (4, 4, 4) mm
    [2.0, 2.0, 1.0]
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import ConfigError

#: Points per look-up chunk (memory: about 100 bytes each).
_CHUNK = 1 << 20

__all__ = ["lattice_to_voxel", "voxel_slabs", "voxel_indices", "sample_nearest", "resample_image", "image_box"]


def lattice_to_voxel(affine, *, origin, spacing) -> tuple[np.ndarray, np.ndarray]:
    """``(M, q0)``: the fractional voxel index of lattice point ``n`` (``(3,)`` node index) is ``q0 + M n``.

    Args:
        affine: ``(4, 4)`` voxel index -> LPS metres.
        origin: the lattice's node ``(0, 0, 0)`` in metres, ``(3,)``.
        spacing: the lattice's spacing ``(3,)`` in metres.

    Returns:
        ``M`` ``(3, 3)`` (column ``a``: the voxel step of one lattice step along axis ``a``) and ``q0`` ``(3,)``.
    """
    A = np.asarray(affine, dtype=np.float64)
    inv = np.linalg.inv(A[:3, :3])
    M = inv * np.asarray(spacing, dtype=np.float64)[None, :]
    q0 = inv @ (np.asarray(origin, dtype=np.float64) - A[:3, 3])
    return M, q0


def voxel_indices(q: torch.Tensor, shape) -> tuple[torch.Tensor, torch.Tensor]:
    """The nearest voxel of fractional indices ``q`` ``(..., 3)``: ``(flat index (...), inside (...))``.

    A point lies in voxel ``round(q)`` (half-way points round to even, as torch rounds); points whose
    voxel is outside the image get ``inside = False`` (and flat index 0).
    """
    r = torch.round(q).to(torch.int64)
    n = torch.tensor(shape, dtype=torch.int64, device=q.device)
    inside = ((r >= 0) & (r < n)).all(-1)
    r = torch.where(inside[..., None], r, torch.zeros_like(r))
    flat = (r[..., 0] * shape[1] + r[..., 1]) * shape[2] + r[..., 2]
    return flat, inside


def sample_nearest(
    values: torch.Tensor, affine, shape_in, *, origin, spacing, shape, offset=(0.0, 0.0, 0.0), outside=0
):
    """Image ``values`` (flat ``(I J K,)`` or ``(I, J, K)``) at the points ``origin + (n + offset) * spacing``.

    Nearest-voxel look-up of every point of a ``shape`` lattice, one D-slab at a time; points
    outside the image take ``outside``. Returns ``(D, H, W)`` of ``values``' dtype.

    Example:
        >>> import numpy as np, torch
        >>> vals = torch.arange(8).view(2, 2, 2)
        >>> out = sample_nearest(vals, np.eye(4), (2, 2, 2), origin=(0, 0, 0), spacing=(1, 1, 1), shape=(3, 2, 2), outside=-1)
        >>> out[:, 0, 0].tolist()                          # the third slab is outside the image
        [0, 4, -1]
    """
    flat_vals = values.reshape(-1)
    out = torch.empty(tuple(shape), dtype=flat_vals.dtype)
    fill = torch.tensor(outside, dtype=flat_vals.dtype)
    for d0, q in voxel_slabs(affine, origin=origin, spacing=spacing, shape=shape, offset=offset):
        flat, inside = voxel_indices(q, shape_in)
        out[d0 : d0 + len(q)] = torch.where(inside, flat_vals[flat], fill)
    return out


def voxel_slabs(affine, *, origin, spacing, shape, offset=(0.0, 0.0, 0.0)):
    """The fractional voxel indices of the lattice points ``origin + (n + offset) * spacing``, slab by slab.

    Yields ``(d0, q)``: the first D index of the slab and float64 ``(d, H, W, 3)`` voxel indices of
    its points (about :data:`_CHUNK` points a slab), built from one base plane and the steps of
    :func:`lattice_to_voxel`.
    """
    M, q0 = lattice_to_voxel(affine, origin=origin, spacing=spacing)
    q0 = q0 + M @ np.asarray(offset, dtype=np.float64)
    Mt = torch.as_tensor(M, dtype=torch.float64)
    D, H, W = shape
    hw = torch.stack(
        torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"), -1
    )  # (H, W, 2)
    plane = hw[..., 0:1] * Mt[:, 1] + hw[..., 1:2] * Mt[:, 2] + torch.as_tensor(q0)  # (H, W, 3)
    step = max(1, _CHUNK // max(H * W, 1))  # slabs per chunk
    for d0 in range(0, D, step):
        d = torch.arange(d0, min(D, d0 + step), dtype=torch.float64).view(-1, 1, 1, 1)
        yield d0, plane + d * Mt[:, 0]


def image_box(affine, index_lo, index_hi) -> tuple[np.ndarray, np.ndarray]:
    """The LPS box ``(lo, hi)`` (metres) holding the voxels ``index_lo..index_hi`` (inclusive), voxel extents included."""
    A = np.asarray(affine, dtype=np.float64)
    lo, hi = np.asarray(index_lo, dtype=np.float64) - 0.5, np.asarray(index_hi, dtype=np.float64) + 0.5
    corners = np.array([[(hi if b else lo)[a] for a, b in enumerate(bits)] for bits in np.ndindex(2, 2, 2)])
    pts = corners @ A[:3, :3].T + A[:3, 3]
    return pts.min(0), pts.max(0)


def resample_image(image, *, origin, spacing, shape, fill: float = -1000.0, dtype=torch.float32) -> torch.Tensor:
    """An image (e.g. a CT in HU) trilinearly resampled onto a lattice-aligned grid of ``shape`` points.

    Point ``n`` is ``origin + n * spacing`` (LPS metres); its value interpolates the image's voxel
    centres (``scipy.ndimage.map_coordinates``, order 1), ``fill`` outside the image (-1000 HU: air).
    The result is a ``(D, H, W)`` volume whose axes are the lattice's, so a volume warp by the
    lattice's node offsets and the body agree.

    Args:
        image: an :class:`~torchdeform.anatomy.images.Image` (``array`` ``(I, J, K)``, ``affine``).
        origin: the first point (metres, 3).
        spacing: the step between points (metres, 3).
        shape: ``(D, H, W)`` point counts.
        fill: the value outside the image.
        dtype: the result's dtype.

    Example:
        >>> import numpy as np
        >>> from torchdeform.anatomy.images import Image
        >>> img = Image(np.arange(27.0).reshape(3, 3, 3), np.diag([0.001, 0.001, 0.001, 1.0]), "demo")
        >>> v = resample_image(img, origin=(0.0005, 0.0, 0.0), spacing=(0.001,) * 3, shape=(2, 1, 1))
        >>> v.flatten().tolist()                           # half-way between voxels 0 and 9, then 9 and 18
        [4.5, 13.5]
    """
    from scipy.ndimage import map_coordinates

    if min(shape) < 1:
        raise ConfigError("image", "a resampling grid of at least one point per axis", got=tuple(shape))
    arr = np.asarray(image.array, dtype=np.float32)
    out = np.empty(tuple(shape), dtype=np.float32)
    for d0, q in voxel_slabs(image.affine, origin=origin, spacing=spacing, shape=shape):
        coords = np.moveaxis(q.numpy(), -1, 0)  # (3, d, H, W)
        out[d0 : d0 + len(q)] = map_coordinates(arr, coords, order=1, mode="constant", cval=fill)
    return torch.from_numpy(out).to(dtype)
