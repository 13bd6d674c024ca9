"""Volume rendering: transfer functions, cameras, compositing, images; through a displacement field.

Rendering modes
---------------
``dvr``      emission-absorption, front to back: ``alpha_k = 1 - exp(-sigma(v_k) dt_k)``,
             ``C += T alpha_k c_k``, ``T *= 1 - alpha_k``; ``dt`` (voxels) is in the formula, so
             the result does not depend on the number of samples (a homogeneous slab of length
             ``L`` transmits exactly ``exp(-sigma L)``). Early termination once every ray's
             transmittance is below ``stop``. Output ``(B, 4, h, w)``: premultiplied RGB and alpha.
``mip``      maximum intensity along each ray, ``(B, 1, h, w)`` in volume units.
``average``  length-weighted mean along each ray, ``(B, 1, h, w)``.

Cameras
-------
* Axis views ``"d"``, ``"h"``, ``"w"`` (rays along +axis) and ``"-d"``, ``"-h"``, ``"-w"``:
  orthographic, one pixel per voxel of the two other axes (or ``size``), the image axes in
  ``(D, H, W)`` order. These march slab by slab.
* :class:`OrbitCamera`: perspective, looking at the volume's centre from ``azimuth`` /
  ``elevation`` degrees (axis D is up), at ``distance`` volume diagonals.

Voxels are unit cubes (coordinates in voxels, the volume occupies ``[-0.5, N - 0.5]`` per
axis), so ``sigma`` is an extinction per voxel length.

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

The fast path (``render(..., engine="eager" | "compiled")``, axis views through offsets, no
gradient): the same samples written as plain tensor code: per chunk of slabs, the offsets from the
image-plane interpolated node layers, trilinear interpolation by hand (eight indexed loads from
the flat volume, :func:`trilinear_flat`), the transfer-function lookup and front-to-back
compositing; under ``torch.compile`` one fused loop per chunk (compiled once per shape, view and
mode; the chunk's start is a 0-d tensor, so it never recompiles). ``dvr`` skips chunks whose
samples can only read values of zero extinction.

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
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from ..checks import check_memory, read_text
from ..errors import ConfigError
from ..outputs import atomic_path
from .deform import DisplacementField, as_offsets, as_volume, axis_weights_at, sample

RENDER_MODES = ("dvr", "mip", "average")
AXIS_VIEWS = ("d", "h", "w", "-d", "-h", "-w")


# ================================================================= transfer functions
class TransferFunction:
    """Piecewise-linear colour and extinction as functions of the voxel value.

    Args:
        values: ``(K,)`` increasing control values (volume units, or fractions of the
            volume's ``[min, max]`` with ``relative=True``).
        colors: ``(K, 3)`` RGB in ``[0, 1]``.
        sigma: ``(K,)`` extinction per voxel length, >= 0 (the "opacity" column).
        relative: ``values`` are fractions of the rendered volume's range.
        resolution: entries of the lookup table (default 4096).
        name: a label.

    The table is built from the tensors on every call, so gradients reach ``colors`` and
    ``sigma`` (make them ``requires_grad``). Values outside the control range take the end
    entries.

    Example:
        >>> import torch
        >>> from torchdeform.volume import TransferFunction
        >>> tf = TransferFunction([0.0, 100.0], [[0, 0, 0], [1, 1, 1]], [0.0, 2.0])
        >>> rgb, s = tf(torch.tensor([50.0]))
        >>> [round(float(c), 3) for c in rgb[0]], round(float(s[0]), 3)
        ([0.5, 0.5, 0.5], 1.0)
    """

    def __init__(self, values, colors, sigma, relative: bool = False, resolution: int = 4096, name: str = "custom"):
        self.values = torch.as_tensor(values, dtype=torch.float64).flatten()
        colors = colors if torch.is_tensor(colors) else torch.as_tensor(colors, dtype=torch.float32)
        sigma = sigma if torch.is_tensor(sigma) else torch.as_tensor(sigma, dtype=torch.float32)
        K = self.values.numel()
        if K < 2 or not bool((self.values[1:] > self.values[:-1]).all()) or not bool(torch.isfinite(self.values).all()):
            raise ConfigError(
                "transfer function values", "at least two finite, strictly increasing values", self.values.tolist()
            )
        if tuple(colors.shape) != (K, 3):
            raise ConfigError("transfer function colors", f"{K} RGB triples (K, 3)", tuple(colors.shape))
        if tuple(sigma.shape) != (K,):
            raise ConfigError("transfer function opacity", f"{K} values", tuple(sigma.shape))
        if (
            not bool(torch.isfinite(colors).all())
            or not bool(torch.isfinite(sigma).all())
            or bool((sigma.detach() < 0).any())
        ):
            raise ConfigError("transfer function", "finite colours and opacities >= 0", "bad values", show_got=True)
        if int(resolution) < 2:
            raise ConfigError("resolution", "an integer >= 2", resolution)
        self.colors, self.sigma, self.relative = colors, sigma, bool(relative)
        self.resolution, self.name = int(resolution), name

    def range(self, volume: torch.Tensor | None = None) -> tuple[float, float]:
        """``(lo, hi)`` of the control values in volume units."""
        lo, hi = float(self.values[0]), float(self.values[-1])
        if self.relative:
            if volume is None:
                raise ConfigError("transfer function", "a volume to resolve relative values", None)
            vmin, vmax = float(volume.min()), float(volume.max())
            span = (vmax - vmin) or 1.0
            lo, hi = vmin + lo * span, vmin + hi * span
        return lo, hi

    def table(self, dtype=torch.float32, device=None) -> torch.Tensor:
        """Lookup table ``(resolution, 4)``: RGB and sigma at evenly spaced values over the range."""
        v = self.values.to(device)
        x = torch.linspace(float(v[0]), float(v[-1]), self.resolution, dtype=torch.float64, device=device)
        i = torch.searchsorted(v, x, right=True).clamp(1, len(v) - 1)
        f = ((x - v[i - 1]) / (v[i] - v[i - 1])).to(dtype)[:, None]
        knots = torch.cat(
            [self.colors.to(dtype=dtype, device=device), self.sigma.to(dtype=dtype, device=device)[:, None]], 1
        )
        return knots[i - 1] * (1 - f) + knots[i] * f

    def lookup(self, v: torch.Tensor, lo: float, hi: float, table: torch.Tensor | None = None) -> torch.Tensor:
        """RGB and sigma of values ``v`` (any shape ``S``) as ``(4, *S)``, by linear interpolation in the table."""
        table = self.table(v.dtype, v.device) if table is None else table
        img = table.t().reshape(1, 4, 1, -1)
        x = (v.reshape(1, 1, -1, 1) - lo) * (2.0 / (hi - lo)) - 1.0
        grid = torch.cat([x, torch.zeros_like(x)], -1)
        out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=True)
        return out.reshape(4, *v.shape)

    def __call__(self, v: torch.Tensor, volume: torch.Tensor | None = None):
        """``(rgb (*S, 3), sigma (*S,))`` at values ``v``."""
        lo, hi = self.range(volume)
        out = self.lookup(v, lo, hi)
        return out[:3].movedim(0, -1), out[3]

    def to(self, dtype) -> TransferFunction:
        """A copy with colours and extinctions in ``dtype`` (the control values stay float64)."""
        return TransferFunction(
            self.values, self.colors.to(dtype), self.sigma.to(dtype), self.relative, self.resolution, self.name
        )

    # ------------------------------------------------------------ files
    def save(self, path) -> None:
        """Write the text format read by :func:`load_tf`."""
        lines = [f"# torchdeform transfer function: {self.name}", "# value  r  g  b  opacity (extinction per voxel)"]
        if self.relative:
            lines.append("relative")
        for v, c, s in zip(self.values.tolist(), self.colors.detach().tolist(), self.sigma.detach().tolist()):
            lines.append(f"{v:g}  {c[0]:.6g} {c[1]:.6g} {c[2]:.6g}  {s:.6g}")
        Path(path).write_text("\n".join(lines) + "\n")


#: name -> (values, colors, sigma, relative). CT values in Hounsfield units.
PRESETS = {
    "ct-bone": (
        [-1000, 150, 250, 400, 1000, 3000],
        [[0, 0, 0], [0.55, 0.25, 0.2], [0.9, 0.75, 0.6], [1.0, 0.95, 0.85], [1, 1, 1], [1, 1, 1]],
        [0.0, 0.0, 0.02, 0.3, 1.0, 1.0],
        False,
    ),
    "ct-soft": (
        [-1000, -300, -120, -60, 20, 60, 90, 200, 400, 3000],
        [
            [0, 0, 0],
            [0, 0, 0],
            [0.9, 0.8, 0.4],
            [0.9, 0.8, 0.4],
            [0.75, 0.3, 0.25],
            [0.85, 0.4, 0.3],
            [1.0, 0.6, 0.4],
            [1.0, 0.3, 0.3],
            [1, 1, 0.95],
            [1, 1, 1],
        ],
        [0.0, 0.0, 0.004, 0.004, 0.01, 0.03, 0.06, 0.1, 0.5, 1.0],
        False,
    ),
    "grey": ([0.0, 1.0], [[0, 0, 0], [1, 1, 1]], [0.0, 0.05], True),
}


def preset(name: str, resolution: int = 4096) -> TransferFunction:
    """A built-in transfer function: ``"ct-bone"``, ``"ct-soft"`` or ``"grey"`` (relative ramp)."""
    if name not in PRESETS:
        raise ConfigError("--tf", "a preset (" + ", ".join(PRESETS) + ") or a transfer-function file", name)
    v, c, s, rel = PRESETS[name]
    return TransferFunction(v, c, s, relative=rel, resolution=resolution, name=name)


def load_tf(path, resolution: int = 4096) -> TransferFunction:
    """Read a transfer-function file.

    Format: one control point per line, ``value r g b opacity`` (five numbers; colours in
    ``[0, 1]``, opacity = extinction per voxel length >= 0), values increasing; ``#`` starts a
    comment; a line ``relative`` makes the values fractions of the volume's ``[min, max]``.

    Raises:
        ConfigError: naming the file and line.
    """
    path = Path(path)
    if not path.exists():
        raise ConfigError(
            "transfer function", "a transfer-function file or a preset (" + ", ".join(PRESETS) + ")", str(path)
        )
    text = read_text(path, "transfer function", "transfer-function file")
    rows, relative, where = [], False, []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#")[0].strip()
        if not line:
            continue
        if line.lower() == "relative":
            relative = True
            continue
        parts = line.replace(",", " ").split()
        try:
            nums = [float(p) for p in parts]
        except ValueError:
            nums = []
        if len(nums) != 5 or not all(math.isfinite(x) for x in nums):
            raise ConfigError("control point", "five numbers: value r g b opacity", line, file=str(path), line=n)
        if not all(0 <= c <= 1 for c in nums[1:4]) or nums[4] < 0:
            raise ConfigError("control point", "colours in [0, 1] and an opacity >= 0", line, file=str(path), line=n)
        if rows and nums[0] <= rows[-1][0]:
            raise ConfigError("control point", "values in increasing order", line, file=str(path), line=n)
        rows.append(nums)
        where.append(n)
    if len(rows) < 2:
        raise ConfigError("transfer function", "at least two control points", f"{len(rows)}", file=str(path))
    t = torch.tensor(rows, dtype=torch.float64)
    return TransferFunction(t[:, 0], t[:, 1:4].float(), t[:, 4].float(), relative, resolution, path.stem)


def get_tf(tf) -> TransferFunction:
    """A :class:`TransferFunction` from itself, a preset name or a file path."""
    if isinstance(tf, TransferFunction):
        return tf
    if tf is None:
        return preset("grey")
    if isinstance(tf, str) and tf in PRESETS:
        return preset(tf)
    return load_tf(tf)


# ================================================================= cameras
@dataclass
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

    def rays(self, shape, dtype=torch.float32, device=None):
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
    if size is None:
        return None
    try:
        s = tuple(int(v) for v in size)
    except (TypeError, ValueError):
        s = ()
    if len(s) != 2 or min(s) < 1:
        raise ConfigError("size", "an image size (height, width) of positive integers", size)
    # the image, its accumulators and one slab of samples: a few dozen float32 values per pixel
    check_memory("size", 128.0 * s[0] * s[1], f"an image of {s[0]} x {s[1]} pixels", got=s)
    return s


# ================================================================= compositing
class _Accumulator:
    """Front-to-back compositing state for one render mode."""

    def __init__(self, mode, tf, lo, hi, table, shape, dtype, device, B):
        self.mode, self.tf, self.lo, self.hi, self.table = mode, tf, lo, hi, table
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
            e = self.tf.lookup(v, self.lo, self.hi, self.table)  # (4, B, S, *img)
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
        return self.mode == "dvr" and stop > 0 and float(self.T.detach().max()) < stop

    def result(self, background: float = 0.0) -> torch.Tensor:
        """The image; ``mip``/``average`` pixels whose ray misses the volume get ``background``."""
        if self.mode == "dvr":
            return torch.cat([self.C, (1 - self.T).unsqueeze(1)], 1)
        if self.mode == "mip":
            return torch.where(torch.isfinite(self.M), self.M, torch.full_like(self.M, background)).unsqueeze(1)
        hit = self.L > 0
        return torch.where(hit, self.S / self.L.clamp(min=1e-12), torch.full_like(self.S, background)).unsqueeze(1)


def _chunk_slabs(n_img: int, chunk_points: int) -> int:
    return max(1, chunk_points // max(n_img, 1))


# ================================================================= render
def render(
    volume,
    tf=None,
    mode: str = "dvr",
    view="d",
    *,
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
            Same image either way up to rounding.
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
        >>> img = render(vol, tf, "dvr", "d", stop=0)
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
    if vol.shape[1] != 1:
        raise ConfigError("volume", "a single-channel volume (B, 1, D, H, W)", tuple(vol.shape))
    if mode not in RENDER_MODES:
        raise ConfigError("mode", "one of " + ", ".join(RENDER_MODES), mode)
    if warp_mode not in ("deform", "knoche"):
        raise ConfigError("warp_mode", '"deform" or "knoche" when rendering through offsets', warp_mode)
    if not (isinstance(step, (int, float)) and step > 0 and math.isfinite(step)):
        raise ConfigError("step", "a positive number of voxels", step)
    if engine not in ENGINES:
        raise ConfigError("engine", "one of " + ", ".join(ENGINES), engine)
    size = _check_size(size)
    shape = tuple(vol.shape[2:])
    field = None
    if pieces is not None:
        if offsets is not None:
            raise ConfigError("pieces", "either offsets or pieces, not both", "both given", show_got=True)
        pieces = _Pieces(pieces, shape, order, warp_mode == "knoche", vol.dtype, vol.device)
        if vol.shape[0] != pieces.batch and 1 not in (vol.shape[0], pieces.batch):
            raise ConfigError("pieces", f"offsets with a batch of 1 or {vol.shape[0]} (the volume's)", pieces.batch)
        if warp_mode == "knoche":
            inverse_iters, padding = 0, "border"
    if offsets is not None:
        u = as_offsets(offsets, shape, dtype=vol.dtype, device=vol.device)
        if vol.shape[0] != u.shape[0] and 1 not in (vol.shape[0], u.shape[0]):
            raise ConfigError("offsets", f"a batch of 1 or {vol.shape[0]} (the volume's)", u.shape[0])
        field = DisplacementField(u, shape, order, cell_centred=(warp_mode == "knoche"))
        if warp_mode == "knoche":
            inverse_iters, padding = 0, "border"
    tf = get_tf(tf) if mode == "dvr" else None
    lo = hi = table = None
    if tf is not None:
        lo, hi = tf.range(vol)
        table = tf.table(vol.dtype, vol.device)
    B = vol.shape[0] if field is None else max(vol.shape[0], field.nodes.shape[0])
    B = B if pieces is None else max(B, pieces.batch)
    if isinstance(view, OrbitCamera):
        return _render_orbit(
            vol, field, tf, mode, view, inverse_iters, padding, fill, step, stop, chunk_points, lo, hi, table, B, pieces
        )
    if view not in AXIS_VIEWS:
        raise ConfigError("view", "an axis (" + ", ".join(AXIS_VIEWS) + ") or an OrbitCamera", view)
    if engine != "grid_sample" and _fast_supported(vol, field, view, inverse_iters, B):
        return _render_axis_fast(
            vol, field, tf, mode, view, padding, fill, step, size, stop, chunk_points, lo, hi, table, engine
        )[0]
    return _render_axis(
        vol,
        field,
        tf,
        mode,
        view,
        inverse_iters,
        padding,
        fill,
        step,
        size,
        stop,
        chunk_points,
        lo,
        hi,
        table,
        B,
        pieces,
    )


def _render_axis(
    vol,
    field,
    tf,
    mode,
    view,
    inverse_iters,
    padding,
    fill,
    step,
    size,
    stop,
    chunk_points,
    lo,
    hi,
    table,
    B,
    pieces=None,
):
    shape = tuple(vol.shape[2:])
    axis = "dhw".index(view[-1])
    reverse = view.startswith("-")
    others = [a for a in range(3) if a != axis]
    N = shape[axis]
    n = max(1, round(N / step))
    dt = N / n
    img_shape = size or tuple(shape[a] for a in others)
    dtype, device = vol.dtype, vol.device
    # pixel centres in voxel coordinates of the two image axes
    pix = [
        (torch.arange(m, dtype=dtype, device=device) + 0.5) * (shape[a] / m) - 0.5 for m, a in zip(img_shape, others)
    ]
    native = size is None or tuple(size) == tuple(shape[a] for a in others)
    direct = field is None and pieces is None and native and n == N  # samples on voxel centres: read slices
    acc = _Accumulator(mode, tf, lo, hi, table, img_shape, dtype, device, B)
    S = _chunk_slabs(img_shape[0] * img_shape[1], chunk_points)
    order_k = range(n - 1, -1, -1) if reverse else range(n)
    ks = list(order_k)
    if field is not None:
        nodes = field.nodes  # (Bn, 3, nd, nh, nw)
        Wb = axis_weights_at(pix[0], field.node_shape[others[0]], shape[others[0]], field.order, field.cell_centred)
        Wc = axis_weights_at(pix[1], field.node_shape[others[1]], shape[others[1]], field.order, field.cell_centred)
        perm = [0, 1, 2 + axis, 2 + others[0], 2 + others[1]]
        nodes_p = nodes.permute(*perm)  # (Bn, 3, na, nb, nc)
        ctr = torch.einsum("bcaij,Hi,Wj->bcaHW", nodes_p, Wb, Wc) if field.order == "linear" else None
    for start in range(0, n, S):
        kk = torch.tensor(ks[start : start + S], dtype=dtype, device=device)
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
                Wa = axis_weights_at(z, field.node_shape[axis], N, field.order, field.cell_centred)
                if ctr is not None:  # linear: reuse the (b, c) products
                    u_perm = torch.einsum("sa,bcaHW->bcsHW", Wa, ctr)
                else:
                    u_perm = torch.einsum("sa,bcaij,Hi,Wj->bcsHW", Wa, nodes_p, Wb, Wc)
                X = p - u_perm
                if inverse_iters:
                    X, _ = _refine(field, p, X, inverse_iters)
            else:
                X = p
            if pieces is not None:
                v = pieces.sample(vol, p, padding, fill, inverse_iters)[:, 0]
            else:
                v = sample(vol, X, padding, fill)[:, 0]  # (B, S, h, w)
        acc.add(v, torch.tensor(dt, dtype=dtype, device=device))
        if acc.done(stop):
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


def _render_orbit(
    vol, field, tf, mode, cam, inverse_iters, padding, fill, step, stop, chunk_points, lo, hi, table, B, pieces=None
):
    shape = tuple(vol.shape[2:])
    dtype, device = vol.dtype, vol.device
    eye, d = cam.rays(shape, dtype, device)  # (3,), (3, h, w)
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
    acc = _Accumulator(mode, tf, lo, hi, table, img, dtype, device, B)
    S = _chunk_slabs(img[0] * img[1], chunk_points)
    for start in range(0, n, S):
        k = torch.arange(start, min(n, start + S), dtype=dtype, device=device).view(-1, 1, 1)
        seg0 = k * step
        seglen = (length.unsqueeze(0) - seg0).clamp(0, step)  # (S, h, w)
        t = t_near.unsqueeze(0) + seg0 + seglen / 2
        p = (eye.view(3, 1, 1, 1) + d.unsqueeze(1) * t.unsqueeze(0))[None]  # (1, 3, S, h, w)
        X = p
        if field is not None:
            X = p - field.at(p)
            if inverse_iters:
                X, _ = _refine(field, p, X, inverse_iters)
        if pieces is not None:
            v = pieces.sample(vol, p, padding, fill, inverse_iters)[:, 0]
        else:
            v = sample(vol, X, padding, fill)[:, 0]
        acc.add(v, seglen.unsqueeze(0))
        if acc.done(stop):
            break
    return acc.result(float(vol.min()))


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
            raise ConfigError("pieces", expected, type(pieces).__name__)
        self.fields, self.materials = [], []
        for u, m in pieces:
            field = DisplacementField(as_offsets(u, shape, "pieces offsets", dtype, device), shape, order, cell_centred)
            m = torch.as_tensor(m).to(dtype=dtype, device=device)
            if tuple(m.shape) != field.node_shape:
                raise ConfigError(
                    "pieces material", f"a node array {field.node_shape} (the offsets' node grid)", tuple(m.shape)
                )
            if not bool(torch.isfinite(m).all()) or bool((m < 0).any()) or bool((m > 1).any()):
                raise ConfigError("pieces material", "values in [0, 1]", "values outside", show_got=True)
            if self.fields and field.node_shape != self.fields[0].node_shape:
                raise ConfigError(
                    "pieces offsets", f"one node grid {self.fields[0].node_shape} for every piece", field.node_shape
                )
            self.fields.append(field)
            self.materials.append(m[None, None])
        batches = {f.nodes.shape[0] for f in self.fields} - {1}
        if len(batches) > 1:
            raise ConfigError("pieces offsets", "one batch size (or 1) for every piece", sorted(batches))
        self.batch = batches.pop() if batches else 1

    def sample(self, vol, p, padding, fill, inverse_iters):
        """Samples ``(B, 1, *S)`` of ``vol`` at the points ``p`` ``(1, 3, *S)`` through the pieces (``fill`` in gaps)."""
        best_w = best_v = None
        for field, m in zip(self.fields, self.materials):
            X = p - field.at(p)
            if inverse_iters:
                X, _ = _refine(field, p, X, inverse_iters)
            w = sample(m, field.to_node_coords(X), "border")  # (B, 1, *S)
            v = sample(vol, X, padding, fill)
            if best_w is None:
                best_w, best_v = w, v
            else:
                better = w > best_w
                best_v = torch.where(better, v, best_v)
                best_w = torch.maximum(w, best_w)
        return torch.where(best_w >= self.INSIDE, best_v, torch.full_like(best_v, fill))


# ================================================================= fast path (axis views through offsets)
ENGINES = ("grid_sample", "eager", "compiled")

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


def trilinear_flat(v: torch.Tensor, X, shape, padding: str = "border", fill: float = 0.0) -> torch.Tensor:
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

    def __init__(self, shape, node_shape, view, mode, img_shape, n, dt, S, padding, fill, cell_centred, resolution):
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
        val = trilinear_flat(v, X, self.shape, self.padding, self.fill)  # (S, h, w)
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
            compiled = torch.compile(fresh(chunk), dynamic=False, options=inductor_options(FAST_INDUCTOR_OPTIONS))
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


def _fast_supported(vol, field, view, inverse_iters, B) -> bool:
    return (
        field is not None
        and isinstance(view, str)
        and view in AXIS_VIEWS
        and B == 1
        and vol.shape[0] == 1
        and field.order == "linear"
        and not inverse_iters
        and vol.dtype in (torch.float32, torch.float64)
        and not (torch.is_grad_enabled() and (vol.requires_grad or field.nodes.requires_grad))
    )


def _transparent_below(table: torch.Tensor, lo: float, hi: float) -> float:
    """Largest value ``t`` such that every value ``<= t`` has zero extinction in ``table``."""
    sig = table[:, 3]
    pos = torch.nonzero(sig > 0)
    if len(pos) == 0:
        return math.inf
    i = int(pos[0])
    if i == 0:
        return -math.inf
    return lo + (i - 1) * (hi - lo) / (table.shape[0] - 1)


_SLAB_MAX: dict = {}


def _slab_max(v: torch.Tensor, others) -> torch.Tensor:
    """Largest voxel value of each slab across ``others``.

    Cached for the last volume: a frame loop renders one volume many times; the key includes the
    tensor's version counter.
    """
    key = (v.data_ptr(), v._version, tuple(v.shape), v.dtype, tuple(others))
    if key not in _SLAB_MAX:
        _SLAB_MAX.clear()
        _SLAB_MAX[key] = v.amax(dim=tuple(others))
    return _SLAB_MAX[key]


def _render_axis_fast(vol, field, tf, mode, view, padding, fill, step, size, stop, chunk_points, lo, hi, table, engine):
    """:func:`render` of an axis view through the offsets, by :class:`_FastAxis` chunks.

    ``engine`` is ``"eager"`` or ``"compiled"``; returns ``(image, info)`` with ``info`` the chunks
    run/skipped.
    """
    shape = tuple(vol.shape[2:])
    dtype, device = vol.dtype, vol.device
    axis = "dhw".index(view[-1])
    others = [a for a in range(3) if a != axis]
    N = shape[axis]
    n = max(1, round(N / step))
    dt = N / n
    img_shape = size or tuple(shape[a] for a in others)
    pix = [
        (torch.arange(m, dtype=dtype, device=device) + 0.5) * (shape[a] / m) - 0.5 for m, a in zip(img_shape, others)
    ]
    S = min(n, _chunk_slabs(img_shape[0] * img_shape[1], chunk_points), 32 if mode == "dvr" else n)
    cc = field.cell_centred
    Wb = axis_weights_at(pix[0], field.node_shape[others[0]], shape[others[0]], "linear", cc).to(dtype)
    Wc = axis_weights_at(pix[1], field.node_shape[others[1]], shape[others[1]], "linear", cc).to(dtype)
    nodes_p = field.nodes[0].to(dtype).permute(0, 1 + axis, 1 + others[0], 1 + others[1])
    ctr = torch.einsum("caij,Hi,Wj->caHW", nodes_p, Wb, Wc).contiguous()  # (3, n_axis, h, w)
    spec = _FastAxis(
        shape,
        field.node_shape,
        view,
        mode,
        img_shape,
        n,
        dt,
        S,
        padding,
        fill,
        cc,
        table.shape[0] if table is not None else 0,
    )
    fn = _fast_chunk_fn(spec, engine)
    v = vol.reshape(-1).contiguous()
    h, w = img_shape
    if mode == "mip":
        state = (torch.full((h, w), -math.inf, dtype=dtype, device=device),)
    elif mode == "average":
        state = (torch.zeros(h, w, dtype=dtype, device=device), torch.zeros(h, w, dtype=dtype, device=device))
    else:
        state = (torch.zeros(3, h, w, dtype=dtype, device=device), torch.ones(h, w, dtype=dtype, device=device))
    tab = table.reshape(-1).contiguous() if table is not None else torch.zeros(8, dtype=dtype, device=device)
    lohi = torch.tensor([lo if lo is not None else 0.0, hi if hi is not None else 1.0], dtype=dtype, device=device)
    # empty-space skipping (dvr): a chunk whose samples can only read values with zero extinction
    skip_below, slab_max, reach = -math.inf, None, 0
    if mode == "dvr":
        skip_below = _transparent_below(table, lo, hi)
        if math.isfinite(skip_below):
            slab_max = _slab_max(vol[0, 0], others)  # (N,)
            if padding == "zeros":
                slab_max = slab_max.clamp(min=fill)
            reach = math.ceil(float(field.nodes[:, axis].abs().max())) + 1
    pix_b, pix_c = pix[0].view(h, 1), pix[1].view(1, w)
    run = skipped = 0
    for start in range(0, n, S):
        if slab_max is not None:
            ks = list((start, min(n, start + S) - 1))
            zs = [-0.5 + ((n - 1 - k if view.startswith("-") else k) + 0.5) * dt for k in ks]
            a = min(N - 1, max(0, math.floor(min(zs)) - reach))
            b = max(a + 1, min(N, math.ceil(max(zs)) + reach + 1))
            if a >= b or float(slab_max[a:b].max()) <= skip_below:
                skipped += 1
                continue
        state = fn(v, ctr, pix_b, pix_c, torch.tensor(float(start), dtype=dtype, device=device), state, tab, lohi)
        run += 1
        if mode == "dvr" and stop > 0 and float(state[1].max()) < stop:
            break
    if mode == "mip":
        M = state[0]
        img = torch.where(torch.isfinite(M), M, torch.zeros_like(M))[None, None]
    elif mode == "average":
        Ssum, L = state
        img = torch.where(L > 0, Ssum / L.clamp(min=1e-12), torch.zeros_like(Ssum))[None, None]
    else:
        C, T = state
        img = torch.cat([C, (1 - T)[None]], 0)[None]
    return img, {"chunks": run, "skipped": skipped, "slabs_per_chunk": S}


# ================================================================= images
def to_image(image: torch.Tensor, window=None, background=(0.0, 0.0, 0.0), flip_up: bool = False):
    """A rendered image ``(B, C, h, w)`` (first of the batch) -> uint8 numpy ``(h, w, 3)``.

    ``dvr`` images are composited over ``background``; ``mip``/``average`` images are mapped
    linearly from ``window = (lo, hi)`` (default: the image's own range) to black..white.
    ``flip_up``: flip the rows (for side views, so that high D is at the top).
    """
    import numpy as np

    img = image.detach()[0].double().cpu()
    if img.shape[0] == 4:
        bg = torch.tensor(background, dtype=torch.float64).view(3, 1, 1)
        rgb = img[:3] + (1 - img[3:4]) * bg
    else:
        lo, hi = window if window is not None else (float(img.min()), float(img.max()))
        rgb = ((img - lo) / ((hi - lo) or 1.0)).expand(3, *img.shape[1:])
    out = (rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).permute(1, 2, 0).numpy()
    if flip_up:
        out = out[::-1]
    return np.ascontiguousarray(out)


def save_png(path, rgb) -> None:
    """Write a uint8 ``(h, w, 3)`` array as PNG."""
    from PIL import Image

    with atomic_path(path) as tmp:  # a failed write leaves an earlier image whole
        Image.fromarray(rgb).save(str(tmp))


def save_gif(path, frames, fps: float = 12.0) -> None:
    """Write uint8 ``(h, w, 3)`` frames as a looping GIF."""
    from PIL import Image

    ims = [Image.fromarray(f) for f in frames]
    with atomic_path(path) as tmp:
        ims[0].save(str(tmp), save_all=True, append_images=ims[1:], duration=int(1000 / fps), loop=0)


def orbit_frames(volume, frames: int = 24, elevation: float = 20.0, size=(256, 256), **kw) -> list:
    """Renders from ``frames`` azimuths around the volume (a turntable), as uint8 images."""
    out = []
    for i in range(int(frames)):
        cam = OrbitCamera(azimuth=360.0 * i / frames, elevation=elevation, size=size)
        with torch.no_grad():
            out.append(to_image(render(volume, view=cam, **kw)))
    return out


__all__ = [
    "TransferFunction",
    "PRESETS",
    "preset",
    "load_tf",
    "get_tf",
    "OrbitCamera",
    "render",
    "to_image",
    "save_png",
    "save_gif",
    "orbit_frames",
    "RENDER_MODES",
    "AXIS_VIEWS",
    "ENGINES",
    "trilinear_flat",
    "RenderCompileWarning",
]
