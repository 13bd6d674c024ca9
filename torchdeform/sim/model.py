"""``Model`` (what a step reads and does not change) and ``State`` (positions, velocities).

Example:
    >>> import torchdeform as td
    >>> grid = td.Grid((5, 5, 5), spacing=0.01, topology=26)
    >>> model = td.Model(grid, stiffness=50.0, damping=0.1, density=1000.0,
    ...                  gravity=(-9.81, 0, 0), fixed=grid.face("bottom"))
    >>> state = model.rest_state()
    >>> state = td.SymplecticEuler().step(model, state, dt=1e-4)
    >>> state.x.shape, state.t
    (torch.Size([1, 3, 5, 5, 5]), 0.0001)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import KW_ONLY, dataclass

import torch

from ..errors import ConfigError
from .forces import as_vec3, home_force
from .grid import CLASSES, FACES, Grid
from .laws import as_law
from .material import (
    CELL_SHARE,
    Elastic,
    VolumeLinearisation,
    cell_field,
    cell_mask,
    spring_stiffness,
    volume_energy,
    volume_forces,
    volume_row_sums,
)
from .springs import Linearisation, node_sums, spring_energy, spring_forces, spring_forces_conv

#: External loads of a step: a force field ``(B, 3, D, H, W)`` (N), a function of time ``t`` (s)
#: returning one, or None.
Loads = torch.Tensor | Callable[[float], torch.Tensor] | None


@dataclass
class State:
    """Positions ``x`` and velocities ``v``, both ``(B, 3, D, H, W)``, at time ``t`` (s).

    ``readings`` holds what the interactions measured over the step that produced the state
    (forces on tools, ``{"<tool>.force": (B, 3), ...}``; see :mod:`torchdeform.interact.reactions`),
    or None.

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> x = torch.zeros(2, 3, 4, 4, 4)
        >>> s = td.State(x, torch.zeros_like(x), t=0.5)
        >>> s.x.shape, s.t
        (torch.Size([2, 3, 4, 4, 4]), 0.5)
    """

    x: torch.Tensor
    v: torch.Tensor
    _: KW_ONLY
    t: float = 0.0
    readings: dict | None = None

    def detach(self) -> State:
        """The same state with ``x``, ``v`` and the readings detached from the autograd graph."""
        readings = None if self.readings is None else {k: r.detach() for k, r in self.readings.items()}
        return State(self.x.detach(), self.v.detach(), t=self.t, readings=readings)


def _as_tensor(value, key, dtype, device) -> torch.Tensor:
    try:
        t = (
            torch.as_tensor(value, dtype=dtype, device=device)
            if not torch.is_tensor(value)
            else value.to(dtype=dtype, device=device)
        )
    except (TypeError, ValueError, RuntimeError):
        raise ConfigError(key, "a number or an array of numbers", got=value) from None
    if not bool(torch.isfinite(t).all()):
        raise ConfigError(key, "finite values (no NaN or inf)", got="non-finite values", show_got=True)
    return t


def _fixed_mask(fixed, grid: Grid) -> torch.Tensor:
    """The fixed nodes, bool ``(D, H, W)`` on the CPU, of a mask or of face names (one or a list)."""
    names = [fixed] if isinstance(fixed, str) else fixed
    if isinstance(names, (list, tuple)) and names and all(isinstance(n, str) for n in names):
        mask = torch.zeros(grid.shape, dtype=torch.bool)
        for name in names:
            if name not in FACES:
                raise ConfigError(
                    "fixed", "a face name (" + ", ".join(FACES) + "), a list of them or a bool mask", got=name
                )
            mask = mask | grid.face(name)
        return mask
    try:
        return torch.as_tensor(fixed, dtype=torch.bool).cpu()
    except (TypeError, ValueError, RuntimeError):
        raise ConfigError(
            "fixed", f"a bool mask of shape {grid.shape}, a face name or a list of them", got=fixed
        ) from None


def spring_param(value, grid: Grid, key: str, dtype, device, *, allow_zero=True) -> torch.Tensor:
    """Normalise a spring parameter to shape ``(Bp, S, 1|D, 1|H, 1|W)``.

    Accepts a number (all springs), a dict by direction class ``{"axis": .., "face": ..,
    "body": ..}``, ``(S,)`` (per half-direction), ``(S, D, H, W)`` (per spring), ``(B, S)`` or
    ``(B, S, D, H, W)`` (per batch entry). Values must be finite and >= 0.
    """
    if isinstance(value, dict):
        classes = grid.direction_class()
        unknown = set(value) - set(CLASSES)
        missing = set(classes) - set(value)
        if unknown or missing:
            raise ConfigError(key, f"one value per direction class {sorted(set(classes))}", got=value)
        value = [float(value[c]) for c in classes]
    t = _as_tensor(value, key, dtype, device)
    S, shape = grid.S, grid.shape
    if t.dim() == 0:
        t = t.expand(1, S).reshape(1, S, 1, 1, 1)
    elif t.dim() == 1 and t.shape[0] == S:
        t = t.view(1, S, 1, 1, 1)
    elif t.dim() == 2 and t.shape[1] == S:
        t = t.view(-1, S, 1, 1, 1)
    elif t.dim() == 4 and tuple(t.shape) == (S,) + shape:
        t = t.unsqueeze(0)
    elif not (t.dim() == 5 and tuple(t.shape[1:]) == (S,) + shape):
        raise ConfigError(
            key, f"a number, (S,), (S, D, H, W) or (B, S, D, H, W) with S = {S}, grid {shape}", got=tuple(t.shape)
        )
    if bool((t < 0).any()) or (not allow_zero and bool((t == 0).any())):
        raise ConfigError(key, "values >= 0" if allow_zero else "values > 0", got=float(t.min()))
    return t


def node_param(value, grid: Grid, key: str, dtype, device) -> torch.Tensor:
    """Normalise a per-node parameter to ``(Bp, 1, 1|D, 1|H, 1|W)``.

    Accepts a number, ``(D, H, W)``, ``(B, 1, D, H, W)``, or its own result (each of the last three
    axes 1 or the grid's), so that a model rebuilt from another model's parameters works.
    """
    t = _as_tensor(value, key, dtype, device)
    if t.dim() == 0:
        return t.view(1, 1, 1, 1, 1)
    if tuple(t.shape) == grid.shape:
        return t.view(1, 1, *grid.shape)
    if t.dim() == 5 and t.shape[1] == 1 and all(n in (1, g) for n, g in zip(t.shape[2:], grid.shape)):
        return t
    raise ConfigError(key, f"a number, (D, H, W) or (B, 1, D, H, W) with grid {grid.shape}", got=tuple(t.shape))


def lumped_mass(grid: Grid, density: float, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """Node masses ``(1, 1, D, H, W)`` from a density (kg/m^3).

    Every existing node owns the box-shaped voxel around it (its dual cell), cut at the faces
    of the grid: ``density * prod_a spacing_a * w_a`` with ``w_a = 1/2`` on the first and last
    node along axis ``a`` (when it has more than one node). For a box this is the usual lumped
    mass (corners 1/8 of a cell, interior nodes one cell; total ``density * volume``); with a
    node mask, thin features keep a positive mass.

    Examples:
        >>> import torchdeform as td
        >>> m = td.lumped_mass(td.Grid((3, 3, 3), spacing=0.01), density=1000.0)
        >>> m.shape, round(float(m.sum()), 9)              # 1000 kg/m^3 * (2 cm)^3
        (torch.Size([1, 1, 3, 3, 3]), 0.008)
        >>> round(float(m[0, 0, 1, 1, 1] / m[0, 0, 0, 0, 0]), 9)     # interior node / corner
        8.0
    """
    mass = torch.full(grid.shape, float(density), dtype=torch.float64)
    for axis, (n, h) in enumerate(zip(grid.shape, grid.spacing)):
        w = torch.full((n,), h, dtype=torch.float64)
        if n > 1:
            w[0] = w[-1] = h / 2
        mass = mass * w.view([-1 if a == axis else 1 for a in range(3)])
    mass = mass * grid.nodes()
    return mass.view(1, 1, *grid.shape).to(dtype=dtype, device=device)


class Model:
    """Everything a step reads: grid, masses, spring parameters, other force terms, constraints.

    Only the terms that are given exist: ``damping=None`` costs nothing, no gravity vector means
    no gravity term, and so on.

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid`.
        stiffness: spring stiffness k (N/m); see :func:`spring_param` for the accepted shapes.
            With ``normalize=True`` it is a modulus Y (N) and each spring gets ``k = Y / l0``,
            so a chain keeps its overall stiffness when the resolution changes.
            Or an :class:`~torchdeform.sim.material.Elastic` (Young's modulus and Poisson ratio):
            springs assembled from the cells and, above ``nu = 1/4``, the per-cell volume term
            (:attr:`volume`).
        damping: spring damping (N s/m) like ``stiffness`` (``/ l0`` too when normalised), or None.
        damping_mode: ``"projected"`` (dashpot along the spring) or ``"unprojected"``
            (Radetzky: ``-d (v_i - v_j)``, which also damps rigid rotation of a pair).
        law: None (Hooke's law, ``f = k (l - l0)``), a strain-stiffening law
            (:class:`~torchdeform.sim.laws.Exponential`, :class:`~torchdeform.sim.laws.Polynomial`)
            or its name. ``stiffness`` is then the small-strain stiffness, and the law's
            parameters are spring parameters like it (stored in :attr:`law_params`).
        mass: node mass (kg): a number, ``(D, H, W)`` or ``(B, 1, D, H, W)``; or
        density: kg/m^3, lumped from cell volumes (:func:`lumped_mass`). Exactly one of the two.
        gravity: acceleration ``(gd, gh, gw)`` m/s^2, or None.
        fixed: bool ``(D, H, W)`` of nodes that never move, a face name (``"bottom"`` = ``"d-"``,
            ``"top"`` = ``"d+"``, ``"h-"`` ... ``"w+"``, as ``[boundary] fixed`` of a scene) or a list of
            them, or None.
        drags: list of :class:`~torchdeform.sim.forces.Drag` (prescribed motion), or None.
        home: stiffness (N/m) of home springs to every node's rest position (Punak), or None.
        anchors: ``(stiffness, every)`` anchor springs on every k-th node (Radetzky), or None.
        decay: global drag rate c (1/s): ``v <- v exp(-c dt)`` after every step, or None.
        loads: list of :class:`~torchdeform.sim.forces.PointForce`, ``SurfaceForce`` or
            ``FieldForce``, or None.
        interactions: objects with ``project(model, x, v, t, dt, *, readings) -> (x, v)`` (applied at the end
            of every step) and ``force(model, x, v, t)`` (added to the forces, or None): tool
            contact, grasp, strain limiting (:mod:`torchdeform.interact`); or None. One whose
            ``eager_only`` is true makes the compiled step run eagerly.
        spring_mask: optional bool ``(S, D, H, W)`` of springs that exist (e.g. after a cut).
        dtype: of every tensor of the model.
        device: of every tensor of the model.

    Examples:
        >>> import torchdeform as td
        >>> grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
        >>> model = td.Model(grid, stiffness=50.0, damping=0.1, density=1000.0,
        ...                  gravity=(-9.81, 0, 0), fixed=grid.face("bottom"))
        >>> round(float(model.mass.sum()), 6)                  # 1000 kg/m^3 * (3 cm)^3
        0.027
        >>> state = model.rest_state(batch=2)
        >>> a = model.acceleration(state.x, state.v)           # at rest: gravity only
        >>> a.shape, round(float(a[0, 0, 2, 2, 2]), 4), bool((a[:, :, 0] == 0).all())   # free, fixed base
        (torch.Size([2, 3, 4, 4, 4]), -9.81, True)
    """

    def __init__(
        self,
        grid: Grid,
        stiffness,
        *,
        damping=None,
        damping_mode="projected",
        law=None,
        normalize=False,
        mass=None,
        density=None,
        gravity=None,
        fixed=None,
        drags=None,
        home=None,
        anchors=None,
        decay=None,
        loads=None,
        interactions=None,
        spring_mask=None,
        dtype=torch.float32,
        device=None,
    ):
        self.grid, self.dtype, self.device = grid, dtype, torch.device(device or "cpu")
        dev = self.device
        if damping_mode not in ("projected", "unprojected"):
            raise ConfigError("damping_mode", '"projected" or "unprojected"', got=damping_mode)
        self.projected = damping_mode == "projected"
        self.X = grid.rest_positions(dtype=dtype, device=dev)
        self.rest_length = grid.rest_lengths(dtype=dtype, device=dev).view(1, grid.S, 1, 1, 1)

        # springs (masked only when some springs are missing); a material gives them from its cells
        #: the cell term of an Elastic material ``(kappa_cells, h, shear_cells)``: the volume modulus and
        #: the cells' share of the shear modulus per cell ``(D-1, H-1, W-1)`` (Pa), the cell side (m); or None
        #: (``kappa_cells`` is 0 at missing and dead cells; ``(B, D-1, H-1, W-1)`` after per-entry cuts)
        self.volume: tuple[torch.Tensor, float, torch.Tensor] | None
        #: an Elastic body's shear modulus per cell (Pa), ``(D-1, H-1, W-1)`` (or ``(B, ...)``), 0 at
        #: missing and dead cells: what a topology change re-assembles the springs from; else None
        self.mu_cells: torch.Tensor | None
        stiffness, self.volume, self.mu_cells = _material_springs(stiffness, normalize, grid, dtype, dev)
        k = spring_param(stiffness, grid, "stiffness", dtype, dev)
        c = None if damping is None else spring_param(damping, grid, "damping", dtype, dev)
        if normalize:
            k = k / self.rest_length
            c = None if c is None else c / self.rest_length
        mask = grid.spring_mask(device=dev)
        if spring_mask is not None:
            spring_mask = torch.as_tensor(spring_mask, dtype=torch.bool, device=dev)
            if tuple(spring_mask.shape) != (grid.S,) + grid.shape:
                raise ConfigError(
                    "spring_mask", f"bool (S, D, H, W) = {(grid.S,) + grid.shape}", got=tuple(spring_mask.shape)
                )
            mask = mask & spring_mask
        if grid.node_mask is not None or spring_mask is not None:
            m = mask.unsqueeze(0).to(dtype)
            k = k * m
            c = None if c is None else c * m
        if c is not None and not bool((c != 0).any()):
            c = None
        self.stiffness, self.damping = k, c
        #: the spring law (:mod:`torchdeform.sim.laws`), or None for Hooke's law
        self.law = as_law(law)
        #: the law's parameters as spring fields ``(Bp, S, 1|D, 1|H, 1|W)``, in ``law.params`` order
        self.law_params = (
            ()
            if self.law is None
            else tuple(
                spring_param(value, grid, f"law.{name}", dtype, dev)
                for name, value in zip(self.law.params, self.law.values)
            )
        )

        # masses
        if (mass is None) == (density is None):
            raise ConfigError("mass", "exactly one of mass or density", got={"mass": mass, "density": density})
        if density is not None:
            rho = float(density)
            if not math.isfinite(rho) or rho <= 0:
                raise ConfigError("density", "a positive number (kg/m^3)", got=density)
            mass = lumped_mass(grid, rho, dtype=dtype, device=dev)
        self.mass = node_param(mass, grid, "mass", dtype, dev)

        # constrained nodes: fixed, dragged, and nodes outside the node mask
        self.drags = list(drags or [])
        constrained = ~grid.nodes()
        if fixed is not None:
            fixed = _fixed_mask(fixed, grid)  # a mask on any device, or face names as scenes give them
            if tuple(fixed.shape) != grid.shape:
                raise ConfigError("fixed", f"a bool mask of shape {grid.shape}", got=tuple(fixed.shape))
            constrained = constrained | fixed
        for d in self.drags:
            constrained = constrained | torch.as_tensor(d.nodes, dtype=torch.bool).cpu()
        self.drag_masks = [torch.as_tensor(d.nodes, dtype=torch.bool, device=dev)[None, None] for d in self.drags]
        self.constrained = constrained.to(dev)
        #: bool ``(D, H, W)`` of nodes removed from the body by a topology change (cautery), or None
        self.removed = None
        #: bool ``(D, H, W)`` of nodes at the ends of springs cut so far (for pre-tension), or None
        self.cut_nodes = None
        #: the spring fields stored once with a compiled step (``compiled_step(..., editable=...)``)
        self.shared: tuple[str, ...] = ()
        free = (~constrained).to(dtype=dtype, device=dev)[None, None]
        bad = (self.mass <= 0) & (free > 0)
        if bool(bad.any()):
            idx = tuple(int(i) for i in bad.expand(-1, -1, *grid.shape).nonzero()[0][2:])
            raise ConfigError(
                "mass",
                f"a positive mass at every free node; node {idx} has "
                f"{float(self.mass.expand(-1, -1, *grid.shape)[(0, 0) + idx]):g} kg",
                show_got=False,
            )
        self.free = None if not bool(constrained.any()) else free
        safe_mass = torch.where(self.mass > 0, self.mass, torch.ones_like(self.mass))
        self.inv_mass = 1.0 / safe_mass if self.free is None else free / safe_mass

        # other terms
        self.gravity = (
            None
            if gravity is None
            else torch.tensor(as_vec3(gravity, "gravity"), dtype=dtype, device=dev).view(1, 3, 1, 1, 1)
        )
        k_home = None
        if home is not None:
            k_home = node_param(home, grid, "home", dtype, dev)
        if anchors is not None:
            ka, every = anchors
            ka = node_param(ka, grid, "anchors.stiffness", dtype, dev)
            ka = ka * grid.every_kth(every).to(dtype=dtype, device=dev)[None, None]
            k_home = ka if k_home is None else k_home + ka
        if k_home is not None and bool((k_home < 0).any()):
            raise ConfigError("home", "stiffness >= 0", got=float(k_home.min()))
        self.k_home = k_home
        if decay is not None and (not math.isfinite(float(decay)) or float(decay) < 0):
            raise ConfigError("decay", "a rate >= 0 (1/s)", got=decay)
        self.decay = None if not decay else float(decay)
        self.loads = [(ld, ld.dense(grid, dtype, dev)) for ld in (loads or [])]
        for c in interactions or []:
            if not (callable(getattr(c, "project", None)) and callable(getattr(c, "force", None))):
                raise ConfigError(
                    "interactions",
                    "interactions with project() and force() (torchdeform.interact.ProjectionContact, PenaltyContact)",
                    got=type(c).__name__,
                )
        self.interactions = list(interactions or [])

    # --------------------------------------------------------------- states
    def rest_state(self, *, batch: int = 1) -> State:
        """The body at rest: ``x = X``, ``v = 0``, each ``(batch, 3, D, H, W)``."""
        x = self.X.expand(batch, -1, -1, -1, -1).clone()
        return State(x, torch.zeros_like(x), t=0.0)

    def _vector(self, value, like: torch.Tensor) -> torch.Tensor:
        """A 3-vector as ``(1, 3, 1, ...)`` broadcasting against node fields like ``like``."""
        return torch.as_tensor(value, dtype=self.dtype, device=self.device).view(1, 3, *[1] * (like.dim() - 2))

    def start(self, state):
        """The state a run starts from: fixed nodes at rest, dragged nodes on their path at ``state.t``.

        Fixed nodes never move: a start velocity given to them is dropped (every integrator then
        agrees). :func:`~torchdeform.sim.engine.simulate` and the other runners call this first.

        Examples:
            >>> import torch
            >>> import torchdeform as td
            >>> grid = td.Grid((3, 3, 3), spacing=0.01)
            >>> model = td.Model(grid, stiffness=10.0, mass=1e-3, fixed=grid.face("bottom"))
            >>> s = model.rest_state()
            >>> moving = td.State(s.x, torch.full_like(s.v, 0.1))
            >>> v = model.start(moving).v
            >>> float(v[0, :, 0].abs().max()), round(float(v[0, :, 1:].min()), 6)    # fixed base at rest
            (0.0, 0.1)
        """
        x = getattr(state, "x", None)
        if torch.is_tensor(x) and (x.dim() == 4 or (x.dim() == 5 and tuple(x.shape[1:]) != (3, *self.grid.shape))):
            raise ConfigError(
                "state",
                f"positions and velocities of shape (B, 3, D, H, W) = (B, 3, {', '.join(map(str, self.grid.shape))})"
                + (": add the batch dimension, State(x[None], v[None])" if x.dim() == 4 else ""),
                got=tuple(x.shape),
            )
        if self.free is None:
            return state
        v = state.v * self.free
        x, v = self.constrain(state.x, v, state.t) if self.drags else (state.x, v)
        return State(x, v, t=state.t, readings=getattr(state, "readings", None))

    def constrain(self, x: torch.Tensor, v: torch.Tensor, t):
        """Put dragged nodes on their path at time ``t`` (positions and velocities)."""
        for d, m in zip(self.drags, self.drag_masks):
            off, vel = self._vector(d.offset(t), x), self._vector(d.velocity(t), x)
            x = torch.where(m, self.X + off, x)
            v = torch.where(m, vel.expand_as(v), v)
        return x, v

    def keep(self, field: torch.Tensor) -> torch.Tensor:
        """A field that many operations will read: identity here.

        The packed model of the compiled step stores it in memory instead of letting each read
        recompute it.
        """
        return field

    # --------------------------------------------------------------- forces
    def external(self, t):
        """Sum of point and surface loads at time ``t``, ``(1, 3, D, H, W)``, or None."""
        total = None
        for load, dense in self.loads:
            f = load.factor(t)
            if torch.is_tensor(f) or f:
                total = dense * f if total is None else total + dense * f
        return total

    def forces(self, x, v, *, t: float = 0.0, loads: Loads = None, impl: str = "fast") -> torch.Tensor:
        """Total force on every node (springs, home/anchor springs, gravity, loads), ``(B, 3, D, H, W)``.

        Args:
            x: positions ``(B, 3, D, H, W)``.
            v: velocities ``(B, 3, D, H, W)``.
            t: time (s) for time-dependent loads.
            loads: extra force ``(B|1, 3, D, H, W)`` or a callable ``t -> force``, or None.
            impl: ``"fast"`` (shifted slices) or ``"conv"`` (conv3d reference).
        """
        F = self.spring_forces(x, v, impl=impl)
        if self.volume is not None:
            F = F + self.volume_forces(x)
        if self.k_home is not None:
            F = F + home_force(x, self.X, self.k_home)
        if self.gravity is not None:
            F = F + self.mass * self.gravity
        ext = self.external(t)
        if ext is not None:
            F = F + ext
        if loads is not None:
            F = F + (loads(t) if callable(loads) else loads)
        for contact in self.interactions:
            f = contact.force(self, x, v, t)
            if f is not None:
                F = F + f
        return F

    def spring_forces(self, x, v, *, impl: str = "fast") -> torch.Tensor:
        """Forces of the grid springs alone, ``(B, 3, D, H, W)``; ``impl`` as in :meth:`forces`."""
        fn = spring_forces if impl == "fast" else spring_forces_conv
        return fn(
            x,
            v,
            self.grid,
            self.stiffness,
            self.rest_length,
            c=self.damping,
            projected=self.projected,
            law=self.law,
            lp=self.law_params,
        )

    def volume_forces(self, x: torch.Tensor) -> torch.Tensor:
        """Forces of the volume term of an :class:`~torchdeform.sim.material.Elastic` material (N), ``(B, 3, D, H, W)``."""
        assert self.volume is not None
        return volume_forces(x, *self.volume)

    def volume_rows(self) -> torch.Tensor | None:
        """Gershgorin row sums of the volume term at rest per node (N/m), ``(1|B, 1, D, H, W)``, or None without one.

        (:func:`~torchdeform.sim.material.volume_row_sums`.)
        """
        return None if self.volume is None else self._volume_rows()

    def _volume_rows(self, *, diagonal: bool = False) -> torch.Tensor:
        assert self.volume is not None
        kappa, h, shear = self.volume
        return volume_row_sums(kappa, h, self.grid.shape, shear, diagonal=diagonal)

    def volume_diagonal(self) -> torch.Tensor | None:
        """The diagonal of the cell term's stiffness at rest per node (N/m), ``(1|B, 1, D, H, W)``, or None."""
        return None if self.volume is None else self._volume_rows(diagonal=True)

    def spring_sums(self, p: torch.Tensor) -> torch.Tensor:
        """``sum_j p_ij`` over the springs at each node, ``(Bp, 1, D, H, W)``.

        ``p`` is a spring parameter such as :attr:`stiffness` (Gershgorin bounds, Jacobi
        preconditioners).
        """
        return node_sums(self.grid, p)

    def stiffness_row_sums(self) -> torch.Tensor:
        """Gershgorin row sums of the stiffness at rest per node (N/m), ``(Bp, 1, D, H, W)``.

        ``2 sum_j k_ij`` over the springs, plus the volume term's rows and the home springs:
        with the masses, a bound on the top eigenvalue; alone, a Jacobi preconditioner.
        """
        rows = 2 * self.spring_sums(self.stiffness)
        volume = self.volume_rows()
        if volume is not None:
            rows = rows + volume
        if self.k_home is not None:
            rows = rows + self.k_home
        return rows

    def inner(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Inner product of two node fields per batch entry, ``(B, 1, 1, ...)`` broadcasting against ``a``.

        Conjugate gradients read their inner products here: a domain-decomposed model
        (:class:`~torchdeform.distributed.domain.SlabModel`) sums over the nodes it owns on every rank.
        (Summed over the axes as they are: a flattened sum would index ``i % P`` under
        ``torch.compile`` and run scalar.)
        """
        return (a * b).sum(tuple(range(1, a.dim())), keepdim=True)

    def acceleration(self, x, v, *, t: float = 0.0, loads: Loads = None) -> torch.Tensor:
        """``M^-1 F``, zero at constrained nodes, ``(B, 3, D, H, W)``."""
        return self.inv_mass * self.forces(x, v, t=t, loads=loads)

    def linearise(self, x, *, clamp=True) -> Linearisation | VolumeLinearisation:
        """Springs (and the volume term) linearised at ``x`` for stiffness products (implicit Euler, bounds)."""
        lin = Linearisation(
            x, self.grid, self.stiffness, self.rest_length, clamp=clamp, law=self.law, lp=self.law_params
        )
        return lin if self.volume is None else VolumeLinearisation(lin, x, *self.volume)

    # --------------------------------------------------------------- energy
    def energy(self, state: State) -> dict:
        """Energies per batch entry, each ``(B,)``.

        ``kinetic``, ``elastic`` (springs, the volume term and home springs), ``gravity`` (``-m g . (x - X)``),
        ``total``. External loads are not included.
        """
        x, v = state.x, state.v
        ke = 0.5 * (self.mass * v * v).flatten(1).sum(1)
        el = spring_energy(x, self.grid, self.stiffness, self.rest_length, law=self.law, lp=self.law_params)
        if self.volume is not None:
            el = el + volume_energy(x, *self.volume)
        if self.k_home is not None:
            el = el + 0.5 * (self.k_home * (x - self.X) ** 2).flatten(1).sum(1)
        out = {"kinetic": ke, "elastic": el}
        total = ke + el
        if self.gravity is not None:
            gp = -(self.mass * self.gravity * (x - self.X)).flatten(1).sum(1)
            out["gravity"] = gp
            total = total + gp
        out["total"] = total
        return out


def _material_springs(stiffness, normalize, grid: Grid, dtype, device):
    """``(stiffness, volume, mu_cells)``: the springs, volume term and cells of :class:`Model`'s ``stiffness``.

    A stiffness gives itself and no volume term or cells; an
    :class:`~torchdeform.sim.material.Elastic` gives springs ``(S, D, H, W)`` assembled from its
    cells, its cell term ``(kappa_cells, h, shear_cells)`` and the shear modulus per cell
    ``(D-1, H-1, W-1)`` (Pa, 0 where a cell is missing).
    """
    if not isinstance(stiffness, Elastic):
        return stiffness, None, None
    material = stiffness
    if normalize:
        raise ConfigError("normalize", "False with an Elastic material (its springs are in N/m)", got=normalize)
    h = material.check_grid(grid)
    cells = cell_mask(grid, device=device).to(dtype)
    mu, _ = material.lame()
    mu_cells = cell_field(mu, grid, dtype=dtype, device=device) * cells
    k = spring_stiffness(grid, mu_cells, h)
    kappa = cell_field(material.volume_modulus(), grid, dtype=dtype, device=device) * cells
    return k, (kappa, h, CELL_SHARE * mu_cells), mu_cells


__all__ = ["Model", "State", "spring_param", "node_param", "lumped_mass"]
