"""NVIDIA Warp baseline for ``torchdeform bench speed``.

The speed scene (:func:`torchdeform.bench.common.speed_cube`: damped springs, symplectic Euler) written
the way Warp users write a mass-spring step, run on Warp's CPU backend, so the speed table can
report torchdeform's throughput relative to Warp (``ratio_vs_warp``).

Two variants of one step ``v' = v + dt F(x, v) / m``, ``x' = x + dt v'``:

==========  =====================================================================================
atomic      warp.sim / Newton style: a per-spring kernel over an edge list ``(i, j, l0, k, c)``
            adds ``+f`` to node ``i`` and ``-f`` to node ``j`` with ``wp.atomic_add`` /
            ``wp.atomic_sub`` into a node force array, then a per-node kernel integrates (and
            clears the force array for the next step). Two launches per step, in place.
gather      one per-node kernel: each node loops over the ``2 S`` stencil offsets of the grid
            (``+d`` and ``-d`` for each half-direction ``d``), sums the forces of its springs
            (each spring is evaluated at both ends, no atomics) and integrates. Positions and
            velocities ping-pong between two buffers. One launch per step.
==========  =====================================================================================

Spring force on node ``i`` from the spring ``(i, j)``: ``f = (k (l - l0) + c ((v_j - v_i) . n)) n``
with ``n = (x_j - x_i) / l`` and ``l = sqrt(max(|x_j - x_i|^2, tiny))`` (torchdeform's guard for
coincident nodes); ``j`` gets ``-f``. Spring parameters are per spring in both variants (warp.sim
keeps per-spring arrays too), taken from the :class:`~torchdeform.sim.model.Model`, so the springs
are exactly torchdeform's (the stencil and rest lengths come from the
:class:`~torchdeform.sim.grid.Grid`).

Warp's CPU backend runs a kernel launch as a serial loop over its threads on the calling
thread (its CPU ``atomic_add`` is a plain add), so the rows report ``threads = 1``.

Importing this module does not import Warp; :func:`warp_available` says whether it can be used.
When this module initialises Warp it raises ``wp.config.log_level`` to ``LOG_WARNING`` first, so
Warp's banner and module-load messages do not mix with benchmark output.

Example:
    >>> from torchdeform.bench.warp_baseline import warp_available, warp_speed_row
    >>> ok, why = warp_available()
    >>> row = warp_speed_row(16, topology=26, variant="atomic") if ok else None   # doctest: +SKIP
"""

import functools
import math
import statistics
import time

import numpy as np
import torch

from .common import speed_cube

#: The step variants, see the module docstring.
VARIANTS = ("atomic", "gather")
INSTALL_HINT = "warp-lang is not installed (pip install warp-lang)"
_SCALARS = {torch.float32: "float32", torch.float64: "float64"}


# --------------------------------------------------------------------- warp itself
def _warp():
    """Import and initialise Warp (quietly the first time); raises ImportError without it."""
    import warp as wp

    if not getattr(_warp, "initialised", False):
        if wp.config.log_level < wp.LOG_WARNING:
            wp.config.log_level = wp.LOG_WARNING
        wp.init()
        _warp.initialised = True
    return wp


def warp_available() -> tuple:
    """Whether the Warp baseline can run here.

    Returns:
        ``(True, "warp-lang <version>")``, or ``(False, reason)`` when ``import warp`` fails,
        Warp fails to initialise, or it has no CPU device.
    """
    try:
        wp = _warp()
    except ImportError:
        return False, INSTALL_HINT
    except Exception as exc:  # broken install, native library missing ...
        return False, f"warp-lang failed to initialise: {type(exc).__name__}: {exc}"
    try:
        devices = [str(d) for d in wp.get_devices()]
    except Exception as exc:
        return False, f"warp-lang cannot list its devices: {type(exc).__name__}: {exc}"
    if "cpu" not in devices:
        return False, f"warp-lang {wp.config.version} has no CPU device"
    return True, f"warp-lang {wp.config.version}"


def _require_warp():
    ok, why = warp_available()
    if not ok:
        raise RuntimeError(why)
    return _warp()


@functools.cache
def _kernels(scalar_name: str) -> dict:
    """The three kernels for ``"float32"`` (``wp.vec3``) or ``"float64"`` (``wp.vec3d``).

    Built once per precision as closures over the vector and scalar types; each lives in its
    own Warp module (``module="unique"``), compiled on first launch and cached on disk by Warp
    (``~/.cache/warp``).
    """
    wp = _warp()
    vec, scalar = (wp.vec3, wp.float32) if scalar_name == "float32" else (wp.vec3d, wp.float64)
    tiny = float(torch.finfo(getattr(torch, scalar_name)).tiny)

    @wp.func
    def spring_force(xi: vec, vi: vec, xj: vec, vj: vec, l0: scalar, k: scalar, c: scalar):
        # force on the node at xi from its spring to xj (the node at xj gets the opposite):
        # (k (l - l0) + c (dv . n)) n with n = d / l, written with one reciprocal (~10% faster
        # on the CPU than normalising d first)
        d = xj - xi
        l = wp.sqrt(wp.max(wp.dot(d, d), scalar(tiny)))
        inv_l = scalar(1.0) / l
        return ((k * (l - l0) + c * wp.dot(vj - vi, d) * inv_l) * inv_l) * d

    @wp.kernel(enable_backward=False, module="unique")
    def springs_atomic(
        x: wp.array(dtype=vec),
        v: wp.array(dtype=vec),
        ei: wp.array(dtype=wp.int32),
        ej: wp.array(dtype=wp.int32),
        l0: wp.array(dtype=scalar),
        k: wp.array(dtype=scalar),
        c: wp.array(dtype=scalar),
        f: wp.array(dtype=vec),
    ):
        s = wp.tid()
        i = ei[s]
        j = ej[s]
        fs = spring_force(x[i], v[i], x[j], v[j], l0[s], k[s], c[s])
        wp.atomic_add(f, i, fs)
        wp.atomic_sub(f, j, fs)

    @wp.kernel(enable_backward=False, module="unique")
    def integrate(
        x: wp.array(dtype=vec),
        v: wp.array(dtype=vec),
        f: wp.array(dtype=vec),
        inv_mass: wp.array(dtype=scalar),
        dt: scalar,
    ):
        i = wp.tid()
        vi = v[i] + f[i] * (inv_mass[i] * dt)
        v[i] = vi
        x[i] = x[i] + vi * dt
        f[i] = vec()  # cleared for the next step's atomics

    @wp.kernel(enable_backward=False, module="unique")
    def gather_step(
        x: wp.array(dtype=vec),
        v: wp.array(dtype=vec),
        dirs: wp.array(dtype=wp.vec3i),
        l0: wp.array2d(dtype=scalar),
        k: wp.array2d(dtype=scalar),
        c: wp.array2d(dtype=scalar),
        inv_mass: wp.array(dtype=scalar),
        dt: scalar,
        nd: int,
        nh: int,
        nw: int,
        x_out: wp.array(dtype=vec),
        v_out: wp.array(dtype=vec),
    ):
        i = wp.tid()
        a = i // (nh * nw)
        b = (i // nw) % nh
        e = i % nw
        xi = x[i]
        vi = v[i]
        f = vec()
        for s in range(dirs.shape[0]):
            d = dirs[s]
            # spring i -> i + d, stored at [s, i]
            pa = a + d[0]
            pb = b + d[1]
            pe = e + d[2]
            if pa >= 0 and pa < nd and pb >= 0 and pb < nh and pe >= 0 and pe < nw:
                j = (pa * nh + pb) * nw + pe
                f = f + spring_force(xi, vi, x[j], v[j], l0[s, i], k[s, i], c[s, i])
            # spring i - d -> i, stored at [s, i - d]
            pa = a - d[0]
            pb = b - d[1]
            pe = e - d[2]
            if pa >= 0 and pa < nd and pb >= 0 and pb < nh and pe >= 0 and pe < nw:
                j = (pa * nh + pb) * nw + pe
                f = f + spring_force(xi, vi, x[j], v[j], l0[s, j], k[s, j], c[s, j])
        vn = vi + f * (inv_mass[i] * dt)
        v_out[i] = vn
        x_out[i] = xi + vn * dt

    return {
        "vec": vec,
        "scalar": scalar,
        "springs_atomic": springs_atomic,
        "integrate": integrate,
        "gather_step": gather_step,
    }


# ---------------------------------------------------------------- springs of a model
def _check_model(model) -> None:
    """The Warp step covers springs (projected damping), masses and fixed nodes only."""
    unsupported = [
        name
        for name, present in (
            ("gravity", model.gravity is not None),
            ("home/anchor springs", model.k_home is not None),
            ("loads", bool(model.loads)),
            ("drags", bool(model.drags)),
            ("decay", model.decay is not None),
            ("unprojected damping", model.damping is not None and not model.projected),
            (
                "batched parameters",
                model.stiffness.shape[0] != 1
                or model.mass.shape[0] != 1
                or (model.damping is not None and model.damping.shape[0] != 1),
            ),
        )
        if present
    ]
    if unsupported:
        raise ValueError(
            "the Warp baseline steps springs, masses and fixed nodes only; this model also has "
            + ", ".join(unsupported)
        )
    if model.dtype not in _SCALARS:
        raise ValueError(f"the Warp baseline runs float32 or float64, not {model.dtype}")


def _per_spring(model) -> tuple:
    """Stiffness, damping and rest length of every spring slot, each ``(S, D, H, W)`` float64 CPU.

    Zero stiffness and damping where no spring exists (``grid.spring_mask``).
    """
    grid = model.grid
    full = (grid.S,) + grid.shape
    mask = grid.spring_mask().to(torch.float64)
    k = model.stiffness[0].to("cpu", torch.float64).expand(full) * mask
    c = (
        torch.zeros(full, dtype=torch.float64)
        if model.damping is None
        else model.damping[0].to("cpu", torch.float64).expand(full) * mask
    )
    l0 = model.rest_length[0].to("cpu", torch.float64).expand(full)
    return k, c, l0


def edge_list(model) -> dict:
    """The springs of ``model`` as an edge list.

    In the Grid's stencil order (half-direction ``s``, then node). Nodes are numbered row-major over
    ``(D, H, W)``: node ``(a, b, e)`` is ``(a H + b) W + e``. Only springs with both ends in the
    grid (and in its node mask) are listed, so ``E = grid.num_springs``.

    Returns:
        dict of numpy arrays, each ``(E,)``: ``i``, ``j`` (int32; ``j = i + direction``),
        ``l0`` (m), ``k`` (N/m), ``c`` (N s/m; zeros without damping), the last three in the
        model's precision.
    """
    grid = model.grid
    np_dtype = np.float32 if model.dtype == torch.float32 else np.float64
    index = torch.arange(math.prod(grid.shape), dtype=torch.int64).view(grid.shape)
    mask = grid.spring_mask()
    k, c, l0 = _per_spring(model)
    parts = {name: [] for name in ("i", "j", "l0", "k", "c")}
    for s, (src, dst) in enumerate(grid.stencil):
        m = mask[(s, *src)]
        parts["i"].append(index[src][m])
        parts["j"].append(index[dst][m])
        for name, p in (("l0", l0), ("k", k), ("c", c)):
            parts[name].append(p[(s, *src)][m])
    out = {name: torch.cat(v).numpy() for name, v in parts.items()}
    out["i"], out["j"] = out["i"].astype(np.int32), out["j"].astype(np.int32)
    for name in ("l0", "k", "c"):
        out[name] = out[name].astype(np_dtype)
    return out


class WarpSprings:
    """torchdeform's spring step (symplectic Euler) for one model, on Warp's CPU backend.

    Args:
        model: a :class:`~torchdeform.sim.model.Model` with springs (projected damping or none),
            masses and optional fixed nodes; nothing else (no gravity, loads, drags, home
            springs, decay; ValueError otherwise), float32 or float64, unbatched parameters.
        state: initial :class:`~torchdeform.sim.model.State`, ``x`` and ``v`` ``(1, 3, D, H, W)``.
        variant: ``"atomic"`` or ``"gather"`` (see the module docstring).

    Arrays live on Warp's ``"cpu"`` device: ``x``, ``v`` ``(N,)`` of ``wp.vec3`` / ``wp.vec3d``
    with ``N = D H W`` nodes (row-major), inverse masses ``(N,)`` (zero at fixed nodes); atomic:
    the edge list (:func:`edge_list`), ``(E,)`` each, and forces ``(N,)``; gather: the
    half-directions ``(S,)`` of ``wp.vec3i`` and ``l0``, ``k``, ``c`` ``(S, N)`` in the Grid's
    ``(S, D, H, W)`` layout, plus a second ``x``, ``v`` buffer.

    :meth:`step` only launches kernels; on the CPU a launch returns when it is done.
    """

    def __init__(self, model, state, *, variant: str = "atomic"):
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        _check_model(model)
        wp = self.wp = _require_warp()
        self.model, self.variant = model, variant
        self.kern = _kernels(_SCALARS[model.dtype])
        self.np_dtype = np.float32 if model.dtype == torch.float32 else np.float64
        grid = model.grid
        self.N = math.prod(grid.shape)
        vec, dev = self.kern["vec"], "cpu"
        inv_mass = model.inv_mass[0, 0].to("cpu").expand(grid.shape).reshape(-1)
        self.inv_mass = wp.array(inv_mass.numpy().astype(self.np_dtype), dtype=self.kern["scalar"], device=dev)
        self.x = wp.zeros(self.N, dtype=vec, device=dev)
        self.v = wp.zeros(self.N, dtype=vec, device=dev)
        if variant == "atomic":
            e = edge_list(model)
            self.num_springs = len(e["i"])
            self.edges = {name: wp.array(a, device=dev) for name, a in e.items()}
            self.f = wp.zeros(self.N, dtype=vec, device=dev)
        else:
            k, c, l0 = _per_spring(model)
            flat = (grid.S, self.N)
            self.params = {
                name: wp.array(p.reshape(flat).numpy().astype(self.np_dtype), device=dev)
                for name, p in (("l0", l0), ("k", k), ("c", c))
            }
            self.dirs = wp.array(np.array(grid.directions, dtype=np.int32), dtype=wp.vec3i, device=dev)
            self.x2 = wp.zeros(self.N, dtype=vec, device=dev)
            self.v2 = wp.zeros(self.N, dtype=vec, device=dev)
            self.num_springs = grid.num_springs
        self._cmds, self._cmd_dt = None, None
        self.set_state(state)

    def load(self) -> float:
        """Build (or load from Warp's kernel cache) the modules of this variant's kernels on the CPU.

        Returns the wall time in seconds (about 0 when they are loaded already).
        """
        names = ("springs_atomic", "integrate") if self.variant == "atomic" else ("gather_step",)
        t0 = time.perf_counter()
        for name in names:
            self.wp.load_module(self.kern[name].module, device="cpu")
        return time.perf_counter() - t0

    def set_state(self, state) -> None:
        """Copy a torch state ``(1, 3, D, H, W)`` into the Warp arrays (outside any timing)."""
        shape = (1, 3) + self.model.grid.shape
        if tuple(state.x.shape) != shape or tuple(state.v.shape) != shape:
            raise ValueError(f"state x and v must be {shape}, got {tuple(state.x.shape)}, {tuple(state.v.shape)}")
        for arr, t in ((self.x, state.x), (self.v, state.v)):
            arr.assign(np.ascontiguousarray(t.detach()[0].to("cpu").reshape(3, -1).T.numpy().astype(self.np_dtype)))
        self.t = float(state.t)
        self._flip = False  # gather: which buffer holds the state

    def _commands(self, dt: float) -> list:
        """Recorded launches (``wp.launch(..., record_cmd=True)``) of one step for ``dt``.

        Gather records the two ping-pong directions.
        """
        if self._cmds is not None and self._cmd_dt == dt:
            return self._cmds
        wp, kern, sc = self.wp, self.kern, self.kern["scalar"]
        if self.variant == "atomic":
            e = self.edges
            cmds = [
                wp.launch(
                    kern["springs_atomic"],
                    dim=len(e["i"]),
                    device="cpu",
                    record_cmd=True,
                    inputs=[self.x, self.v, e["i"], e["j"], e["l0"], e["k"], e["c"], self.f],
                ),
                wp.launch(
                    kern["integrate"],
                    dim=self.N,
                    device="cpu",
                    record_cmd=True,
                    inputs=[self.x, self.v, self.f, self.inv_mass, sc(dt)],
                ),
            ]
        else:
            p, (nd, nh, nw) = self.params, self.model.grid.shape

            def rec(x, v, xo, vo):
                return wp.launch(
                    kern["gather_step"],
                    dim=self.N,
                    device="cpu",
                    record_cmd=True,
                    inputs=[x, v, self.dirs, p["l0"], p["k"], p["c"], self.inv_mass, sc(dt), nd, nh, nw, xo, vo],
                )

            cmds = [rec(self.x, self.v, self.x2, self.v2), rec(self.x2, self.v2, self.x, self.v)]
        self._cmds, self._cmd_dt = cmds, dt
        return cmds

    def step(self, dt: float, *, steps: int = 1) -> None:
        """Advance ``steps`` symplectic Euler steps of ``dt`` seconds (kernels only, no copies)."""
        cmds = self._commands(float(dt))
        if self.variant == "atomic":
            forces, integrate = cmds
            for _ in range(steps):
                forces.launch()
                integrate.launch()
        else:
            for _ in range(steps):
                cmds[self._flip].launch()
                self._flip = not self._flip
        self.t += steps * float(dt)

    def state(self):
        """The current state as a torch :class:`~torchdeform.sim.model.State`.

        ``(1, 3, D, H, W)`` in the model's dtype, on the CPU.
        """
        from ..sim.model import State

        self.wp.synchronize()
        x, v = (self.x2, self.v2) if self._flip else (self.x, self.v)
        shape = (1, 3) + self.model.grid.shape
        to_torch = lambda a: torch.from_numpy(a.numpy().T.copy()).reshape(shape).to(self.model.dtype)
        return State(to_torch(x), to_torch(v), t=self.t)


# ------------------------------------------------------------------------ speed row
def warp_speed_row(
    n: int,
    *,
    topology: int = 26,
    variant: str = "atomic",
    dtype=torch.float32,
    steps=None,
    repeats: int = 5,
    target_s: float = 0.2,
    reference=None,
) -> dict:
    """Time the Warp step on :func:`~torchdeform.bench.common.speed_cube`; one row of the speed table.

    Same keys as :func:`torchdeform.bench.speed.speed_row` (without its private ``_first``):
    ``grid``, ``n``, ``topology``, ``mode`` (``"warp-atomic"`` / ``"warp-gather"``), ``dtype``,
    ``threads`` (1: Warp's CPU backend runs each launch on the calling thread), ``device``
    (``"cpu"``), ``nodes``, ``springs``, ``steps``, ``repeats``, ``ms_per_step``,
    ``msprings_per_s`` (``springs / (s per step) / 1e6``), ``node_steps_per_s``, ``compile_s``
    (:meth:`WarpSprings.load`: building the Warp modules, a few seconds, or loading them from
    Warp's kernel cache in ``~/.cache/warp``, milliseconds; no step included), ``max_abs_diff``
    and ``fallback`` (always False).

    Args:
        n: grid size (``n^3`` nodes).
        topology: 6, 14, 18 or 26.
        variant: ``"atomic"`` or ``"gather"``.
        dtype: ``torch.float32`` (``wp.vec3``) or ``torch.float64`` (``wp.vec3d``).
        steps: steps per timed repeat (default: enough for about ``target_s`` seconds, 3..200).
        repeats: timed repeats; the median seconds per step is kept.
        target_s: wall time aimed at per timed repeat when ``steps`` is None (s).
        reference: torchdeform's eager state after one step from the scene's state
            (``(1, 3, n, n, n)``); computed here with ``SymplecticEuler().step`` when None.
            ``max_abs_diff`` is the largest difference of positions and velocities after one
            Warp step.

    Every repeat starts from the scene's state (copied in outside the timing); warm-up steps
    are excluded and ``wp.synchronize()`` brackets every timed block of steps.
    """
    from ..sim.integrators import SymplecticEuler

    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    wp = _require_warp()
    model, state, dt = speed_cube(n, topology, dtype=dtype)
    if reference is None:
        with torch.no_grad():
            reference = SymplecticEuler().step(model, state, dt)
    sim = WarpSprings(model, state, variant=variant)
    row = {
        "grid": f"{n}^3",
        "n": n,
        "topology": topology,
        "mode": f"warp-{variant}",
        "dtype": str(dtype).replace("torch.", ""),
        "threads": 1,
        "device": "cpu",
        "nodes": model.grid.num_nodes,
        "springs": sim.num_springs,
    }

    compile_s = sim.load()
    sim.step(dt)  # first step: the reference comparison
    first = sim.state()
    diff = max(
        float((first.x - reference.x.to(first.x)).abs().max()), float((first.v - reference.v.to(first.v)).abs().max())
    )

    sim.set_state(state)  # second warm-up step, also sizes the run
    wp.synchronize()
    t0 = time.perf_counter()
    sim.step(dt)
    wp.synchronize()
    warm = max(time.perf_counter() - t0, 1e-7)
    if steps is None:
        steps = int(min(200, max(3, math.ceil(target_s / warm))))
    times = []
    for _ in range(repeats):
        sim.set_state(state)
        wp.synchronize()
        t0 = time.perf_counter()
        sim.step(dt, steps=steps)
        wp.synchronize()
        times.append((time.perf_counter() - t0) / steps)
    sec = statistics.median(times)
    row.update(
        steps=steps,
        repeats=repeats,
        ms_per_step=sec * 1e3,
        msprings_per_s=row["springs"] / sec / 1e6,
        node_steps_per_s=row["nodes"] / sec,
        compile_s=compile_s,
        max_abs_diff=diff,
        fallback=False,
    )
    return row


__all__ = ["VARIANTS", "INSTALL_HINT", "warp_available", "edge_list", "WarpSprings", "warp_speed_row"]
