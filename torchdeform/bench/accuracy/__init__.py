"""``torchdeform bench accuracy``: error against run time of every integrator.

Each *case* is one scene x one method x one parameter; it gives one row with the common
columns ``scene, method, param, dt, steps, error, wall_s, status`` (and a few more). Methods
are entries of :data:`~.methods.METHODS`; a new method (ChainMail against mass-spring,
inverse-warp iterations ...) is one more entry that says which scenes it applies to, which parameters it
sweeps and how one run is computed and compared with the scene's reference.

Scenes (:data:`~.scenes.SCENES`; cubes of side 4 cm, ``n^3`` nodes, 26 neighbours, 1000 kg/m^3,
float64):

=============  ==============================================================================
load           bottom face fixed, a traction of (-100, 100, 0) Pa on the top face from t = 0
               (a step load), damped; run to about the first peak of the response
stiff          the same cube 100x stiffer, the load ramped in over the whole run: slow loading
               of a stiff body, where the explicit stability bound is tiny and implicit Euler
               can take steps far above it
drag           bottom face fixed, the central top patch dragged sideways 4 mm along a path
               (:class:`~torchdeform.sim.forces.Drag`), then held
supports       "falling onto fixed supports": the cube is released from rest under gravity held
               only by four fixed support nodes on its bottom face (posts fixed from t = 0); it
               drops and sags onto them. The supports stay fixed nodes, a smooth problem whose
               errors show each integrator's order; a contact with static obstacles
               (:mod:`torchdeform.interact`, a fixed tool) is not smooth and is tested there
load-static    the ``load`` cube at equilibrium, at several resolutions (the resolution sweep)
=============  ==============================================================================

Reference and error. A dynamic scene's reference is RK4 at a step of ``rk4 bound / ref_div``
(default 20), checked by halving: RK4 at twice that step is also run and their difference is
reported (RK4 is 4th order, so the reference's own error is about 1/15 of it). The error of
a run is the largest node position error over the output times ``T/4, T/2, 3T/4, T``,
divided by the largest node displacement of the reference over the same times:
``max_{t, node} |x - x_ref| / max_{t, node} |x_ref - X|``. Every time step is a multiple of a
stability bound from :func:`~torchdeform.sim.stability.time_step_bound` (power iteration): each
explicit integrator's own bound, the symplectic Euler bound for implicit Euler (whose own bound
is infinite). The step is then shrunk so that a whole number of steps lands on every output
time; ``dt_bound`` is the step actually used over the bound.

Wall time: ``time.perf_counter`` around the run (:func:`~torchdeform.sim.engine.simulate`
with its divergence checks), after one untimed warm-up step; the median of ``--repeats`` runs
(default 3; runs slower than 0.5 s are timed once), 1 with ``--quick``. A run that raises
:class:`~torchdeform.errors.DivergenceError`, ends non-finite, or ends with an error above 10 or
a kinetic energy above 100x the reference's largest (it is blowing up but the monitor has not
caught it yet) is a ``diverged`` row.

The scenes have global drag (``decay``), which every integrator applies after its step
(:meth:`~torchdeform.sim.integrators.Integrator.finish`, a splitting): at small steps that splitting
error, not RK4's own, limits RK4's observed order (about 2 instead of 4).

Resolution sweep (``load-static``). The continuum limit needs physically scaled parameters:
masses from ``density=`` (``rho h^3`` per node), and spring constants ``k = E h s`` with the
node spacing ``h``, a lattice modulus ``E`` (Pa) and ``s`` the share of the grid cells that
border the spring (1 inside; for a spring lying in the body's surface 1/2, on an edge of the
box 1/4), the spring counterpart of lumped masses. In 3-D a lattice's elastic modulus is
``~ k / h``, so ``k ~ E h`` keeps it fixed; the 1-D rule ``k = Y / l0`` (``normalize=True``)
does not. Dashpots scale the same way (``c = tau k``). The static equilibrium is solved with
implicit Euler at ``dt = 1e4 s``, which is Newton's method on ``F(x) = 0`` (``M / dt^2 -> 0``),
until the largest node move is below 1e-8 (1e-10 for the reference) of the displacement; the
coarse grids (default n = 3, 5, 9) are compared with the fine one (n = 17) at the coarse nodes,
which coincide with fine nodes because ``n - 1`` divides ``n_ref - 1``.

Knoche relaxation is left out: it is a first-order relaxation of offsets towards a harmonic
interpolation of fixed nodes (no masses, forces or loads), not a time integrator of these
dynamics nor a solver of this equilibrium.

Modules:

===============  ============================================================================
:mod:`.scenes`   the scaled cubes (:func:`~.scenes.cube`, :func:`~.scenes.cell_share`) and
                 :data:`~.scenes.SCENES`
:mod:`.methods`  a scene's :class:`~.methods.Context` and :class:`~.methods.Reference`, the row
                 families (:class:`~.methods.Method`, :data:`~.methods.METHODS`) and the errors
:mod:`.runner`   the references, :func:`~.runner.run_case`, the command (options, plan, run) and
                 the inverse-warp rows
:mod:`.report`   Pareto front, recommendation, convergence orders, the text and the plot
===============  ============================================================================

Example:
    torchdeform bench accuracy --quick
    torchdeform bench accuracy --out accuracy-out            # about 2 minutes on 2 cores
    torchdeform bench accuracy --scenes load,stiff --methods rk4,implicit --json
"""

from .runner import HELP, add_arguments, run

__all__ = ["HELP", "add_arguments", "run"]
