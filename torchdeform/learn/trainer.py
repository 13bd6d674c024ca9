"""Training loops.

Adam or L-BFGS over a :class:`~torchdeform.learn.loss.WindowLoss`, early stopping, checkpoint
and bitwise resume, a divergence guard.
"""

from __future__ import annotations

import math
import pickle
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm.auto import tqdm

from ..errors import ConfigError, TorchdeformError
from .loss import WindowLoss
from .parameters import Parameters, _check

__all__ = ["Trainer", "Record", "NonFiniteLossError"]


_BLOWUP = 1e30  # the loss L-BFGS sees at trial points where the simulation diverged


class NonFiniteLossError(TorchdeformError, FloatingPointError):
    """Training cannot start: the loss (or a parameter) is not finite at the start values."""


def _start_values(params) -> str:
    """The learned start values, briefly (a float, or the range of a list)."""
    parts = []
    for name, v in params.summary().items():
        if isinstance(v, list):
            flat = [float(x) for x in torch.as_tensor(v).reshape(-1)]
            parts.append(f"{name} {min(flat):.3g}..{max(flat):.3g}")
        else:
            parts.append(f"{name} {v:.3g}")
    return ", ".join(parts)


# ------------------------------------------------------------------- training
@dataclass
class Record:
    """One entry of the learning curve."""

    iteration: int
    loss: float
    grad_norm: float
    seconds: float


class Trainer:
    """Optimise :class:`Parameters` against a :class:`WindowLoss`.

    Args:
        params, loss: what to learn, and from what (a :class:`WindowLoss`, or any loss with its call
            interface and ``num_windows``).
        optimizer: ``"adam"`` or ``"lbfgs"`` (strong-Wolfe line search; one iteration is one
            ``LBFGS.step`` of up to ``lbfgs_inner`` inner iterations).
        lr: learning rate (Adam default 0.05 on the transformed values; L-BFGS default 1).
        iterations: maximum iterations.
        clip: gradient-norm clipping (Adam only), or None.
        windows_per_step: a random subset of this many windows per Adam iteration (seeded), or None.
        patience, min_delta: stop when the loss has not fallen below ``best * (1 - min_delta)``
            for ``patience`` iterations.
        tol: stop when the loss falls below ``tol``.
        seed: seed of the window sampling.
        checkpoint_path, checkpoint_every: save a resumable checkpoint every k iterations.
        progress: tqdm bar.

    Data-parallel (``torchrun``): with a loss shared out over ranks
    (:class:`~torchdeform.distributed.data_parallel.ShardedLoss`, whose values and gradients are
    global on every rank) the same trainer runs on every rank, in step; checkpoints are written by
    rank 0 only (the loss's ``rank``) and every rank waits until they are (the loss's ``barrier``),
    so :meth:`save` and :meth:`run` are called on every rank, and every rank can :meth:`load`.
    """

    def __init__(
        self,
        params: Parameters,
        loss: WindowLoss,
        *,
        optimizer: str = "adam",
        lr: float | None = None,
        iterations: int = 200,
        clip: float | None = 10.0,
        windows_per_step: int | None = None,
        patience: int = 50,
        min_delta: float = 1e-4,
        tol: float = 0.0,
        seed: int = 0,
        checkpoint_path=None,
        checkpoint_every: int = 0,
        progress: bool = True,
        lbfgs_inner: int = 20,
    ):
        _check("optimizer", optimizer, ("adam", "lbfgs"))
        self.params, self.loss, self.kind = params, loss, optimizer
        self.iterations, self.clip, self.patience, self.min_delta = (
            int(iterations),
            clip,
            int(patience),
            float(min_delta),
        )
        self.tol, self.progress = float(tol), progress
        self.windows_per_step = windows_per_step
        if windows_per_step is not None and optimizer == "lbfgs":
            raise ConfigError(
                "windows_per_step", "None with L-BFGS (it needs one fixed objective)", got=windows_per_step
            )
        self.checkpoint_path = None if checkpoint_path is None else Path(checkpoint_path)
        self.checkpoint_every = int(checkpoint_every)
        self.generator = torch.Generator().manual_seed(int(seed))
        learnable = [p for p in params.parameters() if p.requires_grad]
        if not learnable:
            raise ConfigError("params", "at least one learned parameter", got="none", show_got=True)
        if optimizer == "adam":
            self.opt = torch.optim.Adam(learnable, lr=0.05 if lr is None else lr)
        else:
            self.opt = torch.optim.LBFGS(
                learnable,
                lr=1.0 if lr is None else lr,
                max_iter=int(lbfgs_inner),
                tolerance_grad=1e-12,
                tolerance_change=1e-15,
                history_size=20,
                line_search_fn="strong_wolfe",
            )
        self.history: list[Record] = []
        self.iteration = 0
        self.best = math.inf
        self.since_best = 0
        self.stopped = ""
        self.seconds = 0.0
        self._learnable = learnable

    def _windows(self):
        if self.windows_per_step is None or self.windows_per_step >= self.loss.num_windows:
            return None
        return torch.randperm(self.loss.num_windows, generator=self.generator)[: self.windows_per_step]

    def _grad_norm(self) -> float:
        g = [p.grad.detach().reshape(-1) for p in self._learnable if p.grad is not None]
        return float(torch.cat(g).norm()) if g else 0.0

    def step(self) -> float:
        """One iteration; returns the loss (before the update)."""
        windows = self._windows()
        if self.kind == "adam":
            self.opt.zero_grad()
            loss = self.loss(self.params, windows)
            loss.backward()
            loss = loss.detach()
            gn = self._grad_norm()
            if self.clip is not None:
                torch.nn.utils.clip_grad_norm_(self._learnable, self.clip)
            if math.isfinite(float(loss)) and math.isfinite(gn):
                self.opt.step()
            return float(loss), gn

        def closure():
            self.opt.zero_grad()
            try:
                val = self.loss(self.params)
            except ConfigError:  # a trial step outside finite parameters
                val = None
            if val is None or not bool(torch.isfinite(val)):
                # a line-search trial point where the simulation blew up: a large finite value
                # and no gradient send the search back to shorter steps
                for p in self._learnable:
                    p.grad = torch.zeros_like(p)
                return torch.tensor(_BLOWUP, dtype=torch.float64)
            val.backward()
            return val.detach()

        loss = self.opt.step(closure)
        loss = float(loss)
        return (math.inf if loss >= _BLOWUP else loss), self._grad_norm()

    def run(self, *, iterations: int | None = None, stop_after: int | None = None) -> list:
        """Train until ``iterations`` (total), early stopping, or ``stop_after`` iterations of this call.

        ``stop_after`` simulates an interruption. Returns the history (list of :class:`Record`).
        """
        total = self.iterations if iterations is None else int(iterations)
        bar = tqdm(total=total, initial=self.iteration, disable=not self.progress, desc="fit", unit="it")
        done = 0
        while self.iteration < total and not self.stopped:
            if stop_after is not None and done >= stop_after:
                break
            t0 = time.perf_counter()
            snapshot = [p.detach().clone() for p in self._learnable]
            loss, gn = self.step()
            self.iteration += 1
            done += 1
            self.seconds += time.perf_counter() - t0
            self.history.append(Record(self.iteration, loss, gn, self.seconds))
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.3e}")
            if not math.isfinite(loss) or not all(bool(torch.isfinite(p).all()) for p in self._learnable):
                with torch.no_grad():  # keep the last finite values
                    for p, s in zip(self._learnable, snapshot):
                        p.copy_(s)
                what = "the loss" if not math.isfinite(loss) else "a parameter"
                if not any(math.isfinite(r.loss) for r in self.history):
                    self.history.pop()
                    self.iteration -= 1
                    raise NonFiniteLossError(
                        f"training cannot start: {what} is not finite at the start values ({_start_values(self.params)}): "
                        "the rollout diverges there; start closer to the data's values, or use a smaller time step or "
                        "an implicit integrator"
                    )
                self.stopped = "non-finite loss"
                warnings.warn(
                    f"training stopped at iteration {self.iteration}: {what} went non-finite; the last "
                    "finite parameters are kept",
                    UserWarning,
                    stacklevel=2,
                )
                break
            if loss < self.best * (1 - self.min_delta):
                self.best, self.since_best = loss, 0
            else:
                self.since_best += 1
            if loss <= self.tol:
                self.stopped = f"loss <= tol ({self.tol:g})"
            elif self.since_best >= self.patience:
                self.stopped = f"no improvement for {self.patience} iterations"
            if (
                self.checkpoint_path is not None
                and self.checkpoint_every
                and self.iteration % self.checkpoint_every == 0
            ):
                self.save(self.checkpoint_path)
        bar.close()
        return self.history

    def final_loss(self) -> float:
        """Loss at the current parameters (no gradient)."""
        with torch.no_grad():
            return float(self.loss(self.params))

    # ---------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        """Everything a resume needs: parameters, optimizer, sampling RNG, counters and history."""
        return {
            "params": self.params.state_dict(),
            "optimizer": self.opt.state_dict(),
            "generator": self.generator.get_state(),
            "iteration": self.iteration,
            "best": self.best,
            "since_best": self.since_best,
            "stopped": self.stopped,
            "seconds": self.seconds,
            "history": [[r.iteration, r.loss, r.grad_norm, r.seconds] for r in self.history],
        }

    def save(self, path) -> Path:
        """Write a resumable checkpoint (parameters, optimizer, sampling RNG, history).

        With a loss shared out over ranks: rank 0 writes, every rank returns once it is written.
        """
        path = Path(path)
        if getattr(self.loss, "rank", 0) == 0:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(path.suffix + ".tmp")
            torch.save(self.state_dict(), tmp)
            tmp.replace(path)
        wait = getattr(self.loss, "barrier", None)
        if wait is not None:
            wait()
        return path

    def load(self, path) -> Trainer:
        """Resume from a checkpoint written by :meth:`save` (same parameters and optimizer kind)."""
        path = Path(path)
        if not path.is_file():
            raise ConfigError("checkpoint", "an existing checkpoint file", got=str(path))
        try:
            sd = torch.load(path, weights_only=True)
            self.params.load_state_dict(sd["params"])
            self.opt.load_state_dict(sd["optimizer"])
        except (RuntimeError, KeyError, ValueError, EOFError, pickle.UnpicklingError) as e:
            raise ConfigError(
                "checkpoint",
                "a checkpoint of this parameter set and optimizer",
                got=f"{path} ({type(e).__name__}: {str(e).splitlines()[0]})",
            ) from None
        self.generator.set_state(sd["generator"])
        self.iteration, self.best, self.since_best = sd["iteration"], sd["best"], sd["since_best"]
        self.stopped, self.seconds = sd["stopped"], sd["seconds"]
        self.history = [Record(int(a), b, c, d) for a, b, c, d in sd["history"]]
        return self
