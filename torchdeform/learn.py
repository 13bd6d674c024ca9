"""Learning physical parameters from time series (Radetzky's recurrent network, with autograd).

Radetzky (2003, §2.3) trained a recurrent network that *is* the mass-spring system: its
weights are ``1/m``, ``c`` and ``d``. Here the simulator itself is differentiated:

* :class:`SpringParameter` / :class:`NodeParameter`: positive parameters through a ``log``
  or ``softplus`` transform, **shared** (one value), per direction **class**, per **region**
  (node labels; springs between regions take the harmonic mean) or per **spring**
  (``(S, D, H, W)``, masked); masses shared or per node. :class:`Parameters` bundles the
  learned and the fixed ones and builds a :class:`~torchdeform.model.Model`.
* :class:`WindowLoss`: the loss of rollouts over a :class:`~torchdeform.data.Series`.
  **Teacher forcing** restarts every ``window`` observation intervals from the observed
  state (multiple shooting, REFERENCE §4.4); the windows run as one batch. ``window=None`` is
  full back-propagation through time from the initial state; ``checkpoint=k`` recomputes
  the forward pass of every ``k``-step segment in the backward pass
  (:func:`torch.utils.checkpoint.checkpoint`, reentrant: no graph is recorded inside a
  segment), so memory grows with ``T / k + k`` instead of ``T``; the loss must then be
  differentiated with ``.backward()`` (not ``torch.autograd.grad``). Missing observations are masked; ``velocity="carry"`` runs the windows in
  sequence, resetting only the observed positions and carrying the simulated velocities
  (partial observation, sparse snapshots).
* :class:`Trainer`: Adam or L-BFGS, gradient-norm clipping (Adam), early stopping, random
  window subsets, a tqdm bar, checkpoint and resume (bitwise identical to an uninterrupted
  run on the CPU with the same seed), :func:`plot_history`.
* :func:`spread_report` and :func:`curvature_report`: the identifiability report of
  per-spring fits (how far the recovered values spread, and how many parameter directions
  the data do not determine).

The loss is dimensionless: the mean squared position error over the observed node
coordinates, divided by the mean squared displacement of the observations from rest
(``RMS(o - X)^2``). Radetzky's ``E = sum_t 1/2 sum_p |p_p(t) - o_p(t)|^2`` is
``0.5 * loss * ref^2 * count`` (:attr:`WindowLoss.ref`, :attr:`WindowLoss.count`).

Window starting velocity (the source is silent, §4.4): ``"difference"`` uses the backward
difference of the observations, ``(o_i - o_{i-1}) / (every dt)``, which for
``every = 1`` *is* the velocity of symplectic Euler (``x_{n+1} = x_n + dt v_{n+1}``);
``"zero"`` starts at rest (quasi-static data); ``"carry"`` keeps the simulated velocity.
The first window starts from the series' known initial state (rest).

Example:
    >>> from torchdeform import data, learn
    >>> series = data.radetzky_cube(springs=70)
    >>> params = learn.Parameters(series, stiffness=learn.SpringParameter.like(series, 30.0),
    ...                           damping=learn.SpringParameter.like(series, 0.04),
    ...                           mass=series.truth["mass"])
    >>> loss = learn.WindowLoss(series, window=10)
    >>> trainer = learn.Trainer(params, loss, optimizer="lbfgs", iterations=30)
    >>> history = trainer.run()
    >>> params.summary()["stiffness"]              # ~10.0
"""
from __future__ import annotations

import json
import math
import pickle
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.utils.checkpoint import checkpoint as _checkpoint
from tqdm.auto import tqdm

from .data import Series, node_to_springs
from .errors import ConfigError, TorchdeformError
from .integrators import INTEGRATORS
from .model import State

TRANSFORMS = ("log", "softplus")
_BLOWUP = 1e30            # the loss L-BFGS sees at trial points where the simulation diverged
SHARING = ("shared", "class", "region", "spring")


# ------------------------------------------------------------------- transforms
def to_raw(value: torch.Tensor, transform: str) -> torch.Tensor:
    """Inverse of :func:`from_raw`: the unconstrained number for a positive ``value``."""
    if transform == "log":
        return torch.log(value)
    return torch.where(value > 20, value, torch.log(torch.expm1(value)))


def from_raw(raw: torch.Tensor, transform: str) -> torch.Tensor:
    """Positive value of an unconstrained ``raw`` tensor: ``exp`` or ``softplus``."""
    return torch.exp(raw) if transform == "log" else nn.functional.softplus(raw)


def _check(key, value, allowed):
    if value not in allowed:
        raise ConfigError(key, f"one of {', '.join(allowed)}", value)


class Positive(nn.Module):
    """A learnable tensor of positive values, ``value = scale * T(raw)`` with ``T`` = exp or
    softplus (``scale`` makes softplus well-conditioned for values far from 1).

    Args:
        init: positive initial values (any shape).
        transform: ``"log"`` or ``"softplus"``.
    """

    def __init__(self, init, transform: str = "log", dtype=torch.float64):
        super().__init__()
        _check("transform", transform, TRANSFORMS)
        init = torch.as_tensor(init, dtype=dtype).clone()
        if not bool(torch.isfinite(init).all()) or bool((init <= 0).any()):
            raise ConfigError("init", "finite values > 0", init.flatten()[:5].tolist())
        self.transform = transform
        scale = float(init.abs().mean()) if transform == "softplus" else 1.0
        self.register_buffer("scale", torch.tensor(scale, dtype=dtype))
        self.raw = nn.Parameter(to_raw(init / scale, transform))

    def forward(self) -> torch.Tensor:
        return self.scale * from_raw(self.raw, self.transform)


class SpringParameter(nn.Module):
    """A learned spring parameter (stiffness or damping).

    Args:
        grid: the grid; spring_mask: bool ``(S, D, H, W)`` of existing springs (or None).
        init: initial value(s): a number (broadcast to every learned value), or a tensor of
            the learned shape (below).
        sharing: ``"shared"`` (one value, shape ``(1,)``), ``"class"`` (one per direction class
            present: axis/face/body, ``(C,)``), ``"region"`` (one per region label, ``(R,)``;
            needs ``regions``), ``"spring"`` (one per existing spring, ``(n_springs,)``).
        regions: int node labels ``(D, H, W)`` with values ``0 .. R-1`` (``"region"`` only).
        transform: ``"log"`` or ``"softplus"``.

    Calling it returns the per-spring tensor ``(S, D, H, W)`` (zero where no spring exists).
    """

    def __init__(self, grid, spring_mask=None, init=1.0, sharing: str = "shared", regions=None,
                 transform: str = "log", dtype=torch.float64):
        super().__init__()
        _check("sharing", sharing, SHARING)
        self.grid, self.sharing = grid, sharing
        mask = grid.spring_mask() if spring_mask is None else torch.as_tensor(spring_mask, dtype=torch.bool)
        self.register_buffer("mask", mask, persistent=False)
        if sharing == "shared":
            n = 1
        elif sharing == "class":
            classes = grid.direction_class()
            self.classes = sorted(set(classes), key=["axis", "face", "body"].index)
            self.register_buffer("class_index", torch.tensor([self.classes.index(c) for c in classes]),
                                 persistent=False)
            n = len(self.classes)
        elif sharing == "region":
            if regions is None:
                raise ConfigError("regions", "node labels (D, H, W) for sharing='region'", None, show_got=True)
            lab = torch.as_tensor(np.asarray(regions), dtype=torch.long)
            if tuple(lab.shape) != grid.shape or int(lab.min()) < 0:
                raise ConfigError("regions", f"labels >= 0 of shape {grid.shape}", tuple(lab.shape))
            self.register_buffer("regions", lab, persistent=False)
            n = int(lab.max()) + 1
        else:
            n = int(mask.sum())
        init = torch.as_tensor(init, dtype=dtype)
        if init.dim() == 0:
            init = init.expand(n)
        if tuple(init.shape) != (n,):
            raise ConfigError("init", f"a number or {n} values for sharing={sharing!r}", tuple(init.shape))
        self.value = Positive(init, transform, dtype)

    @classmethod
    def like(cls, series: Series, init=1.0, sharing: str = "shared", transform: str = "log"):
        """A parameter on the grid and springs of ``series`` (regions from its truth, if any)."""
        return cls(series.grid, series.spring_mask_tensor(), init, sharing,
                   series.truth.get("regions"), transform)

    def values(self) -> torch.Tensor:
        """The learned values, ``(n,)``."""
        return self.value()

    def forward(self) -> torch.Tensor:
        v = self.value()
        dtype = v.dtype
        mask = self.mask.to(dtype)
        if self.sharing == "shared":
            return v[0] * mask
        if self.sharing == "class":
            return v[self.class_index].view(-1, 1, 1, 1) * mask
        if self.sharing == "region":
            return node_to_springs(v[self.regions], self.grid, self.mask)
        out = torch.zeros(self.mask.shape, dtype=dtype, device=v.device)
        return out.masked_scatter(self.mask, v)

    def per_spring(self, tensor: torch.Tensor) -> torch.Tensor:
        """The existing springs' entries of a ``(S, D, H, W)`` tensor, ``(n_springs,)``, in the
        order of ``sharing="spring"`` values."""
        return torch.as_tensor(tensor)[self.mask]


class NodeParameter(nn.Module):
    """A learned node mass: ``"shared"`` (one value) or ``"node"`` (one per node ``(D, H, W)``).
    Calling it returns ``(D, H, W)``."""

    def __init__(self, grid, init=1.0, sharing: str = "shared", transform: str = "log", dtype=torch.float64):
        super().__init__()
        _check("sharing", sharing, ("shared", "node"))
        self.grid, self.sharing = grid, sharing
        n = 1 if sharing == "shared" else grid.num_nodes
        init = torch.as_tensor(init, dtype=dtype)
        if init.dim() == 0:
            init = init.expand(n)
        init = init.reshape(-1)
        if init.shape[0] == math.prod(grid.shape) and n != init.shape[0]:
            init = init[grid.nodes().reshape(-1)]
        if tuple(init.shape) != (n,):
            raise ConfigError("init", f"a number or {n} values for sharing={sharing!r}", tuple(init.shape))
        self.register_buffer("nodes", grid.nodes(), persistent=False)
        self.value = Positive(init, transform, dtype)

    def values(self) -> torch.Tensor:
        return self.value()

    def forward(self) -> torch.Tensor:
        v = self.value()
        if self.sharing == "shared":
            return v[0] * self.nodes.to(v.dtype)
        return torch.zeros(self.grid.shape, dtype=v.dtype).masked_scatter(self.nodes, v)


class FuzzySprings(nn.Module):
    """Stiffness and damping from a fuzzy system (Radetzky's shape modeler), learnable
    through its inputs (slider values) or its membership functions.

    The body is one tissue: the system is evaluated once and its outputs set every spring.

    Args:
        fis: a :class:`~torchdeform.fuzzy.MamdaniSystem` (e.g. ``fuzzy.load_preset("susilap_g")``).
        inputs: ``{input name: value}`` (the sliders).
        outputs: ``{"stiffness": output name, "damping": output name}``.
        scale: ``{"stiffness": factor, "damping": factor}``: simulator units per fuzzy output unit.
        learn: ``"inputs"`` (sliders, kept inside each input's range by a sigmoid),
            ``"membership"`` (the output variables' membership parameters) or ``"both"``.
        grid, spring_mask: where the springs are.

    Use :meth:`part` to plug it into :class:`Parameters`::

        fs = FuzzySprings(fis, {"consistency": 7.0}, grid=series.grid, spring_mask=series.spring_mask_tensor())
        params = Parameters(series, fs.part("stiffness"), fs.part("damping"), mass)
    """

    def __init__(self, fis, inputs: dict, outputs=None, scale=None, learn: str = "inputs", grid=None,
                 spring_mask=None):
        super().__init__()
        _check("learn", learn, ("inputs", "membership", "both"))
        self.fis = fis.double()
        self.outputs = dict(outputs or {"stiffness": "spring_const", "damping": "viscosity"})
        self.scale = dict(scale or {})
        names = self.fis.input_names()
        if set(inputs) != set(names):
            raise ConfigError("inputs", f"a value for each input ({', '.join(names)})", sorted(inputs))
        for role, out in self.outputs.items():
            if out not in self.fis.output_names():
                raise ConfigError(f"outputs.{role}", f"an output of {self.fis.name} "
                                                     f"({', '.join(self.fis.output_names())})", out)
        self.fis.requires_grad_(False)
        if learn in ("membership", "both"):
            for v in self.fis.outputs:
                if v.name in self.outputs.values():
                    v.requires_grad_(True)
        lo = torch.tensor([float(v.range[0]) for v in self.fis.inputs], dtype=torch.float64)
        hi = torch.tensor([float(v.range[1]) for v in self.fis.inputs], dtype=torch.float64)
        self.register_buffer("lo", lo)
        self.register_buffer("hi", hi)
        x = torch.tensor([float(inputs[n]) for n in names], dtype=torch.float64)
        if bool(((x <= lo) | (x >= hi)).any()):
            raise ConfigError("inputs", "values strictly inside each input's range", inputs)
        u = (x - lo) / (hi - lo)
        self.raw_inputs = nn.Parameter(torch.log(u / (1 - u)), requires_grad=learn in ("inputs", "both"))
        self.grid = grid
        mask = grid.spring_mask() if spring_mask is None else torch.as_tensor(spring_mask, dtype=torch.bool)
        self.register_buffer("mask", mask, persistent=False)

    def inputs(self) -> torch.Tensor:
        """Current slider values ``(n_inputs,)``."""
        return self.lo + (self.hi - self.lo) * torch.sigmoid(self.raw_inputs)

    def forward(self) -> dict:
        """``{role: value}`` in simulator units (0-d tensors)."""
        y = self.fis(self.inputs()[None])[0]
        names = self.fis.output_names()
        return {role: y[names.index(out)] * float(self.scale.get(role, 1.0)) for role, out in self.outputs.items()}

    def part(self, role: str) -> nn.Module:
        """A module returning the per-spring tensor ``(S, D, H, W)`` of ``role``."""
        return _FuzzyPart(self, role)


class _FuzzyPart(nn.Module):
    def __init__(self, source: FuzzySprings, role: str):
        super().__init__()
        self.source, self.role = source, role

    def values(self) -> torch.Tensor:
        return self.source()[self.role].reshape(1)

    def forward(self) -> torch.Tensor:
        return self.source()[self.role] * self.source.mask.to(torch.float64)


class Parameters(nn.Module):
    """Learned and fixed parameters of a series' model.

    Args:
        series: the :class:`~torchdeform.data.Series` (grid, springs, constraints).
        stiffness, damping: a :class:`SpringParameter` (learned) or fixed values (a number or
            ``(S, D, H, W)``).
        mass: a :class:`NodeParameter` (learned) or fixed kg per node (a number or ``(D, H, W)``).
    """

    def __init__(self, series: Series, stiffness, damping, mass, dtype=torch.float64):
        super().__init__()
        self.series, self.dtype = series, dtype
        self.learned = nn.ModuleDict()
        self.fixed = {}
        for name, value in (("stiffness", stiffness), ("damping", damping), ("mass", mass)):
            if isinstance(value, nn.Module):
                self.learned[name] = value
            else:
                self.fixed[name] = torch.as_tensor(np.asarray(value, dtype=np.float64)
                                                   if not torch.is_tensor(value) else value).to(dtype)

    def physical(self) -> dict:
        """``{"stiffness": (S, D, H, W) or number, "damping": ..., "mass": (D, H, W) or number}``."""
        out = dict(self.fixed)
        for name, mod in self.learned.items():
            out[name] = mod()
        return out

    def model(self):
        """The :class:`~torchdeform.model.Model` with the current values (differentiable)."""
        p = self.physical()
        return self.series.model(p["stiffness"], p["damping"], p["mass"], self.dtype)

    def summary(self) -> dict:
        """Learned values as plain Python: a float for one value, else a list."""
        out = {}
        for name, mod in self.learned.items():
            v = mod.values().detach().cpu().numpy()
            out[name] = float(v[0]) if v.size == 1 else v.tolist()
        return out


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

    Call with a :class:`Parameters` (or a model) and optionally ``windows`` (a LongTensor of
    window indices, for stochastic subsets) to get a 0-d loss tensor.
    """

    def __init__(self, series: Series, window: int | None = 10, velocity: str = "difference",
                 checkpoint: int | None = None, detach: bool = True, integrator=None, smooth: int = 0,
                 dtype=torch.float64):
        _check("velocity", velocity, ("difference", "zero", "carry"))
        self.series, self.velocity, self.dtype, self.detach = series, velocity, dtype, bool(detach)
        steps = np.asarray(series.steps)
        T = len(steps)
        E = series.every
        if T < 2 or (np.diff(steps) != E).any():
            raise ConfigError("series.steps", "evenly spaced observation steps (resample the series first)",
                              steps[:6].tolist())
        if window is not None and int(window) < 1:
            raise ConfigError("window", "an integer >= 1 (observation intervals) or None", window)
        if checkpoint is not None and int(checkpoint) < 1:
            raise ConfigError("checkpoint", "an integer >= 1 (steps per segment) or None", checkpoint)
        self.K = T - 1 if window is None else min(int(window), T - 1)
        self.every, self.T = E, T
        self.checkpoint = None if checkpoint is None else int(checkpoint)
        self.integrator = integrator or INTEGRATORS[series.integrator]()
        self.obs = torch.as_tensor(series.positions, dtype=dtype)                 # (T, 3, D, H, W)
        free = ~torch.as_tensor(series.constrained())
        self.weight = (torch.as_tensor(series.mask) & free).to(dtype).unsqueeze(1)  # (T, 1, D, H, W)
        X = series.grid.rest_positions(dtype)
        disp = ((self.obs - X) ** 2 * self.weight).sum()
        self.count = float(self.weight.sum()) * 3
        if self.count == 0:
            raise ConfigError("series.mask", "at least one observed free node", "none", show_got=True)
        self.ref = math.sqrt(max(float(disp) / self.count, 1e-300))
        self.starts = list(range(0, T - 1, self.K))                               # window start observations
        if int(smooth) < 0:
            raise ConfigError("smooth", "an integer >= 0 (half-width in observations)", smooth)
        self.smooth = int(smooth)
        # normalisation over the whole series, so a subset of windows has the same scale
        self.scale = 1.0 / (self.count * self.ref ** 2)

    @property
    def num_windows(self) -> int:
        return len(self.starts)

    # ---------------------------------------------------------------- starting states
    def _start(self, model, starts: list) -> State:
        s = self.series
        st = s.start_state(model, len(starts))
        x, v = st.x, st.v
        if all(i == 0 for i in starts):
            return State(x, v, 0.0)
        idx = torch.tensor(starts)
        obs, w = self.obs[idx], torch.as_tensor(s.mask)[idx].unsqueeze(1)
        later = torch.tensor([i > 0 for i in starts]).view(-1, 1, 1, 1, 1)
        free = ~torch.as_tensor(s.constrained())
        use = w & later & free
        x = torch.where(use, obs, x)
        tab = s.tables(model.dtype, model.device)
        if tab["drag"] is not None:                                # boundary: known prescribed positions
            steps = torch.as_tensor(s.steps)[idx]
            x = torch.where(tab["drag_mask"], tab["drag"][steps], x)
        if self.smooth:
            xs, dv, ok = self._smoothed(starts)
            x = torch.where(use & ok, xs, x)
        if self.velocity == "difference":
            prev = (idx - 1).clamp_min(0)
            both = use & torch.as_tensor(s.mask)[prev].unsqueeze(1)
            if not self.smooth:
                dv, ok = (obs - self.obs[prev]) / (self.every * s.dt), both
            v = torch.where(use & ok, dv, v)
            if tab["drag"] is not None:
                steps = torch.as_tensor(s.steps)[idx]
                vd = (tab["drag"][steps] - tab["drag"][(steps - 1).clamp_min(0)]) / s.dt
                v = torch.where(tab["drag_mask"] & later, vd, v)
        return State(x, v, 0.0)

    def _smoothed(self, starts: list):
        """Savitzky-Golay start states for noisy data: a quadratic fitted by least squares to
        the observations ``i - smooth .. i + smooth`` (clipped to the series) gives the
        position ``a`` and, with ``b`` and ``c`` its first coefficients, the symplectic-Euler
        velocity ``b - c dt`` (the backward difference of the fitted path). Returns
        ``(x, v, ok)`` with ``ok`` False where a node is unobserved somewhere in the stencil."""
        h, E, dt = self.smooth, self.every, self.series.dt
        xs, vs, oks = [], [], []
        mask = torch.as_tensor(self.series.mask)
        for i in starts:
            j = np.arange(max(0, i - h), min(self.T - 1, i + h) + 1)
            tau = (j - i) * E * dt
            V = np.stack([np.ones_like(tau), tau, tau ** 2], 1)
            W = torch.as_tensor(np.linalg.pinv(V), dtype=self.dtype)          # (3, len(j))
            o = self.obs[torch.as_tensor(j)]
            a = torch.einsum("j,j...->...", W[0], o)
            b = torch.einsum("j,j...->...", W[1], o)
            c = torch.einsum("j,j...->...", W[2], o)
            xs.append(a)
            vs.append(b - c * dt)
            oks.append(mask[torch.as_tensor(j)].all(0)[None])
        return torch.stack(xs), torch.stack(vs), torch.stack(oks)

    # ---------------------------------------------------------------- rollouts
    def _segment(self, model, x, v, n0: torch.Tensor, length: int, offset: int, targets, weights):
        """``length`` steps from per-entry steps ``n0 + offset``; loss at every observation step."""
        s = self.series
        loss = x.new_zeros(())
        st = State(x, v, 0.0)
        for j in range(length):
            n = (n0 + offset + j).clamp_max(s.num_steps)
            st = s.advance(model, st, n, self.integrator)
            local = offset + j + 1
            if local % self.every == 0:
                k = local // self.every - 1
                loss = loss + (((st.x - targets[:, k]) ** 2) * weights[:, k]).sum()
        return st.x, st.v, loss

    def _window_loss(self, model, state: State, starts: list):
        """Loss of the windows starting at observation indices ``starts`` (one batch)."""
        K, E = self.K, self.every
        idx = torch.tensor(starts)
        obs_idx = (idx.view(-1, 1) + torch.arange(1, K + 1).view(1, -1))         # (B, K)
        valid = (obs_idx <= self.T - 1).to(self.dtype).view(len(starts), K, 1, 1, 1, 1)
        obs_idx = obs_idx.clamp_max(self.T - 1)
        targets = self.obs[obs_idx]                                              # (B, K, 3, D, H, W)
        weights = self.weight[obs_idx] * valid                                  # (B, K, 1, D, H, W)
        n0 = torch.as_tensor(self.series.steps)[idx]
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
                    sub = self.series.model(k, c, m, model.dtype, model.device)
                    return self._segment(sub, x, v, n0, length, off, targets, weights)
                x, v, part = _checkpoint(segment, x, v, k, c, m, use_reentrant=True)
            else:
                x, v, part = self._segment(model, x, v, n0, length, off, targets, weights)
            loss = loss + part
        return loss, State(x, v, 0.0)

    def __call__(self, params, windows=None) -> torch.Tensor:
        model = params.model() if isinstance(params, Parameters) else params
        chosen = self.starts if windows is None else [self.starts[int(i)] for i in windows]
        if self.velocity != "carry":
            loss, _ = self._window_loss(model, self._start(model, chosen), chosen)
            return loss * self.scale
        # in sequence: reset observed free positions at each window start, carry the rest
        state = self.series.start_state(model)
        total = state.x.new_zeros(())
        s = self.series
        free = ~torch.as_tensor(s.constrained())
        for i in self.starts:
            if i > 0:
                w = torch.as_tensor(s.mask)[i][None, None] & free
                state = State(torch.where(w, self.obs[i:i + 1], state.x), state.v, 0.0)
            loss, state = self._window_loss(model, state, [i])
            if i in chosen:
                total = total + loss
            if self.detach:
                state = state.detach()
        return total * self.scale


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
        params, loss: what to learn, and from what.
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
    """

    def __init__(self, params: Parameters, loss: WindowLoss, optimizer: str = "adam", lr: float | None = None,
                 iterations: int = 200, clip: float | None = 10.0, windows_per_step: int | None = None,
                 patience: int = 50, min_delta: float = 1e-4, tol: float = 0.0, seed: int = 0,
                 checkpoint_path=None, checkpoint_every: int = 0, progress: bool = True, lbfgs_inner: int = 20):
        _check("optimizer", optimizer, ("adam", "lbfgs"))
        self.params, self.loss, self.kind = params, loss, optimizer
        self.iterations, self.clip, self.patience, self.min_delta = int(iterations), clip, int(patience), float(min_delta)
        self.tol, self.progress = float(tol), progress
        self.windows_per_step = windows_per_step
        if windows_per_step is not None and optimizer == "lbfgs":
            raise ConfigError("windows_per_step", "None with L-BFGS (it needs one fixed objective)", windows_per_step)
        self.checkpoint_path = None if checkpoint_path is None else Path(checkpoint_path)
        self.checkpoint_every = int(checkpoint_every)
        self.generator = torch.Generator().manual_seed(int(seed))
        learnable = [p for p in params.parameters() if p.requires_grad]
        if not learnable:
            raise ConfigError("params", "at least one learned parameter", "none", show_got=True)
        if optimizer == "adam":
            self.opt = torch.optim.Adam(learnable, lr=0.05 if lr is None else lr)
        else:
            self.opt = torch.optim.LBFGS(learnable, lr=1.0 if lr is None else lr, max_iter=int(lbfgs_inner),
                                         tolerance_grad=1e-12, tolerance_change=1e-15, history_size=20,
                                         line_search_fn="strong_wolfe")
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
        return torch.randperm(self.loss.num_windows, generator=self.generator)[:self.windows_per_step]

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
            except ConfigError:                   # a trial step outside finite parameters
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

    def run(self, iterations: int | None = None, stop_after: int | None = None) -> list:
        """Train until ``iterations`` (total), early stopping, or ``stop_after`` iterations of
        this call (to simulate an interruption). Returns the history (list of :class:`Record`)."""
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
                with torch.no_grad():                       # keep the last finite values
                    for p, s in zip(self._learnable, snapshot):
                        p.copy_(s)
                self.stopped = "non-finite loss"
                break
            if loss < self.best * (1 - self.min_delta):
                self.best, self.since_best = loss, 0
            else:
                self.since_best += 1
            if loss <= self.tol:
                self.stopped = f"loss <= tol ({self.tol:g})"
            elif self.since_best >= self.patience:
                self.stopped = f"no improvement for {self.patience} iterations"
            if self.checkpoint_path is not None and self.checkpoint_every and \
                    self.iteration % self.checkpoint_every == 0:
                self.save(self.checkpoint_path)
        bar.close()
        return self.history

    def final_loss(self) -> float:
        """Loss at the current parameters (no gradient)."""
        with torch.no_grad():
            return float(self.loss(self.params))

    # ---------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        return {"params": self.params.state_dict(), "optimizer": self.opt.state_dict(),
                "generator": self.generator.get_state(), "iteration": self.iteration, "best": self.best,
                "since_best": self.since_best, "stopped": self.stopped, "seconds": self.seconds,
                "history": [[r.iteration, r.loss, r.grad_norm, r.seconds] for r in self.history]}

    def save(self, path) -> Path:
        """Write a resumable checkpoint (parameters, optimizer, sampling RNG, history)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        torch.save(self.state_dict(), tmp)
        tmp.replace(path)
        return path

    def load(self, path) -> "Trainer":
        """Resume from a checkpoint written by :meth:`save` (same parameters and optimizer kind)."""
        path = Path(path)
        if not path.is_file():
            raise ConfigError("checkpoint", "an existing checkpoint file", str(path))
        try:
            sd = torch.load(path, weights_only=True)
            self.params.load_state_dict(sd["params"])
            self.opt.load_state_dict(sd["optimizer"])
        except (RuntimeError, KeyError, ValueError, EOFError, pickle.UnpicklingError) as e:
            raise ConfigError("checkpoint", "a checkpoint of this parameter set and optimizer",
                              f"{path} ({type(e).__name__}: {str(e).splitlines()[0]})") from None
        self.generator.set_state(sd["generator"])
        self.iteration, self.best, self.since_best = sd["iteration"], sd["best"], sd["since_best"]
        self.stopped, self.seconds = sd["stopped"], sd["seconds"]
        self.history = [Record(int(a), b, c, d) for a, b, c, d in sd["history"]]
        return self


# ------------------------------------------------------------------- reports and plots
def active_springs(series: Series) -> torch.Tensor:
    """Bool ``(S, D, H, W)``: springs that exist and have at least one end free to move.

    A spring between two fixed (or dragged) nodes never changes length, so no data can
    determine its parameters; identifiability reports leave those out and count them."""
    from .springs import difference
    c = torch.as_tensor(series.constrained()).to(torch.float64)[None, None]
    far = c + difference(c, series.grid)[:, :, 0]
    both = (c > 0) & (far > 0)
    return series.spring_mask_tensor() & ~both[0]


def relative_error(value, truth) -> float:
    """``|value - truth| / |truth|`` for numbers."""
    return abs(float(value) - float(truth)) / abs(float(truth))


def spread_report(learned, truth) -> dict:
    """How far per-spring (or per-node) values spread around their true values.

    Args:
        learned, truth: ``(n,)`` values of the same springs.
    Returns:
        dict: ``n``; quantiles of the ratio learned/true (``min, p05, p25, median, p75, p95,
        max``); ``log_ratio_std``; ``median_rel_error``, ``max_rel_error``;
        ``within_1pct``, ``within_10pct`` (fractions); ``verdict``: "recovered" when 95 %
        are within 10 %, else "not determined by the data".
    """
    a = np.asarray(torch.as_tensor(learned).detach().cpu(), dtype=np.float64).reshape(-1)
    b = np.asarray(torch.as_tensor(truth).detach().cpu(), dtype=np.float64).reshape(-1)
    r = a / b
    rel = np.abs(r - 1)
    q = np.quantile(r, [0, 0.05, 0.25, 0.5, 0.75, 0.95, 1])
    within10 = float(np.mean(rel <= 0.1))
    return {"n": int(a.size), "ratio": dict(zip(["min", "p05", "p25", "median", "p75", "p95", "max"],
                                                 map(float, q))),
            "log_ratio_std": float(np.std(np.log(r))), "median_rel_error": float(np.median(rel)),
            "max_rel_error": float(rel.max()), "within_1pct": float(np.mean(rel <= 0.01)),
            "within_10pct": within10,
            "verdict": "recovered" if within10 >= 0.95 else "not determined by the data"}


def curvature_report(params: Parameters, loss, rel_threshold: float = 1e-6, max_params: int = 600) -> dict:
    """Eigenvalues of the loss Hessian in the transformed (log) parameters at the current values.

    Directions with curvature below ``rel_threshold * max`` are (practically) not determined
    by the data. Costs one Hessian-vector product per parameter (``max_params`` at most).

    Returns:
        dict: ``n``, ``eigenvalues`` (sorted, descending), ``condition`` (max/min of the
        positive ones), ``undetermined`` (count below the threshold).
    """
    learnable = [p for p in params.parameters() if p.requires_grad]
    n = sum(p.numel() for p in learnable)
    if n > max_params:
        return {"n": n, "skipped": f"more than {max_params} parameters"}
    val = loss(params)
    grads = torch.autograd.grad(val, learnable, create_graph=True)
    g = torch.cat([x.reshape(-1) for x in grads])
    rows = []
    for i in range(n):
        h = torch.autograd.grad(g[i], learnable, retain_graph=True, allow_unused=True)
        rows.append(torch.cat([(x if x is not None else torch.zeros_like(p)).reshape(-1)
                               for x, p in zip(h, learnable)]).detach())
    H = torch.stack(rows)
    H = 0.5 * (H + H.T)
    ev = torch.linalg.eigvalsh(H).flip(0).cpu().numpy()
    top = max(float(ev[0]), 1e-300)
    pos = ev[ev > 0]
    return {"n": n, "eigenvalues": ev.tolist(), "condition": float(pos[0] / pos[-1]) if pos.size else math.inf,
            "undetermined": int((ev < rel_threshold * top).sum()), "threshold": rel_threshold}


def plot_history(history, path, title: str = "learning curve", extra: dict | None = None) -> Path:
    """Loss against iteration (log scale) to ``path`` (PNG); ``extra``: more curves
    ``{label: (iterations, values)}``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, ax = plt.subplots(figsize=(6, 4))
    it = [r.iteration if isinstance(r, Record) else r["iteration"] for r in history]
    ls = [r.loss if isinstance(r, Record) else r["loss"] for r in history]
    ax.semilogy(it, ls, label="loss")
    for label, (x, y) in (extra or {}).items():
        ax.semilogy(x, y, label=label)
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss (relative mean squared error)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_scan(values, losses, marker_at, path, xlabel: str, marker: str = "true value", title: str = "scan",
              logx: bool = False) -> Path:
    """Loss against one scanned parameter (log loss axis), a vertical line at ``marker_at``;
    written to ``path`` (PNG). Returns the path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    (ax.loglog if logx else ax.semilogy)(values, losses, ".-")
    ax.axvline(marker_at, color="k", lw=1, label=marker)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def plot_spread(learned, truth, path, title: str = "per-spring recovery") -> Path:
    """Histogram of learned/true ratios (log scale) to ``path``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = np.asarray(torch.as_tensor(learned).detach(), dtype=np.float64) / np.asarray(torch.as_tensor(truth),
                                                                                      dtype=np.float64)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.hist(np.log10(r), bins=30)
    ax.axvline(0.0, color="k", lw=1)
    ax.set_xlabel("log10(learned / true)")
    ax.set_ylabel("springs")
    ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def history_dicts(history) -> list:
    """The history as JSON-able dicts."""
    return [{"iteration": r.iteration, "loss": r.loss, "grad_norm": r.grad_norm, "seconds": r.seconds}
            for r in history]


__all__ = ["Positive", "SpringParameter", "NodeParameter", "FuzzySprings", "Parameters", "WindowLoss", "Trainer", "Record",
           "to_raw", "from_raw", "active_springs", "spread_report", "curvature_report", "relative_error", "plot_history",
           "plot_spread", "history_dicts", "TRANSFORMS", "SHARING"]


def run_script(name: str, args, fit, summary) -> int:
    """The frame every training script shares: ``args.threads`` torch threads, the ``args.out``
    folder, wall and CPU time, ``result.json``, and one line on stderr (exit status 2) for a
    :class:`~torchdeform.errors.TorchdeformError`.

    ``fit(args, out) -> dict`` does the work and returns the result; ``summary(result) -> str``
    is printed at the end (the result then also holds ``wall_seconds``, ``cpu_seconds`` and
    ``threads``). Returns the exit status.
    """
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        result = fit(args, out)
    except TorchdeformError as e:
        print(f"{name}: {e}", file=sys.stderr)
        return 2
    result.update(wall_seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0, threads=args.threads)
    (out / "result.json").write_text(json.dumps(result, indent=1))
    print(summary(result))
    return 0
