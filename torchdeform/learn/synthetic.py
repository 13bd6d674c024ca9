"""Synthetic series for learning, each simulated with known ("true") parameters.

Radetzky's cube, n^3 cubes under several loads, and Radetzky's balloon.

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

Noise is Gaussian with standard deviation ``noise * RMS(x - X)`` over the free-node coordinates
of the clean observations (so ``noise=0.01`` is "1 % noise"). Heterogeneous materials: integer
region labels per node; a spring whose ends lie in different regions gets the harmonic mean of
the two values (two half-springs in series, as :mod:`torchdeform.fuzzy.coupling` does).

Example:
    >>> from torchdeform import learn
    >>> s = learn.cube_series(n=3, load="sine", steps=20)
    >>> s.positions.shape, type(s.loads[0]).__name__
    ((21, 3, 3, 3, 3), 'Drag')
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import ConfigError, positive_number
from ..sim.forces import Drag, FieldForce, PointForce
from ..sim.grid import Grid
from .parameters import NodeParameter, Parameters, SpringParameter, expand_spring_param
from .series import Series

__all__ = [
    "radetzky_cube",
    "per_spring_start",
    "cube_series",
    "balloon_series",
    "cube_grid",
    "indentation",
    "layered_regions",
    "inclusion_regions",
    "SPRING_SETS",
]

#: Radetzky's cube spring sets: number of springs -> (topology, kept half-directions or None).
#: 70 is Radetzky's count; the thesis figure that placed its 16 extra springs is lost, so we
#: add one crossing pair of body diagonals per cell (half-directions (1,1,1) and (1,-1,-1)).
SPRING_SETS = {54: (6, None), 70: (14, ((1, 1, 1), (1, -1, -1))), 86: (14, None), 126: (18, None)}


def indentation(grid: Grid, depth: float, *, radius: int = 0, duration: float = 0.5) -> Drag:
    """An indenter pushed ``depth`` metres into the top face (axis D, ``"top"``) over ``duration`` seconds.

    The top nodes within ``radius`` nodes (Chebyshev) of the face centre are prescribed at
    ``X - depth e_D`` (a ramp).
    """
    D, H, W = grid.shape
    ch, cw = (H - 1) / 2, (W - 1) / 2
    nodes = [
        (D - 1, j, k) for j in range(H) for k in range(W) if abs(j - ch) <= radius + 0.5 and abs(k - cw) <= radius + 0.5
    ]
    return Drag(grid.index_mask(nodes), offset=(-float(depth), 0.0, 0.0), ramp=float(duration))


def cube_grid(*, n: int = 3, spacing: float = 0.01, springs: int | None = None, topology: int = 26):
    """A cube of ``n^3`` nodes and its spring mask.

    Args:
        n: nodes per edge.
        spacing: node spacing (metres).
        springs: one of Radetzky's sets (54, 70, 86, 126; ``n = 3`` only), or None to use ``topology``.
        topology: 6, 14, 18 or 26 (when ``springs`` is None).

    Returns:
        ``(grid, spring_mask)``: the mask is bool ``(S, D, H, W)`` or None (every spring).
    """
    if springs is not None:
        if springs not in SPRING_SETS:
            raise ConfigError("springs", f"one of {', '.join(map(str, SPRING_SETS))}", got=springs)
        if n != 3:
            raise ConfigError("springs", "Radetzky's spring sets only on a 3 x 3 x 3 cube (n = 3)", got=n)
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


def _simulate_truth(
    series: Series,
    stiffness,
    damping,
    mass,
    noise: float,
    every: int,
    observe,
    seed: int,
    dtype=torch.float64,
    integrator=None,
) -> Series:
    """Fill ``series.positions/steps/mask/truth`` by simulating the true model."""
    grid = series.grid
    smask = series.spring_mask_tensor()
    regions = series.truth.get("regions")
    k = expand_spring_param(stiffness, grid, regions=regions, spring_mask=smask)
    c = expand_spring_param(damping, grid, regions=regions, spring_mask=smask)
    m = torch.as_tensor(np.asarray(mass, dtype=np.float64)).expand(grid.shape).clone() * grid.nodes()
    series.truth.update({"stiffness": k.numpy(), "damping": c.numpy(), "mass": m.numpy()})
    with torch.no_grad():
        model = series.model(k, c, m, dtype=dtype)
        xs = series.simulate(model, integrator=integrator)[:, 0].to(torch.float64).numpy()  # (N + 1, 3, D, H, W)
    _check_diverged(series, model, xs, integrator)
    N = xs.shape[0] - 1
    steps = np.arange(0, N + 1, int(every))
    clean = xs[steps]
    obs = np.ones((len(steps),) + grid.shape, dtype=bool)
    if observe is not None:
        obs &= np.asarray(observe, dtype=bool)[None]
    obs &= grid.nodes().numpy()[None]
    pos = clean.copy()
    if noise > 0:
        X = grid.rest_positions(dtype=torch.float64)[0].numpy()
        free = ~series.constrained() & grid.nodes().numpy()
        disp = (clean - X[None])[:, :, free]
        sigma = float(noise) * float(np.sqrt(np.mean(disp**2)))
        rng = np.random.default_rng(seed)
        pos = pos + rng.normal(0.0, sigma, size=pos.shape)
        series.meta["noise_sigma"] = sigma
    pos[~np.broadcast_to(obs[:, None], pos.shape)] = 0.0  # unobserved entries carry no data
    series.positions, series.steps, series.mask = pos, steps, obs
    series.meta.update({"noise": float(noise), "seed": int(seed), "every": int(every)})
    return series


#: a synthetic body that moved farther than this many body sizes from rest has diverged
RUNAWAY_SIZES = 10.0


def _check_diverged(series: Series, model, xs: np.ndarray, integrator) -> None:
    """Raise :class:`~torchdeform.errors.DivergenceError` when the true run blew up.

    Non-finite positions, or a node farther than :data:`RUNAWAY_SIZES` body sizes from its rest
    position (an explicit step past its stability bound grows geometrically: 1e117 m is finite but
    no data); names the first such step and a safe time step.
    """
    from ..errors import DivergenceError

    X = series.grid.rest_positions(dtype=torch.float64)[0].numpy()
    size = max(n * h for n, h in zip(series.grid.shape, series.grid.spacing))
    with np.errstate(invalid="ignore", over="ignore"):
        far = np.abs(xs - X[None]).reshape(len(xs), -1).max(1)
    bad = ~np.isfinite(far) | (far > RUNAWAY_SIZES * size)
    if not bad.any():
        return
    step = int(np.argmax(bad))
    safe = None
    try:
        from ..sim.stability import time_step_bound

        safe = 0.9 * time_step_bound(model, integrator=integrator or series.integrator)
    except Exception:  # a bound is a hint only
        safe = None
    raise DivergenceError(step, "displacement (m)", float(far[step]), float(series.dt), safe)


def _truth_meta(stiffness, damping, mass) -> dict:
    def js(v):
        a = np.asarray(v, dtype=np.float64)
        return float(a) if a.ndim == 0 else a.tolist()

    return {"stiffness": js(stiffness), "damping": js(damping), "mass": js(mass)}


def radetzky_cube(
    *,
    springs: int = 70,
    stiffness=10.0,
    damping=0.1,
    mass=0.01,
    force=(-0.05, 0.0, 0.0),
    steps: int = 250,
    dt: float = 0.005,
    spacing: float = 0.01,
    noise: float = 0.0,
    every: int = 1,
    observe=None,
    seed: int = 0,
    damping_mode: str = "unprojected",
    integrator=None,
) -> Series:
    """Radetzky's cube experiment: 3 x 3 x 3 nodes, lower 9 fixed, a constant force on the top-centre node.

    The force acts for all ``steps`` steps. The thesis gives neither the parameters, the force,
    ``t_c`` nor the edge length; these defaults (k = 10 N/m, d = 0.1 N s/m unprojected as in his
    eq. 2.21, m = 10 g, 1 cm edges, dt = 5 ms, force (-0.05, 0, 0) N: pushing the top-centre node
    down) bring every spring set to equilibrium within the 250 steps (a sideways force makes the
    54- and 70-spring cubes, which have little or no shear stiffness, creep for much longer).

    Args:
        springs: 54 (axes), 70 (axes + 16 body diagonals), 86 (axes + 32 body diagonals) or
            126 (axes + 72 face diagonals); see :data:`SPRING_SETS`.
        stiffness: true stiffness (N/m): a number, ``(S,)`` or ``(S, D, H, W)``.
        damping: true damping (N s/m): a number, ``(S,)`` or ``(S, D, H, W)``.
        mass: kg per node, a number or ``(3, 3, 3)``.
        force: newtons on node (2, 1, 1) (axis D is up).
        steps: number of time steps simulated.
        dt: time step (s).
        spacing: edge length of one cell (m).
        noise: as in :func:`cube_series`.
        every: as in :func:`cube_series`.
        observe: as in :func:`cube_series`.
        seed: as in :func:`cube_series`.
        damping_mode: ``"unprojected"`` (Radetzky's eq. 2.21) or ``"projected"`` (along the spring).
        integrator: the integrator that makes the truth (an instance, e.g. a tight
            ``ImplicitEuler(cg_tol=1e-12)`` for a stiff cube at a large ``dt``), or None: symplectic
            Euler. The series records its name.

    Returns:
        a :class:`Series`.
    """
    grid, smask = cube_grid(n=3, spacing=spacing, springs=springs)
    s = Series(
        np.zeros(0),
        np.zeros(0, dtype=np.int64),
        np.zeros(0, dtype=bool),
        positive_number(dt, "dt"),
        grid,
        None if smask is None else smask.numpy(),
        grid.face("bottom").numpy(),
        [PointForce((2, 1, 1), tuple(float(c) for c in force))],
        damping_mode=damping_mode,
        meta={
            "generator": "radetzky_cube",
            "springs": springs,
            "steps": int(steps),
            "description": f"Radetzky's cube, {springs} springs, lower 9 nodes fixed, "
            f"constant force {tuple(force)} N on the top-centre node",
            "truth": _truth_meta(stiffness, damping, mass),
        },
    )
    if integrator is not None:
        s.integrator = integrator.name
    return _finish(s, stiffness, damping, mass, noise, every, observe, seed, steps, integrator)


def per_spring_start(series: Series, *, seed: int = 0, with_mass: bool = False, spread=(0.2, 5.0)):
    """Radetzky's per-spring start: every spring's stiffness and damping at ``U[lo, hi]`` x truth.

    The factors are log-uniform between ``spread`` (Radetzky's runs 1 and 2: 0.2 and 5), drawn
    from a generator seeded with ``seed``: stiffness first, then damping, then (``with_mass``)
    one mass per node.

    Returns:
        ``(params, truth)``: the :class:`Parameters` (per-spring stiffness and damping, per-node
        masses when ``with_mass``, otherwise the true masses), and the true values in the same
        order as the learned ones: ``{"stiffness": (n,), "damping": (n,)[, "mass": (D, H, W)]}``.

    Example:
        >>> from torchdeform import learn
        >>> series = learn.radetzky_cube(springs=70, steps=20)
        >>> params, truth = learn.per_spring_start(series, seed=1)
        >>> ratio = params.learned["stiffness"].values().detach() / truth["stiffness"]
        >>> len(ratio), bool(((ratio >= 0.2) & (ratio <= 5.0)).all())
        (70, True)
    """
    lo, hi = (float(v) for v in spread)
    g = torch.Generator().manual_seed(int(seed))

    def factors(n):
        return torch.exp(torch.empty(n, dtype=torch.float64).uniform_(np.log(lo), np.log(hi), generator=g))

    probe = SpringParameter.like(series, init=1.0, sharing="spring")
    truth = {key: probe.per_spring(torch.as_tensor(series.truth[key])) for key in ("stiffness", "damping")}
    n = len(truth["stiffness"])
    k = SpringParameter.like(series, init=truth["stiffness"] * factors(n), sharing="spring")
    c = SpringParameter.like(series, init=truth["damping"] * factors(n), sharing="spring")
    mass = series.truth["mass"]
    if with_mass:
        truth["mass"] = torch.as_tensor(mass, dtype=torch.float64).expand(series.grid.shape)[series.grid.nodes()]
        mass = NodeParameter(series.grid, init=truth["mass"] * factors(len(truth["mass"])), sharing="node")
    return Parameters(series, k, c, mass), truth


def _finish(s: Series, stiffness, damping, mass, noise, every, observe, seed, steps, integrator=None) -> Series:
    if int(steps) < 1:
        raise ConfigError("steps", "an integer >= 1", got=steps)
    if int(every) < 1 or int(steps) % int(every):
        raise ConfigError("every", f"a divisor of steps = {steps} (>= 1)", got=every)
    if not (0 <= float(noise) < 1):
        raise ConfigError("noise", "a relative noise level in [0, 1)", got=noise)
    s.steps = np.array([0, int(steps)])  # num_steps for the tables
    s.meta["num_steps"] = int(steps)
    return _simulate_truth(
        s, stiffness, damping, mass, float(noise), int(every), observe, int(seed), integrator=integrator
    )


def layered_regions(grid: Grid, *, layers: int = 2) -> np.ndarray:
    """Region labels ``(D, H, W)``: ``layers`` horizontal slabs along axis D (0 at the bottom)."""
    D = grid.shape[0]
    lab = (np.arange(D) * layers) // D
    return np.broadcast_to(lab[:, None, None], grid.shape).astype(np.int64).copy()


def inclusion_regions(grid: Grid, radius: float) -> np.ndarray:
    """Region labels ``(D, H, W)``: 1 inside a sphere about the centre, 0 outside.

    The sphere has ``radius`` node spacings (a stiff or soft inclusion).
    """
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in grid.shape], indexing="ij"))
    c = (np.array(grid.shape) - 1)[:, None, None, None] / 2
    return (np.sqrt(((idx - c) ** 2).sum(0)) <= radius).astype(np.int64)


def cube_series(
    *,
    n: int = 4,
    topology: int = 26,
    load: str = "constant",
    amplitude: float | None = None,
    stiffness=10.0,
    damping=0.1,
    mass=0.01,
    regions=None,
    steps: int = 250,
    dt: float = 0.005,
    spacing: float = 0.01,
    noise: float = 0.0,
    every: int = 1,
    observe=None,
    seed: int = 0,
    damping_mode: str = "unprojected",
    period: float = 0.5,
    duration: float = 0.5,
) -> Series:
    """An ``n^3`` cube with its bottom face fixed under one of several loads.

    Args:
        n: nodes per edge (>= 2).
        topology: 6, 14, 18 or 26.
        load: ``"constant"`` (force on the top-centre node), ``"ramp"`` (the same force ramped
            in over ``duration``), ``"sine"`` (the top face dragged sideways,
            ``amplitude sin(2 pi t / period)``), ``"indent"`` (top-centre patch pushed down by
            ``amplitude`` over ``duration``).
        amplitude: N for forces (default 0.05 N), m for drags and indentation (default 0.2 spacing).
        stiffness: true stiffness (N/m): a number, or a per-region table ``(R,)`` with ``regions``,
            or ``(S,)`` / ``(S, D, H, W)``.
        damping: true damping (N s/m), the same shapes as ``stiffness``.
        mass: kg per node, a number or ``(D, H, W)``.
        regions: node labels ``(D, H, W)`` (see :func:`layered_regions`, :func:`inclusion_regions`).
        steps: number of time steps.
        dt: time step (s).
        spacing: node spacing (m).
        noise: relative observation noise (0.01 = 1 %).
        every: observe every k-th step (sparse times).
        observe: bool ``(D, H, W)`` of observed nodes (partial observation), or None (all).
        seed: noise seed.
        damping_mode: ``"unprojected"`` (Radetzky) or ``"projected"`` (along the spring).
        period: period of the ``"sine"`` drag (s).
        duration: ramp time of ``"ramp"`` and ``"indent"`` (s).

    Returns:
        a :class:`Series`.
    """
    if int(n) < 2:
        raise ConfigError("n", "an integer >= 2", got=n)
    grid, _ = cube_grid(n=int(n), spacing=spacing, springs=None, topology=topology)
    top = (n - 1, (n - 1) // 2, (n - 1) // 2)
    if load in ("constant", "ramp"):
        a = 0.05 if amplitude is None else float(amplitude)
        ld = PointForce(top, (-a, 0.25 * a, 0.0), ramp=float(duration) if load == "ramp" else 0.0)
    elif load == "sine":
        a = 0.2 * spacing if amplitude is None else float(amplitude)
        ld = Drag(grid.face("top"), offset=(0.0, a, 0.0), period=float(period))
    elif load == "indent":
        a = 0.2 * spacing if amplitude is None else float(amplitude)
        ld = indentation(grid, a, radius=max(0, (n - 3) // 3), duration=duration)
    else:
        raise ConfigError("load", "one of constant, ramp, sine, indent", got=load)
    truth = {} if regions is None else {"regions": np.asarray(regions, dtype=np.int64)}
    if regions is not None and tuple(np.shape(regions)) != grid.shape:
        raise ConfigError("regions", f"integer labels of shape {grid.shape}", got=np.shape(regions))
    s = Series(
        np.zeros(0),
        np.zeros(0, dtype=np.int64),
        np.zeros(0, dtype=bool),
        positive_number(dt, "dt"),
        grid,
        None,
        grid.face("bottom").numpy(),
        [ld],
        damping_mode=damping_mode,
        truth=truth,
        meta={
            "generator": "cube_series",
            "n": int(n),
            "load": load,
            "steps": int(steps),
            "description": f"{n}^3 cube, {topology} neighbours, bottom fixed, load {load}",
            "truth": _truth_meta(stiffness, damping, mass),
        },
    )
    return _finish(s, stiffness, damping, mass, noise, every, observe, seed, steps)


def balloon_series(
    *,
    subdivisions: int = 1,
    radius: float = 0.05,
    spacing: float | None = None,
    topology: int = 26,
    stiffness=2.0,
    damping=0.05,
    mass=0.05,
    pressure: float = 30.0,
    snapshots: int = 5,
    interval: float = 1.0,
    dt: float = 0.02,
    noise: float = 0.0,
    seed: int = 0,
    mesh=None,
) -> Series:
    """Radetzky's balloon, synthetically: a voxelised closed surface inflated by a rising pressure.

    A closed trimesh surface (an icosphere by default) voxelised into a grid body, inflated by a
    pressure rising linearly over the run, applied along the mesh's vertex normals at the surface
    nodes; observed in ``snapshots`` snapshots ``interval`` seconds apart (``interval / dt`` steps
    between them, 50 with the defaults).

    Args:
        subdivisions: subdivisions of ``trimesh.creation.icosphere`` (when ``mesh`` is None).
        radius: radius (m) of the icosphere (when ``mesh`` is None).
        spacing: grid spacing (default ``radius / 2``: a coarse body of a few dozen nodes).
        topology: 6, 14, 18 or 26.
        stiffness: as in :func:`cube_series`.
        damping: as in :func:`cube_series`.
        mass: as in :func:`cube_series`.
        pressure: final pressure (Pa) at the end of the run; each surface node gets
            ``pressure * spacing^2`` newtons along the normal of its nearest mesh vertex.
        snapshots: number of observations (the first at rest).
        interval: time between snapshots (s), a whole number of steps.
        dt: time step (s).
        noise: as in :func:`cube_series`.
        seed: as in :func:`cube_series`.
        mesh: a closed ``trimesh.Trimesh`` or a mesh file instead of the icosphere.

    Returns:
        a :class:`Series` whose centre node is fixed (it pins the free body in space).
    """
    import trimesh
    from scipy.spatial import cKDTree

    from ..mesh import grid_from_mesh, load_mesh

    if mesh is None:
        mesh = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=float(radius))
    spacing = float(radius) / 2 if spacing is None else positive_number(spacing, "spacing")
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
    X = grid.rest_positions(dtype=torch.float64)[0].numpy()
    pts = X[:, surface].T
    _, nearest = cKDTree(vertices).query(pts)
    field_ = np.zeros((3,) + grid.shape)
    field_[:, surface] = (normals[nearest] * float(pressure) * spacing**2).T
    steps_per = round(float(interval) / float(dt))
    if steps_per < 1 or abs(steps_per * dt - interval) > 1e-9 * interval:
        raise ConfigError("interval", f"a whole number of time steps dt = {dt}", got=interval)
    steps = steps_per * (int(snapshots) - 1)
    fixed = np.zeros(grid.shape, dtype=bool)
    centre = np.unravel_index(
        np.argmin(np.where(nodes, ((X - X[:, nodes].mean(1)[:, None, None, None]) ** 2).sum(0), np.inf)), grid.shape
    )
    fixed[centre] = True
    ld = FieldForce(field_, ramp=steps * dt)
    s = Series(
        np.zeros(0),
        np.zeros(0, dtype=np.int64),
        np.zeros(0, dtype=bool),
        positive_number(dt, "dt"),
        grid,
        None,
        fixed,
        [ld],
        damping_mode="unprojected",
        meta={
            "generator": "balloon_series",
            "steps": steps,
            "snapshots": int(snapshots),
            "interval": float(interval),
            "surface_nodes": int(surface.sum()),
            "description": f"voxelised closed surface ({grid.num_nodes} nodes, {grid.num_springs} springs), "
            f"pressure ramped to {pressure} Pa along vertex normals, "
            f"{snapshots} snapshots {interval} s apart",
            "truth": _truth_meta(stiffness, damping, mass),
        },
    )
    return _finish(s, stiffness, damping, mass, noise, steps_per, None, seed, steps)
