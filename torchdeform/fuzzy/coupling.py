"""From linguistic inputs per node or per region to per-spring stiffness and damping.

Radetzky's shape modeler sets the fuzzy system's inputs inside user-placed ellipsoids and
writes the resulting spring constant and viscosity to every spring there. Here:

1. :func:`node_inputs` paints input values onto the grid: a base value per input, then
   regions in order (boolean masks ``(D, H, W)`` or :class:`Ellipsoid` s), later ones on top.
2. :func:`spring_parameters` evaluates the fuzzy system **once per distinct input row**
   (``torch.unique`` over the nodes, so a body made of three tissues costs three
   evaluations, not one per node) and turns node values into per-spring tensors
   ``(S, D, H, W)``: each spring is two half-springs in series, one in each end node's
   material, so its value is the harmonic mean of the two end values (equal ends give that
   value). Springs that do not exist are 0.

The result plugs into :class:`~torchdeform.sim.model.Model` (``stiffness=``, ``damping=``).

Example:
    >>> from torchdeform.fuzzy import load_preset
    >>> from torchdeform.fuzzy.coupling import Ellipsoid, node_inputs, spring_parameters
    >>> from torchdeform.sim import Grid, Model
    >>> fis = load_preset("susilap_g")
    >>> grid = Grid((10, 10, 10), spacing=0.01, topology=26)
    >>> inputs = node_inputs(grid, fis, {"consistency": 5.5},
    ...                      regions=[(Ellipsoid((0.05, 0.05, 0.05), (0.02, 0.03, 0.02)), {"consistency": 10.1})])
    >>> params = spring_parameters(fis, grid, inputs)
    >>> params["_evaluations"], tuple(params["spring_const"].shape)      # two tissues: two evaluations
    (2, (13, 10, 10, 10))
    >>> model = Model(grid, stiffness=params["spring_const"], damping=params["viscosity"], density=1000.0)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..errors import ConfigError
from ..sim.grid import Grid
from ..sim.springs import harmonic_mean_of_ends
from .system import MamdaniSystem

__all__ = ["Ellipsoid", "node_inputs", "spring_parameters"]


@dataclass(frozen=True)
class Ellipsoid:
    """An axis-aligned ellipsoid in world coordinates.

    Metres, in the grid's ``(D, H, W)`` axis order: ``center`` ``(3,)``, ``radii`` ``(3,)``.
    """

    center: tuple
    radii: tuple

    def mask(self, grid: Grid) -> torch.Tensor:
        """Bool ``(D, H, W)``: nodes whose rest position lies inside (boundary included)."""
        if len(self.center) != 3 or len(self.radii) != 3 or min(self.radii) <= 0:
            raise ConfigError(
                "ellipsoid", "center (3 numbers) and radii (3 positive numbers)", got=(self.center, self.radii)
            )
        X = grid.rest_positions(dtype=torch.float64)[0]
        c = torch.tensor(self.center, dtype=torch.float64).view(3, 1, 1, 1)
        r = torch.tensor(self.radii, dtype=torch.float64).view(3, 1, 1, 1)
        return (((X - c) / r) ** 2).sum(0) <= 1.0 + 1e-12


def node_inputs(grid: Grid, fis: MamdaniSystem, base: dict, *, regions=()) -> torch.Tensor:
    """Input values per node, ``(n_inputs, D, H, W)`` (float64).

    Args:
        grid: the grid.
        fis: the system (its input names and order).
        base: a value for every input everywhere, ``{name: number}``.
        regions: ``[(mask or Ellipsoid, {name: number}), ...]``; each sets the named inputs
            on its nodes, in order (later regions win).
    """
    names = fis.input_names()
    missing = [n for n in names if n not in base]
    if missing:
        raise ConfigError("base", f"a value for every input ({', '.join(names)})", got=f"missing {missing}")
    out = torch.empty((len(names),) + grid.shape, dtype=torch.float64)
    for i, n in enumerate(names):
        out[i] = float(base[n])
    for k, (where, values) in enumerate(regions):
        mask = where.mask(grid) if isinstance(where, Ellipsoid) else torch.as_tensor(where, dtype=torch.bool)
        if tuple(mask.shape) != grid.shape:
            raise ConfigError(f"regions[{k}]", f"a mask of shape {grid.shape} or an Ellipsoid", got=tuple(mask.shape))
        for n, v in values.items():
            if n not in names:
                raise ConfigError(f"regions[{k}]", f"input names of {fis.name} ({', '.join(names)})", got=n)
            out[names.index(n)][mask] = float(v)
    return out


def spring_parameters(fis: MamdaniSystem, grid: Grid, inputs: torch.Tensor, *, dtype=torch.float32) -> dict:
    """Per-spring values of every output: ``{output name: (S, D, H, W)}``.

    Args:
        fis: the fuzzy system.
        grid: the grid.
        inputs: ``(n_inputs, D, H, W)`` input values per node (see :func:`node_inputs`).
        dtype: dtype of the results.

    Returns:
        dict of per-spring tensors on the device of ``inputs`` (the system is evaluated on its
        own device); also ``"_evaluations"``: how many distinct input rows were evaluated.
    """
    if inputs.dim() != 4 or inputs.shape[0] != len(fis.inputs) or tuple(inputs.shape[1:]) != grid.shape:
        raise ConfigError(
            "inputs", f"shape ({len(fis.inputs)}, {', '.join(map(str, grid.shape))})", got=tuple(inputs.shape)
        )
    rows = inputs.reshape(len(fis.inputs), -1).T
    unique, inverse = torch.unique(rows, dim=0, return_inverse=True)
    values = fis(unique.to(dtype=fis.dtype, device=fis.device)).to(dtype=torch.float64, device=inputs.device)
    nodes = values[inverse].T.reshape((len(fis.outputs),) + grid.shape)  # (O, D, H, W)
    mean = harmonic_mean_of_ends(nodes, grid)  # (O, S, D, H, W)
    out = {name: mean[o].to(dtype) for o, name in enumerate(fis.output_names())}
    out["_evaluations"] = int(unique.shape[0])
    return out
