"""The virtual-endoscopy camera: a wide-angle pinhole with a round image and barrel distortion.

Coordinates are voxels of the volume in ``(D, H, W)`` order, voxel centres at integer
coordinates, the volume occupying ``[-0.5, N - 0.5]`` per axis (as :mod:`.cameras`). Axis D is
"up" by default.

The model
---------
The camera sits at ``position`` and looks along ``direction`` (normalised). Its frame
(:meth:`EndoscopeCamera.basis`) is ``forward = direction / |direction|``, ``up`` = the given up
vector made orthogonal to ``forward`` (Gram-Schmidt; when it is parallel to ``forward`` the
coordinate axis least aligned with ``forward`` is used instead) and ``right = forward x up``,
the cross product taken in ``(D, H, W)`` components as :class:`~torchdeform.volume.OrbitCamera`
does (so both cameras give the same image for the same pose).

A ray at angle ``theta`` to ``forward`` has the pinhole radius ``r_u = tan(theta) / tan(fov / 2)``,
normalised so that the image circle's edge is ``r_u = 1`` (``fov`` is the full angle across the
image circle's diameter, or across ``min(h, w)`` for a rectangular image without the mask).
Barrel distortion (Brown's first radial term) moves it to ``r_d = r_u (1 + k1 r_u^2)`` (``k1 < 0``:
barrel, ``k1 > 0``: pincushion); ``k1`` must keep ``r_d`` increasing over the image, i.e.
``1 + 3 k1 r_u^2 > 0`` up to the radius of the image's farthest pixel.

Pixels: the image is ``size = (h, w)``; pixel ``(i, j)`` has its centre at ``(row, col) =
(i + 0.5, j + 0.5)`` in pixel units; its normalised image coordinates are
``x = (col - w / 2) / m``, ``y = (h / 2 - row) / m`` with ``m = min(h, w) / 2`` (rows go down,
``y`` up), and ``r_d = sqrt(x^2 + y^2)``. The round mask keeps the pixels with ``r_d <= 1``.
:meth:`EndoscopeCamera.rays` inverts the distortion by Newton's method (exact pinhole for
``k1 = 0``) and returns unit directions ``forward + tan(fov / 2) r_u / r_d (x right + y up)``,
normalised; :meth:`EndoscopeCamera.project` is its exact inverse for points in front of the
camera.

The pose is differentiable: ``position`` and ``direction`` may be tensors that require grad; the
rays are built from them by tensor operations only.

Example:
    >>> import torch
    >>> from torchdeform.volume import EndoscopeCamera
    >>> cam = EndoscopeCamera(position=(8.0, 8.0, 2.0), direction=(0.0, 0.0, 1.0), fov=90.0, size=(5, 5))
    >>> eye, d, valid = cam.rays((16, 16, 16))
    >>> tuple(d.shape), int(valid.sum())            # the round mask keeps 21 of 25 pixels
    ((3, 5, 5), 21)
    >>> [round(float(c), 3) for c in d[:, 2, 2]]    # the centre pixel looks straight ahead
    [0.0, 0.0, 1.0]
    >>> pix, depth = cam.project(torch.tensor([[8.0, 8.0, 10.0]]))
    >>> pix.tolist(), depth.tolist()                # (row, col) of the image centre, 8 voxels ahead
    ([[2.5, 2.5]], [8.0])
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from ..errors import ConfigError
from .cameras import _check_size

__all__ = ["EndoscopeCamera", "INSIDE_MODES"]

#: What :class:`EndoscopeCamera` requires of its position: inside the volume's box, or anywhere.
INSIDE_MODES = ("require", "allow")

#: camera-frame rays by image (size, fov, distortion, mask, dtype, device), shared by every camera
_LOCAL_RAYS: dict = {}
_NEWTON_ITERS = 30  # undistortion: monotone convergence from r_d, a handful of steps in practice


def _vec3(value, key: str) -> torch.Tensor:
    """``value`` as a ``(3,)`` tensor (a tensor is kept as it is, with its grad; others become float64)."""
    if torch.is_tensor(value):
        t = value if value.is_floating_point() else value.to(torch.float64)
    else:
        try:
            t = torch.as_tensor([float(v) for v in value], dtype=torch.float64)
        except (TypeError, ValueError):
            raise ConfigError(key, "three numbers (D, H, W) in voxels", got=value) from None
    if tuple(t.shape) != (3,):
        raise ConfigError(key, "three numbers (D, H, W) in voxels", got=tuple(t.shape))
    if not bool(torch.isfinite(t.detach()).all()):
        raise ConfigError(key, "finite numbers (D, H, W) in voxels", got=t.detach().tolist())
    return t


def _float(value, key: str, expected: str) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ConfigError(key, expected, got=value) from None


@dataclass(kw_only=True, eq=False)
class EndoscopeCamera:
    """A virtual endoscope: a wide-angle pinhole inside the volume, round image, barrel distortion.

    Args:
        position: the eye ``(3,)`` in voxels ``(D, H, W)``; a tensor may require grad.
        direction: the view direction ``(3,)`` (normalised internally); a tensor may require grad.
        up: the image's up direction ``(3,)``, made orthogonal to ``direction`` (default +D).
        fov: degrees, the full angle across the image circle's diameter (across ``min(h, w)``
            without the mask), in the open interval (0, 180).
        size: image ``(h, w)`` in pixels.
        near: the start of every ray [voxels along the ray], >= 0.
        far: the end of every ray [voxels along the ray], > ``near`` (``inf``: the volume's box).
        mask: the round mask: pixels whose centre is farther than ``min(h, w) / 2`` from the
            image centre are outside (``valid`` False; rendered as 0).
        distortion: the radial coefficient ``k1`` of ``r_d = r_u (1 + k1 r_u^2)`` (negative: barrel).
        inside: ``"require"`` (the position must lie inside the volume's box, else
            :class:`~torchdeform.errors.ConfigError`) or ``"allow"``.

    Raises:
        ConfigError: ``fov`` outside (0, 180), a zero direction or up vector, a bad ``size``,
            ``far <= near``, a ``distortion`` that is not monotonic over the image, a bad ``inside``.

    Example:
        >>> from torchdeform.volume import EndoscopeCamera
        >>> cam = EndoscopeCamera.look_at((4.0, 4.0, 1.0), (4.0, 4.0, 7.0), size=(3, 4), mask=False)
        >>> [[round(float(c), 3) for c in v] for v in cam.basis()]   # forward, up, right
        [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    """

    position: Any
    direction: Any
    up: Any = (1.0, 0.0, 0.0)
    fov: float = 100.0
    size: tuple = (256, 256)
    near: float = 0.0
    far: float = math.inf
    mask: bool = True
    distortion: float = 0.0
    inside: str = "require"

    def __post_init__(self):
        self.position = _vec3(self.position, "position")
        self.direction = _vec3(self.direction, "direction")
        if float(self.direction.detach().norm()) < 1e-12:
            raise ConfigError("direction", "a non-zero view direction (3,)", got=self.direction.detach().tolist())
        self.up = _vec3(self.up, "up")
        if float(self.up.detach().norm()) < 1e-12:
            raise ConfigError("up", "a non-zero up vector (3,)", got=self.up.detach().tolist())
        fov = _float(self.fov, "fov", "an angle in degrees strictly between 0 and 180")
        if not (0.0 < fov < 180.0):
            raise ConfigError("fov", "an angle in degrees strictly between 0 and 180", got=self.fov)
        self.fov = fov
        size = _check_size(self.size)
        if size is None:
            raise ConfigError("size", "an image size (height, width) of positive integers", got=None)
        self.size = size
        near = _float(self.near, "near", "a distance >= 0 along the ray in voxels")
        if not (math.isfinite(near) and near >= 0):
            raise ConfigError("near", "a finite distance >= 0 along the ray in voxels", got=self.near)
        far = _float(self.far, "far", "a distance along the ray in voxels, greater than near")
        if math.isnan(far) or far <= near:
            raise ConfigError("far", f"a distance along the ray in voxels greater than near ({near:g})", got=self.far)
        self.near, self.far = near, far
        self.mask = bool(self.mask)
        k1 = _float(self.distortion, "distortion", "a finite radial coefficient k1")
        if not math.isfinite(k1):
            raise ConfigError("distortion", "a finite radial coefficient k1", got=self.distortion)
        if k1 < 0:
            # r + k1 r^3 increases up to r* = 1 / sqrt(-3 k1), where it reaches 2 r* / 3: that must exceed
            # the distorted radius of the image's farthest pixel centre
            r_max = self._max_radius()
            if 2.0 / (3.0 * math.sqrt(-3.0 * k1)) <= r_max:
                bound = -4.0 / (27.0 * r_max * r_max)
                raise ConfigError(
                    "distortion",
                    f"a k1 > {bound:.4g} (r_u (1 + k1 r_u^2) must increase over the image)",
                    got=self.distortion,
                )
        self.distortion = k1
        if self.inside not in INSIDE_MODES:
            raise ConfigError("inside", "one of " + ", ".join(INSIDE_MODES), got=self.inside)

    @classmethod
    def look_at(cls, position, target, **kw) -> EndoscopeCamera:
        """A camera at ``position`` looking at ``target`` (both ``(3,)`` voxels); other fields as keywords."""
        p = _vec3(position, "position")
        t = _vec3(target, "target")
        p2, t2 = (p, t.to(p.dtype)) if p.dtype == t.dtype or not t.requires_grad else (p.to(t.dtype), t)
        return cls(position=p, direction=t2 - p2, **kw)

    # ------------------------------------------------------------ geometry
    def _max_radius(self) -> float:
        """The largest normalised (distorted) radius of a pixel centre the image uses."""
        h, w = self.size
        m = min(h, w) / 2.0
        if self.mask:
            return 1.0
        return math.hypot((h - 1) / 2.0, (w - 1) / 2.0) / m

    def basis(self, *, dtype=None, device=None):
        """``(forward, up, right)``: unit vectors ``(3,)`` of the camera frame in ``(D, H, W)``.

        Differentiable with respect to ``direction``; ``dtype`` defaults to the direction's.
        """
        dtype = dtype or self.direction.dtype
        f = self.direction.to(dtype=dtype, device=device)
        f = f / f.norm()
        up = self.up.to(dtype=dtype, device=device)
        u = up - (up @ f) * f
        if float(u.detach().norm()) < 1e-6 * float(up.detach().norm()):
            axis = int(f.detach().abs().argmin())
            e = torch.zeros(3, dtype=dtype, device=device)
            e[axis] = 1.0
            u = e - (e @ f) * f
        u = u / u.norm()
        r = torch.linalg.cross(f, u)
        return f, u, r

    def _image_plane(self, dtype, device):
        """Pinhole image-plane coordinates ``(a, b)`` ``(h, w)`` (right, up; tan units) and the mask ``(h, w)``."""
        h, w = self.size
        m = min(h, w) / 2.0
        y = (h / 2.0 - (torch.arange(h, dtype=torch.float64) + 0.5)) / m
        x = ((torch.arange(w, dtype=torch.float64) + 0.5) - w / 2.0) / m
        y, x = torch.meshgrid(y, x, indexing="ij")
        rd = torch.sqrt(x * x + y * y)
        k1 = self.distortion
        ru = rd.clone()
        if k1 != 0.0:
            target = rd
            if k1 < 0:  # beyond the image (masked pixels) rd may exceed the largest reachable 2 r* / 3: saturate
                r_star = 1.0 / math.sqrt(-3.0 * k1)
                beyond = rd >= (2.0 / 3.0) * r_star * (1 - 1e-12)
                target = torch.where(beyond, torch.zeros_like(rd), rd)
                ru = target.clone()
            for _ in range(_NEWTON_ITERS):  # solve ru + k1 ru^3 = rd: monotone convergence from ru = rd
                step = (ru + k1 * ru**3 - target) / (1.0 + 3.0 * k1 * ru * ru)
                ru = ru - step
                if float(step.abs().max()) < 1e-15:
                    break
            if k1 < 0:
                ru = torch.where(beyond, torch.full_like(ru, r_star), ru)
        scale = torch.where(rd > 0, ru / rd.clamp(min=1e-300), torch.ones_like(rd))
        tan = math.tan(math.radians(self.fov) / 2.0)
        valid = rd <= 1.0 if self.mask else torch.ones_like(rd, dtype=torch.bool)
        a = (x * scale * tan).to(dtype=dtype, device=device)
        b = (y * scale * tan).to(dtype=dtype, device=device)
        return a, b, valid.to(device=device)

    def check_inside(self, shape) -> None:
        """Refuse a position outside the box of a volume of ``shape`` ``(D, H, W)`` (``inside="require"``).

        Raises:
            ConfigError: naming ``position``, when it lies outside ``[-0.5, N - 0.5]`` on some axis.
        """
        if self.inside != "require":
            return
        p = self.position.detach().to(torch.float64).cpu().tolist()
        if any(not (-0.5 <= c <= n - 0.5) for c, n in zip(p, shape)):
            box = " x ".join(f"[-0.5, {n - 0.5:g}]" for n in shape)
            raise ConfigError(
                "position",
                f"a camera position inside the volume's box {box} (or inside='allow')",
                got=[round(c, 4) for c in p],
            )

    def local_rays(self, *, dtype=torch.float32, device=None):
        """Unit ray directions in the camera's own frame ``(3, h, w)`` (right, up, forward) and the mask ``(h, w)``.

        They depend on the image only (size, fov, distortion, mask), not on the pose: kept from one
        call to the next (a 700 x 600 image's undistortion is tens of milliseconds), so a moving camera
        only rotates them (:meth:`rays`).
        """
        key = (self.size, self.fov, self.distortion, self.mask, dtype, None if device is None else str(device))
        cached = _LOCAL_RAYS.get(key)
        if cached is None:
            a, b, valid = self._image_plane(torch.float64, None)
            local = torch.stack([a, b, torch.ones_like(a)])
            local = local / local.norm(dim=0, keepdim=True)
            cached = (local.to(dtype=dtype, device=device), valid.to(device=device))
            if len(_LOCAL_RAYS) >= 8:  # a few image kinds at a time: drop the oldest
                _LOCAL_RAYS.pop(next(iter(_LOCAL_RAYS)))
            _LOCAL_RAYS[key] = cached
        return cached

    def rays(self, shape, *, dtype=torch.float32, device=None):
        """The eye, unit ray directions and the mask of a volume of ``shape`` ``(D, H, W)``.

        Returns:
            ``eye`` ``(3,)`` [voxels], ``dirs`` ``(3, h, w)`` unit vectors, ``valid`` ``(h, w)`` bool
            (inside the round mask; all True with ``mask=False``). Differentiable in the pose.

        Raises:
            ConfigError: with ``inside="require"``, a position outside the volume's box.
        """
        self.check_inside(shape)
        eye = self.position.to(dtype=dtype, device=device)
        f, u, r = self.basis(dtype=dtype, device=device)
        local, valid = self.local_rays(dtype=dtype, device=device)
        h, w = local.shape[1:]
        d = (torch.stack([r, u, f], 1) @ local.reshape(3, -1)).reshape(3, h, w)  # the frame's rotation
        return eye, d, valid

    def project(self, points):
        """Pixel coordinates and depth of points ``(..., 3)`` [voxels].

        Returns:
            ``pixels`` ``(..., 2)`` as (row, col) in pixel units (pixel ``(i, j)``'s centre is at
            ``(i + 0.5, j + 0.5)``) and ``depth`` ``(...)``, the distance along the view axis
            [voxels]. Points at or behind the eye (depth <= 0) get NaN pixels. The pinhole model
            with the distortion: the exact inverse of :meth:`rays` for points in front.
        """
        points = torch.as_tensor(points)
        if not points.is_floating_point():
            points = points.to(torch.float64)
        dtype, device = points.dtype, points.device
        f, u, r = self.basis(dtype=dtype, device=device)
        rel = points - self.position.to(dtype=dtype, device=device)
        depth = rel @ f
        front = depth > 0
        safe = torch.where(front, depth, torch.ones_like(depth))
        tan = math.tan(math.radians(self.fov) / 2.0)
        xu = (rel @ r) / safe / tan
        yu = (rel @ u) / safe / tan
        g = 1.0 + self.distortion * (xu * xu + yu * yu)
        h, w = self.size
        m = min(h, w) / 2.0
        row = h / 2.0 - yu * g * m
        col = w / 2.0 + xu * g * m
        pix = torch.stack([row, col], -1)
        pix = torch.where(front.unsqueeze(-1), pix, torch.full_like(pix, math.nan))
        return pix, depth
