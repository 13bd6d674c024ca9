"""Fits for the data-parallel tests: run under ``torchrun`` (sharded) and in one process (the reference).

``python -m torch.distributed.run --standalone --nproc-per-node N tests/distributed/data_parallel_fits.py OUT.json``
runs every case with :class:`ShardedLoss` over the ranks; rank 0 writes the learned values (as
``float.hex``), per-rank facts (checkpoint writes, whether every rank ended with the same bits)
and the error every rank saw from a rollout that failed on one rank only. The test runs the same
cases in its own process with plain :class:`WindowLoss` objects (:func:`reference`).
"""

from __future__ import annotations

import json
import signal
import sys
from pathlib import Path

import torch

from torchdeform import learn
from torchdeform.errors import ConfigError

CASES = ("lbfgs", "adam")


def shared(series, k, c):
    return learn.Parameters(
        series,
        learn.SpringParameter.like(series, init=k),
        learn.SpringParameter.like(series, init=c),
        series.truth["mass"],
    )


class SumOfLosses:
    """Reference for several series: their windows numbered one after the other, the loss their sum."""

    def __init__(self, losses):
        self.losses = losses
        self.num_windows = sum(x.num_windows for x in losses)

    def __call__(self, params, windows=None):
        total, lo = 0.0, 0
        chosen = list(range(self.num_windows)) if windows is None else [int(i) for i in windows]
        for x in self.losses:
            sel = [i - lo for i in chosen if lo <= i < lo + x.num_windows]
            if sel:
                total = total + x(params, torch.tensor(sel))
            lo += x.num_windows
        return total


def lbfgs_case():
    """Radetzky's cube, 120 steps (12 windows), shared k and d from 3x and 0.4x: 3 L-BFGS steps."""
    s = learn.radetzky_cube(springs=70, steps=120)
    p = shared(s, 30.0, 0.04)
    return p, [learn.WindowLoss(s, window=10)], dict(optimizer="lbfgs", iterations=3, lbfgs_inner=5)


def adam_case():
    """Two series of the cube (clean, and noisy at 1 %), 17 windows; Adam on random subsets of 5."""
    a = learn.radetzky_cube(springs=70, steps=100)
    b = learn.radetzky_cube(springs=70, steps=70, noise=0.01, seed=3)
    p = shared(a, 20.0, 0.05)
    return (
        p,
        [learn.WindowLoss(a, window=10), learn.WindowLoss(b, window=10)],
        dict(optimizer="adam", iterations=10, windows_per_step=5, seed=11, lr=0.1),
    )


def learned(params) -> dict:
    return {n: [float(v).hex() for v in p.detach().reshape(-1)] for n, p in params.named_parameters()}


def reference(case: str) -> dict:
    """The case in one process, without torch.distributed: plain window losses (their sum)."""
    params, losses, kw = {"lbfgs": lbfgs_case, "adam": adam_case}[case]()
    loss = losses[0] if len(losses) == 1 else SumOfLosses(losses)
    trainer = learn.Trainer(params, loss, progress=False, patience=100, **kw)
    trainer.run()
    return {"learned": learned(params), "losses": [r.loss.hex() for r in trainer.history]}


def sharded(case: str, tmp: Path) -> dict:
    """The case over the ranks; Adam stops half-way, checkpoints (rank 0) and resumes on every rank."""
    from torchdeform.distributed.data_parallel import ShardedLoss

    params, losses, kw = {"lbfgs": lbfgs_case, "adam": adam_case}[case]()
    loss = ShardedLoss(losses)
    trainer = learn.Trainer(params, loss, progress=False, patience=100, **kw)
    if kw["optimizer"] == "adam":
        trainer.run(stop_after=kw["iterations"] // 2)
        trainer.save(tmp / "adam.pt")
        params, _, _ = adam_case()
        trainer = learn.Trainer(params, loss, progress=False, patience=100, **kw).load(tmp / "adam.pt")
    trainer.run()
    return {"learned": learned(params), "losses": [r.loss.hex() for r in trainer.history]}


class FailsOnLastWindow:
    """A loss of one window that raises, as a rollout that fails on the rank holding it."""

    num_windows = 1

    def __call__(self, params, windows=None):
        raise ConfigError("rollout", "a run that does not fail", got="a failure on one rank")


def main(out: str) -> int:
    import torch.distributed as dist

    from torchdeform.distributed.data_parallel import ShardedLoss, process_group

    signal.alarm(120)  # a rank that hangs ends itself (the test bounds torchrun too)
    torch.set_num_threads(1)
    saves = []
    plain_save = torch.save

    def counting_save(*a, **k):
        saves.append(1)
        return plain_save(*a, **k)

    torch.save = counting_save
    with process_group() as (rank, world):
        result = {"world": world}
        for case in CASES:
            result[case] = sharded(case, Path(out).parent)
        # a rank without windows (a 2-window loss on 3 ranks) adds zero; value and gradient are global
        s = learn.radetzky_cube(springs=70, steps=20)
        p = shared(s, 12.0, 0.08)
        value = ShardedLoss(learn.WindowLoss(s, window=10))(p)
        value.backward()
        result["few"] = {"value": float(value.detach()).hex(), "grad": [float(q.grad).hex() for q in p.parameters()]}
        # a failure in one rank's rollouts is raised on every rank (no rank left waiting)
        try:
            ShardedLoss([learn.WindowLoss(s, window=10), FailsOnLastWindow()])(p)
            seen = "no error"
        except ConfigError as e:
            seen = f"{type(e).__name__}: {e} (key {e.key})"
        mine = {"saves": len(saves), "seen": seen, "learned": [result[c]["learned"] for c in CASES]}
        every = [None] * world
        dist.all_gather_object(every, mine)
        if rank == 0:
            result["saves"] = [m["saves"] for m in every]
            result["seen"] = [m["seen"] for m in every]
            result["same_on_all_ranks"] = all(m["learned"] == mine["learned"] for m in every)
            Path(out).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
