"""The render plan: what :func:`~torchdeform.volume.render` resolves once and every path reads.

:func:`~torchdeform.volume.render` checks its arguments once, builds what they name (the volume
as ``(B, 1, D, H, W)``, the displacement field or the pieces of a cut body, the transfer
function's range and lookup table) and freezes it all in one :class:`RenderPlan`. The axis-view
path, the orbit path and the fast path (:mod:`.rendering`, :mod:`.fastpath`) take the plan and
nothing else, so an option is named in one place and a path reads only the fields it needs.

Units and shapes
----------------
* Coordinates and lengths are voxels of the volume (unit cubes, centres at integer
  coordinates, ``(D, H, W)`` order): ``step``, ``dt``, pixel centres, node offsets.
* ``lo``, ``hi`` (volume units) map values onto the ``table`` ``(resolution, 4)`` (RGB and
  extinction per voxel length at evenly spaced values) of :class:`~torchdeform.volume.TransferFunction`.
* An axis view samples ``n`` slabs of thickness ``dt = N / n`` along its axis of ``N`` voxels
  (``n = round(N / step)``, at least 1), at pixel centres ``(m + 0.5) N_a / h - 0.5`` of the two
  other axes (``h`` pixels over ``N_a`` voxels): :meth:`RenderPlan.axis_samples`.

The vocabularies of the plan's options are :data:`RENDER_MODES`, :data:`AXIS_VIEWS` and
:data:`ENGINES`.

Example:
    >>> import torch
    >>> from torchdeform.volume.plan import RenderPlan
    >>> plan = RenderPlan(volume=torch.zeros(1, 1, 10, 6, 8), mode="mip", view="-h", step=0.7)
    >>> s = plan.axis_samples()
    >>> s.axis, s.reverse, s.n, round(s.dt, 4), s.img_shape
    (1, True, 9, 0.6667, (10, 8))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import torch

__all__ = ["RENDER_MODES", "AXIS_VIEWS", "ENGINES", "RenderPlan"]

#: Render modes: emission-absorption (``dvr``), maximum intensity (``mip``), length-weighted mean (``average``).
RENDER_MODES = ("dvr", "mip", "average")
#: Axis views: rays along +D, +H, +W, or along -D, -H, -W.
AXIS_VIEWS = ("d", "h", "w", "-d", "-h", "-w")
#: How an axis view samples the volume: ``grid_sample`` (every option, differentiable), the fast
#: path through offsets, ``eager`` or ``compiled`` (:mod:`torchdeform.volume.fastpath`), the C
#: kernel (``native``, :mod:`torchdeform.volume.native_march`), or ``auto`` (native where it applies).
ENGINES = ("grid_sample", "eager", "compiled", "native", "auto")


class _AxisSamples(NamedTuple):
    """The sample lattice of an axis view (see :meth:`RenderPlan.axis_samples`)."""

    axis: int  # the ray axis, 0..2 of (D, H, W)
    reverse: bool  # rays along -axis
    others: list  # the two image axes, in (D, H, W) order
    n: int  # samples (slabs) per ray
    dt: float  # slab thickness [voxels]
    img_shape: tuple  # (h, w) pixels
    pix: list  # pixel centres of the two image axes [voxels], tensors (h,) and (w,)


@dataclass(frozen=True, eq=False, kw_only=True)
class RenderPlan:
    """One :func:`~torchdeform.volume.render` call, resolved: its inputs built and checked, its options.

    Args:
        volume: the volume ``(B_v, 1, D, H, W)``, float32 or float64 (volume units).
        mode: one of :data:`RENDER_MODES`.
        view: one of :data:`AXIS_VIEWS` or an :class:`~torchdeform.volume.OrbitCamera`.
        batch: images rendered ``B`` (the largest of the volume's, the offsets' and the pieces' batch).
        field: the :class:`~torchdeform.volume.DisplacementField` of the node offsets (voxels), or None.
        pieces: the pieces of a cut body (per piece a displacement field and its rest-space
            material), or None.
        tf: the :class:`~torchdeform.volume.TransferFunction` (``dvr``), or None.
        lo: the value at the table's first entry (volume units; ``dvr``), or None.
        hi: the value at the table's last entry (volume units; ``dvr``), or None.
        table: the transfer function's lookup table ``(resolution, 4)`` in the volume's dtype
            (``dvr``), or None.
        inverse_iters: fixed-point inverse iterations (0: ``X = p - u(p)``).
        padding: volume lookups outside the volume, ``"border"`` or ``"zeros"``.
        fill: the value outside the volume with ``padding="zeros"`` and in a cut's gaps.
        step: sample spacing along the rays [voxels].
        size: axis-view image ``(h, w)`` in pixels, or None (the volume's own two axes).
        stop: early ray termination once every transmittance is below this (0: never).
        chunk_points: samples per chunk of slabs.
        engine: one of :data:`ENGINES`.
    """

    volume: torch.Tensor
    mode: str
    view: Any
    batch: int = 1
    field: Any = None
    pieces: Any = None
    tf: Any = None
    lo: float | None = None
    hi: float | None = None
    table: torch.Tensor | None = None
    inverse_iters: int = 0
    padding: str = "border"
    fill: float = 0.0
    step: float = 1.0
    size: tuple | None = None
    stop: float = 1e-3
    chunk_points: int = 1 << 20
    engine: str = "grid_sample"

    @property
    def shape(self) -> tuple:
        """The volume's ``(D, H, W)`` [voxels]."""
        return tuple(self.volume.shape[2:])

    @property
    def dtype(self) -> torch.dtype:
        """The volume's dtype, which every sample and image takes."""
        return self.volume.dtype

    @property
    def device(self) -> torch.device:
        """The volume's device."""
        return self.volume.device

    def slabs_per_chunk(self, n_img: int) -> int:
        """Slabs per chunk for images of ``n_img`` pixels: ``chunk_points`` samples, at least one slab."""
        return max(1, self.chunk_points // max(n_img, 1))

    def axis_samples(self) -> _AxisSamples:
        """The sample lattice of the axis view ``view``: ray axis, slabs, image shape, pixel centres."""
        shape = self.shape
        axis = "dhw".index(self.view[-1])
        others = [a for a in range(3) if a != axis]
        N = shape[axis]
        n = max(1, round(N / self.step))
        img_shape = self.size or tuple(shape[a] for a in others)
        pix = [
            (torch.arange(m, dtype=self.dtype, device=self.device) + 0.5) * (shape[a] / m) - 0.5
            for m, a in zip(img_shape, others)
        ]
        return _AxisSamples(axis, self.view.startswith("-"), others, n, N / n, img_shape, pix)
