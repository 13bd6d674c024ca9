"""Time series of deforming bodies (:class:`Series`) and their files, for learning their parameters.

A :class:`Series` holds observed node positions at some steps of a simulation plus everything
needed to run that simulation again: the grid and its springs, fixed nodes, loads, the time
step, the integrator and, for synthetic data, the true parameters.

The generators of synthetic series are in :mod:`torchdeform.learn.synthetic`.

Conventions:

* Dynamics are those of :class:`~torchdeform.sim.integrators.SymplecticEuler` (default) with
  the external force of step ``n`` evaluated at ``t_n = n dt`` and prescribed (dragged) nodes
  put on their path at ``t_{n+1}`` after every step; :meth:`Series.advance` is that step, the
  same for generation and learning, so a model with the true parameters reproduces clean
  data to rounding.
* The series starts from rest (``x = X``, ``v = 0``) at step 0.
* Observations ``positions[i]`` are taken at step ``steps[i]``; ``mask[i]`` says which nodes
  were seen (missing data / partial observation).

Files are ``.npz``: arrays plus one JSON string ``meta`` (format version, dt, grid, spring
set, integrator, loads, noise, seed, description). :func:`load_series` validates everything
and raises a one-line :class:`~torchdeform.errors.ConfigError` naming the file and the key.

Loads are those of every model (:mod:`torchdeform.sim.forces`): :class:`PointForce`,
:class:`SurfaceForce`, :class:`FieldForce` and :class:`Drag`, with their time profiles; a series
turns them into per-step tables (:meth:`Series.tables`). In the file each is one JSON table:
``kind`` (``"force"``, ``"traction"``, ``"field"``, ``"drag"``), ``profile`` (``"constant"``,
``"ramp"``, ``"sine"``) with ``start``, ``duration`` (the ramp) and ``period``, and ``nodes`` +
``vector``, ``face`` + ``vector``, ``array`` (the name of a stored ``(3, D, H, W)`` field) or
``nodes`` + ``path`` (waypoints).

Example:
    >>> from torchdeform import learn
    >>> s = learn.radetzky_cube(springs=70)
    >>> s.positions.shape, int(s.steps[-1]), int(s.spring_mask_tensor().sum())
    ((251, 3, 3, 3, 3), 250, 70)
    >>> path = s.save(getfixture("tmp_path") / "cube70.npz")
    >>> learn.load_series(path).loads
    [PointForce(node=(2, 1, 1), force=(-0.05, 0.0, 0.0), start=0.0, ramp=0.0, period=None)]
"""

from __future__ import annotations

import json
import math
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..errors import ConfigError
from ..outputs import atomic_path, require_finite
from ..sim.catalog import INTEGRATORS
from ..sim.forces import Drag, FieldForce, PointForce, SurfaceForce
from ..sim.grid import FACES, Grid
from ..sim.model import Model, State

__all__ = ["Series", "load_series", "FORMAT", "PROFILES", "LOAD_KINDS", "load_to_json", "load_from_json"]

FORMAT = "torchdeform-series/1"

PROFILES = ("constant", "ramp", "sine")
LOAD_KINDS = ("force", "traction", "field", "drag")


# ---------------------------------------------------------------------------- loads in files
def load_to_json(load, index: int) -> tuple[dict, dict]:
    """One load as a JSON table, and the arrays it needs stored beside it (``{name: array}``).

    Args:
        load: a :class:`PointForce`, :class:`SurfaceForce`, :class:`FieldForce` or :class:`Drag`.
        index: its position in the series' list (names its stored array).
    """
    profile = "sine" if load.period is not None else "ramp" if load.ramp > 0 else "constant"
    d = {
        "kind": None,
        "profile": profile,
        "start": float(load.start),
        "duration": float(load.ramp),
        "period": 1.0 if load.period is None else float(load.period),
    }
    arrays = {}
    if isinstance(load, PointForce):
        d.update(kind="force", nodes=[[int(c) for c in load.node]], vector=[float(c) for c in load.force])
    elif isinstance(load, SurfaceForce):
        d.update(kind="traction", face=load.face, vector=[float(c) for c in load.traction])
    elif isinstance(load, FieldForce):
        d.update(kind="field", array=f"load_field_{index}")
        arrays[d["array"]] = np.asarray(load.field, dtype=np.float64)
    elif isinstance(load, Drag):
        d.update(kind="drag", nodes=[[int(c) for c in n] for n in load.mask().nonzero().tolist()])
        if load.path is None:
            d["vector"] = [float(c) for c in load.offset_vector]
        else:
            d["path"] = [[float(t), [float(c) for c in o]] for t, o in load.path]
    else:
        raise ConfigError(f"loads[{index}]", "a PointForce, SurfaceForce, FieldForce or Drag", got=type(load).__name__)
    return d, arrays


def load_from_json(d, arrays: dict, shape: tuple, where: str) -> list:
    """The loads of one JSON table (see :func:`load_to_json`).

    A ``"force"`` on several nodes is one :class:`PointForce` per node. Raises a
    :class:`ConfigError` naming ``where`` and the key.
    """
    if not isinstance(d, dict):
        raise ConfigError(where, "a table with kind, profile, ...", got=d)
    kind = d.get("kind")
    if kind not in LOAD_KINDS:
        raise _bad_load(where, "kind", f"one of {', '.join(LOAD_KINDS)}", kind)
    timing = _load_timing(d, where)
    if kind == "field":
        name = d.get("array")
        if name not in arrays:
            raise _bad_load(where, "array", "the name of a (3, D, H, W) array stored in the file", name)
        arr = np.asarray(arrays[name], dtype=np.float64)
        if arr.shape != (3,) + tuple(shape):
            raise _bad_load(where, "array", f"shape (3, {', '.join(map(str, shape))})", arr.shape)
        return [FieldForce(arr, **timing)]
    vector = _load_vector(d, where) if kind != "drag" or "path" not in d else d.get("vector")
    if kind == "traction":
        if d.get("face") not in FACES:
            raise _bad_load(where, "face", f"a face name: {', '.join(FACES)}", d.get("face"))
        return [SurfaceForce(d["face"], vector, **timing)]
    nodes = _load_nodes(d, shape, where)
    if kind == "force":
        return [PointForce(nd, vector, **timing) for nd in nodes]
    mask = torch.zeros(tuple(shape), dtype=torch.bool)
    for nd in nodes:
        mask[nd] = True
    if "path" not in d:
        return [Drag(mask, offset=vector, **timing)]
    path = d["path"]
    try:
        path = [(float(p[0]), tuple(float(c) for c in p[1])) for p in path]
    except (TypeError, ValueError, IndexError, KeyError):
        raise _bad_load(where, "path", "waypoints [[t, [od, oh, ow]], ...]", d.get("path")) from None
    return [Drag(mask, path=path)]


def _bad_load(where: str, key: str, expected: str, got) -> ConfigError:
    """The error for key ``key`` of the load table at ``where``."""
    return ConfigError(f"{where}.{key}", expected, got=got)


def _load_timing(d: dict, where: str) -> dict:
    """The ``start``, ``ramp`` and ``period`` keywords of a load table's ``profile`` and times (s)."""
    profile = d.get("profile", "constant")
    if profile not in PROFILES:
        raise _bad_load(where, "profile", f"one of {', '.join(PROFILES)}", profile)
    nums = {}
    for k, default in (("start", 0.0), ("duration", 0.0), ("period", 1.0)):
        v = d.get(k, default)
        if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise _bad_load(where, k, "a finite number >= 0 (s)", v)
        nums[k] = float(v)
    if profile == "sine" and nums["period"] <= 0:
        raise _bad_load(where, "period", "a positive number (s)", nums["period"])
    return {
        "start": nums["start"],
        "ramp": 0.0 if profile == "constant" else nums["duration"],
        "period": nums["period"] if profile == "sine" else None,
    }


def _load_vector(d: dict, where: str) -> tuple:
    """A load table's ``vector``: three finite numbers ``(d, h, w)``."""
    try:
        vector = tuple(float(c) for c in d.get("vector"))
    except (TypeError, ValueError):
        vector = ()
    if len(vector) != 3 or not all(math.isfinite(c) for c in vector):
        raise _bad_load(where, "vector", "three finite numbers (d, h, w)", d.get("vector"))
    return vector


def _load_nodes(d: dict, shape: tuple, where: str) -> list:
    """A load table's ``nodes``: distinct ``(i, j, k)`` index triples inside the grid, in order."""
    nodes = d.get("nodes")
    try:
        nodes = [tuple(int(c) for c in n) for n in nodes]
        ok = all(len(n) == 3 for n in nodes) and len(nodes) > 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise _bad_load(where, "nodes", "a non-empty list of node indices [[i, j, k], ...]", d.get("nodes"))
    for nd in nodes:
        if not all(0 <= c < n for c, n in zip(nd, shape)):
            raise _bad_load(where, "nodes", f"node indices inside the grid {tuple(shape)}", list(nd))
    return list(dict.fromkeys(nodes))


# ---------------------------------------------------------------------------- series
@dataclass
class Series:
    """An observed time series of node positions and the set-up that produced it.

    Attributes:
        positions: observations ``(T, 3, D, H, W)`` (float64 numpy), metres.
        steps: step index of each observation ``(T,)`` (int, strictly increasing).
        mask: bool ``(T, D, H, W)``: node observed at that time.
        dt: time step (s).
        grid: the :class:`~torchdeform.sim.grid.Grid`; spring_mask: bool ``(S, D, H, W)`` or None.
        fixed: bool ``(D, H, W)`` nodes that never move.
        loads: list of :class:`~torchdeform.sim.forces.PointForce`, ``SurfaceForce``,
            ``FieldForce`` and :class:`~torchdeform.sim.forces.Drag` (the loads of every model).
        damping_mode: ``"unprojected"`` (Radetzky) or ``"projected"``.
        integrator: name in :data:`~torchdeform.sim.integrators.INTEGRATORS` (``"symplectic"``).
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
    _: KW_ONLY
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

    def spring_mask_tensor(self, *, device=None) -> torch.Tensor:
        """Bool ``(S, D, H, W)`` of existing springs."""
        base = self.grid.spring_mask(device=device)
        return base if self.spring_mask is None else base & torch.as_tensor(self.spring_mask, device=device)

    def prescribed(self) -> np.ndarray:
        """Bool ``(D, H, W)``: dragged nodes."""
        m = np.zeros(self.grid.shape, dtype=bool)
        for ld in self.loads:
            if isinstance(ld, Drag):
                m |= ld.mask().numpy()
        return m

    def constrained(self) -> np.ndarray:
        """Bool ``(D, H, W)``: fixed or dragged."""
        return self.fixed | self.prescribed()

    def tables(self, *, dtype=torch.float64, device=None) -> dict:
        """Dense load tables over steps ``0 .. num_steps + 1``.

        ``force`` ``(N + 2, 3, D, H, W)`` (external force at ``t_n``) or None, and
        ``drag`` ``(N + 2, 3, D, H, W)`` (prescribed positions at ``t_n``) with ``drag_mask``
        ``(1, 1, D, H, W)``, or None.
        """
        key = (dtype, str(device))
        cache = self.__dict__.setdefault("_tables", {})
        if key in cache:
            return cache[key]
        n = self.num_steps + 2
        t = np.arange(n) * self.dt
        force, offset = None, None
        for ld in self.loads:
            if isinstance(ld, Drag):
                off = ld.offset(t)[:, :, None, None, None] * ld.mask().numpy()[None, None]  # (n, 3, D, H, W)
                offset = off if offset is None else offset + off
            else:
                f = ld.factor(t)[:, None, None, None, None]
                dense = ld.dense(self.grid, torch.float64, "cpu").numpy()  # (1, 3, D, H, W)
                force = f * dense if force is None else force + f * dense
        out = {"force": None, "drag": None, "drag_mask": None}
        if force is not None:
            out["force"] = torch.as_tensor(force, dtype=dtype, device=device)
        if offset is not None:
            X = self.grid.rest_positions(dtype=dtype, device=device)
            out["drag"] = X + torch.as_tensor(offset, dtype=dtype, device=device)
            out["drag_mask"] = torch.as_tensor(self.prescribed(), device=device)[None, None]
        cache[key] = out
        return out

    def model(self, stiffness, damping, mass, *, dtype=torch.float64, device=None) -> Model:
        """The :class:`~torchdeform.sim.model.Model` of this set-up with the given parameters.

        Any shape :class:`Model` accepts; tensors keep their autograd graph.
        """
        fixed = torch.as_tensor(self.constrained())
        return Model(
            self.grid,
            stiffness=stiffness,
            damping=damping,
            damping_mode=self.damping_mode,
            mass=mass,
            fixed=fixed,
            spring_mask=None if self.spring_mask is None else torch.as_tensor(self.spring_mask),
            dtype=dtype,
            device=device,
        )

    def true_model(self, *, dtype=torch.float64, device=None) -> Model:
        """The model with the true parameters (synthetic series)."""
        if not self.truth:
            raise ConfigError("truth", "a synthetic series with true parameters", got="none stored", show_got=True)
        return self.model(
            torch.as_tensor(self.truth["stiffness"]),
            torch.as_tensor(self.truth["damping"]),
            torch.as_tensor(self.truth["mass"]),
            dtype=dtype,
            device=device,
        )

    def advance(self, model: Model, state: State, n, *, integrator=None) -> State:
        """One step of the series' dynamics from step ``n`` to ``n + 1``.

        ``n`` is an int, or a ``(B,)`` LongTensor of per-batch-entry steps. External force at
        ``t_n``, the integrator's step, dragged nodes onto their positions at ``t_{n+1}``.
        """
        tab = self.tables(dtype=model.dtype, device=model.device)
        integrator = integrator or INTEGRATORS[self.integrator]()
        now, nxt = (n, n + 1) if torch.is_tensor(n) else (slice(n, n + 1), slice(n + 1, n + 2))
        loads = None if tab["force"] is None else tab["force"][now]
        new = integrator.step(model, state, self.dt, loads=loads)
        if tab["drag"] is not None:
            target = tab["drag"][nxt]
            vel = (target - tab["drag"][now]) / self.dt
            m = tab["drag_mask"]
            new = State(torch.where(m, target, new.x), torch.where(m, vel, new.v), t=new.t)
        return new

    def start_state(self, model: Model, *, batch: int = 1) -> State:
        """The state at step 0 (rest; dragged nodes on their path)."""
        st = model.rest_state(batch=batch)
        tab = self.tables(dtype=model.dtype, device=model.device)
        if tab["drag"] is not None:
            m = tab["drag_mask"]
            st = State(torch.where(m, tab["drag"][0], st.x), st.v, t=0.0)
        return st

    def simulate(self, model: Model, *, steps: int | None = None, integrator=None) -> torch.Tensor:
        """Positions ``(N + 1, B, 3, D, H, W)`` at steps ``0 .. N``.

        No gradient tracking unless the model's parameters require it.
        """
        steps = self.num_steps if steps is None else int(steps)
        integrator = integrator or INTEGRATORS[self.integrator]()
        st = self.start_state(model)
        xs = [st.x]
        for n in range(steps):
            st = self.advance(model, st, n, integrator=integrator)
            xs.append(st.x)
        return torch.stack(xs)

    # ---------------------------------------------------------------- files
    def save(self, path) -> Path:
        """Write the series to ``path`` (``.npz``, compressed); returns the path."""
        path = Path(path)
        arrays = {
            "positions": np.asarray(self.positions, dtype=np.float64),
            "steps": np.asarray(self.steps, dtype=np.int64),
            "mask": np.asarray(self.mask, dtype=bool),
            "fixed": np.asarray(self.fixed, dtype=bool),
        }
        if self.spring_mask is not None:
            arrays["spring_mask"] = np.asarray(self.spring_mask, dtype=bool)
        for k in ("stiffness", "damping", "mass", "regions"):
            if k in self.truth:
                arrays[f"true_{k}"] = np.asarray(self.truth[k])
        loads = []
        for i, ld in enumerate(self.loads):
            table, stored = load_to_json(ld, i)
            loads.append(table)
            arrays.update(stored)
        g = self.grid
        meta = dict(self.meta)
        meta.update(
            {
                "format": FORMAT,
                "dt": float(self.dt),
                "shape": list(g.shape),
                "spacing": list(g.spacing),
                "origin": list(g.origin),
                "topology": g.topology,
                "damping_mode": self.damping_mode,
                "integrator": self.integrator,
                "loads": loads,
                "start": "rest",
                "node_mask": g.node_mask is not None,
            }
        )
        if g.node_mask is not None:
            arrays["node_mask"] = g.node_mask.numpy()
        arrays["meta"] = np.array(json.dumps(meta))
        for k, a in arrays.items():
            require_finite(
                f"{path.name}: {k}",
                a,
                what="observation, axis, d, h, w" if k == "positions" else "",
                cause="the simulated body diverged (a load or amplitude too large for its time step?)"
                if k == "positions"
                else "",
            )
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        return path


# ---------------------------------------------------------------------------- loading
def _fail(path, key, expected, got=None, show_got=True):
    return ConfigError(key, expected, got=got, file=str(path), show_got=show_got)


def load_series(path) -> Series:
    """Read and validate a series written by :meth:`Series.save`.

    Raises:
        ConfigError: one line naming the file and the key: a missing or unreadable file,
            missing arrays, wrong shapes, NaN/inf, or metadata that does not match the arrays.
    """
    path = Path(path)
    arrays = _read_arrays(path)
    meta = _read_meta(path, arrays)
    shape = tuple(meta["shape"])
    grid = _read_grid(path, meta, arrays, shape)
    pos, steps, mask, fixed, smask = _read_observations(path, arrays, grid)
    series = Series(
        pos.astype(np.float64),
        steps.astype(np.int64),
        mask,
        float(meta["dt"]),
        grid,
        smask,
        fixed,
        _read_loads(path, meta, arrays, shape),
        damping_mode=meta["damping_mode"],
        integrator=meta["integrator"],
        truth=_read_truth(path, arrays, grid),
        meta=meta,
    )
    if "num_steps" in meta and meta["num_steps"] != series.num_steps:
        raise _fail(path, "meta.num_steps", f"the last entry of steps ({series.num_steps})", meta["num_steps"])
    return series


def _read_arrays(path: Path) -> dict:
    """The arrays of the ``.npz`` file at ``path``, the required ones checked present."""
    if not path.is_file():
        raise _fail(path, "file", "an existing .npz series file", "not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # zip/pickle/format errors of many kinds
        raise _fail(path, "file", "a .npz archive written by torchdeform.learn", f"{type(e).__name__}: {e}") from None
    for key in ("meta", "positions", "steps", "mask", "fixed"):
        if key not in arrays:
            raise _fail(path, key, "an array in the file", "missing")
    return arrays


def _read_meta(path: Path, arrays: dict) -> dict:
    """The JSON metadata of a series file: format, time step, shape, integrator and damping mode checked."""
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
    if meta["integrator"] not in INTEGRATORS or meta["integrator"] in ("implicit", "knoche"):
        raise _fail(
            path,
            "meta.integrator",
            "an explicit integrator name (symplectic, explicit, verlet, rk4)",
            meta["integrator"],
        )
    if meta["damping_mode"] not in ("projected", "unprojected"):
        raise _fail(path, "meta.damping_mode", "projected or unprojected", meta["damping_mode"])
    return meta


def _read_grid(path: Path, meta: dict, arrays: dict, shape: tuple) -> Grid:
    """The :class:`~torchdeform.sim.grid.Grid` of a series file (with its node mask, if any)."""
    node_mask = None
    if meta.get("node_mask"):
        if "node_mask" not in arrays:
            raise _fail(path, "node_mask", "an array in the file (meta.node_mask is true)", "missing")
        node_mask = arrays["node_mask"]
        if node_mask.shape != shape or node_mask.dtype != bool:
            raise _fail(
                path, "node_mask", f"bool of shape {shape} (meta.shape)", f"{node_mask.dtype} {node_mask.shape}"
            )
    try:
        return Grid(
            shape,
            spacing=meta["spacing"],
            topology=meta["topology"],
            node_mask=None if node_mask is None else torch.from_numpy(node_mask),
            origin=meta.get("origin", (0.0, 0.0, 0.0)),
        )
    except ConfigError as e:
        raise _fail(path, f"meta.{e.key.split('.')[-1]}", e.expected, e.got) from None


def _read_observations(path: Path, arrays: dict, grid: Grid) -> tuple:
    """``(positions, steps, mask, fixed, spring_mask)`` of a series file, shapes and values checked."""
    shape, S = grid.shape, grid.S
    pos = arrays["positions"]
    if pos.ndim != 5 or pos.shape[1:] != (3,) + shape:
        raise _fail(path, "positions", f"shape (T, 3, {', '.join(map(str, shape))}) to match meta.shape", pos.shape)
    if not np.issubdtype(pos.dtype, np.floating):
        raise _fail(path, "positions", "floating-point values", str(pos.dtype))
    if not np.isfinite(pos).all():
        bad = np.argwhere(~np.isfinite(pos))[0]
        raise _fail(
            path,
            "positions",
            "finite values (no NaN or inf; mark missing data in 'mask')",
            f"{pos[tuple(bad)]} at observation {bad[0]}",
        )
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
        raise _fail(
            path,
            "spring_mask",
            f"bool of shape {(S,) + shape} (topology {grid.topology})",
            f"{smask.dtype} {smask.shape}",
        )
    return pos, steps, mask, fixed, smask


def _read_loads(path: Path, meta: dict, arrays: dict, shape: tuple) -> list:
    """The loads of a series file (``meta.loads``), errors naming the file."""
    if not isinstance(meta["loads"], list):
        raise _fail(path, "meta.loads", "a list of load tables", meta["loads"])
    loads = []
    for i, d in enumerate(meta["loads"]):
        try:
            loads += load_from_json(d, arrays, shape, f"meta.loads[{i}]")
        except ConfigError as e:
            raise ConfigError(e.key, e.expected, got=e.got, file=str(path), show_got=e.show_got) from None
    return loads


def _read_truth(path: Path, arrays: dict, grid: Grid) -> dict:
    """The true parameters stored in a series file (``true_stiffness``, ...), shapes and values checked."""
    shape, S = grid.shape, grid.S
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
    return truth
