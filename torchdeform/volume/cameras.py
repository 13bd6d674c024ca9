"""Cameras of the volume renderer: axis views and a perspective orbit camera.

Coordinates are voxels of the rendered volume, in ``(D, H, W)`` order: voxels are unit cubes
with centres at integer coordinates, so the volume occupies ``[-0.5, N - 0.5]`` per axis.

* Axis views (``"d"``, ``"h"``, ``"w"``: rays along +axis; ``"-d"``, ``"-h"``, ``"-w"``: along
  -axis) are orthographic, one pixel per voxel of the two other axes or an image ``size``
  ``(h, w)`` spread over them; :func:`~torchdeform.volume.render` marches them slab by slab.
* :class:`OrbitCamera` is perspective, on a sphere around the volume's centre (axis D is up):
  ``azimuth`` and ``elevation`` in degrees, ``distance`` in volume diagonals, a vertical
  ``fov`` in degrees and an image ``size`` ``(h, w)`` in pixels. :meth:`OrbitCamera.rays`
  gives the eye ``(3,)`` and unit ray directions ``(3, h, w)`` in voxel coordinates.

Example:
    >>> from torchdeform.volume import OrbitCamera
    >>> eye, d = OrbitCamera(azimuth=0.0, elevation=0.0, size=(4, 6)).rays((8, 8, 8))
    >>> tuple(d.shape), [round(float(c), 2) for c in eye]   # 1.6 diagonals before the centre along -H
    ((3, 4, 6), [3.5, -18.67, 3.5])
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..checks import check_memory
from ..errors import ConfigError

__all__ = ["OrbitCamera"]


@dataclass(kw_only=True)
class OrbitCamera:
    """Perspective camera on a sphere around the volume's centre; axis D is up.

    Args:
        azimuth: degrees around D, 0 = looking along +H.
        elevation: degrees above the H-W plane.
        distance: eye distance from the centre in volume diagonals.
        fov: vertical field of view in degrees.
        size: image ``(height, width)`` in pixels.
    """

    azimuth: float = 30.0
    elevation: float = 20.0
    distance: float = 1.6
    fov: float = 40.0
    size: tuple = (256, 256)

    def __post_init__(self):
        self.size = _check_size(self.size)

    def rays(self, shape, *, dtype=torch.float32, device=None):
        """Origins ``(3,)`` and unit directions ``(3, h, w)`` in voxel coordinates ``(D, H, W)``."""
        centre = torch.tensor([(n - 1) / 2 for n in shape], dtype=torch.float64)
        diag = math.sqrt(sum(n * n for n in shape))
        az, el = math.radians(self.azimuth), math.radians(self.elevation)
        # view direction (from eye to centre) in (D, H, W)
        fwd = torch.tensor(
            [-math.sin(el), math.cos(el) * math.cos(az), math.cos(el) * math.sin(az)], dtype=torch.float64
        )
        eye = centre - fwd * self.distance * diag
        up0 = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        right = torch.linalg.cross(fwd, up0)
        if float(right.norm()) < 1e-9:
            right = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        right = right / right.norm()
        up = torch.linalg.cross(right, fwd)
        h, w = (int(s) for s in self.size)
        tan = math.tan(math.radians(self.fov) / 2)
        ys = (1 - (torch.arange(h, dtype=torch.float64) + 0.5) / h * 2) * tan
        xs = ((torch.arange(w, dtype=torch.float64) + 0.5) / w * 2 - 1) * tan * w / h
        d = fwd.view(3, 1, 1) + up.view(3, 1, 1) * ys.view(1, h, 1) + right.view(3, 1, 1) * xs.view(1, 1, w)
        d = d / d.norm(dim=0, keepdim=True)
        return eye.to(dtype=dtype, device=device), d.to(dtype=dtype, device=device)


def _check_size(size):
    """``size`` as ``(h, w)`` positive ints (None stays None), its image's memory checked."""
    if size is None:
        return None
    try:
        s = tuple(int(v) for v in size)
    except (TypeError, ValueError):
        s = ()
    if len(s) != 2 or min(s) < 1:
        raise ConfigError("size", "an image size (height, width) of positive integers", got=size)
    # the image, its accumulators and one slab of samples: a few dozen float32 values per pixel
    check_memory("size", 128.0 * s[0] * s[1], f"an image of {s[0]} x {s[1]} pixels", got=s)
    return s
