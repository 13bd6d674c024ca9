"""Learnable physical parameters.

Positive transforms, spring and node parameters (shared, per direction class, per region, per
spring), fuzzy springs, and the bundle that builds a :class:`~torchdeform.sim.model.Model`
(Radetzky's network weights ``1/m``, ``c``, ``d``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from ..errors import ConfigError
from ..sim.grid import Grid
from ..sim.springs import harmonic_mean_of_ends
from .series import Series

__all__ = [
    "Positive",
    "SpringParameter",
    "NodeParameter",
    "FuzzySprings",
    "Parameters",
    "to_raw",
    "from_raw",
    "node_to_springs",
    "expand_spring_param",
    "TRANSFORMS",
    "SHARING",
]


TRANSFORMS = ("log", "softplus")
_BLOWUP = 1e30  # the loss L-BFGS sees at trial points where the simulation diverged
SHARING = ("shared", "class", "region", "spring")


def node_to_springs(values: torch.Tensor, grid: Grid, *, spring_mask=None) -> torch.Tensor:
    """Per-node values to per-spring values: harmonic mean of the two end nodes.

    Args:
        values: ``(..., D, H, W)`` with at most one leading dimension (``(D, H, W)`` or ``(B, D, H, W)``).
        grid: the grid (its springs' directions).
        spring_mask: bool ``(S, D, H, W)`` of existing springs, or None (every spring of the grid).

    Returns:
        ``(S, D, H, W)`` (or ``(B, S, D, H, W)``), zero where no spring exists. Differentiable.
    """
    lead = values.dim() == 4
    out = harmonic_mean_of_ends(values if lead else values.unsqueeze(0), grid, spring_mask=spring_mask)
    return out if lead else out[0]


def expand_spring_param(value, grid: Grid, *, regions=None, spring_mask=None, dtype=torch.float64):
    """A spring parameter as ``(S, D, H, W)``.

    ``value`` is a number, a per-region table ``(R,)`` (with node ``regions`` labels
    ``(D, H, W)``), ``(S,)`` or ``(S, D, H, W)``; zero where no spring exists.
    """
    t = torch.as_tensor(np.asarray(value, dtype=np.float64) if not torch.is_tensor(value) else value).to(dtype)
    S, shape = grid.S, grid.shape
    mask = (grid.spring_mask() if spring_mask is None else spring_mask).to(dtype)
    if t.dim() == 0:
        return t * mask
    if regions is not None and t.dim() == 1:
        lab = torch.as_tensor(regions, dtype=torch.long)
        return node_to_springs(t[lab], grid, spring_mask=spring_mask)
    if t.dim() == 1 and t.shape[0] == S:
        return t.view(S, 1, 1, 1) * mask
    if tuple(t.shape) == (S,) + shape:
        return t * mask
    raise ConfigError(
        "spring parameter", f"a number, (R,) with regions, (S,) or (S, D, H, W) = {(S,) + shape}", got=tuple(t.shape)
    )


# ------------------------------------------------------------------- transforms
def to_raw(value: torch.Tensor, transform: str) -> torch.Tensor:
    """Inverse of :func:`from_raw`: the unconstrained number for a positive ``value``."""
    if transform == "log":
        return torch.log(value)
    return torch.where(value > 20, value, torch.log(torch.expm1(value)))


def from_raw(raw: torch.Tensor, transform: str) -> torch.Tensor:
    """Positive value of an unconstrained ``raw`` tensor: ``exp`` or ``softplus``."""
    return torch.exp(raw) if transform == "log" else nn.functional.softplus(raw)


def _check(key, value, allowed):
    if value not in allowed:
        raise ConfigError(key, f"one of {', '.join(allowed)}", got=value)


class Positive(nn.Module):
    """A learnable tensor of positive values, ``value = scale * T(raw)``.

    ``T`` is exp or softplus (``scale`` makes softplus well-conditioned for values far from 1).

    Args:
        init: positive initial values (any shape).
        transform: ``"log"`` or ``"softplus"``.
    """

    def __init__(self, init, *, transform: str = "log", dtype=torch.float64):
        super().__init__()
        _check("transform", transform, TRANSFORMS)
        init = torch.as_tensor(init, dtype=dtype).clone()
        if not bool(torch.isfinite(init).all()) or bool((init <= 0).any()):
            raise ConfigError("init", "finite values > 0", got=init.flatten()[:5].tolist())
        self.transform = transform
        scale = float(init.abs().mean()) if transform == "softplus" else 1.0
        self.register_buffer("scale", torch.tensor(scale, dtype=dtype))
        self.raw = nn.Parameter(to_raw(init / scale, transform))

    def forward(self) -> torch.Tensor:
        """The positive values (the shape of ``init``)."""
        return self.scale * from_raw(self.raw, self.transform)


class SpringParameter(nn.Module):
    """A learned spring parameter (stiffness or damping).

    Args:
        grid: the grid; spring_mask: bool ``(S, D, H, W)`` of existing springs (or None).
        init: initial value(s): a number (broadcast to every learned value), or a tensor of
            the learned shape (below).
        sharing: ``"shared"`` (one value, shape ``(1,)``), ``"class"`` (one per direction class
            present: axis/face/body, ``(C,)``), ``"region"`` (one per region label, ``(R,)``;
            needs ``regions``), ``"spring"`` (one per existing spring, ``(n_springs,)``).
        regions: int node labels ``(D, H, W)`` with values ``0 .. R-1`` (``"region"`` only).
        transform: ``"log"`` or ``"softplus"``.

    Calling it returns the per-spring tensor ``(S, D, H, W)`` (zero where no spring exists).
    """

    def __init__(
        self,
        grid,
        *,
        spring_mask=None,
        init=1.0,
        sharing: str = "shared",
        regions=None,
        transform: str = "log",
        dtype=torch.float64,
    ):
        super().__init__()
        _check("sharing", sharing, SHARING)
        self.grid, self.sharing = grid, sharing
        mask = grid.spring_mask() if spring_mask is None else torch.as_tensor(spring_mask, dtype=torch.bool)
        self.register_buffer("mask", mask, persistent=False)
        if sharing == "shared":
            n = 1
        elif sharing == "class":
            classes = grid.direction_class()
            self.classes = sorted(set(classes), key=["axis", "face", "body"].index)
            self.register_buffer(
                "class_index", torch.tensor([self.classes.index(c) for c in classes]), persistent=False
            )
            n = len(self.classes)
        elif sharing == "region":
            if regions is None:
                raise ConfigError("regions", "node labels (D, H, W) for sharing='region'", got=None, show_got=True)
            lab = torch.as_tensor(np.asarray(regions), dtype=torch.long)
            if tuple(lab.shape) != grid.shape or int(lab.min()) < 0:
                raise ConfigError("regions", f"labels >= 0 of shape {grid.shape}", got=tuple(lab.shape))
            self.register_buffer("regions", lab, persistent=False)
            n = int(lab.max()) + 1
        else:
            n = int(mask.sum())
        init = torch.as_tensor(init, dtype=dtype)
        if init.dim() == 0:
            init = init.expand(n)
        if tuple(init.shape) != (n,):
            raise ConfigError("init", f"a number or {n} values for sharing={sharing!r}", got=tuple(init.shape))
        self.value = Positive(init, transform=transform, dtype=dtype)

    @classmethod
    def like(cls, series: Series, *, init=1.0, sharing: str = "shared", transform: str = "log"):
        """A parameter on the grid and springs of ``series`` (regions from its truth, if any)."""
        return cls(
            series.grid,
            spring_mask=series.spring_mask_tensor(),
            init=init,
            sharing=sharing,
            regions=series.truth.get("regions"),
            transform=transform,
        )

    def values(self) -> torch.Tensor:
        """The learned values, ``(n,)``."""
        return self.value()

    def forward(self) -> torch.Tensor:
        """The per-spring tensor ``(S, D, H, W)`` (zero where no spring exists)."""
        v = self.value()
        dtype = v.dtype
        mask = self.mask.to(dtype)
        if self.sharing == "shared":
            return v[0] * mask
        if self.sharing == "class":
            return v[self.class_index].view(-1, 1, 1, 1) * mask
        if self.sharing == "region":
            return node_to_springs(v[self.regions], self.grid, spring_mask=self.mask)
        out = torch.zeros(self.mask.shape, dtype=dtype, device=v.device)
        return out.masked_scatter(self.mask, v)

    def per_spring(self, tensor: torch.Tensor) -> torch.Tensor:
        """The existing springs' entries of a ``(S, D, H, W)`` tensor, ``(n_springs,)``.

        In the order of ``sharing="spring"`` values.
        """
        return torch.as_tensor(tensor, device=self.mask.device)[self.mask]


class NodeParameter(nn.Module):
    """A learned node mass: ``"shared"`` (one value) or ``"node"`` (one per node ``(D, H, W)``).

    Calling it returns ``(D, H, W)``.
    """

    def __init__(self, grid, *, init=1.0, sharing: str = "shared", transform: str = "log", dtype=torch.float64):
        super().__init__()
        _check("sharing", sharing, ("shared", "node"))
        self.grid, self.sharing = grid, sharing
        n = 1 if sharing == "shared" else grid.num_nodes
        init = torch.as_tensor(init, dtype=dtype)
        if init.dim() == 0:
            init = init.expand(n)
        init = init.reshape(-1)
        if init.shape[0] == math.prod(grid.shape) and n != init.shape[0]:
            init = init[grid.nodes().reshape(-1)]
        if tuple(init.shape) != (n,):
            raise ConfigError("init", f"a number or {n} values for sharing={sharing!r}", got=tuple(init.shape))
        self.register_buffer("nodes", grid.nodes(), persistent=False)
        self.value = Positive(init, transform=transform, dtype=dtype)

    def values(self) -> torch.Tensor:
        """The learned values, ``(1,)`` (shared) or ``(num_nodes,)`` (per node)."""
        return self.value()

    def forward(self) -> torch.Tensor:
        """Mass per node ``(D, H, W)`` (zero outside the body)."""
        v = self.value()
        if self.sharing == "shared":
            return v[0] * self.nodes.to(v.dtype)
        return torch.zeros(self.grid.shape, dtype=v.dtype, device=v.device).masked_scatter(self.nodes, v)


class FuzzySprings(nn.Module):
    """Stiffness and damping from a fuzzy system (Radetzky's shape modeler).

    Learnable through its inputs (slider values) or its membership functions.

    The body is one tissue: the system is evaluated once and its outputs set every spring.

    Args:
        fis: a :class:`~torchdeform.fuzzy.MamdaniSystem` (e.g. ``fuzzy.load_preset("susilap_g")``).
        inputs: ``{input name: value}`` (the sliders).
        outputs: ``{"stiffness": output name, "damping": output name}``.
        scale: ``{"stiffness": factor, "damping": factor}``: simulator units per fuzzy output unit.
        learn: ``"inputs"`` (sliders, kept inside each input's range by a sigmoid),
            ``"membership"`` (the output variables' membership parameters) or ``"both"``.
        grid, spring_mask: where the springs are.

    Use :meth:`part` to plug it into :class:`Parameters`::

        fs = FuzzySprings(fis, {"consistency": 7.0}, grid=series.grid, spring_mask=series.spring_mask_tensor())
        params = Parameters(series, fs.part("stiffness"), fs.part("damping"), mass)
    """

    def __init__(
        self, fis, inputs: dict, *, outputs=None, scale=None, learn: str = "inputs", grid=None, spring_mask=None
    ):
        super().__init__()
        _check("learn", learn, ("inputs", "membership", "both"))
        self.fis = fis.double()
        self.outputs = dict(outputs or {"stiffness": "spring_const", "damping": "viscosity"})
        self.scale = dict(scale or {})
        names = self.fis.input_names()
        if set(inputs) != set(names):
            raise ConfigError("inputs", f"a value for each input ({', '.join(names)})", got=sorted(inputs))
        for role, out in self.outputs.items():
            if out not in self.fis.output_names():
                raise ConfigError(
                    f"outputs.{role}", f"an output of {self.fis.name} ({', '.join(self.fis.output_names())})", got=out
                )
        self.fis.requires_grad_(False)
        if learn in ("membership", "both"):
            for v in self.fis.outputs:
                if v.name in self.outputs.values():
                    v.requires_grad_(True)
        lo = torch.tensor([float(v.range[0]) for v in self.fis.inputs], dtype=torch.float64)
        hi = torch.tensor([float(v.range[1]) for v in self.fis.inputs], dtype=torch.float64)
        self.register_buffer("lo", lo)
        self.register_buffer("hi", hi)
        x = torch.tensor([float(inputs[n]) for n in names], dtype=torch.float64)
        if bool(((x <= lo) | (x >= hi)).any()):
            raise ConfigError("inputs", "values strictly inside each input's range", got=inputs)
        u = (x - lo) / (hi - lo)
        self.raw_inputs = nn.Parameter(torch.log(u / (1 - u)), requires_grad=learn in ("inputs", "both"))
        self.grid = grid
        mask = grid.spring_mask() if spring_mask is None else torch.as_tensor(spring_mask, dtype=torch.bool)
        self.register_buffer("mask", mask, persistent=False)

    def inputs(self) -> torch.Tensor:
        """Current slider values ``(n_inputs,)``."""
        return self.lo + (self.hi - self.lo) * torch.sigmoid(self.raw_inputs)

    def forward(self) -> dict:
        """``{role: value}`` in simulator units (0-d tensors)."""
        y = self.fis(self.inputs()[None])[0]
        names = self.fis.output_names()
        return {role: y[names.index(out)] * float(self.scale.get(role, 1.0)) for role, out in self.outputs.items()}

    def part(self, role: str) -> nn.Module:
        """A module returning the per-spring tensor ``(S, D, H, W)`` of ``role``."""
        return _FuzzyPart(self, role)


class _FuzzyPart(nn.Module):
    def __init__(self, source: FuzzySprings, role: str):
        super().__init__()
        self.source, self.role = source, role

    def values(self) -> torch.Tensor:
        return self.source()[self.role].reshape(1)

    def forward(self) -> torch.Tensor:
        return self.source()[self.role] * self.source.mask.to(torch.float64)


class Parameters(nn.Module):
    """Learned and fixed parameters of a series' model.

    Args:
        series: the :class:`~torchdeform.learn.series.Series` (grid, springs, constraints).
        stiffness, damping: a :class:`SpringParameter` (learned) or fixed values (a number or
            ``(S, D, H, W)``).
        mass: a :class:`NodeParameter` (learned) or fixed kg per node (a number or ``(D, H, W)``).
        dtype: of the fixed values and the model.
        device: where the learned modules (moved there) and the fixed values go, and where
            :meth:`model` builds the model (default: where the learned parameters are). The module
            follows ``.to(device)`` later on, fixed values included.
    """

    def __init__(self, series: Series, stiffness, damping, mass, *, dtype=torch.float64, device=None):
        super().__init__()
        self.series, self.dtype = series, dtype
        self.learned = nn.ModuleDict()
        self.fixed = {}
        for name, value in (("stiffness", stiffness), ("damping", damping), ("mass", mass)):
            if isinstance(value, nn.Module):
                self.learned[name] = value
            else:
                self.fixed[name] = torch.as_tensor(
                    np.asarray(value, dtype=np.float64) if not torch.is_tensor(value) else value
                ).to(dtype=dtype, device=device)
        if device is not None:
            self.learned.to(device)

    def _apply(self, fn, recurse=True):
        """``.to()``, ``.cuda()``, ``.double()`` ...: the fixed values follow the learned ones."""
        super()._apply(fn, recurse)
        self.fixed = {name: fn(t) for name, t in self.fixed.items()}
        return self

    @property
    def device(self) -> torch.device:
        """Where the learned parameters are (the CPU when nothing is learned): :meth:`model` builds there."""
        for t in self.parameters():
            return t.device
        return next(iter(self.fixed.values())).device if self.fixed else torch.device("cpu")

    def physical(self) -> dict:
        """``{"stiffness": (S, D, H, W) or number, "damping": ..., "mass": (D, H, W) or number}``."""
        out = dict(self.fixed)
        for name, mod in self.learned.items():
            out[name] = mod()
        return out

    def model(self):
        """The :class:`~torchdeform.sim.model.Model` with the current values (differentiable)."""
        p = self.physical()
        return self.series.model(p["stiffness"], p["damping"], p["mass"], dtype=self.dtype, device=self.device)

    def summary(self) -> dict:
        """Learned values as plain Python: a float for one value, else a list."""
        out = {}
        for name, mod in self.learned.items():
            v = mod.values().detach().cpu().numpy()
            out[name] = float(v[0]) if v.size == 1 else v.tolist()
        return out
