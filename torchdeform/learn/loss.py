"""The loss of rollouts over a series.

Teacher-forcing windows, checkpointed back-propagation through time, masks for missing
observations.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch.utils.checkpoint import checkpoint as _checkpoint

from ..checks import check_memory
from ..errors import ConfigError
from ..sim.catalog import INTEGRATORS
from ..sim.model import State
from .parameters import Parameters, _check
from .series import Series

__all__ = ["WindowLoss", "LOSS_ENGINES"]

#: How a :class:`WindowLoss` runs its rollouts: ``"eager"`` (the reference) or ``"compiled"``.
LOSS_ENGINES = ("eager", "compiled")


# ------------------------------------------------------------------- loss
class WindowLoss:
    """Loss of (teacher-forced) rollouts over a series.

    Args:
        series: observations and set-up (observation steps must be evenly spaced).
        window: observation intervals per window (teacher forcing every ``window``
            intervals, Radetzky's K); None: one window over the whole series (full BPTT).
        velocity: start velocity of windows after the first: ``"difference"``, ``"zero"``
            or ``"carry"`` (windows in sequence; see the module docstring).
        checkpoint: steps per gradient-checkpoint segment (None: keep the whole graph).
        detach: with ``velocity="carry"``, cut the gradient between windows (truncated BPTT).
        integrator: an integrator instance (default: the series' own).
        smooth: for noisy data, start windows from a local quadratic fit over ``2 smooth + 1``
            observations (positions and velocities) instead of the raw observation and the
            backward difference (0: off).
        engine: ``"eager"`` (the reference) or ``"compiled"``: each step of a rollout is one
            ``torch.compile`` graph, forward and backward (AOTAutograd), that takes the model's
            tensors as inputs, so new parameter values never recompile. The loss and gradients
            are those of the eager rollout (same operations in the same order; the tests hold
            them to 1e-12 in float64). It compiles on first use (Radetzky's cube: about 35 s on
            2 cores, less when inductor's on-disk cache has the graphs), and again for a new
            batch of windows (``windows`` subsets of another size) or a call without gradient.
            Where compilation fails the loss warns once and runs eagerly.
        backend: the ``torch.compile`` backend of ``engine="compiled"`` (default inductor;
            ``"aot_eager"`` captures and differentiates the same graphs without generating code,
            a check in seconds).

    Call with a :class:`Parameters` (or a model) and optionally ``windows`` (a LongTensor of
    window indices, for stochastic subsets) to get a 0-d loss tensor.
    """

    def __init__(
        self,
        series: Series,
        *,
        window: int | None = 10,
        velocity: str = "difference",
        checkpoint: int | None = None,
        detach: bool = True,
        integrator=None,
        smooth: int = 0,
        dtype=torch.float64,
        engine: str = "eager",
        backend="inductor",
    ):
        _check("velocity", velocity, ("difference", "zero", "carry"))
        _check("engine", engine, LOSS_ENGINES)
        self.engine = engine
        self._compiled = None
        if engine == "compiled":
            # imported here: it loads inductor, which would add 2 s to every import of torchdeform
            from .._compile import fresh

            # its own code object: dynamo keeps compiled graphs (and its recompile limit) per code object
            self._compiled = torch.compile(
                fresh(type(self)._advance).__get__(self), dynamic=False, fullgraph=True, backend=backend
            )
        self.series, self.velocity, self.dtype, self.detach = series, velocity, dtype, bool(detach)
        steps = np.asarray(series.steps)
        T = len(steps)
        E = series.every
        if T < 2 or (np.diff(steps) != E).any():
            raise ConfigError(
                "series.steps", "evenly spaced observation steps (resample the series first)", got=steps[:6].tolist()
            )
        if window is not None and int(window) < 1:
            raise ConfigError("window", "an integer >= 1 (observation intervals) or None", got=window)
        if checkpoint is not None and int(checkpoint) < 1:
            raise ConfigError("checkpoint", "an integer >= 1 (steps per segment) or None", got=checkpoint)
        self.K = T - 1 if window is None else min(int(window), T - 1)
        self.last_step = series.num_steps
        self.every, self.T = E, T
        self.checkpoint = None if checkpoint is None else int(checkpoint)
        self.integrator = integrator or INTEGRATORS[series.integrator]()
        self.obs = torch.as_tensor(series.positions, dtype=dtype)  # (T, 3, D, H, W)
        free = ~torch.as_tensor(series.constrained())
        self.weight = (torch.as_tensor(series.mask) & free).to(dtype).unsqueeze(1)  # (T, 1, D, H, W)
        X = series.grid.rest_positions(dtype=dtype)
        disp = ((self.obs - X) ** 2 * self.weight).sum()
        self.count = float(self.weight.sum()) * 3
        if self.count == 0:
            raise ConfigError("series.mask", "at least one observed free node", got="none", show_got=True)
        self.ref = math.sqrt(max(float(disp) / self.count, 1e-300))
        self.starts = list(range(0, T - 1, self.K))  # window start observations
        # the autograd graph of one evaluation: every step of every window keeps its node fields (state,
        # forces, spring terms); a checkpoint keeps one segment and the segment ends
        steps = (T - 1) * E
        held = steps if self.checkpoint is None else self.checkpoint + steps // self.checkpoint
        g = series.grid
        check_memory(
            "checkpoint" if checkpoint is not None else "window",
            float(held) * g.num_nodes * torch.finfo(dtype).bits / 8 * (30 + 3 * g.S),
            f"the autograd graph of {held} steps of {g.num_nodes} nodes (set checkpoint to keep fewer)",
            got=checkpoint if checkpoint is not None else window,
        )
        if int(smooth) < 0:
            raise ConfigError("smooth", "an integer >= 0 (half-width in observations)", got=smooth)
        self.smooth = int(smooth)
        # normalisation over the whole series, so a subset of windows has the same scale
        self.scale = 1.0 / (self.count * self.ref**2)

    @property
    def num_windows(self) -> int:
        """Number of teacher-forcing windows (1 for ``window=None``)."""
        return len(self.starts)

    # ---------------------------------------------------------------- data on the model's device
    def _data(self, device) -> dict:
        """The series' tensors on ``device`` (copied once per device).

        ``obs`` ``(T, 3, D, H, W)`` and ``weight`` ``(T, 1, D, H, W)`` (the loss's dtype), ``mask``
        bool ``(T, D, H, W)``, ``free`` bool ``(D, H, W)`` (neither fixed nor dragged), ``steps``
        int64 ``(T,)``. The rollouts index them with tensors on the same device, so no step of a
        rollout copies from the host.
        """
        device = torch.device(device)
        cache = self.__dict__.setdefault("_by_device", {})
        key = str(device)
        if key not in cache:
            s = self.series
            cache[key] = {
                "obs": self.obs.to(device),
                "weight": self.weight.to(device),
                "mask": torch.as_tensor(s.mask).to(device),
                "free": (~torch.as_tensor(s.constrained())).to(device),
                "steps": torch.as_tensor(s.steps).to(device),
            }
        return cache[key]

    # ---------------------------------------------------------------- starting states
    def _start(self, model, starts: list) -> State:
        s = self.series
        st = s.start_state(model, batch=len(starts))
        x, v = st.x, st.v
        if all(i == 0 for i in starts):
            return State(x, v, t=0.0)
        d = self._data(model.device)
        idx = torch.tensor(starts, device=model.device)
        obs, w = d["obs"][idx], d["mask"][idx].unsqueeze(1)
        later = (idx > 0).view(-1, 1, 1, 1, 1)
        use = w & later & d["free"]
        x = torch.where(use, obs, x)
        tab = s.tables(dtype=model.dtype, device=model.device)
        if tab["drag"] is not None:  # boundary: known prescribed positions
            steps = d["steps"][idx]
            x = torch.where(tab["drag_mask"], tab["drag"][steps], x)
        if self.smooth:
            xs, dv, ok = self._smoothed(starts, d)
            x = torch.where(use & ok, xs, x)
        if self.velocity == "difference":
            prev = (idx - 1).clamp_min(0)
            both = use & d["mask"][prev].unsqueeze(1)
            if not self.smooth:
                dv, ok = (obs - d["obs"][prev]) / (self.every * s.dt), both
            v = torch.where(use & ok, dv, v)
            if tab["drag"] is not None:
                steps = d["steps"][idx]
                vd = (tab["drag"][steps] - tab["drag"][(steps - 1).clamp_min(0)]) / s.dt
                v = torch.where(tab["drag_mask"] & later, vd, v)
        return State(x, v, t=0.0)

    def _smoothed(self, starts: list, data: dict):
        """Savitzky-Golay start states for noisy data.

        A quadratic fitted by least squares to the observations ``i - smooth .. i + smooth``
        (clipped to the series) gives the position ``a`` and, with ``b`` and ``c`` its first
        coefficients, the symplectic-Euler velocity ``b - c dt`` (the backward difference of the
        fitted path). Returns ``(x, v, ok)`` with ``ok`` False where a node is unobserved
        somewhere in the stencil. ``data``: :meth:`_data` on the device of the rollout.
        """
        h, E, dt = self.smooth, self.every, self.series.dt
        xs, vs, oks = [], [], []
        obs, mask = data["obs"], data["mask"]
        for i in starts:
            j = np.arange(max(0, i - h), min(self.T - 1, i + h) + 1)
            tau = (j - i) * E * dt
            V = np.stack([np.ones_like(tau), tau, tau**2], 1)
            W = torch.as_tensor(np.linalg.pinv(V), dtype=self.dtype, device=obs.device)  # (3, len(j))
            o = obs[int(j[0]) : int(j[-1]) + 1]  # the observations j (consecutive)
            a = torch.einsum("j,j...->...", W[0], o)
            b = torch.einsum("j,j...->...", W[1], o)
            c = torch.einsum("j,j...->...", W[2], o)
            xs.append(a)
            vs.append(b - c * dt)
            oks.append(mask[int(j[0]) : int(j[-1]) + 1].all(0)[None])
        return torch.stack(xs), torch.stack(vs), torch.stack(oks)

    # ---------------------------------------------------------------- rollouts
    def _segment(self, model, x, v, n0: torch.Tensor, length: int, offset: int, targets, weights):
        """``length`` steps from per-entry steps ``n0 + offset``; loss at every observation step."""
        loss = x.new_zeros(())
        for j in range(length):
            n = (n0 + offset + j).clamp_max(self.last_step)
            x, v = self._step(model, x, v, n)
            local = offset + j + 1
            if local % self.every == 0:
                k = local // self.every - 1
                loss = loss + (((x - targets[:, k]) ** 2) * weights[:, k]).sum()
        return x, v, loss

    def _advance(self, model, x, v, n):
        """One step of the series from per-entry steps ``n``: ``(x, v)`` at ``n + 1``.

        The series' loads and drags are indexed by step, so the state's time is not needed
        (and a time that changed every call would make the compiled step recompile).
        """
        st = self.series.advance(model, State(x, v, t=0.0), n, integrator=self.integrator)
        return st.x, st.v

    def _step(self, model, x, v, n):
        """:meth:`_advance`, compiled with ``engine="compiled"``."""
        if self._compiled is not None:
            try:
                return self._compiled(model, x, v, n)
            except Exception as e:
                from .._compile import warn_fallback

                self._compiled = None
                first = (str(e).strip().splitlines() or [""])[0][:160]
                warn_fallback(f"{type(e).__name__}: {first}", what="the eager rollout")
        return self._advance(model, x, v, n)

    def _window_loss(self, model, state: State, starts: list):
        """Loss of the windows starting at observation indices ``starts`` (one batch)."""
        K, E = self.K, self.every
        d = self._data(model.device)
        idx = torch.tensor(starts, device=model.device)
        obs_idx = idx.view(-1, 1) + torch.arange(1, K + 1, device=model.device).view(1, -1)  # (B, K)
        valid = (obs_idx <= self.T - 1).to(self.dtype).view(len(starts), K, 1, 1, 1, 1)
        obs_idx = obs_idx.clamp_max(self.T - 1)
        targets = d["obs"][obs_idx]  # (B, K, 3, D, H, W)
        weights = d["weight"][obs_idx] * valid  # (B, K, 1, D, H, W)
        n0 = d["steps"][idx]  # on the model's device: the steps index the load tables there
        total = K * E
        seg = self.checkpoint or total
        x, v = state.x, state.v
        loss = x.new_zeros(())
        for off in range(0, total, seg):
            length = min(seg, total - off)
            if self.checkpoint is not None and torch.is_grad_enabled():
                # reentrant checkpointing runs the segment's forward without building a graph
                # (the non-reentrant kind still records every autograd node, which for small
                # bodies is most of the memory); the parameters go in as explicit inputs and
                # the segment rebuilds its model from them
                k, c, m = model.stiffness, model.damping, model.mass

                def segment(x, v, k, c, m, off=off, length=length):
                    sub = self.series.model(k, c, m, dtype=model.dtype, device=model.device)
                    return self._segment(sub, x, v, n0, length, off, targets, weights)

                x, v, part = _checkpoint(segment, x, v, k, c, m, use_reentrant=True)
            else:
                x, v, part = self._segment(model, x, v, n0, length, off, targets, weights)
            loss = loss + part
        return loss, State(x, v, t=0.0)

    def __call__(self, params, windows=None) -> torch.Tensor:
        """The loss, a 0-d tensor.

        Args:
            params: a :class:`Parameters` (or a model) to simulate with.
            windows: indices of the windows to include (a stochastic subset), or None (all).
        """
        model = params.model() if isinstance(params, Parameters) else params
        chosen = self.starts if windows is None else [self.starts[int(i)] for i in windows]
        if self.velocity != "carry":
            loss, _ = self._window_loss(model, self._start(model, chosen), chosen)
            return loss * self.scale
        # in sequence: reset observed free positions at each window start, carry the rest
        state = self.series.start_state(model)
        total = state.x.new_zeros(())
        d = self._data(model.device)
        for i in self.starts:
            if i > 0:
                w = d["mask"][i][None, None] & d["free"]
                state = State(torch.where(w, d["obs"][i : i + 1], state.x), state.v, t=0.0)
            loss, state = self._window_loss(model, state, [i])
            if i in chosen:
                total = total + loss
            if self.detach:
                state = state.detach()
        return total * self.scale
