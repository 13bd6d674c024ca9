"""Data-parallel learning: the windows of a loss shared out over ranks (``torchrun``, gloo).

The data of a fit are the teacher-forcing windows of one or more
:class:`~torchdeform.learn.loss.WindowLoss` objects (several series: several losses, their
windows numbered one after the other). Each loss is normalised over its whole series, so the
loss of a set of windows is the sum of the per-window losses,

    L(theta) = sum_w l_w(theta) = sum_r L_r(theta),    L_r = sum of the windows of rank r,

and so is its gradient. :class:`ShardedLoss` evaluates only this rank's windows (:func:`shard`:
contiguous blocks of the window list, sizes differing by at most one; with ``windows``, a
random subset every rank drew from the same seeded generator, the blocks of that subset), and
makes value and gradient global with two autograd functions:

* the value: ``L = Sum(L_r)`` gathers every rank's partial value and adds them in rank order
  (forward); the backward passes the gradient through (``dL/dL_r = 1``);
* the parameters: every learnable parameter enters the model through ``Share(theta)``, the
  identity (forward), whose backward gathers every rank's gradient and adds them in rank order.
  The parameters are concatenated first, so one backward pass makes exactly one collective
  call whatever the autograd engine's order, and ``theta.grad`` is then ``sum_r dL_r/dtheta``
  on every rank.

So a :class:`~torchdeform.learn.trainer.Trainer` works unchanged: L-BFGS's line search sees
the same objective on every rank, Adam's window subsets are drawn from the trainer's seeded
generator on every rank and then shared out, gradient clipping sees the global norm, and
``.backward()``, ``torch.autograd.grad`` and second derivatives (the Hessian of
:func:`~torchdeform.learn.reports.curvature_report`) are all global. Every rank adds the same
numbers in the same order, so every rank holds the same bits and the parameters stay equal
without a broadcast. Against one process, only the order of the sums differs: rounding (in
float64, shared stiffness and damping fitted over 2 or 3 ranks agree with one process to a unit or
two in the last place; 140 per-spring values after two L-BFGS iterations to 2e-13 relative).
Checkpoints: :meth:`Trainer.save` writes on rank 0 only and waits at
:meth:`ShardedLoss.barrier`; every rank loads.

Speed: the ranks divide the windows, so they gain where a window costs arithmetic. Radetzky's
27-node cube gains nothing (a step is the same few hundred small tensor operations whatever the
batch); a 12^3 cube (25 windows) trains 1.8x faster on 2 ranks than on one single-threaded
process, 1.15x faster than on one process with 2 threads. ``torchrun`` adds ~5 s of start-up.

A rank without windows (more ranks than windows) contributes zero. An error a rank raises in
its own rollouts (a :class:`~torchdeform.errors.TorchdeformError`) is flagged in the same
collective call as the value and raised on every rank, so no rank waits for a peer that left.
Losses with ``velocity="carry"`` run their windows in sequence: the sum is still right, but
every rank simulates the whole series (no speed-up).

Launch (one process per rank; ``--threads`` per process, 1 for small bodies)::

    torchrun --standalone --nproc-per-node 2 training/fit_cube.py --runs 3 --out runs/cube-2

Shapes: a window is a batch entry of the rollouts, ``(B, 3, D, H, W)`` with ``B`` this rank's
window count; the gathered value is ``(world, 2)`` (value, failure flag), the gathered gradient
``(world, P)`` for ``P`` learned numbers.

Example (one process is rank 0 of 1; :meth:`ShardedLoss.partial` gives a rank's share without
communication):
    >>> from torchdeform import learn
    >>> from torchdeform.distributed.data_parallel import ShardedLoss, shard
    >>> [list(shard(8, r, 3)) for r in range(3)]
    [[0, 1, 2], [3, 4, 5], [6, 7]]
    >>> series = learn.radetzky_cube(springs=70, steps=60)
    >>> params = learn.Parameters(series, learn.SpringParameter.like(series, init=12.0),
    ...                           learn.SpringParameter.like(series, init=0.08), series.truth["mass"])
    >>> loss = learn.WindowLoss(series, window=10)
    >>> sharded = ShardedLoss(loss)
    >>> sharded.num_windows, bool(sharded(params) == loss(params))
    (6, True)
    >>> parts = [ShardedLoss(loss, rank=r, world=4).partial(params) for r in range(4)]
    >>> [ShardedLoss(loss, rank=r, world=4).windows() for r in range(4)]
    [[0, 1], [2, 3], [4], [5]]
    >>> abs((sum(parts) / loss(params)).item() - 1) < 1e-14
    True
"""

from __future__ import annotations

import pickle
from contextlib import contextmanager

import torch
from torch import nn

from ..errors import ConfigError, TorchdeformError
from .commands import rank_and_world

__all__ = ["ShardedLoss", "shard", "process_group", "parallel_loss", "is_main"]


def shard(n: int, rank: int, world: int) -> range:
    """The positions ``0 .. n-1`` that rank ``rank`` of ``world`` takes: a contiguous block.

    Blocks follow rank order and cover every position once; the first ``n % world`` ranks
    take one more. A rank past ``n`` gets an empty range.

    Examples:
        >>> [list(shard(5, r, 2)) for r in range(2)], list(shard(2, 2, 3))
        ([[0, 1, 2], [3, 4]], [])
    """
    n, rank, world = int(n), int(rank), int(world)
    if world < 1 or not 0 <= rank < world:
        raise ConfigError("rank", f"0 <= rank < world (world >= 1), world = {world}", got=rank)
    q, extra = divmod(n, world)
    start = rank * q + min(rank, extra)
    return range(start, start + q + (rank < extra))


def _gather_sum(t: torch.Tensor, group, world: int) -> torch.Tensor:
    """Every rank's ``t`` added in rank order: the same bits on every rank (``(world,) + shape`` gathered)."""
    import torch.distributed as dist

    parts = [torch.empty_like(t) for _ in range(world)]
    dist.all_gather(parts, t.contiguous(), group=group)
    return torch.stack(parts).sum(0)


class _Sum(torch.autograd.Function):
    """Forward: the sum over ranks; backward: the gradient passes through (``dL/dL_r = 1``)."""

    @staticmethod
    def forward(ctx, local, group, world):
        return _gather_sum(local.detach(), group, world)

    @staticmethod
    def backward(ctx, grad):
        return grad, None, None


class _Share(torch.autograd.Function):
    """Forward: the identity; backward: the sum of every rank's gradient (differentiable again)."""

    @staticmethod
    def forward(ctx, flat, group, world):
        ctx.group, ctx.world = group, world
        return flat.clone()

    @staticmethod
    def backward(ctx, grad):
        return _Sum.apply(grad, ctx.group, ctx.world), None, None


@contextmanager
def _substituted(module: nn.Module, values: dict):
    """Swap parameters for tensors for the block: ``values`` is ``{id(parameter): tensor}``.

    Every registration of such a parameter in ``module`` and its submodules holds the tensor
    instead. (:func:`torch.func.functional_call` does not restore a parameter of a submodule registered under
    two names, as :meth:`FuzzySprings.part` registers its slider: seen with torch 2.13.)
    """
    saved = []
    try:
        for m in module.modules():
            for name, p in list(m._parameters.items()):
                if p is not None and id(p) in values:
                    saved.append((m, name, p))
                    m._parameters[name] = values[id(p)]
        yield
    finally:
        for m, name, p in reversed(saved):
            m._parameters[name] = p


class ShardedLoss:
    """One rank's share of the windows of one or more window losses, with a global value and gradient.

    Args:
        losses: a :class:`~torchdeform.learn.loss.WindowLoss`, or a list of them (several series
            of one body: their windows numbered one after the other, the loss their sum).
        rank, world: this process's rank and the number of ranks (default: those of the
            initialised ``torch.distributed`` process group, else 0 and 1). Without a process
            group, ``world > 1`` is allowed for :meth:`partial` only.
        group: the process group (default: the whole world).

    Call it like a :class:`WindowLoss`, on every rank: ``loss(params, windows=None)`` with a
    :class:`~torchdeform.learn.parameters.Parameters` (any ``nn.Module`` with a ``model()``
    method) and optionally ``windows`` (indices into the ``num_windows`` windows, the same on every
    rank), to get the 0-d loss over all ranks. Its gradients (``.backward()`` or
    ``torch.autograd.grad``) are the global ones on every rank.
    """

    def __init__(self, losses, *, rank: int | None = None, world: int | None = None, group=None):
        import torch.distributed as dist

        self.losses = list(losses) if isinstance(losses, (list, tuple)) else [losses]
        if not self.losses or not all(hasattr(x, "num_windows") and callable(x) for x in self.losses):
            raise ConfigError("losses", "a WindowLoss or a non-empty list of them", got=losses)
        joined = dist.is_available() and dist.is_initialized()
        self.group = group
        self.rank = int(rank if rank is not None else dist.get_rank(group) if joined else 0)
        self.world = int(world if world is not None else dist.get_world_size(group) if joined else 1)
        shard(0, self.rank, self.world)  # checks rank and world
        self.offsets = [0]
        for x in self.losses:
            self.offsets.append(self.offsets[-1] + int(x.num_windows))
        self.dtype = getattr(self.losses[0], "dtype", torch.float64)

    @property
    def num_windows(self) -> int:
        """Windows of all the losses together (what a trainer's ``windows_per_step`` draws from)."""
        return self.offsets[-1]

    def windows(self, *, windows=None) -> list:
        """This rank's windows: global indices, in order (its block of ``windows``, default all)."""
        chosen = list(range(self.num_windows)) if windows is None else [int(i) for i in windows]
        bad = [i for i in chosen if not 0 <= i < self.num_windows]
        if bad:
            raise ConfigError("windows", f"window indices in 0 .. {self.num_windows - 1}", got=bad[:5])
        return [chosen[j] for j in shard(len(chosen), self.rank, self.world)]

    def _local(self, model, windows):
        """The sum of this rank's windows, or None when it has none."""
        mine = self.windows(windows=windows)
        total = None
        for n, loss in enumerate(self.losses):
            lo, hi = self.offsets[n], self.offsets[n + 1]
            sel = [i - lo for i in mine if lo <= i < hi]
            if not sel:
                continue
            part = loss(model, None if sel == list(range(hi - lo)) else torch.tensor(sel))
            total = part if total is None else total + part
        return total

    def partial(self, params, *, windows=None) -> torch.Tensor:
        """This rank's part of the loss (no communication): the sum over ranks is the loss.

        Its gradient is this rank's part of the gradient.
        """
        model = params.model() if isinstance(params, nn.Module) else params
        local = self._local(model, windows)
        return torch.zeros((), dtype=self.dtype) if local is None else local

    def __call__(self, params, windows=None) -> torch.Tensor:
        """The loss over every rank's windows, a 0-d tensor (the same on every rank); call on every rank."""
        if self.world == 1:
            return self.partial(params, windows=windows)
        import torch.distributed as dist

        if not (dist.is_available() and dist.is_initialized()):
            raise ConfigError(
                "ShardedLoss",
                f"an initialised torch.distributed process group for {self.world} ranks (torchrun; see process_group)",
                got=None,
            )
        shared = None
        failure = None
        try:
            if isinstance(params, nn.Module):
                model, shared = self._shared_model(params)
            else:
                model = params
                if torch.is_grad_enabled() and any(
                    torch.is_tensor(t) and t.requires_grad for t in (model.stiffness, model.damping, model.mass)
                ):
                    raise ConfigError(
                        "params",
                        "a Parameters (a model's own tensors get no gradient from the other ranks)",
                        got=type(params).__name__,
                    )
            local = self._local(model, windows)
        except TorchdeformError as e:  # flagged in the collective below: every rank raises
            failure, local = e, None
        if local is None:
            local = torch.zeros((), dtype=self.dtype) if shared is None else shared.sum() * 0
        flag = torch.tensor(float(failure is not None), dtype=local.dtype, device=local.device)
        total = _Sum.apply(torch.stack([local, flag]), self.group, self.world)
        if float(total[1].detach()) > 0:
            self._raise(failure)
        return total[0]

    def _shared_model(self, params):
        """``params.model()`` with every learnable parameter entering through one :class:`_Share`."""
        learned = [p for p in params.parameters() if p.requires_grad]
        if not learned or not torch.is_grad_enabled():
            return params.model(), None
        flat = torch.cat([p.reshape(-1) for p in learned])
        shared = _Share.apply(flat, self.group, self.world)
        pieces = shared.split([p.numel() for p in learned])
        with _substituted(params, {id(p): t.view_as(p).to(p.dtype) for p, t in zip(learned, pieces)}):
            return params.model(), shared

    def _raise(self, failure):
        """Raise on every rank the error of the first rank that failed (its own on that rank)."""
        import torch.distributed as dist

        info = None
        if failure is not None:
            info = (type(failure), failure.args, dict(vars(failure)))
            try:
                pickle.dumps(info)
            except Exception:
                info = (TorchdeformError, (str(failure),), {})
        infos = [None] * self.world
        dist.all_gather_object(infos, info, group=self.group)
        if failure is not None:
            raise failure
        cls, args, attrs = next(i for i in infos if i is not None)
        err = cls.__new__(cls)
        Exception.__init__(err, *args)
        err.__dict__.update(attrs)
        raise err

    def barrier(self) -> None:
        """Wait for every rank (no-op on one)."""
        if self.world > 1:
            import torch.distributed as dist

            dist.barrier(group=self.group)


def parallel_loss(losses):
    """``losses`` shared out over the ranks of the process group when there are several, else unchanged.

    One loss on one process comes back as it is (the single-process path); a list of losses
    becomes a :class:`ShardedLoss` (their sum) either way.

    Examples:
        >>> from torchdeform import learn
        >>> loss = learn.WindowLoss(learn.radetzky_cube(springs=70, steps=20), window=10)
        >>> parallel_loss(loss) is loss, type(parallel_loss([loss, loss])).__name__
        (True, 'ShardedLoss')
    """
    sharded = ShardedLoss(losses)
    if sharded.world == 1 and len(sharded.losses) == 1:
        return sharded.losses[0]
    return sharded


def is_main() -> bool:
    """True on rank 0 of an initialised process group, and in a process without one (who writes files).

    Examples:
        >>> is_main()
        True
    """
    import torch.distributed as dist

    return not (dist.is_available() and dist.is_initialized()) or dist.get_rank() == 0


@contextmanager
def process_group(*, backend: str = "gloo"):
    """Join ``torchrun``'s process group for the block when ``WORLD_SIZE`` > 1; yield ``(rank, world)``.

    Without torchrun (no ``WORLD_SIZE``) nothing is started: ``(0, 1)``. At a normal end every
    rank waits at a barrier (a rank that tears down early can abort its peers), then the group
    is destroyed; after an exception it is destroyed at once (``torchrun`` stops the other ranks).

    Examples:
        >>> with process_group() as (rank, world):
        ...     rank, world
        (0, 1)
    """
    rank, world = rank_and_world()
    started = False
    if world > 1:
        # torch._dynamo (which the first optimizer step imports) keeps references to the process
        # groups that exist when it is imported: destroy_process_group then cannot join gloo's
        # threads, and one that frees a finished collective's tensors while the interpreter shuts
        # down aborts the rank ("terminate called without an active exception"; 1 in ~10
        # three-rank runs of the tests). Imported before the group exists, it holds none.
        import torch._dynamo  # noqa: F401
        import torch.distributed as dist

        if not dist.is_initialized():
            dist.init_process_group(backend)
            started = True
    clean = False
    try:
        yield rank, world
        clean = True
    finally:
        if started:
            if clean:
                dist.barrier()
            dist.destroy_process_group()
