"""Domain decomposition: one body split into slabs along D over ranks, a one-layer halo.

Rank ``r`` of ``N`` owns the rows ``[lo_r, hi_r)`` of the grid's first axis (:func:`slab_rows`:
as equal as the rows allow) and simulates them with one more row on each side that a neighbour
owns (the halo). Every spring touching an owned node then lies inside the slab, so the forces on
owned nodes are the single-process forces, computed by the same spring operator in the same
order. The halo rows are refreshed from the neighbours (:class:`Halo`, point-to-point
``torch.distributed`` messages) before every force evaluation and every stiffness product; an
integrator's node-wise update does the rest. Conjugate gradients (implicit Euler) read their inner
products from :meth:`SlabModel.inner`: the sum over owned nodes, all-reduced over ranks.

What a decomposed run supports: the explicit integrators (explicit and symplectic Euler, damped
Verlet, RK4) and implicit Euler; every model term that acts node by node or along grid springs
(fixed nodes, drags, gravity, loads, home and anchor springs, global drag, strain-stiffening laws,
node masks, springs removed by a cut, blades cutting during the run) and the volume term of an
:class:`~torchdeform.sim.material.Elastic` body. Tool interactions (contact, grasp, strain limits)
need the whole body and are refused.

An Elastic body's cells (8 corners each) need no more halo: a cell at an owned node has its
corners in the owned rows and the halo, so each slab keeps the cells between its rows
``[ext_lo, ext_hi)`` (``model.volume`` and ``model.mu_cells`` restricted to them) and computes the
volume term and its stiffness products on owned nodes as one process does. A blade cutting during
the run kills the same cells on every slab that holds them (every spring of such a cell lies in the
slab, and the halo carries the positions the blade is tested at), and each slab re-assembles its
springs from its cells: right for every spring at an owned node (its cells are all in the slab);
only springs joining two halo nodes may miss a cell beyond the halo, and those act on halo nodes
alone, which the next exchange overwrites. At the end, each rank gives the cells whose lower
corner row it owns.

Bytes per exchange: each inner slab boundary sends ``B x C x H x W`` values each way per field
(``C = 3``; positions and velocities go in one message when the springs are damped).

Example (one process: a single slab with no halo runs exactly as :func:`~torchdeform.sim.engine.simulate`;
launched with ``torchrun --nproc-per-node 2``, each rank runs half the body)::

    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.distributed.domain import decomposed_simulate, slab_rows
    >>> slab_rows(10, 3)
    [(0, 4), (4, 7), (7, 10)]
    >>> grid = td.Grid((6, 4, 4), spacing=0.01)
    >>> model = td.Model(grid, stiffness=50.0, damping=0.1, density=1000.0, gravity=(-9.81, 0, 0),
    ...                  fixed=grid.face("bottom"), dtype=torch.float64)
    >>> run = decomposed_simulate(model, model.rest_state(), 1e-4, steps=20, record_every=10)
    >>> final, _ = td.simulate(model, model.rest_state(), 1e-4, steps=20)
    >>> run.final.x.shape, bool((run.final.x == final.x).all()), run.record["x"].shape
    (torch.Size([1, 3, 6, 4, 4]), True, torch.Size([3, 1, 3, 6, 4, 4]))
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import KW_ONLY, dataclass, field

import torch

from ..errors import ConfigError
from ..sim.grid import Grid
from ..sim.integrators import SymplecticEuler
from ..sim.material import VolumeLinearisation
from ..sim.model import Model, State
from ..sim.springs import Linearisation
from ..sim.stability import DivergenceMonitor

__all__ = [
    "slab_rows",
    "Halo",
    "SlabModel",
    "decompose",
    "DecomposedRun",
    "decomposed_simulate",
    "SUPPORTED_INTEGRATORS",
]

#: the integrators a decomposed run takes (by ``name``)
SUPPORTED_INTEGRATORS = ("explicit", "symplectic", "verlet", "rk4", "implicit")


def slab_rows(depth: int, world: int) -> list:
    """The rows ``[(lo, hi), ...]`` of each of ``world`` ranks along an axis of ``depth`` nodes.

    As equal as the rows allow (the first ``depth % world`` slabs have one row more).

    Raises:
        ConfigError: more ranks than rows (each rank needs a slab of at least one row).
    """
    if world > depth:
        raise ConfigError(
            "ranks",
            f"at most {depth} ranks for a grid of {depth} rows along D (each rank "
            f"simulates a slab of at least one row)",
            got=world,
        )
    base, extra = divmod(depth, world)
    out, lo = [], 0
    for r in range(world):
        hi = lo + base + (r < extra)
        out.append((lo, hi))
        lo = hi
    return out


@dataclass
class Halo:
    """The halo exchange of one rank: its first and last owned rows to its neighbours, theirs back.

    Local rows are those of the slab with its halo: ``[ext_lo, ext_hi)`` of the global grid; row
    ``0`` is a halo row when there is a rank below, row ``-1`` when there is one above.

    Attributes:
        seconds: wall time spent in exchanges and reductions so far.
        exchanges: exchanges so far.
        bytes: bytes this rank sent so far.
    """

    rank: int
    world: int
    below: bool
    above: bool
    _: KW_ONLY
    group: object = None
    seconds: float = 0.0
    exchanges: int = 0
    bytes: int = 0

    def exchange(self, *fields: torch.Tensor) -> None:
        """Refresh the halo rows of ``fields`` (each ``(B, C, D_local, H, W)``) in place, in one message per side."""
        if not (self.below or self.above):
            return
        import torch.distributed as dist

        t0 = time.perf_counter()
        ops, recv = [], []
        for side, (own, halo, peer) in (("below", (1, 0, self.rank - 1)), ("above", (-2, -1, self.rank + 1))):
            if not getattr(self, side):
                continue
            send = torch.cat([f[:, :, own] for f in fields], 1)
            got = torch.empty_like(send)
            ops += [dist.P2POp(dist.isend, send, peer, self.group), dist.P2POp(dist.irecv, got, peer, self.group)]
            recv.append((halo, got))
            self.bytes += send.numel() * send.element_size()
        for req in dist.batch_isend_irecv(ops):
            req.wait()
        for halo, got in recv:
            c = 0
            for f in fields:
                f[:, :, halo] = got[:, c : c + f.shape[1]]
                c += f.shape[1]
        self.exchanges += 1
        self.seconds += time.perf_counter() - t0

    def all_reduce(self, t: torch.Tensor, *, op=None) -> torch.Tensor:
        """``t`` reduced over ranks (sum by default), in place; returns ``t``."""
        if self.world == 1:
            return t
        import torch.distributed as dist

        t0 = time.perf_counter()
        dist.all_reduce(t, op=op or dist.ReduceOp.SUM, group=self.group)
        self.seconds += time.perf_counter() - t0
        return t


class _SlabLinearisation(Linearisation):
    """A linearisation whose products first refresh the halo of their argument."""

    halo: Halo

    def scaled(self, *args, **kwargs):
        out = super().scaled(*args, **kwargs)
        out.halo = self.halo
        return out

    def apply(self, u, *args, **kwargs):
        self.halo.exchange(u)
        return super().apply(u, *args, **kwargs)


class SlabModel(Model):
    """One rank's part of a :class:`~torchdeform.sim.model.Model`: its slab of rows and a one-layer halo.

    Made by :func:`decompose`. Its fields are the global model's rows ``[ext_lo, ext_hi)`` (copies,
    so edits such as cuts stay local); forces and stiffness products refresh the halo first, and
    :meth:`inner` sums over owned nodes on all ranks.

    Attributes:
        rows: ``(lo, hi)`` global rows this rank owns.
        extent: ``(ext_lo, ext_hi)`` global rows of the slab with its halo.
        owned: the local rows it owns, a slice of the local first axis.
        halo: its :class:`Halo`.
        whole: the global model it was cut from.
    """

    rows: tuple
    extent: tuple
    owned: slice
    halo: Halo
    whole: Model

    def inner(self, a, b):
        """The inner product over the nodes this rank owns, summed over ranks, ``(B, 1, 1, 1, 1)``."""
        o = self.owned
        return self.halo.all_reduce(super().inner(a[:, :, o], b[:, :, o]))

    def forces(self, x, v, *, t: float = 0.0, loads=None, impl: str = "fast"):
        """The model's forces after refreshing the halo of ``x`` (and ``v``, damped springs) in place.

        Right on the owned nodes.
        """
        if self.damping is not None:
            self.halo.exchange(x, v)
        else:
            self.halo.exchange(x)
        return super().forces(x, v, t=t, loads=loads, impl=impl)

    def linearise(self, x, *, clamp=True):
        """Springs (and volume term) linearised at ``x`` (halo refreshed); products refresh their argument's halo."""
        self.halo.exchange(x)
        lin = _SlabLinearisation(
            x, self.grid, self.stiffness, self.rest_length, clamp=clamp, law=self.law, lp=self.law_params
        )
        lin.halo = self.halo
        # the volume term's product reads its argument after the springs' product refreshed its halo
        return lin if self.volume is None else VolumeLinearisation(lin, x, *self.volume)


def _rows(t, lo: int, hi: int, shape: tuple):
    """``t`` restricted to the rows ``[lo, hi)`` where it is a field over ``shape`` (a copy), else as it is."""
    if not torch.is_tensor(t) or t.dim() < 3 or tuple(t.shape[-3:]) != shape:
        return t
    return t[..., lo:hi, :, :].clone()


def _cell_rows(t: torch.Tensor, lo: int, hi: int) -> torch.Tensor:
    """The cells between node rows ``[lo, hi)``: rows ``[lo, hi - 1)`` of ``(..., D-1, H-1, W-1)`` (a copy)."""
    return t[..., lo : hi - 1, :, :].clone()


def decompose(model: Model, rank: int, world: int, *, group=None) -> SlabModel:
    """Rank ``rank``'s slab of ``model`` among ``world`` ranks (:func:`slab_rows` along D).

    Args:
        model: the global model (every rank builds the same one).
        rank: this rank.
        world: the number of ranks.
        group: the ``torch.distributed`` process group (default the global one).

    Raises:
        ConfigError: more ranks than rows, tool interactions, or a slab without any existing node.
    """
    if model.interactions:
        raise ConfigError(
            "interactions",
            "no tool interactions in a domain-decomposed run (contact and grasps "
            "need the whole body); run it on one rank",
            got=len(model.interactions),
        )
    grid = model.grid
    lo, hi = slab_rows(grid.shape[0], world)[rank]
    below, above = rank > 0, rank < world - 1
    e_lo, e_hi = lo - below, hi + above
    shape = grid.shape
    mask = None if grid.node_mask is None else grid.node_mask[e_lo:e_hi]
    if mask is not None and not bool(mask.any()):
        raise ConfigError(
            "ranks", f"fewer ranks: rank {rank}'s slab (rows {lo}..{hi - 1} along D) has no node of the body", got=world
        )
    origin = (grid.origin[0] + e_lo * grid.spacing[0],) + tuple(grid.origin[1:])
    local = copy.copy(model)
    local.__class__ = SlabModel
    local.grid = Grid(
        (e_hi - e_lo,) + shape[1:], spacing=grid.spacing, topology=grid.topology, node_mask=mask, origin=origin
    )
    for name in (
        "X",
        "stiffness",
        "damping",
        "rest_length",
        "mass",
        "inv_mass",
        "free",
        "k_home",
        "removed",
        "cut_nodes",
        "constrained",
    ):
        setattr(local, name, _rows(getattr(model, name), e_lo, e_hi, shape))
    # an Elastic body's cells: those of the slab with its halo (every cell at an owned node)
    if getattr(model, "mu_cells", None) is not None:
        local.mu_cells = _cell_rows(model.mu_cells, e_lo, e_hi)
    if getattr(model, "volume", None) is not None:
        kappa, h, shear = model.volume
        local.volume = (_cell_rows(kappa, e_lo, e_hi), h, _cell_rows(shear, e_lo, e_hi))
    local.law_params = tuple(_rows(p, e_lo, e_hi, shape) for p in model.law_params)
    local.drag_masks = [_rows(m, e_lo, e_hi, shape) for m in model.drag_masks]
    local.loads = [(ld, _rows(dense, e_lo, e_hi, shape)) for ld, dense in model.loads]
    local.shared = ()
    local.rows, local.extent = (lo, hi), (e_lo, e_hi)
    local.owned = slice(lo - e_lo, hi - e_lo)
    local.halo = Halo(rank, world, below, above, group=group)
    local.whole = model
    return local


@dataclass
class DecomposedRun:
    """What :func:`decomposed_simulate` returns on every rank.

    Attributes:
        final: the global final state on rank 0 (gathered), None on other ranks.
        record: on rank 0, ``{"t": (T,), "x": (T, B, 3, D, H, W), "v": ...}`` of the recorded
            steps (empty without ``record_every``); empty on other ranks.
        whole: on rank 0, the global model with the spring fields the run edited (cuts) gathered
            from the slabs (its energies then count only the springs left); None elsewhere.
        local: this rank's final slab state (with its halo rows).
        model: this rank's :class:`SlabModel`.
        wall_s: wall time of the steps (s).
        comm_s: of which in halo exchanges and reductions (s).
        steps: steps run.
    """

    final: State | None
    record: dict
    whole: Model | None
    local: State
    model: SlabModel
    wall_s: float
    comm_s: float
    steps: int
    _: KW_ONLY
    extra: dict = field(default_factory=dict)

    @property
    def comm_share(self) -> float:
        """Share of the wall time spent communicating (0 on one rank)."""
        return self.comm_s / self.wall_s if self.wall_s > 0 else 0.0

    def summary(self) -> dict:
        """The ``"domain"`` part of a run's summary: ranks, slabs, bytes and time communicating."""
        m = self.model
        halo = m.halo
        return {
            "ranks": halo.world,
            "axis": "D",
            "rows": list(m.rows),
            "halo_rows": 1,
            "exchanges": halo.exchanges,
            "bytes_sent": halo.bytes,
            "bytes_per_exchange": halo.bytes // halo.exchanges if halo.exchanges else 0,
            "comm_s": self.comm_s,
            "wall_s": self.wall_s,
            "comm_share": self.comm_share,
            **self.extra,
        }


def _rank_and_world(group):
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(group), dist.get_world_size(group)
    return 0, 1


def decomposed_simulate(
    model: Model,
    state: State,
    dt: float,
    steps: int,
    *,
    integrator=None,
    record_every: int | None = None,
    check_every: int = 10,
    progress: bool = False,
    cuts=(),
    group=None,
) -> DecomposedRun:
    """Run ``steps`` steps of ``model`` split over the ranks of ``group`` (one process: the whole body).

    Every rank calls it with the same global model and start state; rank 0 gets the gathered
    result. Dragged nodes start on their path, as in :func:`~torchdeform.sim.engine.simulate`.

    Args:
        model: the global :class:`~torchdeform.sim.model.Model`.
        state: global start state ``(B, 3, D, H, W)``.
        dt: time step (s).
        steps: number of steps.
        integrator: one of :data:`SUPPORTED_INTEGRATORS` (default symplectic Euler).
        record_every: gather every k-th state to rank 0, or None.
        check_every: steps between checks for non-finite values and runaway kinetic energy, summed over
            the slabs (all ranks stop together, with the message of
            :class:`~torchdeform.sim.stability.DivergenceMonitor`).
        progress: a progress bar on rank 0.
        cuts: ``[(time, blade), ...]``: each :class:`~torchdeform.topology.Blade` cuts the springs it
            crosses at the first state whose time reaches ``time`` (before that step).
        group: the ``torch.distributed`` process group (default the global one, if initialised).

    Returns:
        a :class:`DecomposedRun`.
    """
    import torch.distributed as dist
    from tqdm.auto import tqdm

    integrator = integrator or SymplecticEuler()
    if integrator.name not in SUPPORTED_INTEGRATORS:
        raise ConfigError(
            "integrator.name",
            f"one of {', '.join(SUPPORTED_INTEGRATORS)} in a domain-decomposed run",
            got=integrator.name,
        )
    steps = int(steps)
    if steps < 0:
        raise ConfigError("steps", "an integer >= 0", got=steps)
    rank, world = _rank_and_world(group)
    local = decompose(model, rank, world, group=group)
    e_lo, e_hi = local.extent
    own = local.owned
    state = model.start(state)  # fixed nodes at rest, dragged nodes on their path
    monitor = DivergenceMonitor(model, dt, integrator)  # the whole body's energy scale and safe dt
    st = State(state.x[:, :, e_lo:e_hi].clone(), state.v[:, :, e_lo:e_hi].clone(), t=state.t)
    pending = sorted(((float(at), blade) for at, blade in cuts), key=lambda c: c[0])
    ts, xs, vs = [], [], []

    def keep(s):
        ts.append(s.t)
        xs.append(s.x[:, :, own].detach().cpu().clone())
        vs.append(s.v[:, :, own].detach().cpu().clone())

    if record_every:
        keep(st)
    wall = 0.0
    with torch.no_grad():
        for i in tqdm(range(1, steps + 1), disable=not progress or rank != 0 or None, desc="simulate", unit="step"):
            t0 = time.perf_counter()
            while pending and st.t >= pending[0][0] - 1e-6 * dt:
                from ..topology import cut

                local.halo.exchange(st.x)
                cut(local, st.x, pending.pop(0)[1])
            st = integrator.step(local, st, dt)
            wall += time.perf_counter() - t0
            if i % check_every == 0 or i == steps:
                # one collective: non-finite values and the kinetic energy of each batch entry, summed over
                # the slabs (on the state's device: NCCL reduces there); then the checks of one process
                x_own, v_own = st.x[:, :, own], st.v[:, :, own]
                bad = (~torch.isfinite(x_own)).sum() + (~torch.isfinite(v_own)).sum()
                mass = local.mass if local.mass.shape[2] == 1 else local.mass[:, :, own]  # uniform: (1, 1, 1, 1, 1)
                ke = (0.5 * mass * v_own * v_own).flatten(1).sum(1)
                sums = torch.cat([bad.to(ke.dtype).reshape(1), torch.nan_to_num(ke, nan=0.0, posinf=0.0)])
                if world > 1:
                    dist.all_reduce(sums, op=dist.ReduceOp.SUM, group=group)
                if sums[0].item() > 0:
                    monitor.fail(i, "position or velocity", math.nan)
                if float(sums[1:].max()) > monitor.limit:
                    monitor.fail(i, "kinetic energy (runaway)", float(sums[1:].max()))
            if record_every and i % record_every == 0:
                keep(st)
    final, rec, whole = _gather(local, st, ts, xs, vs, rank, world, group)
    return DecomposedRun(final, rec, whole, st, local, wall, local.halo.seconds, steps)


#: the spring fields a run may edit (cuts), stored at each spring's first node
EDITED = ("stiffness", "damping", "rest_length")


def _gather(local: SlabModel, st: State, ts, xs, vs, rank: int, world: int, group):
    """The final state, the records and the edited global model, gathered to rank 0 (None elsewhere)."""
    own = local.owned
    shape = local.grid.shape
    edited = {
        name: getattr(local, name)[..., own, :, :].cpu()
        for name in EDITED
        if torch.is_tensor(getattr(local, name)) and tuple(getattr(local, name).shape[-3:]) == shape
    }
    # an Elastic body's cells: each rank gives those whose lower corner row it owns
    cells = slice(own.start, min(own.stop, shape[0] - 1))
    if getattr(local, "mu_cells", None) is not None:
        edited["mu_cells"] = local.mu_cells[..., cells, :, :].cpu()
    if getattr(local, "volume", None) is not None:
        edited["volume"] = local.volume[0][..., cells, :, :].cpu()
        edited["volume_shear"] = local.volume[2][..., cells, :, :].cpu()
    mine = (
        st.x[:, :, own].detach().cpu(),
        st.v[:, :, own].detach().cpu(),
        torch.stack(xs) if xs else None,
        torch.stack(vs) if vs else None,
        edited,
    )
    if world > 1:
        import torch.distributed as dist

        parts = [None] * world if rank == 0 else None
        dist.gather_object(mine, parts, dst=0, group=group)
        if rank != 0:
            return None, {}, None
    else:
        parts = [mine]
    dev = st.x.device
    final = State(torch.cat([p[0] for p in parts], 2).to(dev), torch.cat([p[1] for p in parts], 2).to(dev), t=st.t)
    rec = {}
    if xs:
        rec = {
            "t": torch.tensor(ts, dtype=torch.float64),
            "x": torch.cat([p[2] for p in parts], 3),
            "v": torch.cat([p[3] for p in parts], 3),
        }
    whole = copy.copy(local.whole)
    joined = {name: _cat_rows([p[4][name] for p in parts]).to(dev) for name in parts[0][4]}
    for name, t in joined.items():
        if name == "volume":
            whole.volume = (t, whole.volume[1], joined["volume_shear"])
        elif name != "volume_shear":
            setattr(whole, name, t)
    return final, rec, whole


def _cat_rows(parts: list) -> torch.Tensor:
    """Rows along D from each rank, ``(..., rows, H', W')``, joined (batches broadcast to the largest)."""
    n = max(p.dim() for p in parts)
    parts = [p.reshape((1,) * (n - p.dim()) + tuple(p.shape)) for p in parts]
    lead = torch.broadcast_shapes(*(p.shape[:-3] for p in parts))
    return torch.cat([p.expand(*lead, *p.shape[-3:]) for p in parts], -3)
