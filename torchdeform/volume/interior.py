"""Rendering from inside a (deformed) volume: :func:`render_endoscope` for an :class:`EndoscopeCamera`.

Coordinates and lengths are voxels of the volume (``(D, H, W)`` order, voxel centres at integer
coordinates, the volume occupying ``[-0.5, N - 0.5]`` per axis); images are ``(B, 4, h, w)``.

The ray march
-------------
Each pixel inside the camera's mask has a ray ``p(t) = e + t d`` (unit ``d``,
:meth:`~torchdeform.volume.EndoscopeCamera.rays`). It is marched from
``t0 = max(near, box entry, 0)`` to ``t1 = min(far, box exit, t_hit)`` (``t_hit``: the first
opaque surface, below) in segments of ``step`` voxels (the last one shorter), with one sample at
each segment's midpoint, exactly as the orbit view of :func:`~torchdeform.volume.render`.

* Through node offsets ``u`` (voxels, a :class:`~torchdeform.volume.DisplacementField`) a
  sample at ``p`` reads the rest volume at ``X = p - u(p)`` (first order, as ``render``); the
  value ``v = V(X)`` is trilinear with border padding.
* The transfer function gives ``(r, g, b, sigma)(v)`` (``sigma``: extinction per voxel length).
* Headlight (``light="headlight"`` or a :class:`Headlight`; ``None``: unlit): the light sits at
  the eye, so the direction to the light is ``l = -d``. The gradient ``g`` of the volume at
  ``X`` is taken by central differences of trilinear samples, one voxel per axis, in rest
  space: the deformation's Jacobian is left out, which is exact to first order in ``grad u``.
  The colour is shaded two-sided (from inside a lumen the tissue's gradient points either way):
  ``c' = c (ambient + diffuse |g . l| / |g|)``, with ``ambient + diffuse`` where
  ``|g| < 1e-6 (hi - lo)`` (a flat region faces the light).
* Emission-absorption front to back: ``alpha = 1 - exp(-sigma dt)``, ``C += T alpha c'``,
  ``T *= 1 - alpha``; the image is premultiplied RGB and ``alpha = 1 - T``. Pixels outside the
  round mask are 0 in all four channels.

Opaque surfaces (``surfaces``: :class:`Sphere`, :class:`Capsule`, :class:`Mesh`, e.g. tools, organ surfaces and the
endoscope's own shaft) are intersected analytically; the march stops at the first hit ``t_hit``
(within ``[near, far]``) and the surface's headlit colour ``colour (ambient + diffuse |n . l|)``
(analytic normal ``n``; unlit: ``colour``) is added with the remaining transmittance ``T``.
The depth (``return_depth=True``) is the ``t`` at which the accumulated alpha first exceeds
1/2, exact inside a segment of constant extinction (``t_s + ln(2 T_s) / sigma``), ``t_hit`` when
a surface does it, ``inf`` if never.

Speed
-----
Rays are processed in chunks of ``chunk_rays`` and segments in chunks of
``chunk_points / chunk_rays`` (at least one), so memory is bounded for any image and volume;
a chunk stops early once every ray's transmittance is below ``stop``. Without a gradient,
``skip_empty`` starts each ray at the first segment that can read a value with non-zero
extinction: a max-pooled occupancy grid of blocks of 8 voxels (each block widened by the
trilinear footprint and by ``max |u|`` through offsets) is probed in pieces of 8 voxels along
the ray (the blocks each piece's bounding box touches); the skipped segments have zero opacity,
so the image is unchanged. The native kernel
(:mod:`.native_march`, when present) is tried by ``engine="auto"`` when no gradient is needed;
``engine="torch"`` is this code, differentiable with respect to the volume, the offsets, the
transfer function's colours and extinctions, and the camera pose.

Example:
    >>> import math
    >>> import torch
    >>> from torchdeform.volume import EndoscopeCamera, TransferFunction, render_endoscope
    >>> vol = torch.full((12, 12, 12), 100.0)
    >>> tf = TransferFunction([0.0, 200.0], [[1, 1, 1], [1, 1, 1]], [0.1, 0.1])
    >>> cam = EndoscopeCamera(position=(5.5, 5.5, 0.0), direction=(0, 0, 1), fov=60.0, size=(9, 9))
    >>> img = render_endoscope(vol, cam, tf=tf, light=None, stop=0)
    >>> tuple(img.shape)
    (1, 4, 9, 9)
    >>> round(float(img[0, 3, 4, 4]), 4), round(1 - math.exp(-0.1 * 11.5), 4)   # 11.5 voxels to the far wall
    (0.6834, 0.6834)
    >>> float(img[0, 3, 0, 0])                                                # outside the round mask
    0.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F

from ..checks import check_memory
from ..errors import ConfigError
from .deform import DisplacementField, as_offsets, as_volume, sample
from .endoscope import EndoscopeCamera
from .fastpath import _transparent_below
from .transfer import get_tf

__all__ = ["Headlight", "Sphere", "Capsule", "Mesh", "render_endoscope", "ENDOSCOPE_ENGINES", "LIGHTS"]

#: Engines of :func:`render_endoscope`: ``"auto"`` (the native kernel when present and no gradient is
#: needed, else ``"torch"``) and ``"torch"``.
ENDOSCOPE_ENGINES = ("auto", "native", "torch")
#: Light names of :func:`render_endoscope` (or a :class:`Headlight`, or None for unlit).
LIGHTS = ("headlight",)

_BLOCK = 8  # occupancy block [voxels] of the empty-space skipping, also its probe spacing along a ray


@dataclass(frozen=True, kw_only=True)
class Headlight:
    """A light at the eye: shaded colour ``c (ambient + diffuse |n . l|)``, ``l = -d``, two-sided.

    Example:
        >>> from torchdeform.volume import Headlight
        >>> Headlight().ambient + Headlight().diffuse
        1.0
    """

    ambient: float = 0.2
    diffuse: float = 0.8

    def __post_init__(self):
        for key in ("ambient", "diffuse"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"light.{key}", "a finite number >= 0", got=v)


def _colour(value, key):
    try:
        c = [float(x) for x in value]
    except (TypeError, ValueError):
        c = []
    if len(c) != 3 or not all(math.isfinite(x) for x in c):
        raise ConfigError(key, "an RGB triple of finite numbers", got=value)
    return tuple(c)


def _point(value, key):
    if torch.is_tensor(value):
        p = value.detach().to(torch.float64).flatten().tolist()
    else:
        try:
            p = [float(x) for x in value]
        except (TypeError, ValueError):
            p = []
    if len(p) != 3 or not all(math.isfinite(x) for x in p):
        raise ConfigError(key, "a point (D, H, W) of three finite numbers in voxels", got=value)
    return tuple(p)


def _radius(value, key):
    try:
        r = float(value)
    except (TypeError, ValueError):
        r = math.nan
    if not (math.isfinite(r) and r > 0):
        raise ConfigError(key, "a positive radius in voxels", got=value)
    return r


def _roots(b, c):
    """Both roots of ``t^2 + 2 b t + c = 0`` (NaN-free: ``inf, -inf`` where there is none)."""
    disc = b * b - c
    hit = disc >= 0
    s = torch.sqrt(disc.clamp(min=0))
    lo = torch.where(hit, -b - s, torch.full_like(b, math.inf))
    hi = torch.where(hit, -b + s, torch.full_like(b, -math.inf))
    return lo, hi


def _first(lo, hi, tmin):
    """The first of an interval's ends at or after ``tmin`` (entry, else exit from inside), else inf."""
    return torch.where(lo >= tmin, lo, torch.where(hi >= tmin, hi, torch.full_like(lo, math.inf)))


@dataclass(frozen=True)
class Sphere:
    """An opaque sphere: ``centre`` ``(3,)`` and ``radius`` in voxels, ``colour`` RGB in ``[0, 1]``.

    Example:
        >>> import torch
        >>> from torchdeform.volume import Sphere
        >>> t, n = Sphere((0.0, 0.0, 5.0), 1.0, (1, 0, 0)).hit(torch.zeros(3), torch.tensor([[0.0], [0.0], [1.0]]))
        >>> t.tolist(), n[:, 0].tolist()
        ([4.0], [0.0, 0.0, -1.0])
    """

    centre: Any
    radius: float
    colour: Any

    def __post_init__(self):
        object.__setattr__(self, "centre", _point(self.centre, "sphere.centre"))
        object.__setattr__(self, "radius", _radius(self.radius, "sphere.radius"))
        object.__setattr__(self, "colour", _colour(self.colour, "sphere.colour"))

    def hit(self, eye, dirs, *, tmin: float = 0.0):
        """First hit ``t`` ``(R,)`` (inf: none) at or after ``tmin`` and the unit outward normal ``(3, R)``.

        The rays are ``eye + t dirs``, ``eye`` ``(3,)`` and unit ``dirs`` ``(3, R)`` in voxels.
        """
        c = torch.tensor(self.centre, dtype=dirs.dtype, device=dirs.device)
        oc = eye - c
        b = oc @ dirs
        cc = oc @ oc - self.radius**2
        t = _first(*_roots(b, cc.expand_as(b)), tmin)
        tt = torch.where(torch.isfinite(t), t, torch.zeros_like(t))
        n = (oc[:, None] + dirs * tt) / self.radius
        return t, n


@dataclass(frozen=True)
class Capsule:
    """An opaque capsule: the points within ``radius`` of the segment ``a``-``b`` (voxels), ``colour`` RGB.

    A tool's shaft, or the endoscope's own.

    Example:
        >>> import torch
        >>> from torchdeform.volume import Capsule
        >>> cap = Capsule((0.0, -3.0, 5.0), (0.0, 3.0, 5.0), 1.0, (1, 1, 1))
        >>> t, n = cap.hit(torch.zeros(3), torch.tensor([[0.0], [0.0], [1.0]]))
        >>> t.tolist(), n[:, 0].tolist()
        ([4.0], [0.0, 0.0, -1.0])
    """

    a: Any
    b: Any
    radius: float
    colour: Any

    def __post_init__(self):
        object.__setattr__(self, "a", _point(self.a, "capsule.a"))
        object.__setattr__(self, "b", _point(self.b, "capsule.b"))
        object.__setattr__(self, "radius", _radius(self.radius, "capsule.radius"))
        object.__setattr__(self, "colour", _colour(self.colour, "capsule.colour"))

    def hit(self, eye, dirs, *, tmin: float = 0.0):
        """First hit ``t`` ``(R,)`` (inf: none) at or after ``tmin`` and the unit outward normal ``(3, R)``.

        The capsule is convex and the union of a finite cylinder and two balls, so the ray's
        interval inside it is the union of its intervals inside the pieces.
        """
        dtype, device = dirs.dtype, dirs.device
        a = torch.tensor(self.a, dtype=dtype, device=device)
        b = torch.tensor(self.b, dtype=dtype, device=device)
        R = self.radius
        inf = torch.full_like(dirs[0], math.inf)
        enter, leave = inf, -inf
        for c in (a, b):  # the end balls
            oc = eye - c
            bb = oc @ dirs
            lo, hi = _roots(bb, (oc @ oc - R * R).expand_as(bb))
            enter, leave = torch.minimum(enter, lo), torch.maximum(leave, hi)
        ba = b - a
        L = float(ba.norm())
        if L > 0:
            axis = ba / L
            oa = eye - a
            da = axis @ dirs  # (R,)
            oa_ax = oa @ axis
            dp = dirs - axis[:, None] * da  # (3, R) components across the axis
            op = oa - axis * oa_ax
            A = (dp * dp).sum(0)
            par = A < 1e-12
            As = torch.where(par, torch.ones_like(A), A)
            lo, hi = _roots((op @ dp) / As, ((op @ op - R * R) / As).expand_as(A))
            inside_inf = bool(op.detach() @ op.detach() <= R * R)  # rays parallel to the axis: all or nothing
            lo = torch.where(par, -inf if inside_inf else inf, lo)
            hi = torch.where(par, inf if inside_inf else -inf, hi)
            # the slab 0 <= oa_ax + t da <= L along the axis
            das = torch.where(da.abs() < 1e-12, torch.full_like(da, 1e-12), da)
            s0, s1 = (0.0 - oa_ax) / das, (L - oa_ax) / das
            in_slab = (oa_ax >= 0) & (oa_ax <= L)
            s_lo = torch.where(da.abs() < 1e-12, torch.where(in_slab, -inf, inf), torch.minimum(s0, s1))
            s_hi = torch.where(da.abs() < 1e-12, torch.where(in_slab, inf, -inf), torch.maximum(s0, s1))
            lo, hi = torch.maximum(lo, s_lo), torch.minimum(hi, s_hi)
            ok = lo <= hi
            enter = torch.where(ok, torch.minimum(enter, lo), enter)
            leave = torch.where(ok, torch.maximum(leave, hi), leave)
        t = _first(enter, leave, tmin)
        tt = torch.where(torch.isfinite(t), t, torch.zeros_like(t))
        p = eye[:, None] + dirs * tt
        if L > 0:
            s = ((p - a[:, None]).T @ axis).clamp(0, L)
            q = a[:, None] + axis[:, None] * s
        else:
            q = a[:, None]
        return t, (p - q) / R


@dataclass(frozen=True, eq=False)
class Mesh:
    """An opaque triangle mesh (an embedded organ surface): ``vertices`` ``(V, 3)`` voxels, ``faces`` ``(F, 3)``.

    ``colour`` RGB in ``[0, 1]``. Rays meet it by the Moller-Trumbore test against every triangle
    (in chunks of triangles; those behind the eye are left out), exact for the flat triangles; the
    normal is the triangle's. Cost grows with rays times triangles: meshes of a few thousand
    triangles and endoscope images of a few hundred pixels across.

    Example:
        >>> import torch
        >>> from torchdeform.volume import Mesh
        >>> square = Mesh([[-1.0, -1.0, 5.0], [1.0, -1.0, 5.0], [1.0, 1.0, 5.0], [-1.0, 1.0, 5.0]],
        ...               [[0, 1, 2], [0, 2, 3]], (1, 1, 1))
        >>> t, n = square.hit(torch.zeros(3), torch.tensor([[0.0, 0.6], [0.0, 0.0], [1.0, 0.8]]))
        >>> t.tolist(), [abs(round(v, 6)) for v in n[:, 0].tolist()]   # the second ray passes beside it
        ([5.0, inf], [0.0, 0.0, 1.0])
    """

    vertices: Any
    faces: Any
    colour: Any

    def __post_init__(self):
        try:
            v = torch.as_tensor(self.vertices, dtype=torch.float64).detach().cpu()
            f = torch.as_tensor(self.faces).detach().cpu()
        except (TypeError, ValueError, RuntimeError):
            raise ConfigError("mesh", "vertices (V, 3) and faces (F, 3) of a triangle mesh", got=None) from None
        if v.dim() != 2 or v.shape[1] != 3 or not bool(torch.isfinite(v).all()):
            raise ConfigError("mesh.vertices", "finite vertices (V, 3) in voxels", got=tuple(v.shape))
        if (
            f.dim() != 2
            or f.shape[1] != 3
            or f.is_floating_point()
            or (f.numel() and (f.min() < 0 or f.max() >= len(v)))
        ):
            raise ConfigError("mesh.faces", f"integer faces (F, 3) indexing the {len(v)} vertices", got=tuple(f.shape))
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f.long())
        object.__setattr__(self, "colour", _colour(self.colour, "mesh.colour"))

    def hit(self, eye, dirs, *, tmin: float = 0.0, chunk: int = 1 << 22):
        """First hit ``t`` ``(R,)`` (inf: none) at or after ``tmin`` and the unit normal ``(3, R)`` (zero where none)."""
        dtype, device = dirs.dtype, dirs.device
        v = self.vertices.to(dtype=dtype, device=device)
        a, b, c = (v[self.faces[:, k].to(device)] for k in range(3))  # (F, 3)
        e1, e2 = b - a, c - a
        R = dirs.shape[1]
        best = torch.full((R,), math.inf, dtype=dtype, device=device)
        normal = torch.zeros(3, R, dtype=dtype, device=device)
        if not len(a):
            return best, normal
        front = ((torch.stack([a, b, c]) - eye) @ (dirs.mean(1) if R else eye)).amax(0) > -1e-9  # any corner ahead
        a, e1, e2 = a[front], e1[front], e2[front]
        n_face = torch.linalg.cross(e1, e2)
        n_face = n_face / n_face.norm(dim=1, keepdim=True).clamp(min=torch.finfo(dtype).tiny)
        D = dirs.T  # (R, 3)
        step = max(1, chunk // max(R, 1))
        eps = 1e-12 if dtype == torch.float64 else 1e-7
        for k in range(0, len(a), step):
            A, E1, E2 = a[k : k + step], e1[k : k + step], e2[k : k + step]
            p = torch.linalg.cross(D[:, None, :].expand(-1, len(A), -1), E2[None].expand(R, -1, -1))  # (R, C, 3)
            det = (p * E1[None]).sum(-1)
            ok = det.abs() > eps * (E1.norm(dim=1) * E2.norm(dim=1))[None]
            inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
            sv = eye[None] - A  # (C, 3)
            u = (p * sv[None]).sum(-1) * inv
            q = torch.linalg.cross(sv, E1)  # (C, 3)
            w = (D @ q.T) * inv
            t = (E2 * q).sum(1)[None] * inv
            hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t >= tmin)
            t = torch.where(hit, t, torch.full_like(t, math.inf))
            tc, idx = t.min(1)
            closer = tc < best
            best = torch.where(closer, tc, best)
            normal = torch.where(closer[None], n_face[k + idx].T, normal)
        return best, normal


# ------------------------------------------------------------------ the resolved render
@dataclass(eq=False, kw_only=True)
class EndoscopePlan:
    """One :func:`render_endoscope` call resolved, for the torch path and the native kernel.

    Fields: ``volume`` ``(B_v, 1, D, H, W)``; ``field`` the
    :class:`~torchdeform.volume.DisplacementField` of the node offsets (voxels) or None;
    ``batch`` images ``B``; ``tf``, ``lo``, ``hi``, ``table`` ``(resolution, 4)`` as
    :class:`~torchdeform.volume.plan.RenderPlan`; ``camera``; ``eye`` ``(3,)``, ``dirs``
    ``(3, h, w)``, ``valid`` ``(h, w)`` its rays in the volume's dtype; ``light`` a
    :class:`Headlight` or None; ``surfaces`` a list; ``step`` [voxels]; ``stop``; ``skip_empty``;
    ``needs_grad``; ``chunk_rays``; ``chunk_points``.
    """

    volume: torch.Tensor
    field: Any
    batch: int
    tf: Any
    lo: float
    hi: float
    table: torch.Tensor
    camera: EndoscopeCamera
    eye: torch.Tensor
    dirs: torch.Tensor
    valid: torch.Tensor
    light: Headlight | None
    surfaces: list
    step: float
    stop: float
    skip_empty: bool
    needs_grad: bool
    chunk_rays: int
    chunk_points: int

    def surface_hits(self, eye: torch.Tensor, dirs: torch.Tensor) -> tuple:
        """The first opaque surface along each ray within ``[near, far]``: ``(t_hit (R,), colour (3, R))``.

        ``t_hit`` is inf where the ray meets none; the colour is headlit (unlit without a light);
        ``dirs`` ``(3, R)``. Both engines composite it behind the volume.
        """
        cam, n_rays = self.camera, dirs.shape[1]
        t_hit = torch.full((n_rays,), math.inf, dtype=dirs.dtype, device=dirs.device)
        s_rgb = torch.zeros(3, n_rays, dtype=dirs.dtype, device=dirs.device)
        for s in self.surfaces:
            t_s, n_s = s.hit(eye, dirs, tmin=max(float(cam.near), 0.0))
            t_s = torch.where(t_s <= cam.far, t_s, torch.full_like(t_s, math.inf))
            col = torch.tensor(s.colour, dtype=dirs.dtype, device=dirs.device).view(3, 1)
            if self.light is not None:
                col = col * (self.light.ambient + self.light.diffuse * (n_s * dirs).sum(0).abs())
            closer = t_s < t_hit
            s_rgb = torch.where(closer, col.expand(3, n_rays), s_rgb)
            t_hit = torch.where(closer, t_s, t_hit)
        return t_hit, s_rgb


def render_endoscope(
    volume,
    camera: EndoscopeCamera,
    *,
    tf=None,
    offsets=None,
    light="headlight",
    step: float = 0.5,
    stop: float = 1e-3,
    surfaces=None,
    engine: str = "auto",
    skip_empty: bool = True,
    chunk_rays: int = 1 << 16,
    chunk_points: int = 1 << 20,
    return_depth: bool = False,
):
    """Render a (deformed) volume from inside, through an :class:`EndoscopeCamera`.

    Args:
        volume: ``(D, H, W)`` or ``(B, 1, D, H, W)`` (volume units, e.g. Hounsfield).
        camera: the :class:`EndoscopeCamera` (voxel coordinates of this volume).
        tf: a :class:`~torchdeform.volume.TransferFunction`, preset name or file (default ``"grey"``).
        offsets: node offsets ``(3, n_d, n_h, n_w)`` / ``(B, 3, ...)`` in voxels, or None; a sample
            at ``p`` reads the volume at ``p - u(p)``.
        light: ``"headlight"``, a :class:`Headlight`, or None (unlit).
        step: segment length along the rays [voxels], > 0.
        stop: early ray termination once every ray of a chunk has transmittance below this (0: never).
        surfaces: opaque :class:`Sphere`, :class:`Capsule` and :class:`Mesh` objects composited by depth, or None.
        engine: ``"auto"`` (the native kernel when it can render this and no gradient is needed,
            else the torch code), ``"native"`` (the kernel or an error) or ``"torch"``.
        skip_empty: skip the segments that can only read fully transparent values (no gradient only;
            the image is unchanged).
        chunk_rays: rays per chunk (memory).
        chunk_points: samples per chunk of segments (memory); ``chunk_points // chunk_rays``
            segments per chunk, at least one.
        return_depth: also return the depth ``(B, h, w)`` [voxels along the ray]: where the alpha
            first exceeds 1/2 (inf: never; masked pixels: inf).

    Returns:
        ``(B, 4, h, w)`` premultiplied RGB and alpha (0 outside the round mask), and with
        ``return_depth`` the tuple ``(image, depth)``.

    Raises:
        ConfigError: a bad step, light, engine or surface, or the camera outside the volume's box
            with ``inside="require"`` (one sentence naming the key).

    Example:
        >>> import torch
        >>> from torchdeform.volume import EndoscopeCamera, Sphere, TransferFunction, render_endoscope
        >>> vol = torch.zeros(16, 16, 16)
        >>> cam = EndoscopeCamera(position=(7.5, 7.5, 0.0), direction=(0, 0, 1), fov=40.0, size=(5, 5))
        >>> ball = Sphere((7.5, 7.5, 10.0), 3.0, (1.0, 0.5, 0.0))
        >>> img, depth = render_endoscope(vol, cam, surfaces=[ball], return_depth=True)
        >>> [round(float(c), 3) for c in img[0, :, 2, 2]], float(depth[0, 2, 2])   # facing the light
        ([1.0, 0.5, 0.0, 1.0], 7.0)
    """
    vol, _ = as_volume(volume)
    if vol.shape[1] != 1:
        raise ConfigError("volume", "a single-channel volume (B, 1, D, H, W)", got=tuple(vol.shape))
    if not isinstance(camera, EndoscopeCamera):
        raise ConfigError("camera", "an EndoscopeCamera", got=type(camera).__name__)
    if isinstance(step, bool) or not (isinstance(step, (int, float)) and math.isfinite(step) and step > 0):
        raise ConfigError("step", "a positive number of voxels", got=step)
    if isinstance(stop, bool) or not (isinstance(stop, (int, float)) and 0 <= stop < 1):
        raise ConfigError("stop", "a transmittance in [0, 1)", got=stop)
    if engine not in ENDOSCOPE_ENGINES:
        raise ConfigError("engine", "one of " + ", ".join(ENDOSCOPE_ENGINES), got=engine)
    light = _light(light)
    for key, n in (("chunk_rays", chunk_rays), ("chunk_points", chunk_points)):
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ConfigError(key, "a positive integer", got=n)
    surfaces = list(surfaces or [])
    for s in surfaces:
        if not isinstance(s, (Sphere, Capsule, Mesh)):
            raise ConfigError("surfaces", "a list of Sphere, Capsule and Mesh objects", got=type(s).__name__)
    shape = tuple(vol.shape[2:])
    field = None
    if offsets is not None:
        u = as_offsets(offsets, volume_shape=shape, dtype=vol.dtype, device=vol.device)
        if vol.shape[0] != u.shape[0] and 1 not in (vol.shape[0], u.shape[0]):
            raise ConfigError("offsets", f"a batch of 1 or {vol.shape[0]} (the volume's)", got=u.shape[0])
        field = DisplacementField(u, shape)
    tf = get_tf(tf)
    lo, hi = tf.range(volume=vol)
    table = tf.table(dtype=vol.dtype, device=vol.device)
    eye, dirs, valid = camera.rays(shape, dtype=vol.dtype, device=vol.device)
    B = vol.shape[0] if field is None else max(vol.shape[0], field.nodes.shape[0])
    needs_grad = torch.is_grad_enabled() and any(
        x is not None and x.requires_grad for x in (vol, field.nodes if field else None, table, eye, dirs)
    )
    # the largest chunk: B images x chunk_points samples x 7 reads (lit) x a dozen numbers, twice for autograd
    n_pts = min(chunk_points, max(chunk_rays, 1) * max(1, chunk_points // chunk_rays))
    item = vol.element_size()
    check_memory("chunk_points", 2.0 * B * n_pts * 7 * 12 * item, f"a chunk of {n_pts} samples", got=chunk_points)
    plan = EndoscopePlan(
        volume=vol,
        field=field,
        batch=B,
        tf=tf,
        lo=lo,
        hi=hi,
        table=table,
        camera=camera,
        eye=eye,
        dirs=dirs,
        valid=valid,
        light=light,
        surfaces=surfaces,
        step=float(step),
        stop=float(stop),
        skip_empty=bool(skip_empty),
        needs_grad=needs_grad,
        chunk_rays=chunk_rays,
        chunk_points=chunk_points,
    )
    out = None
    if engine in ("auto", "native") and not needs_grad:
        out = _native_render(plan)
    if out is None and engine == "native":
        why = "a gradient is needed" if needs_grad else _native_blocker(plan)
        raise ConfigError("engine", "a render the native kernel can make (or engine='auto')", got=why, show_got=True)
    if out is None:
        out = _render_torch(plan)
    return out if return_depth else out[0]


def _light(light):
    if light is None or isinstance(light, Headlight):
        return light
    if isinstance(light, str) and light in LIGHTS:
        return Headlight()
    raise ConfigError("light", '"headlight", a Headlight or None (unlit)', got=light)


def _native_blocker(plan: EndoscopePlan) -> str:
    """Why the native kernel does not render ``plan`` (for the error of ``engine="native"``)."""
    from . import native_march

    why = native_march.unavailable()
    if why:
        return why
    if plan.volume.device.type != "cpu":
        return f"the kernel runs on the CPU (the volume is on {plan.volume.device.type})"
    return f"the kernel takes a float32 volume (this one is {plan.volume.dtype})"


def _native_render(plan: EndoscopePlan):
    """The native kernel's ``(image, depth)`` for ``plan``, or None when it is unavailable.

    The hook of ``engine="auto"``: :mod:`.native_march` (imported lazily) may define
    ``render_endoscope_native(plan) -> (image (B, 4, h, w), depth (B, h, w)) or None`` (None: it
    does not support this plan). Only called when no gradient is needed.
    """
    try:
        from . import native_march
    except ImportError:
        return None
    fn = getattr(native_march, "render_endoscope_native", None)
    if fn is None:
        return None
    return fn(plan)


# ------------------------------------------------------------------ the torch path
def _ray_box(eye, d, shape, near: float, far: float):
    """``t0 = max(near, box entry, 0)`` and ``t1 = min(far, box exit)`` of rays ``(3, R)``."""
    dtype, device = d.dtype, d.device
    lo_b = torch.full((3, 1), -0.5, dtype=dtype, device=device)
    hi_b = torch.tensor([n - 0.5 for n in shape], dtype=dtype, device=device).view(3, 1)
    small = d.abs() < 1e-12
    inv = 1.0 / torch.where(small, torch.full_like(d, 1e-12), d)
    ta = (lo_b - eye.view(3, 1)) * inv
    tb = (hi_b - eye.view(3, 1)) * inv
    # a ray parallel to a face: all of t if the eye is between the faces, none otherwise
    between = (eye.view(3, 1) >= lo_b) & (eye.view(3, 1) <= hi_b)
    t_in = torch.where(small, torch.where(between, -math.inf, math.inf), torch.minimum(ta, tb))
    t_out = torch.where(small, torch.where(between, math.inf, -math.inf), torch.maximum(ta, tb))
    t0 = t_in.amax(0).clamp(min=max(near, 0.0))
    t1 = t_out.amin(0).clamp(max=far)
    return t0, t1


def _occupancy(plan: EndoscopePlan):
    """The block occupancy ``(nb_d, nb_h, nb_w)`` bool: can a sample in the block read an opaque value.

    None when no value is transparent, False when every value is.

    A sample at ``p`` reads the voxels within one voxel of ``X = p - u(p)`` clamped to the volume, so
    within ``1 + max(|u|, 1/2)`` of ``p``: block ``a`` (points ``8a - 0.5 .. 8a + 7.5``) takes the
    maximum over the voxels ``8a - m .. 8a + 7 + m`` with ``m = ceil(2 + max |u|)``.
    """
    skip_below = _transparent_below(plan.table.detach(), plan.lo, plan.hi)
    if not math.isfinite(skip_below):
        return None if skip_below == -math.inf else False  # -inf: nothing transparent; inf: all is
    vol = plan.volume.detach()
    opaque = (vol > skip_below).any(0, keepdim=True).to(vol.dtype)  # (1, 1, D, H, W)
    reach = 0.0 if plan.field is None else float(plan.field.nodes.detach().abs().max())
    m = math.ceil(2.0 + reach)
    nb = [math.ceil(n / _BLOCK) for n in vol.shape[2:]]
    pad = []
    for n, k in zip(reversed(vol.shape[2:]), reversed(nb)):
        pad += [m, k * _BLOCK - n + m]
    occ = F.max_pool3d(F.pad(opaque, pad), kernel_size=_BLOCK + 2 * m, stride=_BLOCK)
    return occ[0, 0] > 0


def _first_segments(plan, occ, eye, d, t0, length):
    """Per ray the first segment index that may read a value with non-zero extinction, ``(R,)`` long.

    The ray is cut into probes of ``8`` voxels; a probe is free when every block that the bounding box
    of its two ends touches (at most two per axis) is empty; the march starts at the first probe
    that is not free, less one segment of margin.
    """
    step = plan.step
    n_seg = torch.ceil(length / step).long()
    if occ is None:
        return torch.zeros_like(n_seg)
    if occ is False:
        return n_seg
    nb = torch.tensor(occ.shape, device=d.device).view(3, 1, 1)
    occ_flat = occ.reshape(-1)
    K = max(1, math.ceil(float(length.max()) / _BLOCK)) if length.numel() else 1
    first = torch.full_like(n_seg, K)
    found = torch.zeros_like(n_seg, dtype=torch.bool)
    t_end = (t0 + length).unsqueeze(0)
    cap = max(1, (1 << 22) // max(1, d.shape[1]))  # probes per batch: at most a few million lookups
    k0, P = 0, 2
    while k0 < K:  # batches of 2, 4, 8, ... probes: rays usually meet tissue early
        kk = torch.arange(k0, min(K, k0 + P), dtype=d.dtype, device=d.device).view(-1, 1)
        ta = t0.unsqueeze(0) + _BLOCK * kk  # (P, R)
        tb = torch.minimum(ta + _BLOCK, t_end)
        pa = eye.view(3, 1, 1) + d.unsqueeze(1) * ta  # (3, P, R)
        pb = eye.view(3, 1, 1) + d.unsqueeze(1) * tb
        lo = torch.minimum(torch.floor((torch.minimum(pa, pb) + 0.5) / _BLOCK).long().clamp(min=0), nb - 1)
        hi = torch.minimum(torch.floor((torch.maximum(pa, pb) + 0.5) / _BLOCK).long().clamp(min=0), nb - 1)
        busy = torch.zeros(kk.shape[0], d.shape[1], dtype=torch.bool, device=d.device)
        for i in (lo[0], hi[0]):
            for j in (lo[1], hi[1]):
                ij = (i * occ.shape[1] + j) * occ.shape[2]
                for k in (lo[2], hi[2]):
                    busy |= occ_flat[ij + k]
        busy &= ta < t_end
        any_busy = busy.any(0)
        idx = torch.where(any_busy, busy.to(torch.uint8).argmax(0) + k0, first)
        first = torch.where(found, first, idx)
        found |= any_busy
        k0 += P
        P = min(2 * P, cap)
        if bool(found.all()):
            break
    t_start = first.to(d.dtype) * _BLOCK  # everything before is transparent (relative to t0)
    k = torch.floor(t_start / step).long() - 1  # one segment of margin for rounding
    return torch.minimum(k.clamp(min=0), n_seg)


def _render_torch(plan: EndoscopePlan):
    """``(image (B, 4, h, w), depth (B, h, w))`` by the torch march (the module docstring)."""
    vol, field, step, B = plan.volume, plan.field, plan.step, plan.batch
    dtype, device = vol.dtype, vol.device
    shape = tuple(vol.shape[2:])
    cam = plan.camera
    h, w = plan.valid.shape
    idx = plan.valid.reshape(-1).nonzero().squeeze(1)
    d_all = plan.dirs.reshape(3, -1).index_select(1, idx)  # (3, N)
    eye = plan.eye
    t0_all, t1_all = _ray_box(eye, d_all, shape, cam.near, cam.far)
    n_rays = d_all.shape[1]
    t_hit, s_rgb = plan.surface_hits(eye, d_all)
    t_end = torch.minimum(t1_all, t_hit)
    length_all = (t_end - t0_all).clamp(min=0)
    skip = plan.skip_empty and not plan.needs_grad
    occ = _occupancy(plan) if skip else None
    thr = 1e-6 * (plan.hi - plan.lo)
    tiny = torch.finfo(dtype).tiny
    light = plan.light
    lit = light is not None
    if lit:
        offs = torch.zeros(7, 3, dtype=dtype, device=device)
        for c in range(3):
            offs[1 + 2 * c, c], offs[2 + 2 * c, c] = 1.0, -1.0
        offs = offs.t().reshape(1, 3, 7, 1, 1)
    colours, alphas, depths = [], [], []
    for r0 in range(0, n_rays, plan.chunk_rays):
        sl = slice(r0, min(n_rays, r0 + plan.chunk_rays))
        d, t0, length = d_all[:, sl], t0_all[sl], length_all[sl]
        R = d.shape[1]
        S = max(1, plan.chunk_points // R)
        with torch.no_grad():
            k0 = _first_segments(plan, occ, eye.detach(), d.detach(), t0.detach(), length.detach()) if skip else None
            n_seg = torch.ceil(length.detach() / step).long()
            n = int((n_seg - k0).max()) if k0 is not None else int(n_seg.max())
        C = torch.zeros(B, 3, R, dtype=dtype, device=device)
        T = torch.ones(B, R, dtype=dtype, device=device)
        depth = torch.full((B, R), math.inf, dtype=dtype, device=device)
        for j0 in range(0, n, S):
            k = torch.arange(j0, min(n, j0 + S), device=device).view(-1, 1)  # (S, 1)
            if k0 is not None:
                k = k + k0.view(1, -1)
            seg0 = k.to(dtype) * step  # (S, R) or (S, 1)
            seglen = (length.unsqueeze(0) - seg0).clamp(0, step)  # (S, R)
            t = t0.unsqueeze(0) + seg0 + seglen / 2
            p = (eye.view(3, 1, 1) + d.unsqueeze(1) * t.unsqueeze(0))[None]  # (1, 3, S, R)
            X = p - field.at(p) if field is not None else p  # (B or 1, 3, S, R)
            if light is not None:
                v7 = sample(vol, X.unsqueeze(2) + offs)[:, 0]  # (B, 7, S, R)
                v = v7[:, 0]
                g = 0.5 * (v7[:, 1::2] - v7[:, 2::2])  # (B, 3, S, R), per voxel
                gl = (g * d.view(1, 3, 1, R)).sum(1).abs()
                gn = (g * g).sum(1).clamp(min=tiny).sqrt()
                cos = gl / gn.clamp(min=max(thr, tiny))
                shade = light.ambient + light.diffuse * torch.where(gn < thr, torch.ones_like(cos), cos)
            else:
                v = sample(vol, X)[:, 0]  # (B, S, R)
            if v.shape[0] != B:
                v = v.expand(B, *v.shape[1:])
            e = plan.tf.lookup(v, plan.lo, plan.hi, table=plan.table)  # (4, B, S, R)
            rgb = e[:3] * shade if lit else e[:3]
            alpha = -torch.expm1(-e[3] * seglen)
            trans = torch.cumprod(1 - alpha, dim=1)
            before = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], 1) * T.unsqueeze(1)  # (B, S, R)
            C = C + torch.einsum("cbsr,bsr->bcr", rgb, before * alpha)
            with torch.no_grad():
                after = before * (1 - alpha)
                cross = (before >= 0.5) & (after < 0.5)
                first = cross & (cross.cumsum(1) == 1)
                sig = e[3].detach().clamp(min=tiny)
                t_seg = t0.detach().unsqueeze(0) + seg0  # the segments' starts
                tc = (t_seg + torch.log(2 * before.detach().clamp(min=0.5)) / sig).expand_as(before)
                found = first.any(1)
                tcross = torch.where(first, tc, torch.zeros_like(tc)).sum(1)
                depth = torch.where(found & torch.isinf(depth), tcross, depth)
            T = T * trans[:, -1]
            if plan.stop > 0 and float(T.detach().max()) < plan.stop:
                break
        if plan.surfaces:
            hit = torch.isfinite(t_hit[sl])
            C = C + torch.where(hit, T.unsqueeze(1) * s_rgb[:, sl], torch.zeros_like(C))
            with torch.no_grad():
                depth = torch.where(hit & (T >= 0.5) & torch.isinf(depth), t_hit[sl].expand_as(depth), depth)
            T = torch.where(hit, torch.zeros_like(T), T)
        colours.append(C)
        alphas.append(1 - T)
        depths.append(depth)
    img = torch.zeros(B, 4, h * w, dtype=dtype, device=device)
    dep = torch.full((B, h * w), math.inf, dtype=dtype, device=device)
    if n_rays:
        vals = torch.cat([torch.cat(colours, 2), torch.cat(alphas, 1).unsqueeze(1)], 1)  # (B, 4, N)
        img = img.index_copy(2, idx, vals)
        dep = dep.index_copy(1, idx, torch.cat(depths, 1))
    return img.view(B, 4, h, w), dep.view(B, h, w)
