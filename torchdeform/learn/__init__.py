"""Learning physical parameters from time series (Radetzky's recurrent network, with autograd).

Radetzky (2003, §2.3) trained a recurrent network that *is* the mass-spring system: its
weights are ``1/m``, ``c`` and ``d``. Here the simulator itself is differentiated:

* :class:`SpringParameter` / :class:`NodeParameter`: positive parameters through a ``log``
  or ``softplus`` transform, **shared** (one value), per direction **class**, per **region**
  (node labels; springs between regions take the harmonic mean) or per **spring**
  (``(S, D, H, W)``, masked); masses shared or per node. :class:`Parameters` bundles the
  learned and the fixed ones and builds a :class:`~torchdeform.sim.model.Model`.
* :class:`WindowLoss`: the loss of rollouts over a :class:`~torchdeform.learn.series.Series`.
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

Modules: :mod:`.series` (series and their files), :mod:`.synthetic` (generators),
:mod:`.parameters`, :mod:`.loss`, :mod:`.trainer`, :mod:`.reports`, :mod:`.commands`
(``torchdeform data`` and the frame of the training scripts).

Example:
    >>> from torchdeform import learn
    >>> series = learn.radetzky_cube(springs=70, steps=100)          # the first 100 of its 250 steps
    >>> params = learn.Parameters(series, stiffness=learn.SpringParameter.like(series, init=30.0),
    ...                           damping=learn.SpringParameter.like(series, init=0.04),
    ...                           mass=series.truth["mass"])
    >>> loss = learn.WindowLoss(series, window=10)
    >>> trainer = learn.Trainer(params, loss, optimizer="lbfgs", iterations=30, tol=1e-12, progress=False)
    >>> history = trainer.run()
    >>> trainer.stopped, len(history) < 30
    ('loss <= tol (1e-12)', True)
    >>> round(params.summary()["stiffness"], 3), round(params.summary()["damping"], 4)
    (10.0, 0.1)
"""

from .commands import run_script
from .loss import LOSS_ENGINES, WindowLoss
from .parameters import (
    SHARING,
    TRANSFORMS,
    FuzzySprings,
    NodeParameter,
    Parameters,
    Positive,
    SpringParameter,
    expand_spring_param,
    from_raw,
    node_to_springs,
    to_raw,
)
from .reports import (
    active_springs,
    curvature_report,
    history_dicts,
    plot_history,
    plot_scan,
    plot_spread,
    relative_error,
    spread_report,
)
from .series import FORMAT, Series, load_series
from .static import POISSON_LIMITS, ElasticRegions, LoadCase, StaticLoss, face_traction, roller_faces
from .synthetic import (
    SPRING_SETS,
    balloon_series,
    cube_grid,
    cube_series,
    inclusion_regions,
    indentation,
    layered_regions,
    per_spring_start,
    radetzky_cube,
)
from .trainer import Record, Trainer

__all__ = [
    "Series",
    "load_series",
    "FORMAT",
    "radetzky_cube",
    "per_spring_start",
    "cube_series",
    "balloon_series",
    "cube_grid",
    "indentation",
    "layered_regions",
    "inclusion_regions",
    "SPRING_SETS",
    "Positive",
    "SpringParameter",
    "NodeParameter",
    "FuzzySprings",
    "Parameters",
    "to_raw",
    "from_raw",
    "node_to_springs",
    "expand_spring_param",
    "TRANSFORMS",
    "SHARING",
    "WindowLoss",
    "LOSS_ENGINES",
    "Trainer",
    "Record",
    "active_springs",
    "relative_error",
    "spread_report",
    "curvature_report",
    "plot_history",
    "plot_scan",
    "plot_spread",
    "history_dicts",
    "run_script",
    "LoadCase",
    "StaticLoss",
    "ElasticRegions",
    "face_traction",
    "roller_faces",
    "POISSON_LIMITS",
]
