"""Synthetic time series of deforming bodies, for learning their parameters (``torchdeform.learn``).

A :class:`Series` holds observed node positions at some steps of a simulation plus everything
needed to run that simulation again: the grid and its springs, fixed nodes, loads, the time
step, the integrator and, for synthetic data, the true parameters.

=========================  ================================================================
generator                  what
=========================  ================================================================
:func:`radetzky_cube`      Radetzky's cube: 3 x 3 x 3 nodes, 54 / 70 / 86 / 126 springs,
                           lower 9 nodes fixed, a constant force on the top-centre node,
                           250 steps (thesis §2.3, EUFIT'99)
:func:`cube_series`        n^3 cubes, any topology, loads (constant, ramps, sinusoidal
                           drags, indentation), heterogeneous materials by region,
                           observation noise, partial observation, sparse times
:func:`balloon_series`     a closed surface from trimesh (icosphere by default) voxelised
                           into a grid, inflated by a rising pressure along the vertex
                           normals, observed in a few snapshots (Radetzky's balloon)
=========================  ================================================================

Conventions:

* Dynamics are those of :class:`~torchdeform.integrators.SymplecticEuler` (default) with
  the external force of step ``n`` evaluated at ``t_n = n dt`` and prescribed (dragged) nodes
  put on their path at ``t_{n+1}`` after every step; :meth:`Series.advance` is that step, the
  same for generation and learning, so a model with the true parameters reproduces clean
  data to rounding.
* The series starts from rest (``x = X``, ``v = 0``) at step 0.
* Observations ``positions[i]`` are taken at step ``steps[i]``; ``mask[i]`` says which nodes
  were seen (missing data / partial observation).
* Noise: Gaussian with standard deviation ``noise * RMS(x - X)`` over the free-node
  coordinates of the clean observations (so ``noise=0.01`` is "1 % noise").
* Heterogeneous materials: integer region labels per node; a spring whose ends lie in
  different regions gets the harmonic mean of the two values (two half-springs in series,
  as :mod:`torchdeform.fuzzy.coupling` does).

Files are ``.npz``: arrays plus one JSON string ``meta`` (format version, dt, grid, spring
set, integrator, loads, noise, seed, description). :func:`load_series` validates everything
and raises a one-line :class:`~torchdeform.errors.ConfigError` naming the file and the key.

Example:
    >>> from torchdeform import data
    >>> s = data.radetzky_cube(springs=70)
    >>> s.positions.shape, s.steps[-1], s.grid.num_springs
    ((251, 3, 3, 3, 3), 250, 70)
    >>> s.save("cube70.npz"); s2 = data.load_series("cube70.npz")
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .errors import ConfigError
from .grid import Grid
from .integrators import INTEGRATORS
from .model import Model, State
from .springs import harmonic_mean_of_ends

FORMAT = "torchdeform-series/1"

#: Radetzky's cube spring sets: number of springs -> (topology, kept half-directions or None).
#: 70 is Radetzky's count; the thesis figure that placed its 16 extra springs is lost, so we
#: add one crossing pair of body diagonals per cell (half-directions (1,1,1) and (1,-1,-1)).
SPRING_SETS = {54: (6, None), 70: (14, ((1, 1, 1), (1, -1, -1))), 86: (14, None), 126: (18, None)}

PROFILES = ("constant", "ramp", "sine")
LOAD_KINDS = ("force", "field", "drag")


# ---------------------------------------------------------------------------- loads
@dataclass
class Load:
    """One load term of a series (JSON-serialisable).

    Args:
        kind: ``"force"`` (``vector`` newtons on each node of ``nodes``), ``"field"`` (a dense
            force field ``(3, D, H, W)`` given as ``array``, e.g. pressure along normals) or
            ``"drag"`` (``nodes`` prescribed at ``X + vector * factor(t)``: drags and
            indentation).
        nodes: node indices ``[[i, j, k], ...]`` (force, drag).
        vector: ``(3,)`` newtons (force) or metres (drag); for ``field`` a scale factor
            ``[s, s, s]`` is not used (use ``array``).
        profile: ``"constant"`` (1 from ``start`` on), ``"ramp"`` (0 to 1 over ``duration``
            seconds from ``start``) or ``"sine"`` (``sin(2 pi (t - start) / period)`` from ``start``).
        array: the field ``(3, D, H, W)`` (``field`` only).
    """
    kind: str
    nodes: list = field(default_factory=list)
    vector: tuple = (0.0, 0.0, 0.0)
    profile: str = "constant"
    start: float = 0.0
    duration: float = 0.0
    period: float = 1.0
    array: np.ndarray | None = None

    def factor(self, t: np.ndarray) -> np.ndarray:
        """Profile value at times ``t`` (seconds), same shape."""
        t = np.asarray(t, dtype=np.float64)
        on = t >= self.start
        if self.profile == "constant":
            f = np.ones_like(t)
        elif self.profile == "ramp":
            f = np.ones_like(t) if self.duration <= 0 else np.clip((t - self.start) / self.duration, 0.0, 1.0)
        else:
            f = np.sin(2 * math.pi * (t - self.start) / self.period)
        return np.where(on, f, 0.0)

    def to_json(self, index: int) -> dict:
        d = {"kind": self.kind, "profile": self.profile, "start": self.start, "duration": self.duration,
             "period": self.period}
        if self.kind == "field":
            d["array"] = f"load_field_{index}"
        else:
            d["nodes"] = [list(map(int, n)) for n in self.nodes]
            d["vector"] = [float(c) for c in self.vector]
        return d

    @staticmethod
    def from_json(d, arrays: dict, where: str) -> "Load":
        def bad(key, expected, got):
            return ConfigError(f"{where}.{key}", expected, got)
        if not isinstance(d, dict):
            raise ConfigError(where, "a table with kind, profile, ...", d)
        kind = d.get("kind")
        if kind not in LOAD_KINDS:
            raise bad("kind", f"one of {', '.join(LOAD_KINDS)}", kind)
        profile = d.get("profile", "constant")
        if profile not in PROFILES:
            raise bad("profile", f"one of {', '.join(PROFILES)}", profile)
        nums = {}
        for k, default in (("start", 0.0), ("duration", 0.0), ("period", 1.0)):
            v = d.get(k, default)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise bad(k, "a finite number >= 0 (s)", v)
            nums[k] = float(v)
        if profile == "sine" and nums["period"] <= 0:
            raise bad("period", "a positive number (s)", nums["period"])
        if kind == "field":
            name = d.get("array")
            if name not in arrays:
                raise bad("array", "the name of a (3, D, H, W) array stored in the file", name)
            return Load(kind, profile=profile, array=np.asarray(arrays[name], dtype=np.float64), **nums)
        nodes, vector = d.get("nodes"), d.get("vector")
        try:
            nodes = [tuple(int(c) for c in n) for n in nodes]
            ok = all(len(n) == 3 for n in nodes) and len(nodes) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise bad("nodes", "a non-empty list of node indices [[i, j, k], ...]", d.get("nodes"))
        try:
            vector = tuple(float(c) for c in vector)
        except (TypeError, ValueError):
            vector = ()
        if len(vector) != 3 or not all(math.isfinite(c) for c in vector):
            raise bad("vector", "three finite numbers (d, h, w)", d.get("vector"))
        return Load(kind, nodes=nodes, vector=vector, profile=profile, **nums)


def point_force(node, force, profile="constant", **kw) -> Load:
    """A force (N) on one node, e.g. ``point_force((2, 1, 1), (-0.1, 0, 0))``."""
    return Load("force", nodes=[tuple(node)], vector=tuple(force), profile=profile, **kw)


def drag(nodes, offset, profile="sine", **kw) -> Load:
    """Nodes moved rigidly to ``X + offset * factor(t)``; default a sinusoidal drag."""
    return Load("drag", nodes=[tuple(n) for n in nodes], vector=tuple(offset), profile=profile, **kw)


def indentation(grid: Grid, depth: float, radius: int = 0, duration: float = 0.5) -> Load:
    """An indenter pushed ``depth`` metres into the top face (axis D, ``"top"``) over
    ``duration`` seconds: the top nodes within ``radius`` nodes (Chebyshev) of the face centre
    are prescribed at ``X - depth e_D`` (ramp)."""
    D, H, W = grid.shape
    ch, cw = (H - 1) / 2, (W - 1) / 2
    nodes = [(D - 1, j, k) for j in range(H) for k in range(W)
             if abs(j - ch) <= radius + 0.5 and abs(k - cw) <= radius + 0.5]
    return Load("drag", nodes=nodes, vector=(-float(depth), 0.0, 0.0), profile="ramp", duration=float(duration))


# ---------------------------------------------------------------------------- springs
def cube_grid(n: int = 3, spacing: float = 0.01, springs: int | None = None, topology: int = 26):
    """A cube of ``n^3`` nodes and its spring mask.

    Args:
        n: nodes per edge; spacing: metres.
        springs: one of Radetzky's sets (54, 70, 86, 126; ``n = 3`` only), or None to use ``topology``.
        topology: 6, 14, 18 or 26 (when ``springs`` is None).
    Returns:
        ``(grid, spring_mask)``: the mask is bool ``(S, D, H, W)`` or None (every spring).
    """
    if springs is not None:
        if springs not in SPRING_SETS:
            raise ConfigError("springs", f"one of {', '.join(map(str, SPRING_SETS))}", springs)
        if n != 3:
            raise ConfigError("springs", "Radetzky's spring sets only on a 3 x 3 x 3 cube (n = 3)", n)
        topology, keep = SPRING_SETS[springs]
    else:
        keep = None
    grid = Grid((n, n, n), spacing=spacing, topology=topology)
    if keep is None:
        return grid, None
    mask = grid.spring_mask().clone()
    for s, d in enumerate(grid.directions):
        if sum(map(abs, d)) == 3 and d not in keep:
            mask[s] = False
    return grid, mask


def node_to_springs(values: torch.Tensor, grid: Grid, spring_mask=None) -> torch.Tensor:
    """Per-node values to per-spring values: harmonic mean of the two end nodes.

    Args:
        values: ``(..., D, H, W)`` with at most one leading dimension (``(D, H, W)`` or ``(B, D, H, W)``).
    Returns:
        ``(S, D, H, W)`` (or ``(B, S, D, H, W)``), zero where no spring exists. Differentiable.
    """
    lead = values.dim() == 4
    out = harmonic_mean_of_ends(values if lead else values.unsqueeze(0), grid, spring_mask)
    return out if lead else out[0]


def expand_spring_param(value, grid: Grid, regions=None, spring_mask=None, dtype=torch.float64):
    """A spring parameter as ``(S, D, H, W)``: a number, a per-region table ``(R,)`` (with
    node ``regions`` labels ``(D, H, W)``), ``(S,)`` or ``(S, D, H, W)``."""
    t = torch.as_tensor(np.asarray(value, dtype=np.float64) if not torch.is_tensor(value) else value).to(dtype)
    S, shape = grid.S, grid.shape
    mask = (grid.spring_mask() if spring_mask is None else spring_mask).to(dtype)
    if t.dim() == 0:
        return t * mask
    if regions is not None and t.dim() == 1:
        lab = torch.as_tensor(regions, dtype=torch.long)
        return node_to_springs(t[lab], grid, spring_mask)
    if t.dim() == 1 and t.shape[0] == S:
        return t.view(S, 1, 1, 1) * mask
    if tuple(t.shape) == (S,) + shape:
        return t * mask
    raise ConfigError("spring parameter", f"a number, (R,) with regions, (S,) or (S, D, H, W) = {(S,) + shape}",
                      tuple(t.shape))


# ---------------------------------------------------------------------------- series
@dataclass
class Series:
    """An observed time series of node positions and the set-up that produced it.

    Attributes:
        positions: observations ``(T, 3, D, H, W)`` (float64 numpy), metres.
        steps: step index of each observation ``(T,)`` (int, strictly increasing).
        mask: bool ``(T, D, H, W)``: node observed at that time.
        dt: time step (s).
        grid: the :class:`~torchdeform.grid.Grid`; spring_mask: bool ``(S, D, H, W)`` or None.
        fixed: bool ``(D, H, W)`` nodes that never move.
        loads: list of :class:`Load`.
        damping_mode: ``"unprojected"`` (Radetzky) or ``"projected"``.
        integrator: name in :data:`~torchdeform.integrators.INTEGRATORS` (``"symplectic"``).
        truth: true parameters (synthetic data): ``stiffness``, ``damping`` (per-spring
            ``(S, D, H, W)`` arrays), ``mass`` (``(D, H, W)``), optionally ``regions`` (node
            labels) and the scalar/table values in ``meta["truth"]``.
        meta: JSON-able dict (description, generator settings, noise, seed ...).
    """
    positions: np.ndarray
    steps: np.ndarray
    mask: np.ndarray
    dt: float
    grid: Grid
    spring_mask: np.ndarray | None
    fixed: np.ndarray
    loads: list
    damping_mode: str = "unprojected"
    integrator: str = "symplectic"
    truth: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    # ---------------------------------------------------------------- helpers
    @property
    def num_steps(self) -> int:
        """Last simulated step (the series covers steps ``0 .. num_steps``)."""
        return int(self.steps[-1])

    @property
    def every(self) -> int:
        """Steps between observations (requires uniform spacing)."""
        return int(self.steps[1] - self.steps[0]) if len(self.steps) > 1 else 1

    def spring_mask_tensor(self, device=None) -> torch.Tensor:
        """Bool ``(S, D, H, W)`` of existing springs."""
        base = self.grid.spring_mask(device)
        return base if self.spring_mask is None else base & torch.as_tensor(self.spring_mask, device=device)

    def prescribed(self) -> np.ndarray:
        """Bool ``(D, H, W)``: dragged nodes."""
        m = np.zeros(self.grid.shape, dtype=bool)
        for ld in self.loads:
            if ld.kind == "drag":
                for n in ld.nodes:
                    m[tuple(n)] = True
        return m

    def constrained(self) -> np.ndarray:
        """Bool ``(D, H, W)``: fixed or dragged."""
        return self.fixed | self.prescribed()

    def tables(self, dtype=torch.float64, device=None) -> dict:
        """Dense load tables over steps ``0 .. num_steps + 1``:
        ``force`` ``(N + 2, 3, D, H, W)`` (external force at ``t_n``) or None, and
        ``drag`` ``(N + 2, 3, D, H, W)`` (prescribed positions at ``t_n``) with ``drag_mask``
        ``(1, 1, D, H, W)``, or None."""
        key = (dtype, str(device))
        cache = self.__dict__.setdefault("_tables", {})
        if key in cache:
            return cache[key]
        n = self.num_steps + 2
        t = np.arange(n) * self.dt
        shape = self.grid.shape
        force, offset = None, None
        for ld in self.loads:
            f = ld.factor(t)[:, None, None, None, None]
            if ld.kind == "field":
                dense = ld.array[None]
            else:
                dense = np.zeros((1, 3) + shape)
                for nd in ld.nodes:
                    dense[(0, slice(None)) + tuple(nd)] = ld.vector
            if ld.kind == "drag":
                offset = f * dense if offset is None else offset + f * dense
            else:
                force = f * dense if force is None else force + f * dense
        out = {"force": None, "drag": None, "drag_mask": None}
        if force is not None:
            out["force"] = torch.as_tensor(force, dtype=dtype, device=device)
        if offset is not None:
            X = self.grid.rest_positions(dtype, device)
            out["drag"] = X + torch.as_tensor(offset, dtype=dtype, device=device)
            out["drag_mask"] = torch.as_tensor(self.prescribed(), device=device)[None, None]
        cache[key] = out
        return out

    def model(self, stiffness, damping, mass, dtype=torch.float64, device=None) -> Model:
        """The :class:`~torchdeform.model.Model` of this set-up with the given parameters
        (any shape :class:`Model` accepts; tensors keep their autograd graph)."""
        fixed = torch.as_tensor(self.constrained())
        return Model(self.grid, stiffness=stiffness, damping=damping, damping_mode=self.damping_mode, mass=mass,
                     fixed=fixed, spring_mask=None if self.spring_mask is None else torch.as_tensor(self.spring_mask),
                     dtype=dtype, device=device)

    def true_model(self, dtype=torch.float64, device=None) -> Model:
        """The model with the true parameters (synthetic series)."""
        if not self.truth:
            raise ConfigError("truth", "a synthetic series with true parameters", "none stored", show_got=True)
        return self.model(torch.as_tensor(self.truth["stiffness"]), torch.as_tensor(self.truth["damping"]),
                          torch.as_tensor(self.truth["mass"]), dtype, device)

    def advance(self, model: Model, state: State, n, integrator=None) -> State:
        """One step of the series' dynamics from step ``n`` (an int, or a ``(B,)`` LongTensor
        of per-batch-entry steps) to ``n + 1``: external force at ``t_n``, the integrator's
        step, dragged nodes onto their positions at ``t_{n+1}``."""
        tab = self.tables(model.dtype, model.device)
        integrator = integrator or INTEGRATORS[self.integrator]()
        now, nxt = (n, n + 1) if torch.is_tensor(n) else (slice(n, n + 1), slice(n + 1, n + 2))
        loads = None if tab["force"] is None else tab["force"][now]
        new = integrator.step(model, state, self.dt, loads)
        if tab["drag"] is not None:
            target = tab["drag"][nxt]
            vel = (target - tab["drag"][now]) / self.dt
            m = tab["drag_mask"]
            new = State(torch.where(m, target, new.x), torch.where(m, vel, new.v), new.t)
        return new

    def start_state(self, model: Model, batch: int = 1) -> State:
        """The state at step 0 (rest; dragged nodes on their path)."""
        st = model.rest_state(batch)
        tab = self.tables(model.dtype, model.device)
        if tab["drag"] is not None:
            m = tab["drag_mask"]
            st = State(torch.where(m, tab["drag"][0], st.x), st.v, 0.0)
        return st

    def simulate(self, model: Model, steps: int | None = None, integrator=None) -> torch.Tensor:
        """Positions ``(N + 1, B, 3, D, H, W)`` at steps ``0 .. N`` (no gradient tracking
        unless the model's parameters require it)."""
        steps = self.num_steps if steps is None else int(steps)
        integrator = integrator or INTEGRATORS[self.integrator]()
        st = self.start_state(model)
        xs = [st.x]
        for n in range(steps):
            st = self.advance(model, st, n, integrator)
            xs.append(st.x)
        return torch.stack(xs)

    # ---------------------------------------------------------------- files
    def save(self, path) -> Path:
        """Write the series to ``path`` (``.npz``, compressed); returns the path."""
        path = Path(path)
        arrays = {"positions": np.asarray(self.positions, dtype=np.float64),
                  "steps": np.asarray(self.steps, dtype=np.int64),
                  "mask": np.asarray(self.mask, dtype=bool), "fixed": np.asarray(self.fixed, dtype=bool)}
        if self.spring_mask is not None:
            arrays["spring_mask"] = np.asarray(self.spring_mask, dtype=bool)
        for k in ("stiffness", "damping", "mass", "regions"):
            if k in self.truth:
                arrays[f"true_{k}"] = np.asarray(self.truth[k])
        loads = []
        for i, ld in enumerate(self.loads):
            if ld.kind == "field":
                arrays[f"load_field_{i}"] = np.asarray(ld.array, dtype=np.float64)
            loads.append(ld.to_json(i))
        g = self.grid
        meta = dict(self.meta)
        meta.update({"format": FORMAT, "dt": float(self.dt), "shape": list(g.shape), "spacing": list(g.spacing),
                     "origin": list(g.origin), "topology": g.topology, "damping_mode": self.damping_mode,
                     "integrator": self.integrator, "loads": loads, "start": "rest",
                     "node_mask": g.node_mask is not None})
        if g.node_mask is not None:
            arrays["node_mask"] = g.node_mask.numpy()
        arrays["meta"] = np.array(json.dumps(meta))
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        return path


def _simulate_truth(series: Series, stiffness, damping, mass, noise: float, every: int, observe, seed: int,
                    dtype=torch.float64) -> Series:
    """Fill ``series.positions/steps/mask/truth`` by simulating the true model."""
    grid = series.grid
    smask = series.spring_mask_tensor()
    regions = series.truth.get("regions")
    k = expand_spring_param(stiffness, grid, regions, smask)
    c = expand_spring_param(damping, grid, regions, smask)
    m = torch.as_tensor(np.asarray(mass, dtype=np.float64)).expand(grid.shape).clone() * grid.nodes()
    series.truth.update({"stiffness": k.numpy(), "damping": c.numpy(), "mass": m.numpy()})
    with torch.no_grad():
        model = series.model(k, c, m, dtype)
        xs = series.simulate(model)[:, 0].to(torch.float64).numpy()        # (N + 1, 3, D, H, W)
    N = xs.shape[0] - 1
    steps = np.arange(0, N + 1, int(every))
    clean = xs[steps]
    obs = np.ones((len(steps),) + grid.shape, dtype=bool)
    if observe is not None:
        obs &= np.asarray(observe, dtype=bool)[None]
    obs &= grid.nodes().numpy()[None]
    pos = clean.copy()
    if noise > 0:
        X = grid.rest_positions(torch.float64)[0].numpy()
        free = ~series.constrained() & grid.nodes().numpy()
        disp = (clean - X[None])[:, :, free]
        sigma = float(noise) * float(np.sqrt(np.mean(disp ** 2)))
        rng = np.random.default_rng(seed)
        pos = pos + rng.normal(0.0, sigma, size=pos.shape)
        series.meta["noise_sigma"] = sigma
    pos[~np.broadcast_to(obs[:, None], pos.shape)] = 0.0                  # unobserved entries carry no data
    series.positions, series.steps, series.mask = pos, steps, obs
    series.meta.update({"noise": float(noise), "seed": int(seed), "every": int(every)})
    return series


def _truth_meta(stiffness, damping, mass) -> dict:
    def js(v):
        a = np.asarray(v, dtype=np.float64)
        return float(a) if a.ndim == 0 else a.tolist()
    return {"stiffness": js(stiffness), "damping": js(damping), "mass": js(mass)}


def radetzky_cube(springs: int = 70, stiffness=10.0, damping=0.1, mass=0.01, force=(-0.05, 0.0, 0.0),
                  steps: int = 250, dt: float = 0.005, spacing: float = 0.01, noise: float = 0.0, every: int = 1,
                  observe=None, seed: int = 0, damping_mode: str = "unprojected") -> Series:
    """Radetzky's cube experiment: 3 x 3 x 3 nodes, lower 9 fixed, a constant force on the
    top-centre node for ``steps`` steps.

    The thesis gives neither the parameters, the force, ``t_c`` nor the edge length; these
    defaults (k = 10 N/m, d = 0.1 N s/m unprojected as in his eq. 2.21, m = 10 g, 1 cm
    edges, dt = 5 ms, force (-0.05, 0, 0) N: pushing the top-centre node down) bring every
    spring set to equilibrium within the 250 steps (a sideways force makes the 54- and
    70-spring cubes, which have little or no shear stiffness, creep for much longer).

    Args:
        springs: 54 (axes), 70 (axes + 16 body diagonals), 86 (axes + 32 body diagonals) or
            126 (axes + 72 face diagonals); see :data:`SPRING_SETS`.
        stiffness, damping: a number, ``(S,)`` or ``(S, D, H, W)`` (true values).
        mass: kg per node, a number or ``(3, 3, 3)``.
        force: newtons on node (2, 1, 1) (axis D is up).
        noise, every, observe, seed: as in :func:`cube_series`.
    Returns:
        a :class:`Series`.
    """
    grid, smask = cube_grid(3, spacing, springs)
    s = Series(np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool), _pos(dt, "dt"), grid,
               None if smask is None else smask.numpy(), grid.face("bottom").numpy(),
               [point_force((2, 1, 1), force)], damping_mode=damping_mode,
               meta={"generator": "radetzky_cube", "springs": springs, "steps": int(steps),
                     "description": f"Radetzky's cube, {springs} springs, lower 9 nodes fixed, "
                                    f"constant force {tuple(force)} N on the top-centre node",
                     "truth": _truth_meta(stiffness, damping, mass)})
    return _finish(s, stiffness, damping, mass, noise, every, observe, seed, steps)


def _pos(v, key) -> float:
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise ConfigError(key, "a positive number", v) from None
    if not math.isfinite(v) or v <= 0:
        raise ConfigError(key, "a positive number", v)
    return v


def _finish(s: Series, stiffness, damping, mass, noise, every, observe, seed, steps) -> Series:
    if int(steps) < 1:
        raise ConfigError("steps", "an integer >= 1", steps)
    if int(every) < 1 or int(steps) % int(every):
        raise ConfigError("every", f"a divisor of steps = {steps} (>= 1)", every)
    if not (0 <= float(noise) < 1):
        raise ConfigError("noise", "a relative noise level in [0, 1)", noise)
    s.steps = np.array([0, int(steps)])                         # num_steps for the tables
    s.meta["num_steps"] = int(steps)
    return _simulate_truth(s, stiffness, damping, mass, float(noise), int(every), observe, int(seed))


def layered_regions(grid: Grid, layers: int = 2) -> np.ndarray:
    """Region labels ``(D, H, W)``: ``layers`` horizontal slabs along axis D (0 at the bottom)."""
    D = grid.shape[0]
    lab = (np.arange(D) * layers) // D
    return np.broadcast_to(lab[:, None, None], grid.shape).astype(np.int64).copy()


def inclusion_regions(grid: Grid, radius: float) -> np.ndarray:
    """Region labels ``(D, H, W)``: 1 inside a sphere of ``radius`` node spacings about the
    centre, 0 outside (a stiff or soft inclusion)."""
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in grid.shape], indexing="ij"))
    c = (np.array(grid.shape) - 1)[:, None, None, None] / 2
    return (np.sqrt(((idx - c) ** 2).sum(0)) <= radius).astype(np.int64)


def cube_series(n: int = 4, topology: int = 26, load: str = "constant", amplitude: float | None = None,
                stiffness=10.0, damping=0.1, mass=0.01, regions=None, steps: int = 250, dt: float = 0.005,
                spacing: float = 0.01, noise: float = 0.0, every: int = 1, observe=None, seed: int = 0,
                damping_mode: str = "unprojected", period: float = 0.5, duration: float = 0.5) -> Series:
    """An ``n^3`` cube with its bottom face fixed under one of several loads.

    Args:
        n: nodes per edge (>= 2); topology: 6, 14, 18 or 26.
        load: ``"constant"`` (force on the top-centre node), ``"ramp"`` (the same force ramped
            in over ``duration``), ``"sine"`` (the top face dragged sideways,
            ``amplitude sin(2 pi t / period)``), ``"indent"`` (top-centre patch pushed down by
            ``amplitude`` over ``duration``).
        amplitude: N for forces (default 0.05 N), m for drags and indentation (default 0.2 spacing).
        stiffness, damping: true values: a number, or a per-region table ``(R,)`` with ``regions``,
            or ``(S,)`` / ``(S, D, H, W)``.
        mass: kg per node, a number or ``(D, H, W)``.
        regions: node labels ``(D, H, W)`` (see :func:`layered_regions`, :func:`inclusion_regions`).
        steps, dt: number of steps and time step (s).
        noise: relative observation noise (0.01 = 1 %).
        every: observe every k-th step (sparse times).
        observe: bool ``(D, H, W)`` of observed nodes (partial observation), or None (all).
        seed: noise seed.
    Returns:
        a :class:`Series`.
    """
    if int(n) < 2:
        raise ConfigError("n", "an integer >= 2", n)
    grid, _ = cube_grid(int(n), spacing, None, topology)
    top = (n - 1, (n - 1) // 2, (n - 1) // 2)
    if load in ("constant", "ramp"):
        a = 0.05 if amplitude is None else float(amplitude)
        ld = point_force(top, (-a, 0.25 * a, 0.0), profile=load, duration=duration)
    elif load == "sine":
        a = 0.2 * spacing if amplitude is None else float(amplitude)
        nodes = [(n - 1, j, k) for j in range(n) for k in range(n)]
        ld = drag(nodes, (0.0, a, 0.0), "sine", period=period)
    elif load == "indent":
        a = 0.2 * spacing if amplitude is None else float(amplitude)
        ld = indentation(grid, a, radius=max(0, (n - 3) // 3), duration=duration)
    else:
        raise ConfigError("load", "one of constant, ramp, sine, indent", load)
    truth = {} if regions is None else {"regions": np.asarray(regions, dtype=np.int64)}
    if regions is not None and tuple(np.shape(regions)) != grid.shape:
        raise ConfigError("regions", f"integer labels of shape {grid.shape}", np.shape(regions))
    s = Series(np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool), _pos(dt, "dt"), grid, None,
               grid.face("bottom").numpy(), [ld], damping_mode=damping_mode, truth=truth,
               meta={"generator": "cube_series", "n": int(n), "load": load, "steps": int(steps),
                     "description": f"{n}^3 cube, {topology} neighbours, bottom fixed, load {load}",
                     "truth": _truth_meta(stiffness, damping, mass)})
    return _finish(s, stiffness, damping, mass, noise, every, observe, seed, steps)


def balloon_series(subdivisions: int = 1, radius: float = 0.05, spacing: float | None = None, topology: int = 26,
                   stiffness=2.0, damping=0.05, mass=0.05, pressure: float = 30.0, snapshots: int = 5,
                   interval: float = 1.0, dt: float = 0.02, noise: float = 0.0, seed: int = 0,
                   mesh=None) -> Series:
    """Radetzky's balloon, synthetically: a closed trimesh surface (an icosphere by default)
    voxelised into a grid body, inflated by a pressure rising linearly over the run, applied
    along the mesh's vertex normals at the surface nodes; observed in ``snapshots`` snapshots
    ``interval`` seconds apart (``interval / dt`` steps between them, 50 with the defaults).

    Args:
        subdivisions, radius: of ``trimesh.creation.icosphere`` (when ``mesh`` is None).
        spacing: grid spacing (default ``radius / 2``: a coarse body of a few dozen nodes).
        pressure: final pressure (Pa) at the end of the run; each surface node gets
            ``pressure * spacing^2`` newtons along the normal of its nearest mesh vertex.
        mesh: a closed ``trimesh.Trimesh`` or a mesh file instead of the icosphere.
        stiffness, damping, mass, noise, seed: as in :func:`cube_series`.
    Returns:
        a :class:`Series` whose centre node is fixed (it pins the free body in space).
    """
    import trimesh
    from scipy.spatial import cKDTree

    from .mesh import grid_from_mesh, load_mesh

    if mesh is None:
        mesh = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=float(radius))
    spacing = float(radius) / 2 if spacing is None else _pos(spacing, "spacing")
    grid = grid_from_mesh(mesh, spacing, topology=topology)
    vertices, faces = load_mesh(mesh)
    normals = np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals)
    nodes = grid.nodes().numpy()
    # surface nodes: some face neighbour missing (outside the body or outside the box)
    padded = np.pad(nodes, 1)
    inner = nodes.copy()
    for axis in range(3):
        for step in (-1, 1):
            inner &= np.roll(padded, step, axis)[1:-1, 1:-1, 1:-1]
    surface = nodes & ~inner
    X = grid.rest_positions(torch.float64)[0].numpy()
    pts = X[:, surface].T
    _, nearest = cKDTree(vertices).query(pts)
    field_ = np.zeros((3,) + grid.shape)
    field_[:, surface] = (normals[nearest] * float(pressure) * spacing ** 2).T
    steps_per = int(round(float(interval) / float(dt)))
    if steps_per < 1 or abs(steps_per * dt - interval) > 1e-9 * interval:
        raise ConfigError("interval", f"a whole number of time steps dt = {dt}", interval)
    steps = steps_per * (int(snapshots) - 1)
    fixed = np.zeros(grid.shape, dtype=bool)
    centre = np.unravel_index(np.argmin(np.where(nodes, ((X - X[:, nodes].mean(1)[:, None, None, None]) ** 2).sum(0),
                                                   np.inf)), grid.shape)
    fixed[centre] = True
    ld = Load("field", profile="ramp", duration=steps * dt, array=field_)
    s = Series(np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool), _pos(dt, "dt"), grid, None, fixed,
               [ld], damping_mode="unprojected",
               meta={"generator": "balloon_series", "steps": steps, "snapshots": int(snapshots),
                     "interval": float(interval), "surface_nodes": int(surface.sum()),
                     "description": f"voxelised closed surface ({grid.num_nodes} nodes, {grid.num_springs} springs), "
                                    f"pressure ramped to {pressure} Pa along vertex normals, "
                                    f"{snapshots} snapshots {interval} s apart",
                     "truth": _truth_meta(stiffness, damping, mass)})
    return _finish(s, stiffness, damping, mass, noise, steps_per, None, seed, steps)


# ---------------------------------------------------------------------------- loading
def _fail(path, key, expected, got=None, show_got=True):
    return ConfigError(key, expected, got, file=str(path), show_got=show_got)


def load_series(path) -> Series:
    """Read and validate a series written by :meth:`Series.save`.

    Raises:
        ConfigError: one line naming the file and the key: a missing or unreadable file,
            missing arrays, wrong shapes, NaN/inf, or metadata that does not match the arrays.
    """
    path = Path(path)
    if not path.is_file():
        raise _fail(path, "file", "an existing .npz series file", "not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:                                  # zip/pickle/format errors of many kinds
        raise _fail(path, "file", "a .npz archive written by torchdeform.data", f"{type(e).__name__}: {e}") from None
    for key in ("meta", "positions", "steps", "mask", "fixed"):
        if key not in arrays:
            raise _fail(path, key, "an array in the file", "missing")
    try:
        meta = json.loads(str(arrays["meta"]))
    except json.JSONDecodeError as e:
        raise _fail(path, "meta", "a JSON string", f"invalid JSON ({e.msg})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise _fail(path, "meta.format", repr(FORMAT), meta.get("format") if isinstance(meta, dict) else meta)
    for key in ("dt", "shape", "spacing", "topology", "loads", "integrator", "damping_mode"):
        if key not in meta:
            raise _fail(path, f"meta.{key}", "a value", "missing")
    dt = meta["dt"]
    if not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
        raise _fail(path, "meta.dt", "a positive number of seconds", dt)
    shape = meta["shape"]
    if not (isinstance(shape, list) and len(shape) == 3 and all(isinstance(v, int) and v >= 1 for v in shape)):
        raise _fail(path, "meta.shape", "three node counts [D, H, W]", shape)
    shape = tuple(shape)
    if meta["integrator"] not in INTEGRATORS or meta["integrator"] in ("implicit", "knoche"):
        raise _fail(path, "meta.integrator", "an explicit integrator name (symplectic, explicit, verlet, rk4)",
                    meta["integrator"])
    if meta["damping_mode"] not in ("projected", "unprojected"):
        raise _fail(path, "meta.damping_mode", "projected or unprojected", meta["damping_mode"])
    node_mask = None
    if meta.get("node_mask"):
        if "node_mask" not in arrays:
            raise _fail(path, "node_mask", "an array in the file (meta.node_mask is true)", "missing")
        node_mask = arrays["node_mask"]
        if node_mask.shape != shape or node_mask.dtype != bool:
            raise _fail(path, "node_mask", f"bool of shape {shape} (meta.shape)", f"{node_mask.dtype} {node_mask.shape}")
    try:
        grid = Grid(shape, meta["spacing"], meta["topology"], node_mask=None if node_mask is None
                    else torch.from_numpy(node_mask), origin=meta.get("origin", (0.0, 0.0, 0.0)))
    except ConfigError as e:
        raise _fail(path, f"meta.{e.key.split('.')[-1]}", e.expected, e.got) from None
    S = grid.S

    pos = arrays["positions"]
    if pos.ndim != 5 or pos.shape[1:] != (3,) + shape:
        raise _fail(path, "positions", f"shape (T, 3, {', '.join(map(str, shape))}) to match meta.shape", pos.shape)
    if not np.issubdtype(pos.dtype, np.floating):
        raise _fail(path, "positions", "floating-point values", str(pos.dtype))
    if not np.isfinite(pos).all():
        bad = np.argwhere(~np.isfinite(pos))[0]
        raise _fail(path, "positions", "finite values (no NaN or inf; mark missing data in 'mask')",
                    f"{pos[tuple(bad)]} at observation {bad[0]}")
    T = pos.shape[0]
    if T < 2:
        raise _fail(path, "positions", "at least 2 observations", T)
    steps = arrays["steps"]
    if steps.shape != (T,) or not np.issubdtype(steps.dtype, np.integer):
        raise _fail(path, "steps", f"{T} integer step indices (one per observation)", f"{steps.dtype} {steps.shape}")
    if steps[0] < 0 or (np.diff(steps) <= 0).any():
        raise _fail(path, "steps", "non-negative, strictly increasing step indices", steps[:6].tolist())
    mask = arrays["mask"]
    if mask.shape != (T,) + shape or mask.dtype != bool:
        raise _fail(path, "mask", f"bool of shape ({T}, {', '.join(map(str, shape))})", f"{mask.dtype} {mask.shape}")
    fixed = arrays["fixed"]
    if fixed.shape != shape or fixed.dtype != bool:
        raise _fail(path, "fixed", f"bool of shape {shape}", f"{fixed.dtype} {fixed.shape}")
    smask = arrays.get("spring_mask")
    if smask is not None and (smask.shape != (S,) + shape or smask.dtype != bool):
        raise _fail(path, "spring_mask", f"bool of shape {(S,) + shape} (topology {grid.topology})",
                    f"{smask.dtype} {smask.shape}")
    if not isinstance(meta["loads"], list):
        raise _fail(path, "meta.loads", "a list of load tables", meta["loads"])
    loads = []
    for i, d in enumerate(meta["loads"]):
        try:
            ld = Load.from_json(d, arrays, f"meta.loads[{i}]")
        except ConfigError as e:
            raise ConfigError(e.key, e.expected, e.got, file=str(path), show_got=e.show_got) from None
        if ld.kind == "field" and ld.array.shape != (3,) + shape:
            raise _fail(path, f"meta.loads[{i}].array", f"shape (3, {', '.join(map(str, shape))})", ld.array.shape)
        for nd in ld.nodes:
            if not all(0 <= c < n for c, n in zip(nd, shape)):
                raise _fail(path, f"meta.loads[{i}].nodes", f"node indices inside the grid {shape}", list(nd))
        loads.append(ld)
    truth = {}
    for key, want in (("stiffness", (S,) + shape), ("damping", (S,) + shape), ("mass", shape), ("regions", shape)):
        a = arrays.get(f"true_{key}")
        if a is None:
            continue
        if a.shape != want:
            raise _fail(path, f"true_{key}", f"shape {want} to match meta.shape and topology", a.shape)
        if not np.isfinite(a).all() or (a < 0).any():
            raise _fail(path, f"true_{key}", "finite values >= 0", "NaN, inf or negative values")
        truth[key] = a
    series = Series(pos.astype(np.float64), steps.astype(np.int64), mask, float(dt), grid, smask, fixed, loads,
                    meta["damping_mode"], meta["integrator"], truth, meta)
    if "num_steps" in meta and meta["num_steps"] != series.num_steps:
        raise _fail(path, "meta.num_steps", f"the last entry of steps ({series.num_steps})", meta["num_steps"])
    return series


__all__ = ["Series", "Load", "load_series", "radetzky_cube", "cube_series", "balloon_series", "cube_grid",
           "point_force", "drag", "indentation", "node_to_springs", "expand_spring_param", "layered_regions",
           "inclusion_regions", "SPRING_SETS"]


# ---------------------------------------------------------------------------- command line
def add_arguments(parser) -> None:
    """``torchdeform data cube|balloon --out FILE.npz [options]``."""
    sub = parser.add_subparsers(dest="data_command", required=True)
    c = sub.add_parser("cube", help="a cube series: Radetzky's cube (--springs) or an n^3 cube (--n)")
    c.add_argument("--out", required=True, help="output file (.npz)")
    c.add_argument("--springs", type=int, default=None, help="Radetzky's cube with 54, 70, 86 or 126 springs")
    c.add_argument("--n", type=int, default=None, help="nodes per edge of an n^3 cube (instead of --springs)")
    c.add_argument("--topology", type=int, default=26, help="neighbours of the n^3 cube (6, 14, 18, 26)")
    c.add_argument("--load", default="constant", help="n^3 cube load: constant, ramp, sine, indent")
    c.add_argument("--amplitude", type=float, default=None, help="force (N) or displacement (m) of the load")
    c.add_argument("--regions", default=None, help="heterogeneous material: 'layers' or 'inclusion' (n^3 cube)")
    c.add_argument("--stiffness", default="10", help="true stiffness N/m; comma-separated per region")
    c.add_argument("--damping", default="0.1", help="true damping N s/m; comma-separated per region")
    c.add_argument("--mass", type=float, default=0.01, help="node mass, kg")
    c.add_argument("--steps", type=int, default=250)
    c.add_argument("--dt", type=float, default=0.005)
    c.add_argument("--noise", type=float, default=0.0, help="relative observation noise (0.01 = 1%%)")
    c.add_argument("--every", type=int, default=1, help="observe every k-th step")
    c.add_argument("--seed", type=int, default=0)
    b = sub.add_parser("balloon", help="a voxelised icosphere inflated by pressure, seen in a few snapshots")
    b.add_argument("--out", required=True, help="output file (.npz)")
    b.add_argument("--snapshots", type=int, default=5)
    b.add_argument("--interval", type=float, default=1.0)
    b.add_argument("--dt", type=float, default=0.02)
    b.add_argument("--noise", type=float, default=0.0)
    b.add_argument("--seed", type=int, default=0)


def _numbers(text, key):
    try:
        vals = [float(v) for v in str(text).split(",")]
    except ValueError:
        raise ConfigError(key, "a number or comma-separated numbers", text) from None
    return vals[0] if len(vals) == 1 else vals


def command(args) -> int:
    """Run ``torchdeform data ...``; prints a one-line summary."""
    if args.data_command == "balloon":
        s = balloon_series(snapshots=args.snapshots, interval=args.interval, dt=args.dt, noise=args.noise,
                           seed=args.seed)
    else:
        k, c = _numbers(args.stiffness, "--stiffness"), _numbers(args.damping, "--damping")
        if args.n is None:
            s = radetzky_cube(springs=70 if args.springs is None else args.springs, stiffness=k, damping=c,
                              mass=args.mass, steps=args.steps, dt=args.dt, noise=args.noise, every=args.every,
                              seed=args.seed)
        else:
            if args.springs is not None:
                raise ConfigError("--springs", "not together with --n (Radetzky's sets are 3 x 3 x 3)", args.springs)
            regions = None
            if args.regions is not None:
                g, _ = cube_grid(args.n, 0.01, None, args.topology)
                if args.regions not in ("layers", "inclusion"):
                    raise ConfigError("--regions", "layers or inclusion", args.regions)
                regions = layered_regions(g) if args.regions == "layers" else inclusion_regions(g, args.n / 4)
            s = cube_series(n=args.n, topology=args.topology, load=args.load, amplitude=args.amplitude,
                            stiffness=k, damping=c, mass=args.mass, regions=regions, steps=args.steps, dt=args.dt,
                            noise=args.noise, every=args.every, seed=args.seed)
    path = s.save(args.out)
    print(f"{path}: {s.meta['description']}; {len(s.steps)} observations of {s.grid.num_nodes} nodes, "
          f"dt = {s.dt:g} s, {s.grid.num_springs if s.spring_mask is None else int(s.spring_mask.sum())} springs")
    return 0
