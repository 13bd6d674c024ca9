"""Transfer functions: voxel value -> colour and extinction, for emission-absorption rendering.

A transfer function is piecewise linear between ``K`` control points ``(value, r, g, b, sigma)``:
colours in ``[0, 1]``, ``sigma`` the extinction per voxel length (>= 0; the "opacity" column of
the files). :func:`~torchdeform.volume.render` reads it through a lookup table
``(resolution, 4)`` (RGB and sigma at evenly spaced values over the control range, volume
units) by linear interpolation; values outside the range take the end entries. The table is
built from the tensors on every call, so gradients reach ``colors`` and ``sigma``.

Control values are in volume units (Hounsfield units for CT), or with ``relative`` fractions of
the rendered volume's ``[min, max]``.

=====================  ===========================================================================
:class:`TransferFunction`  control points, table, lookup, the text file format
:data:`PRESETS`        ``"ct-bone"``, ``"ct-soft"``, ``"ct-liver"``, ``"ct-lumen"`` (Hounsfield units), ``"grey"`` (relative ramp)
:func:`preset`         a preset by name
:func:`load_tf`        a transfer-function file (errors name the file and line)
:func:`get_tf`         a transfer function from itself, a preset name or a file
=====================  ===========================================================================

Example:
    >>> from torchdeform.volume import get_tf
    >>> tf = get_tf("ct-bone")
    >>> tf.name, tf.range(), tuple(tf.table().shape)
    ('ct-bone', (-1000.0, 3000.0), (4096, 4))
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F

from ..checks import read_text
from ..errors import ConfigError

__all__ = ["TransferFunction", "PRESETS", "preset", "load_tf", "get_tf"]


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

    def __init__(self, values, colors, sigma, *, relative: bool = False, resolution: int = 4096, name: str = "custom"):
        self.values = torch.as_tensor(values, dtype=torch.float64).flatten()
        colors = colors if torch.is_tensor(colors) else torch.as_tensor(colors, dtype=torch.float32)
        sigma = sigma if torch.is_tensor(sigma) else torch.as_tensor(sigma, dtype=torch.float32)
        K = self.values.numel()
        if K < 2 or not bool((self.values[1:] > self.values[:-1]).all()) or not bool(torch.isfinite(self.values).all()):
            raise ConfigError(
                "transfer function values", "at least two finite, strictly increasing values", got=self.values.tolist()
            )
        if tuple(colors.shape) != (K, 3):
            raise ConfigError("transfer function colors", f"{K} RGB triples (K, 3)", got=tuple(colors.shape))
        if tuple(sigma.shape) != (K,):
            raise ConfigError("transfer function opacity", f"{K} values", got=tuple(sigma.shape))
        if (
            not bool(torch.isfinite(colors).all())
            or not bool(torch.isfinite(sigma).all())
            or bool((sigma.detach() < 0).any())
        ):
            raise ConfigError("transfer function", "finite colours and opacities >= 0", got="bad values", show_got=True)
        if int(resolution) < 2:
            raise ConfigError("resolution", "an integer >= 2", got=resolution)
        self.colors, self.sigma, self.relative = colors, sigma, bool(relative)
        self.resolution, self.name = int(resolution), name

    def range(self, *, volume: torch.Tensor | None = None) -> tuple[float, float]:
        """``(lo, hi)`` of the control values in volume units."""
        lo, hi = float(self.values[0]), float(self.values[-1])
        if self.relative:
            if volume is None:
                raise ConfigError("transfer function", "a volume to resolve relative values", got=None)
            vmin, vmax = torch.stack(torch.aminmax(volume.detach())).tolist()  # one host sync
            span = (vmax - vmin) or 1.0
            lo, hi = vmin + lo * span, vmin + hi * span
        return lo, hi

    def table(self, *, dtype=torch.float32, device=None) -> torch.Tensor:
        """Lookup table ``(resolution, 4)``: RGB and sigma at evenly spaced values over the range."""
        v = self.values.to(device)
        lo, hi = float(self.values[0]), float(self.values[-1])  # read where the values are (the host): no sync
        x = torch.linspace(lo, hi, self.resolution, dtype=torch.float64, device=device)
        i = torch.searchsorted(v, x, right=True).clamp(1, len(v) - 1)
        f = ((x - v[i - 1]) / (v[i] - v[i - 1])).to(dtype)[:, None]
        knots = torch.cat(
            [self.colors.to(dtype=dtype, device=device), self.sigma.to(dtype=dtype, device=device)[:, None]], 1
        )
        return knots[i - 1] * (1 - f) + knots[i] * f

    def lookup(self, v: torch.Tensor, lo: float, hi: float, *, table: torch.Tensor | None = None) -> torch.Tensor:
        """RGB and sigma of values ``v`` (any shape ``S``) as ``(4, *S)``, by linear interpolation in the table."""
        table = self.table(dtype=v.dtype, device=v.device) if table is None else table
        img = table.t().reshape(1, 4, 1, -1)
        x = (v.reshape(1, 1, -1, 1) - lo) * (2.0 / (hi - lo)) - 1.0
        grid = torch.cat([x, torch.zeros_like(x)], -1)
        out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=True)
        return out.reshape(4, *v.shape)

    def __call__(self, v: torch.Tensor, volume: torch.Tensor | None = None):
        """``(rgb (*S, 3), sigma (*S,))`` at values ``v``."""
        lo, hi = self.range(volume=volume)
        out = self.lookup(v, lo, hi)
        return out[:3].movedim(0, -1), out[3]

    def to(self, dtype) -> TransferFunction:
        """A copy with colours and extinctions in ``dtype`` (the control values stay float64)."""
        return TransferFunction(
            self.values,
            self.colors.to(dtype),
            self.sigma.to(dtype),
            relative=self.relative,
            resolution=self.resolution,
            name=self.name,
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
    "ct-liver": (
        [-1000, 48, 55, 70, 120, 200, 400, 3000],
        [
            [0, 0, 0],
            [0, 0, 0],
            [0.55, 0.18, 0.12],
            [0.7, 0.25, 0.18],
            [1.0, 0.45, 0.35],
            [1.0, 0.6, 0.5],
            [1, 1, 0.95],
            [1, 1, 1],
        ],
        [0.0, 0.0, 0.02, 0.04, 0.08, 0.15, 0.5, 1.0],
        False,
    ),
    # from inside a lumen (virtual endoscopy): air clear, the wall opaque within a voxel or two;
    # mucosa pink, fat yellowish, vessels red, bone white
    "ct-lumen": (
        [-1000, -600, -300, -100, 40, 150, 300, 3000],
        [
            [0, 0, 0],
            [0.95, 0.6, 0.55],
            [0.95, 0.6, 0.55],
            [0.95, 0.85, 0.5],
            [0.9, 0.5, 0.45],
            [0.85, 0.2, 0.2],
            [1, 1, 0.95],
            [1, 1, 1],
        ],
        [0.0, 0.0, 2.0, 5.0, 6.0, 6.0, 8.0, 8.0],
        False,
    ),
    "grey": ([0.0, 1.0], [[0, 0, 0], [1, 1, 1]], [0.0, 0.05], True),
}


def preset(name: str, *, resolution: int = 4096) -> TransferFunction:
    """A built-in transfer function: ``"ct-bone"``, ``"ct-soft"``, ``"ct-liver"``, ``"ct-lumen"`` or ``"grey"`` (relative ramp)."""
    if name not in PRESETS:
        raise ConfigError("--tf", "a preset (" + ", ".join(PRESETS) + ") or a transfer-function file", got=name)
    v, c, s, rel = PRESETS[name]
    return TransferFunction(v, c, s, relative=rel, resolution=resolution, name=name)


def load_tf(path, *, resolution: int = 4096) -> TransferFunction:
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
            "transfer function", "a transfer-function file or a preset (" + ", ".join(PRESETS) + ")", got=str(path)
        )
    text = read_text(path, "transfer function", what="transfer-function file")
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
            raise ConfigError("control point", "five numbers: value r g b opacity", got=line, file=str(path), line=n)
        if not all(0 <= c <= 1 for c in nums[1:4]) or nums[4] < 0:
            raise ConfigError(
                "control point", "colours in [0, 1] and an opacity >= 0", got=line, file=str(path), line=n
            )
        if rows and nums[0] <= rows[-1][0]:
            raise ConfigError("control point", "values in increasing order", got=line, file=str(path), line=n)
        rows.append(nums)
        where.append(n)
    if len(rows) < 2:
        raise ConfigError("transfer function", "at least two control points", got=f"{len(rows)}", file=str(path))
    t = torch.tensor(rows, dtype=torch.float64)
    return TransferFunction(
        t[:, 0], t[:, 1:4].float(), t[:, 4].float(), relative=relative, resolution=resolution, name=path.stem
    )


def get_tf(tf) -> TransferFunction:
    """A :class:`TransferFunction` from itself, a preset name or a file path."""
    if isinstance(tf, TransferFunction):
        return tf
    if tf is None:
        return preset("grey")
    if isinstance(tf, str) and tf in PRESETS:
        return preset(tf)
    return load_tf(tf)
