"""The packed layout of the fast path: node fields padded by one halo layer and flattened.

A node field ``(B, C, D, H, W)`` becomes ``(B, C, P)`` with ``P >= (D+2)(H+2)(W+2)``: the grid
is padded with a zero halo, flattened, and zero-padded at the end so that the core range below
is a whole number of blocks of :data:`BLOCK` nodes. A neighbour at stencil offset ``d`` is then a
fixed linear offset ``o = d_D (H+2)(W+2) + d_H (W+2) + d_W``, so every spring term is one
contiguous slice ``t[G + o : P - G + o]`` over the "core" range ``[G, P - G)`` (``G`` = the
largest offset). The core covers every real node; the halo nodes it also covers have no mass, no
free degree of freedom and no springs, so they never move.

In this layout each node gathers the forces of all its ``2 S`` springs (every spring is
evaluated from both ends) instead of scattering into shifted slices. That costs twice the
arithmetic but has no read-modify-write, so ``torch.compile`` fuses forces and update into one
vectorised loop over the nodes: the fast path (:mod:`torchdeform.sim.compiled`). The stiffness
products of implicit solves (:class:`PackedLinearisation`) are written as one sum over the
``2 S`` directions instead: ``torch.compile`` makes that a loop over blocks of :data:`BLOCK`
nodes with the directions as its inner loop, reading per-spring fields stored block by block.

:class:`PackedModel` is a :class:`~torchdeform.sim.model.Model` whose tensors are in this layout,
so every integrator runs on it unchanged; only the spring terms differ, and they use the same
spring law (:func:`~torchdeform.sim.springs.spring_law`).

Example:
    >>> import torchdeform as td
    >>> from torchdeform.sim.packed import PackedModel
    >>> model = td.Model(td.Grid((4, 5, 6), spacing=0.01, topology=26), stiffness=50.0, damping=0.1, mass=1e-3)
    >>> pm = PackedModel(model)
    >>> s = pm.pack_state(model.rest_state())     # x, v: (1, 3, P), P >= 6 * 7 * 8
    >>> s = td.SymplecticEuler().step(pm, s, 1e-4)
    >>> pm.unpack_state(s).x.shape
    torch.Size([1, 3, 4, 5, 6])
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import torch
import torch.nn.functional as F

from . import material, native, native_volume
from .model import Model, State
from .springs import combine_coefficients, gate_damping, spring_law

__all__ = ["BLOCK", "PackedModel", "PackedLinearisation", "PackedVolumeLinearisation", "TraceContext"]

#: Nodes per block of the linearisation's field layout (one AVX2 vector of float32): a block's
#: fields for all directions lie together, so a CG product reads them as one stream.
BLOCK = 8


class TraceContext:
    """What a compiled step tells the packed kernels while ``torch.compile`` traces them.

    Under ``torch.compile`` a field computed in the same graph and read at every spring's far end
    (an RK4 stage, a CG direction) must be stored in memory first, or inductor inlines its whole
    computation into every read (and the next stage's into that: compile time explodes). Fields
    that are graph inputs, or inputs of a compiled loop body, are in memory already. The compiled
    step (:mod:`torchdeform.sim.compiled`) owns one context per wrapper, hands the packed model a
    view bound to it (:meth:`PackedModel.traced`) and sets what holds in each part of its graph;
    the eager packed model carries an inert context (``store=None``), so eager steps never store.

    Args:
        store: a function ``t -> t`` that makes inductor keep ``t`` in memory
            (:func:`torchdeform._compile.realize`), or None (eager: nothing is stored).

    Attributes:
        graph_inputs: tensors that are inputs of the graph being traced (need no barrier).
        store_sums: store the node sums of :meth:`PackedModel.gather` (an implicit step's
            right-hand side is read by several reductions; an explicit update reads it once).
        inputs_stored: inside a compiled loop body every field is a body input, in memory.

    Examples:
        >>> import torch
        >>> ctx = TraceContext()                  # inert: nothing is stored
        >>> t = torch.ones(3)
        >>> ctx.operand(t) is t, ctx.keep(t) is t
        (True, True)
    """

    def __init__(self, *, store=None):
        self.store = store
        self.graph_inputs: tuple = ()
        self.store_sums = False
        self.inputs_stored = False

    def set(self, *, graph_inputs: tuple = (), store_sums: bool = False, inputs_stored: bool = False) -> None:
        """Declare what holds for the part of the graph traced next."""
        self.graph_inputs, self.store_sums, self.inputs_stored = tuple(graph_inputs), store_sums, inputs_stored

    def operand(self, f: torch.Tensor) -> torch.Tensor:
        """``f`` about to be read at every spring's far end: stored first unless it is in memory."""
        if self.store is None or self.inputs_stored or any(f is g for g in self.graph_inputs):
            return f
        return self.store(f)

    def keep(self, t: torch.Tensor, *, wanted: bool = True) -> torch.Tensor:
        """``t`` stored in memory when ``wanted`` and tracing; otherwise ``t`` itself."""
        return self.store(t) if self.store is not None and wanted else t


class PackedModel(Model):
    """A :class:`~torchdeform.sim.model.Model` in the packed layout (see the module docstring).

    Node fields are ``(B|1, C, P)``, spring parameters ``(Bp, S, 1)`` (one value per direction)
    or ``(Bp, S, P)`` (one per spring, stored at its first endpoint, zero in the halo). States
    are packed with :meth:`pack_state` and unpacked with :meth:`unpack_state`.

    With ``share`` (an editable model, for topology changes during a run) the stiffness (and the
    spring fields named in ``share``) are stored per spring, the node fields per node, and the
    source model's own fields become grid-layout views of these packed tensors (:meth:`share`):
    an in-place edit through either layout (a cut zeroing stiffness slots, cautery zeroing
    masses) is seen by the other and by a compiled step, which reads the same tensors and never
    recompiles for it.

    Args:
        model: the model to lay out; it is not changed unless ``share``.
        share: False, True (the stiffness per spring: cuts, tears, cautery) or the names of the
            spring fields to store per spring (``"stiffness"``, ``"rest_length"`` for coagulation
            and gaping cuts, ``"damping"`` for coagulation's viscosity rise).
    """

    def __init__(self, model: Model, *, share: bool | tuple[str, ...] = False):
        if isinstance(model, PackedModel):
            raise TypeError("PackedModel(model): the model is already packed")
        self.__dict__.update(model.__dict__)
        self.source = model
        grid = model.grid
        D, H, W = grid.shape
        plane, row = (H + 2) * (W + 2), W + 2
        #: nodes of one padded ``(H + 2)(W + 2)`` plane: the linear offset of one step along D
        self.plane = plane
        self.G = plane + row + 1
        self._P_grid = (D + 2) * plane
        self.P = self._P_grid + (2 * self.G - self._P_grid) % BLOCK
        self.offsets = [dd * plane + dh * row + dw for dd, dh, dw in grid.directions]
        #: the offsets as an int64 tensor on the CPU (the C kernel's argument, :mod:`.native`)
        self.offset_table = torch.tensor(self.offsets, dtype=torch.int64)
        #: (dd + 1, dh + 1, dw + 1) of all ``2 S`` directions (the ``S`` half-directions, then their
        #: opposites), as three ``(2 S,)`` index tensors; see :meth:`ends`
        both = list(grid.directions) + [tuple(-a for a in d) for d in grid.directions]
        self._dir_index = tuple(torch.tensor([d[a] + 1 for d in both], device=model.device) for a in range(3))

        self.inside = self.pack(grid.nodes().to(self.dtype)[None, None].to(self.device))[0, 0]  # (P,)
        self.X = self.pack(model.X)
        self.mass = self._node(model.mass)
        self.inv_mass = self._node(model.inv_mass)
        self.free = self._node(model.inv_mass.new_ones(1, 1, 1, 1, 1) if model.free is None else model.free)
        self.constrained = self.free[0, 0] == 0  # (P,), halo too
        self.drag_masks = [self.pack(m.to(self.dtype)) > 0 for m in model.drag_masks]
        self.k_home = None if model.k_home is None else self._node(model.k_home)
        self.loads = [(ld, self.pack(dense)) for ld, dense in model.loads]
        if model.gravity is not None:
            self.gravity = model.gravity.view(1, 3, 1)
        self.stiffness = self._spring(model.stiffness)
        self.rest_length = self._spring(model.rest_length)
        self.damping = None if model.damping is None else self._spring(model.damping)
        self.law_params = tuple(self._spring(p) for p in model.law_params)
        #: ``(2 S, N, BLOCK)``: 1 where the spring along each direction from each core node exists
        self.spring_exists = self.exists()[0]
        #: the volume term: ``kappa`` (Pa) of each cell at its lowest corner ``(Bk, 1, P)`` (0 where no
        #: cell), the cell side ``h`` (m), and the C kernel's name once chosen (:meth:`traced`)
        self.volume_kappa = self.volume_shear = self.volume_h = self.volume_kernel = None
        #: an Elastic body's springs as the C kernel may make them from its cells (:class:`CellSprings`), or None
        self.cell_springs = None if share else self._cell_springs(model)
        if self.volume is not None:
            kappa, self.volume_h, shear = self.volume
            self.volume_kappa, self.volume_shear = (self._pack_cells(t) for t in (kappa, shear))
        #: the compile-time context (:class:`TraceContext`): inert here; a compiled step traces a
        #: view of this model bound to its own context (:meth:`traced`)
        self.trace = TraceContext()
        if share:
            self.share(model, fields=("stiffness",) if share is True else tuple(share))

    #: the spring fields :meth:`share` may store per spring, and the node fields it always shares
    SHARED_SPRING_FIELDS = ("stiffness", "rest_length", "damping")
    SHARED_NODE_FIELDS = ("mass", "inv_mass", "free", "k_home")

    def share(self, model: Model, *, fields=("stiffness",)) -> None:
        """Make ``model``'s fields grid-layout views of this model's packed fields.

        The spring fields named in ``fields`` become per spring (``(Bp, S, P)`` here,
        ``(Bp, S, D, H, W)`` views in ``model``); the others keep their layout (one value per
        direction costs a step far less memory traffic than one per spring: at 64^3 with 26
        neighbours, three per-spring fields made the compiled step three times slower). A spring
        whose stiffness is zero has no damping either (:func:`~torchdeform.sim.springs.spring_law`),
        so a cut needs only the stiffness. Node fields become per node (``(Bp, 1, P)`` /
        ``(Bp, 1, D, H, W)``), ``model.free`` is made explicit (ones where free) and
        ``model.constrained`` becomes a view of :attr:`constrained`. Absent terms (no damping, no
        home springs) stay absent. ``model.shared`` records the shared spring fields, so that a
        topology change needing another one can say so instead of being silently missed.
        """
        unknown = set(fields) - set(self.SHARED_SPRING_FIELDS)
        if unknown or "stiffness" not in fields:
            raise ValueError(
                f"share: spring fields from {self.SHARED_SPRING_FIELDS}, stiffness included; got {tuple(fields)}"
            )
        S, shape = self.grid.S, self.grid.shape
        model.shared = tuple(f for f in self.SHARED_SPRING_FIELDS if f in fields)
        for name in model.shared:
            p = getattr(model, name)
            if p is not None:
                packed = self.pack(p.expand(p.shape[0], S, *shape))
                setattr(self, name, packed)
                setattr(model, name, self.unpack(packed))
        for name in self.SHARED_NODE_FIELDS:
            t = getattr(self, name)
            if t is not None:
                setattr(model, name, self.unpack(t))
        self.constrained = self.free[0, 0] == 0
        model.constrained = self.unpack(self.constrained.view(1, 1, -1))[0, 0]
        if model.volume is not None:  # the cells' moduli: a cut that kills cells writes them in place
            kappa, h, shear = model.volume
            assert self.volume_kappa is not None and self.volume_shear is not None

            def view(packed: torch.Tensor, own: torch.Tensor) -> torch.Tensor:
                cells = self.unpack(packed)[:, 0, :-1, :-1, :-1]  # (Bk, D-1, H-1, W-1), a view
                return cells[0] if own.dim() == 3 else cells

            model.volume = (view(self.volume_kappa, kappa), h, view(self.volume_shear, shear))

    def keep(self, field: torch.Tensor) -> torch.Tensor:
        """``field`` stored in memory under ``torch.compile`` (see :meth:`TraceContext.keep`)."""
        return self.trace.keep(field)

    def traced(
        self, ctx: TraceContext, *, threads: int | None = None, native_ok: bool = True, build: bool = True
    ) -> PackedModel:
        """A view of this model (same tensors) whose kernels follow the compile-time context ``ctx``.

        ``threads``: the thread count the code is compiled for (default torch's), which chooses
        :attr:`force_form` when it is None; ``native_ok``: the C kernel may be chosen then (an
        implicit step's graph is dominated by its CG loop and gains nothing from it); ``build``:
        build that kernel now (traced code must not), else on its first call. This model itself
        is not changed.
        """
        view = copy.copy(self)
        view.trace = ctx
        # chosen (and a C kernel built) here, outside the traced code (see force_form)
        wanted = self.force_form == "native" or (self.force_form is None and native_ok and ctx.store is not None)
        view.native_why = native.supports(self) if wanted else None
        if wanted and view.native_why is None:
            try:
                var = native.variant_of(self)
                view.native_kernel = native.kernel(var) if build else native.name_of(var)
                view.force_form = "native"
            except native.NativeBuildError as e:
                view.native_why = str(e)
        if view.force_form == "native" and view.native_kernel is None:
            raise native.NativeBuildError(f"force_form='native': {view.native_why}")
        if view.force_form == "native" and self.volume is not None and native_volume.supports(self) is None:
            view.volume_kernel = native_volume.kernel(self.dtype) if build else native.CTYPE_NAMES[self.dtype]
        if view.force_form is None:
            # the gather form only for several CPU threads: on a GPU (Triton) its unrolled kernel
            # took 181 s to compile cold at 16^3 against 13 s for the reduction form, whose step
            # was within 20 % of it there (H100, torch 2.11)
            threads = threads or torch.get_num_threads()
            parallel = threads > 1 and self.device.type == "cpu"
            view.force_form = "gather" if ctx.store is not None and parallel else "reduction"
        return view

    # ------------------------------------------------------------------ layout
    def pack(self, t: torch.Tensor) -> torch.Tensor:
        """``(B, C, D, H, W) -> (B, C, P)`` with a zero halo."""
        return F.pad(F.pad(t, (1, 1, 1, 1, 1, 1)).flatten(2), (0, self.P - self._P_grid))

    def unpack(self, t: torch.Tensor) -> torch.Tensor:
        """``(B, C, P) -> (B, C, D, H, W)`` (a view of the interior)."""
        D, H, W = self.grid.shape
        return t[..., : self._P_grid].view(*t.shape[:2], D + 2, H + 2, W + 2)[..., 1:-1, 1:-1, 1:-1]

    def pack_state(self, state: State) -> State:
        """A grid-layout state (``(B, 3, D, H, W)``) in the packed layout (``(B, 3, P)``)."""
        return State(self.pack(state.x), self.pack(state.v), t=state.t, readings=state.readings)

    def unpack_state(self, state: State) -> State:
        """A packed state back in the grid layout (contiguous ``(B, 3, D, H, W)``)."""
        return State(
            self.unpack(state.x).contiguous(), self.unpack(state.v).contiguous(), t=state.t, readings=state.readings
        )

    def rest_state(self, *, batch: int = 1) -> State:
        """The body at rest, packed: ``x = X``, ``v = 0``, each ``(batch, 3, P)``."""
        return self.pack_state(self.source.rest_state(batch=batch))

    def _node(self, t: torch.Tensor) -> torch.Tensor:
        return self.pack(t.expand(*t.shape[:2], *self.grid.shape))

    def _spring(self, p: torch.Tensor) -> torch.Tensor:
        if p.shape[-3:] == (1, 1, 1):
            return p.reshape(p.shape[0], p.shape[1], 1)
        return self.pack(p.expand(p.shape[0], p.shape[1], *self.grid.shape))

    def shift(self, t: torch.Tensor, o: int) -> torch.Tensor:
        """The core range of ``t`` (last axis ``P``) shifted by the linear offset ``o``."""
        return t[..., self.G + o : self.P - self.G + o]

    def ends(self, t: torch.Tensor) -> torch.Tensor:
        """The far end of the spring along each of the ``2 S`` directions from each core node.

        ``t`` ``(B, C, P)`` -> ``(B, C, 2 S, N, BLOCK)`` (core nodes in ``N`` blocks), one strided
        view indexed by direction (no per-direction copies: under ``torch.compile`` a sum over the
        directions is one loop over the nodes with the directions as its inner reduction).
        """
        _D, H, W = self.grid.shape
        plane, row = (H + 2) * (W + 2), W + 2
        # The corner neighbour (-1, -1, -1) of the first core node G = plane + row + 1 is node 0,
        # so the view starts where t starts.
        t = t.contiguous()
        cube = t.as_strided((*t.shape[:2], 3, 3, 3, self.P - 2 * self.G), (t.stride(0), t.stride(1), plane, row, 1, 1))
        return self.blocks(cube[:, :, self._dir_index[0], self._dir_index[1], self._dir_index[2]])

    def differences(self, t: torch.Tensor) -> torch.Tensor:
        """``t`` at the far end of each spring less ``t`` at its node: ``(B, C, P) -> (B, C, 2 S, N, BLOCK)``."""
        return self.ends(t) - self.blocks(t).unsqueeze(2)

    def exists(self) -> torch.Tensor:
        """``(1, 2 S, N, BLOCK)``: 1 where the spring along each direction from each core node exists.

        Both ends inside, the far one read like a neighbour's position (in cache while a step
        reads positions), not streamed from a stored per-spring mask.
        """
        return self.ends(self.inside.view(1, 1, -1))[:, 0] * self.blocks(self.inside).unsqueeze(0)

    def blocks(self, t: torch.Tensor) -> torch.Tensor:
        """A core-range field ``(..., P_core)`` as ``(..., N, BLOCK)``.

        A full field ``(..., P)`` is cut to its core range first.
        """
        if t.shape[-1] == self.P:
            t = self.shift(t, 0)
        return t.unflatten(-1, (-1, BLOCK))

    def directed(self, p: torch.Tensor) -> torch.Tensor:
        """Spring parameters ``(Bp, S, 1|P)`` along each of the ``2 S`` directions from each core node.

        The result is ``(Bp, 2 S, 1, 1)`` or ``(Bp, 2 S, N, BLOCK)`` (the spring along ``-d_s``
        from node ``i`` is stored at node ``i - o_s``).
        """
        if p.shape[-1] == 1:
            return torch.cat([p, p], 1).unsqueeze(-1)
        both = [self.param(p, s, sign) for sign in (1, -1) for s in range(len(self.offsets))]
        return self.blocks(torch.stack(both, 1))

    def param(self, p: torch.Tensor, s: int, sign: int) -> torch.Tensor:
        """Spring parameter of the spring from each core node along ``sign * d_s``.

        The result is ``(Bp, 1)`` or ``(Bp, P_core)``.
        """
        q = p[:, s]
        if q.shape[-1] == 1:
            return q
        return self.shift(q, 0 if sign > 0 else -self.offsets[s])

    def gather(self, fn, *fields: torch.Tensor) -> torch.Tensor:
        """Sum a spring quantity over the ``2 S`` springs of every node, channels kept apart.

        For each half-direction ``s`` and ``sign`` in ``(+1, -1)``, ``fn(s, sign, mask, *deltas)``
        gets the neighbour mask ``(P_core,)`` (1 where the neighbour exists) and, per field, the
        list of its channel differences ``field_c[i + sign d_s] - field_c[i]``, each
        ``(B, P_core)``; it returns a list of ``C`` terms ``(B|Bp, P_core)``. Keeping channels
        apart (no channel axis) is what lets inductor fuse the whole sum into one loop.

        Returns:
            ``(B, C, P)``, zero at halo nodes and outside the core range.
        """
        comps = [[f[:, a] for a in range(f.shape[1])] for f in map(self.trace.operand, fields)]
        centre = [[self.shift(c, 0) for c in comp] for comp in comps]
        total = None
        for s, o in enumerate(self.offsets):
            for sign in (1, -1):
                deltas = [
                    [self.shift(c, sign * o) - c0 for c, c0 in zip(comp, cen)] for comp, cen in zip(comps, centre)
                ]
                terms = fn(s, sign, self.shift(self.inside, sign * o), *deltas)
                total = terms if total is None else [a + b for a, b in zip(total, terms)]
        # In an implicit step the forces feed the right-hand side, which several reductions and the
        # CG loop's first vectors read: store them rather than let each reader recompute 2 S
        # springs. In an explicit step they feed one fused update, and storing would cost ~30%.
        own = self.shift(self.inside, 0)  # halo nodes get exactly zero
        assert total is not None  # at least 3 half-directions
        return self.spread(torch.stack([t * own for t in total], 1), store=self.trace.store_sums)

    def spread(self, sums: torch.Tensor, *, store: bool = False) -> torch.Tensor:
        """Sums over the core nodes ``(B, C, P_core)`` -> ``(B, C, P)``, zero outside the core range.

        Under ``torch.compile`` the result is stored when ``store``, otherwise computed inside
        each reader.
        """
        return self.trace.keep(F.pad(sums, (self.G, self.G)), wanted=store)

    # ------------------------------------------------------------------ springs
    #: how :meth:`spring_forces` sums the springs: ``"native"`` (each spring once, in a C kernel,
    #: :mod:`.native`), ``"reduction"`` (one sum over the ``2 S`` directions, as the CG products),
    #: ``"gather"`` (the ``2 S`` terms unrolled for inductor) or None: decided by :meth:`traced`
    #: for a compiled step (native where :func:`.native.supports` the model, else gather when
    #: compiled for several threads, else reduction); reduction for eager steps. Measured at 64^3,
    #: 26 neighbours, symplectic with dashpots, float32, 2 idle cores: gather 2.7 ms per step on 2
    #: threads and 5.1 on one, compiled in 37 s; reduction 5.0 and 5.2 ms (it does not scale),
    #: compiled in 13 s.
    force_form: str | None = None
    #: the C kernel's name (:func:`.native.kernel`) when :attr:`force_form` is ``"native"``
    native_kernel: str | None = None
    #: why a compiled step could not use the C kernel (None: it could, or it was not asked)
    native_why: str | None = None

    def spring_forces(self, x, v, *, impl: str = "fast") -> torch.Tensor:
        """Forces of the grid springs, ``(B, 3, P)`` (``impl`` is ignored: one layout, one path)."""
        form = self.force_form or "reduction"
        if form == "native":
            return native.spring_forces(self, x, v, name=self.native_kernel)
        if form == "reduction":
            return self._spring_forces_reduced(x, v)
        k, l0, c, projected = self.stiffness, self.rest_length, self.damping, self.projected

        def fn(s, sign, mask, dx, dv=None):
            sq = dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2]
            dxdv = None if dv is None else dx[0] * dv[0] + dx[1] * dv[1] + dx[2] * dv[2]
            alpha, beta = spring_law(
                sq,
                dxdv,
                self.param(k, s, sign),
                self.param(l0, s, sign),
                None if c is None else self.param(c, s, sign),
                projected,
                law=self.law,
                lp=tuple(self.param(p, s, sign) for p in self.law_params),
            )
            alpha = alpha * mask
            if beta is None:
                return [alpha * d for d in dx]
            beta = beta * mask
            assert dv is not None  # damping terms come with velocity differences
            return [alpha * d + beta * w for d, w in zip(dx, dv)]

        return self.gather(fn, x) if c is None else self.gather(fn, x, v)

    def _spring_forces_reduced(self, x, v) -> torch.Tensor:
        """:meth:`spring_forces` as one sum over the ``2 S`` directions per node (see :meth:`ends`)."""
        k, l0, c = self.directed(self.stiffness), self.directed(self.rest_length), self.damping
        x = self.trace.operand(x)
        dx = self.differences(x)  # (B, 3, 2S, N, L)
        sq = dx[:, 0] * dx[:, 0] + dx[:, 1] * dx[:, 1] + dx[:, 2] * dx[:, 2]  # (B, 2S, N, L)
        dv = dxdv = None
        if c is not None:
            c = self.directed(c)
            v = self.trace.operand(v)
            dv = self.differences(v)
            dxdv = dx[:, 0] * dv[:, 0] + dx[:, 1] * dv[:, 1] + dx[:, 2] * dv[:, 2]
        alpha, beta = spring_law(
            sq, dxdv, k, l0, c, self.projected, law=self.law, lp=tuple(self.directed(p) for p in self.law_params)
        )
        exists = self.exists()
        alpha = alpha * exists
        if beta is None:
            terms = [alpha * dx[:, a] for a in range(3)]
        else:
            beta = beta * exists
            assert dv is not None  # damping terms come with velocity differences
            terms = [alpha * dx[:, a] + beta * dv[:, a] for a in range(3)]
        # channels apart, each sum keeping its direction axis: one loop writes the (B, 3, N, L) buffer
        sums = torch.cat([t.sum(1, keepdim=True) for t in terms], 1)
        return self.spread(sums.flatten(-2), store=self.trace.store_sums)

    def spring_sums(self, p: torch.Tensor) -> torch.Tensor:
        """``sum_j p_ij`` per node, ``(Bp, 1, P)``."""
        return self.gather(lambda s, sign, mask: [self.param(p, s, sign) * mask])

    def _cell_springs(self, model: Model) -> CellSprings | None:
        """:class:`CellSprings` where ``model``'s stiffness is exactly that of its cells, else None.

        (Not for a law other than Hooke's, nor once the stiffness was changed after the model was
        built: a learned scale, a mask; an editable model keeps per-spring stiffness for its cuts.)
        """
        mu = getattr(model, "mu_cells", None)
        if mu is None or model.law is not None or model.stiffness.requires_grad:
            return None
        grid, h = model.grid, float(model.grid.spacing[0])
        k = material.spring_stiffness(grid, mu, h)  # as the model made it (springs from its cells)
        if k.dim() == 4:
            k = k.unsqueeze(0)
        if k.shape[0] != model.stiffness.shape[0] or not torch.equal(k.expand_as(model.stiffness), model.stiffness):
            return None
        _D, H, W = grid.shape
        plane, row = (H + 2) * (W + 2), W + 2
        counts, offsets = [], []
        for d in grid.directions:
            cells = material._cells_of(d)
            counts.append(len(cells))
            offsets += [(a - 1) * plane + (b - 1) * row + (e - 1) for a, b, e in cells]
        factors = material.spring_factors(grid, h)
        mu = mu.reshape(-1, 1, *mu.shape[-3:])
        packed = F.pad(self.pack(F.pad(mu, (0, 1, 0, 1, 0, 1))), (self.G, 0)).contiguous()
        return CellSprings(
            tuple(counts),
            torch.tensor(factors, dtype=self.dtype).view(1, -1, 1).to(model.stiffness.dtype),
            packed,
            torch.tensor(offsets, dtype=torch.int64),
        )

    # ------------------------------------------------------------------ the volume term
    def grid_view(self, t: torch.Tensor) -> torch.Tensor:
        """``(B, C, P) -> (B, C, D+2, H+2, W+2)``: the padded grid, halo included (a view)."""
        D, H, W = self.grid.shape
        return t[..., : self._P_grid].view(*t.shape[:2], D + 2, H + 2, W + 2)

    def from_grid_view(self, t: torch.Tensor) -> torch.Tensor:
        """The inverse of :meth:`grid_view`: ``(B, C, D+2, H+2, W+2) -> (B, C, P)``."""
        return F.pad(t.flatten(2), (0, self.P - self._P_grid))

    def _pack_cells(self, cells: torch.Tensor) -> torch.Tensor:
        """A per-cell field ``(cells)`` or ``(Bk, cells)`` at each cell's lowest corner, packed: ``(Bk, 1, P)``."""
        return self.pack(F.pad(cells.reshape(-1, 1, *cells.shape[-3:]), (0, 1, 0, 1, 0, 1)))

    def _padded_cells(self, packed: torch.Tensor) -> torch.Tensor:
        """A packed per-cell field as the cells of the padded grid ``(Bk, D+1, H+1, W+1)`` (0 in the halo)."""
        return self.grid_view(packed)[:, 0, :-1, :-1, :-1]

    def padded_volume(self) -> tuple:
        """The cell term on the padded grid's cells: ``(kappa, h, shear)`` (see :meth:`grid_view`)."""
        assert self.volume_kappa is not None and self.volume_shear is not None
        return self._padded_cells(self.volume_kappa), self.volume_h, self._padded_cells(self.volume_shear)

    def volume_forces(self, x: torch.Tensor, *, impl: str | None = None) -> torch.Tensor:
        """The volume term's forces (N) at packed positions ``x``, ``(B, 3, P)``.

        ``impl``: ``"native"`` (the C kernel, :mod:`.native_volume`), ``"torch"``
        (:func:`~torchdeform.sim.material.volume_forces` on :meth:`grid_view`), or None: the C
        kernel where :meth:`traced` chose it, else torch.
        """
        if impl == "native" or (impl is None and self.volume_kernel is not None):
            return native_volume.volume_forces(self, x, name=self.volume_kernel)
        return self.from_grid_view(material.volume_forces(self.grid_view(x), *self.padded_volume()))

    def volume_rows(self) -> torch.Tensor | None:
        """The volume term's Gershgorin row sums per node (N/m), ``(1, 1, P)``, or None."""
        rows = self.source.volume_rows()
        return None if rows is None else self.pack(rows)

    def volume_diagonal(self) -> torch.Tensor | None:
        """The cell term's stiffness diagonal per node (N/m), ``(1, 1, P)``, or None."""
        diag = self.source.volume_diagonal()
        return None if diag is None else self.pack(diag)

    def linearise(self, x, *, clamp=True) -> PackedLinearisation | PackedVolumeLinearisation:
        """Springs (and the volume term) linearised at packed positions ``x`` (:class:`PackedLinearisation`)."""
        lin = PackedLinearisation(self, x=x, clamp=clamp)
        return lin if self.volume is None else PackedVolumeLinearisation(self, lin, x)

    def energy(self, state: State) -> dict:
        """Energies of a packed state, as :meth:`~torchdeform.sim.model.Model.energy` (unpacked first)."""
        return self.source.energy(self.unpack_state(state))


class PackedLinearisation:
    """:class:`~torchdeform.sim.springs.Linearisation` in the packed layout.

    ``K u`` products for implicit solves without a matrix.

    The springs are linearised along each of the ``2 S`` directions from each core node (so every
    spring twice, once from each end): :attr:`fields` are the unit direction ``n``
    ``(B, 3, 2 S, N, BLOCK)`` and the coefficients ``a = max(f / l, 0)`` and ``b = df/dl - a`` (Hooke:
    ``a = k max(1 - l0 / l, 0)``, ``b = k - a``)
    ``(B, 2 S, N, BLOCK)``. A product is one sum over the directions per node (:meth:`apply`), which
    ``torch.compile`` turns into one loop over the nodes with the directions as its inner
    reduction. Under ``torch.compile`` these fields are not stored: their few readers recompute
    them from the positions inside their own loops.

    The operator of a CG solve is made once per solve by :meth:`scaled`, and stored.

    Args:
        pm: the packed model.
        x: positions ``(B, 3, P)``.
        clamp: clamp the compressive term.
        fields: fields from an earlier linearisation (then ``x`` is ignored).
        combined: the fields are those of :meth:`scaled`.
    """

    def __init__(
        self, pm: PackedModel, *, x: torch.Tensor | None = None, clamp: bool = True, fields=None, combined: bool = False
    ):
        self.pm, self.combined = pm, combined
        if fields is None:
            if x is None:
                raise ValueError("PackedLinearisation: positions x or fields are needed")
            dx = pm.differences(x)  # (B, 3, 2S, N, L)
            sq = dx[:, 0] * dx[:, 0] + dx[:, 1] * dx[:, 1] + dx[:, 2] * dx[:, 2]  # (B, 2S, N, L)
            k, l0 = pm.directed(pm.stiffness), pm.directed(pm.rest_length)
            lp = tuple(pm.directed(p) for p in pm.law_params)
            a, _ = spring_law(sq, None, k, l0, None, True, law=pm.law, lp=lp)
            if clamp:
                a = a.clamp_min(0)
            l = sq.clamp_min(torch.finfo(sq.dtype).tiny).sqrt()
            n = dx / l.unsqueeze(1)
            slope = k if pm.law is None else pm.law.slope(l, l0, k, *lp)
            fields = (n, a, slope - a)
        self.fields = tuple(fields)

    def scaled(self, *, alpha_scale=1.0, c=None, projected=True, c_scale=1.0) -> PackedLinearisation:
        """The operator ``u -> apply(u, alpha_scale, c, projected, c_scale)``, coefficients combined.

        A linearisation with combined coefficients, the CG loop's inner kernel: per spring
        ``alpha I + beta n n^T`` of ``h2 K + h C`` is stored as 4 fields ``m = sqrt(beta) n`` and
        ``alpha``, already multiplied by the spring-exists mask, so a product reads 4 fields per
        spring and computes ``alpha du + (m . du) m``, with no scaling or masking. ``beta >= 0``
        holds for non-negative stiffness and damping (``b = k - a = k min(l0 / l, 1)``).

        Each field is stored block by block, ``(B, N, 2 S, BLOCK)``: the product's inner loop over
        the directions then reads 4 contiguous streams instead of ``4 x 2 S`` planes at once
        (measured on the 40 x 10 x 10 beam, 2 cores: half the time per product).
        """
        pm, n = self.pm, self.fields[0]
        alpha, beta = self._coefficients(alpha_scale, c, projected, c_scale)
        w = beta.clamp_min(0).sqrt()
        fields = [n[:, a] * w for a in range(3)] + [alpha]
        # Read by every product: under torch.compile stored once (in this axis order), not
        # recomputed by each read.
        return PackedLinearisation(pm, fields=[pm.trace.keep(f.transpose(-3, -2)) for f in fields], combined=True)

    def _coefficients(self, alpha_scale, c, projected, c_scale):
        """Masked ``(alpha, beta)`` of ``h2 K + h C`` per direction and node, ``(B, 2S, N, L)``."""
        pm, (_, a, b) = self.pm, self.fields
        if c is not None:
            c = pm.directed(c)
            if pm.stiffness.shape[-1] != 1 and c.shape[-1] == 1:  # stiffness per spring: gate the damping
                c = gate_damping(c, a + b)
        alpha, beta = combine_coefficients(a, b, alpha_scale=alpha_scale, c=c, projected=projected, c_scale=c_scale)
        return alpha * pm.spring_exists, beta * pm.spring_exists

    def apply(self, u, *, alpha_scale=1.0, c=None, projected=True, c_scale=1.0) -> torch.Tensor:
        """``(h2 K + h C) u``, ``(B, 3, P)``.

        Arguments as :meth:`torchdeform.sim.springs.Linearisation.apply` (a combined operator
        takes none).
        """
        pm = self.pm
        u = pm.trace.operand(u)
        du = pm.differences(u)  # (B, 3, 2S, N, L)
        if self.combined:  # m (= sqrt(beta) n), alpha
            if not (alpha_scale == 1 and c is None):
                raise ValueError("a combined operator (PackedLinearisation.scaled) takes no scales")
            *m, alpha = (f.transpose(-3, -2) for f in self.fields)  # (B, 2S, N, L)
            proj = m[0] * du[:, 0] + m[1] * du[:, 1] + m[2] * du[:, 2]
        else:  # n, a, b
            alpha, beta = self._coefficients(alpha_scale, c, projected, c_scale)
            m = [self.fields[0][:, a] for a in range(3)]
            proj = beta * (m[0] * du[:, 0] + m[1] * du[:, 1] + m[2] * du[:, 2])
        # Channels are kept apart (three sums, one loop): a channel axis would be a second reduction.
        # Each sum keeps its direction axis (size 1), so inductor writes the three straight into
        # the concatenated (B, 3, N, L) buffer (a flattened sum would be copied there, one loop per
        # channel). Readers take it through the padding. Springs of halo nodes do not exist, so
        # the sums are zero there already.
        sums = torch.cat([(alpha * du[:, a] + proj * m[a]).sum(1, keepdim=True) for a in range(3)], 1)
        return -pm.spread(sums.flatten(-2))


class CellSprings(NamedTuple):
    """An Elastic body's springs as the C spring kernel makes them from the cells (:attr:`~.native.Variant.cells`).

    Attributes:
        counts: the number of cells holding a spring along each half-direction (1, 2 or 4).
        factors: ``w h / 2^z`` per half-direction ``(1, S, 1)``: a spring's stiffness is its factor
            times the sum of its cells' shear moduli (:func:`~torchdeform.sim.material.spring_stiffness`).
        mu: the shear modulus of each cell at its lowest corner, packed, after ``G`` leading zeros
            ``(Bm, 1, G + P)`` (a spring of a halo node reads before the layout's start).
        offsets: the cells' linear offsets from a spring's first node, direction by direction ``(sum(counts),)``.
    """

    counts: tuple
    factors: torch.Tensor
    mu: torch.Tensor
    offsets: torch.Tensor


class PackedVolumeLinearisation(material.VolumeLinearisation):
    """Springs and the volume term linearised at packed positions.

    :class:`PackedLinearisation` plus :func:`~torchdeform.sim.material.volume_product` on the padded
    grid (:meth:`PackedModel.grid_view`).

    Args:
        pm: the packed model.
        springs: the springs' :class:`PackedLinearisation` at ``x``.
        x: packed positions ``(B, 3, P)`` (or None with ``at``).
        alpha: the scale of the volume term's product.
        at: :func:`~torchdeform.sim.material.volume_state` on the padded grid, when already known.
    """

    def __init__(self, pm: PackedModel, springs, x, *, alpha: float = 1.0, at: tuple | None = None):
        self.pm, self.springs, self.grid, self.alpha = pm, springs, pm.grid, alpha
        self.kappa, self.h, self.shear = pm.padded_volume()
        self.at = material.volume_state(pm.grid_view(x), self.h) if at is None else at

    def scaled(self, *, alpha_scale=1.0, c=None, projected=True, c_scale=1.0) -> PackedVolumeLinearisation:
        """The operator ``u -> apply(u, alpha_scale, c, projected, c_scale)``, combined once."""
        springs = self.springs.scaled(alpha_scale=alpha_scale, c=c, projected=projected, c_scale=c_scale)
        return PackedVolumeLinearisation(self.pm, springs, None, alpha=self.alpha * alpha_scale, at=self.at)

    def apply(self, u, *, alpha_scale=1.0, c=None, projected=True, c_scale=1.0) -> torch.Tensor:
        """``(h2 K + h C) u``, ``(B, 3, P)`` (the volume term has no damping)."""
        y = self.springs.apply(u, alpha_scale=alpha_scale, c=c, projected=projected, c_scale=c_scale)
        vol = material.volume_product(self.at, self.pm.grid_view(u), self.kappa, self.h, self.shear)
        return y + (self.alpha * alpha_scale) * self.pm.from_grid_view(vol)
