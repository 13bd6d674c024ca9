"""A procedural CT-like abdominal phantom (Hounsfield units), for demos and tests.

Axis D runs along the body (the "up" axis of the built-in scenes), H from front (anterior,
small index) to back, W from right to left. Structures, in HU:

===============================  ==========================================
air                              -1000
subcutaneous fat (outer shell)   -100
soft tissue / muscle             40
liver (an ellipsoid)             60, with contrast-filled vessels 180
tumour in the liver              25 core, 90 enhancing rim
kidneys (two ellipsoids)         30 medulla, 150 cortex
aorta and vena cava              200 and 150
vertebral column                 700 cancellous, 1200 cortical, discs 80
===============================  ==========================================

Gaussian noise (``noise`` HU, default 8) is added inside the body only, so the air stays at
exactly -1000 (empty-space tests can rely on it). Deterministic for a given ``seed``.

Example:
    >>> from torchdeform.volume import phantom
    >>> v = phantom(shape=(32, 32, 32))
    >>> tuple(v.shape), float(v.min()), float(v.max()) > 700
    ((32, 32, 32), -1000.0, True)
"""

from __future__ import annotations

import math

import torch

from ..errors import ConfigError

AIR, FAT, SOFT, LIVER, VESSEL, TUMOUR, RIM = -1000.0, -100.0, 40.0, 60.0, 180.0, 25.0, 90.0
KIDNEY, CORTEX, AORTA, CAVA, BONE, CORTICAL, DISC = 30.0, 150.0, 200.0, 150.0, 700.0, 1200.0, 80.0


def _coords(shape, dtype):
    axes = [torch.linspace(-1, 1, n, dtype=dtype) if n > 1 else torch.zeros(1, dtype=dtype) for n in shape]
    return torch.meshgrid(*axes, indexing="ij")


def _ellipsoid(z, y, x, c, r):
    return ((z - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2 + ((x - c[2]) / r[2]) ** 2


def _segment_distance(z, y, x, a, b):
    """Distance from every point to the segment a-b (normalised coordinates)."""
    ab = [bb - aa for aa, bb in zip(a, b)]
    L2 = sum(c * c for c in ab) or 1.0
    t = (((z - a[0]) * ab[0] + (y - a[1]) * ab[1] + (x - a[2]) * ab[2]) / L2).clamp(0, 1)
    return ((z - a[0] - t * ab[0]) ** 2 + (y - a[1] - t * ab[1]) ** 2 + (x - a[2] - t * ab[2]) ** 2).sqrt()


def lumen_centre(s: float, shape) -> tuple:
    """The centre line of the phantom's bowel lumen at ``s`` in [0, 1]: a point ``(D, H, W)`` in voxels.

    The lumen winds along W from a quarter to three quarters of the width, in the lower front of
    the abdomen (``D`` about 0.3, ``H`` about 0.37 of the extent), with a radius of 0.05 ``W``.

    Example:
        >>> [round(c, 2) for c in lumen_centre(0.0, (100, 100, 100))]
        [30.0, 42.0, 25.0]
    """
    D, H, W = shape
    return (
        D * (0.30 + 0.03 * math.sin(3 * math.pi * s)),
        H * (0.37 + 0.05 * math.cos(2 * math.pi * s)),
        W * (0.25 + 0.5 * s),
    )


def _carve_lumen(v: torch.Tensor) -> torch.Tensor:
    """``v`` with the air-filled lumen around :func:`lumen_centre` (a one-voxel linear edge)."""
    D, H, W = v.shape
    w = torch.arange(W, dtype=v.dtype)
    s = (w / W - 0.25) / 0.5
    cd = D * (0.30 + 0.03 * torch.sin(3 * math.pi * s))
    ch = H * (0.37 + 0.05 * torch.cos(2 * math.pi * s))
    r = 0.05 * W
    dd = torch.arange(D, dtype=v.dtype).view(D, 1, 1) - cd.view(1, 1, W)
    hh = torch.arange(H, dtype=v.dtype).view(1, H, 1) - ch.view(1, 1, W)
    dist = (dd * dd + hh * hh).sqrt()
    air = ((r + 0.5 - dist).clamp(0, 1)) * ((s >= 0) & (s <= 1)).to(v.dtype).view(1, 1, W)
    return torch.where(air >= 1, torch.full_like(v, AIR), v + air * (AIR - v)).contiguous()


def phantom(
    *, shape=(128, 128, 128), noise: float = 8.0, seed: int = 0, lumen: bool = False, dtype=torch.float32
) -> torch.Tensor:
    """The phantom as a ``(D, H, W)`` tensor of Hounsfield units.

    Args:
        shape: voxels ``(D, H, W)``, each >= 8.
        noise: standard deviation (HU) of the Gaussian noise inside the body.
        seed: noise seed.
        lumen: carve an air-filled bowel loop through the abdomen (:func:`lumen_centre`), for
            virtual endoscopy (``"phantom-lumen:N"`` as a volume source).
        dtype: floating-point dtype of the result.
    """
    try:
        shape = tuple(int(n) for n in shape)
    except (TypeError, ValueError):
        shape = ()
    if len(shape) != 3 or min(shape) < 8:
        raise ConfigError("shape", "three voxel counts (D, H, W), each >= 8", got=shape)
    if not (isinstance(noise, (int, float)) and noise >= 0 and math.isfinite(noise)):
        raise ConfigError("noise", "a number >= 0 (HU)", got=noise)
    z, y, x = _coords(shape, dtype)
    v = torch.full(shape, AIR, dtype=dtype)
    body = _ellipsoid(z, y, x, (0, 0, 0), (0.92, 0.72, 0.9))
    inside = body <= 1
    v[inside] = FAT
    v[_ellipsoid(z, y, x, (0, 0, 0), (0.88, 0.64, 0.82)) <= 1] = SOFT
    liver = _ellipsoid(z, y, x, (0.15, -0.05, -0.38), (0.45, 0.42, 0.36)) <= 1
    v[liver] = LIVER
    for a, b in (
        ((0.45, 0.1, -0.3), (0.0, -0.05, -0.45)),
        ((0.0, -0.05, -0.45), (-0.2, -0.25, -0.3)),
        ((0.0, -0.05, -0.45), (-0.15, 0.2, -0.55)),
        ((0.45, 0.1, -0.3), (0.3, -0.3, -0.2)),
    ):
        v[liver & (_segment_distance(z, y, x, a, b) < 0.035)] = VESSEL
    t = _ellipsoid(z, y, x, (0.25, -0.2, -0.5), (0.12, 0.12, 0.12))
    v[t <= 1] = RIM
    v[t <= 0.55] = TUMOUR
    for side in (-1, 1):
        k = _ellipsoid(z, y, x, (-0.2, 0.3, 0.38 * side), (0.25, 0.13, 0.1))
        v[k <= 1] = CORTEX
        v[k <= 0.5] = KIDNEY
    v[_segment_distance(z, y, x, (0.9, 0.12, 0.08), (-0.9, 0.12, 0.08)) < 0.07] = AORTA
    v[_segment_distance(z, y, x, (0.9, 0.1, -0.12), (-0.9, 0.1, -0.12)) < 0.08] = CAVA
    r = ((y - 0.42) ** 2 + x**2).sqrt()
    column = (r < 0.16) & (z.abs() < 0.85)
    disc = torch.cos(z * math.pi * 6).abs() > 0.93
    v[column] = BONE
    v[column & (r > 0.12)] = CORTICAL
    v[column & disc] = DISC
    spinous = (_segment_distance(z, y, x, (0, 0.55, 0), (0, 0.66, 0)) < 0.05) & ~disc & (z.abs() < 0.85)
    v[spinous] = CORTICAL
    if noise > 0:
        g = torch.Generator().manual_seed(int(seed))
        v = torch.where(inside, v + noise * torch.randn(shape, generator=g, dtype=dtype), v)
    return _carve_lumen(v) if lumen else v


__all__ = ["phantom", "lumen_centre"]
