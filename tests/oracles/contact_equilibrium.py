"""Independent oracle for quasi-static frictionless contact of a spring network with rigid obstacles.

Nothing here calls torchdeform. The body is an explicit edge list ``(i, j, k_ij, l0_ij)`` (build it
with :func:`edges_from` from :class:`tests.oracles.edge_list.EdgeList`), node masses, a gravity
vector and a fixed-node mask; obstacles are plain numpy signed-distance functions
(:func:`sphere`: ``|x - c| - R``; :func:`half_space`: ``(x - p) . n``), positive outside.

:func:`contact_equilibrium` finds the constrained equilibrium

    minimise   E(x) = sum_e 1/2 k_e (|x_i - x_j| - l0_e)^2 - sum_i m_i g . x_i   over the free nodes
    subject to sdf_o(x_i) >= 0 for every free node i and obstacle o,

in three stages:

1. ``scipy.optimize.minimize(method="SLSQP")`` from the rest positions, with analytic gradients and
   constraint Jacobians, on a scaled problem (displacements in units of the mean rest length,
   energy in units of ``k l0^2``) so that its tolerances mean something; a failure reported by
   scipy raises;
2. a Newton polish of the KKT system of the active set that SLSQP found
   (``grad E = sum_a lambda_a grad c_a``, ``c_a = 0``), with the exact Hessians of the springs and
   of the obstacles; constraints with a negative multiplier leave the active set, violated ones
   join it, until the set is consistent. SLSQP alone lands 1e-11..2e-7 m from the answer (a
   tighter ``ftol`` than the default makes its line search stop at round-off with status 8,
   "positive directional derivative", on some sphere contacts); the polish reaches round-off;
3. an independent check of the KKT conditions at the returned point: stationarity
   ``|grad E - J^T lambda|`` relative to the force scale, primal feasibility, dual feasibility
   ``lambda >= 0``, complementarity, and the second-order condition (the Hessian of the Lagrangian
   positive definite on the tangent space of the active constraints with positive multipliers),
   so that no non-converged point or saddle is returned silently.

Examples:
    >>> import numpy as np
    >>> X = np.array([[0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])     # a hanging spring, node 0 fixed
    >>> edges = (np.array([0]), np.array([1]), np.array([10.0]), np.array([1.0]))
    >>> floor = half_space((-1.5, 0.0, 0.0), (1.0, 0.0, 0.0))    # it would sag to -1.981 without
    >>> eq = contact_equilibrium(X, edges, mass=np.array([1.0, 1.0]), gravity=(-9.81, 0.0, 0.0),
    ...                          fixed=np.array([True, False]), obstacles=[floor])
    >>> round(float(eq.x[1, 0]), 12), round(float(eq.multipliers[1, 0]), 12)   # 9.81 - 10 * 0.5
    (-1.5, 4.81)
"""

from __future__ import annotations

import contextlib
import ctypes
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize

__all__ = [
    "Obstacle",
    "sphere",
    "half_space",
    "edges_from",
    "energy",
    "gradient",
    "hessian",
    "Equilibrium",
    "contact_equilibrium",
    "check_kkt",
    "one_blas_thread",
]


# ------------------------------------------------------------------------------------------- threads
_BLAS_THREADS = [
    ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
    ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
    ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
    ("openblas_get_num_threads", "openblas_set_num_threads"),
]


@contextlib.contextmanager
def one_blas_thread():
    """Run the block with every loaded OpenBLAS (numpy's and scipy's) on one thread.

    The matrices here are at most a few hundred wide: OpenBLAS threads only add wake-up latency,
    and on a busy two-core machine SLSQP and the dense solves become 50x slower with them. Without
    ``/proc/self/maps`` or OpenBLAS this does nothing.
    """
    restore = []
    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({ln.split()[-1] for ln in maps if "openblas" in ln.lower() and "/" in ln})
        for path in paths:
            lib = ctypes.CDLL(path)
            for get, set_ in _BLAS_THREADS:
                if hasattr(lib, get) and hasattr(lib, set_):
                    n = int(getattr(lib, get)())
                    getattr(lib, set_)(1)
                    restore.append((getattr(lib, set_), n))
                    break
    except OSError:
        pass
    try:
        yield
    finally:
        for set_, n in restore:
            set_(n)


# ------------------------------------------------------------------------------------------ obstacles
@dataclass(frozen=True)
class Obstacle:
    """A rigid obstacle as numpy functions of points ``(M, 3)``.

    ``sdf -> (M,)`` signed distance (positive outside), ``grad -> (M, 3)`` its gradient (the outward
    normal), ``hess -> (M, 3, 3)`` its Hessian.
    """

    sdf: object
    grad: object
    hess: object
    name: str = "obstacle"


def sphere(centre, radius) -> Obstacle:
    """A ball: ``sdf = |x - c| - R``."""
    c = np.asarray(centre, dtype=np.float64)
    R = float(radius)

    def sdf(x):
        return np.linalg.norm(x - c, axis=1) - R

    def grad(x):
        d = x - c
        return d / np.linalg.norm(d, axis=1)[:, None]

    def hess(x):
        d = x - c
        r = np.linalg.norm(d, axis=1)
        n = d / r[:, None]
        return (np.eye(3)[None] - n[:, :, None] * n[:, None, :]) / r[:, None, None]

    return Obstacle(sdf, grad, hess, f"sphere(c={c.tolist()}, R={R})")


def half_space(point, normal) -> Obstacle:
    """The half-space behind a plane: ``sdf = (x - p) . n`` with the outward unit normal ``n``."""
    p = np.asarray(point, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    return Obstacle(
        lambda x: (x - p) @ n,
        lambda x: np.broadcast_to(n, x.shape).copy(),
        lambda x: np.zeros((len(x), 3, 3)),
        f"half_space(p={p.tolist()}, n={n.tolist()})",
    )


# ------------------------------------------------------------------------------------------- springs
def edges_from(edge_list, k) -> tuple:
    """``(i, j, k, l0)`` arrays from an :class:`~tests.oracles.edge_list.EdgeList` (``k``: a number or one per spring)."""
    k = np.broadcast_to(np.asarray(k, dtype=np.float64), edge_list.l0.shape).copy()
    return edge_list.a.copy(), edge_list.b.copy(), k, edge_list.l0.copy()


def _edges(edges):
    i, j, k, l0 = (np.asarray(e) for e in edges)
    return i.astype(np.int64), j.astype(np.int64), k.astype(np.float64), l0.astype(np.float64)


def energy(x, edges, mass, gravity) -> float:
    """``sum_e 1/2 k (l - l0)^2 - sum_i m_i g . x_i`` (J) at positions ``x`` ``(N, 3)``."""
    i, j, k, l0 = _edges(edges)
    l = np.linalg.norm(x[i] - x[j], axis=1)
    return float(0.5 * np.sum(k * (l - l0) ** 2) - np.sum(mass[:, None] * gravity[None] * x))


def gradient(x, edges, mass, gravity) -> np.ndarray:
    """``dE/dx`` ``(N, 3)`` (minus the spring and gravity forces)."""
    i, j, k, l0 = _edges(edges)
    d = x[i] - x[j]
    l = np.linalg.norm(d, axis=1)
    f = (k * (l - l0) / l)[:, None] * d  # dE/dx_i of each spring
    g = np.zeros_like(x)
    np.add.at(g, i, f)
    np.add.at(g, j, -f)
    return g - mass[:, None] * gravity[None]


def hessian(x, edges) -> np.ndarray:
    """Exact ``d^2E/dx^2`` ``(3N, 3N)``: blocks ``k [(1 - l0/l)(I - n n^T) + n n^T]`` per spring."""
    i, j, k, l0 = _edges(edges)
    N = len(x)
    d = x[i] - x[j]
    l = np.linalg.norm(d, axis=1)
    n = d / l[:, None]
    nn = n[:, :, None] * n[:, None, :]
    blk = k[:, None, None] * ((1 - l0 / l)[:, None, None] * (np.eye(3)[None] - nn) + nn)
    H = np.zeros((N, 3, N, 3))
    for p, q, s in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        np.add.at(H, (p, slice(None), q, slice(None)), s * blk)
    return H.reshape(3 * N, 3 * N)


# ------------------------------------------------------------------------------------------ the solve
@dataclass
class Equilibrium:
    """The constrained equilibrium and its certificate.

    Attributes:
        x: positions ``(N, 3)``.
        multipliers: ``(N, n_obstacles)`` contact forces (N) along the obstacles' normals, 0 where
            inactive; the contact force on node ``i`` is ``sum_o multipliers[i, o] grad sdf_o(x_i)``.
        active: bool ``(N, n_obstacles)``, the active set (free nodes on an obstacle's surface).
        sdf: ``(N, n_obstacles)`` signed distances at ``x``.
        stationarity: ``max |grad E - J^T lambda|`` over free nodes (N).
        force_scale: the force the tolerances are relative to (N).
        reduced_hessian_min: smallest eigenvalue of the Hessian of the Lagrangian on the tangent space
            of the active constraints (N/m, > 0 at a strict local minimum).
        slsqp_x: SLSQP's own answer ``(N, 3)`` before the polish.
        slsqp: scipy's result object.
        energy: ``E(x)`` (J).
    """

    x: np.ndarray
    multipliers: np.ndarray
    active: np.ndarray
    sdf: np.ndarray
    stationarity: float
    force_scale: float
    reduced_hessian_min: float
    slsqp_x: np.ndarray
    slsqp: object = field(repr=False)
    energy: float = 0.0


def _constraints(obstacles, y_nodes):
    """Values ``(F * O,)`` (obstacle-major) and Jacobian rows ``(F * O, F, 3)`` at free positions ``(F, 3)``."""
    F = len(y_nodes)
    c = np.concatenate([o.sdf(y_nodes) for o in obstacles]) if obstacles else np.zeros(0)
    J = np.zeros((len(obstacles) * F, F, 3))
    rows = np.arange(F)
    for a, o in enumerate(obstacles):
        J[a * F + rows, rows] = o.grad(y_nodes)
    return c, J


def contact_equilibrium(
    X,
    edges,
    mass,
    gravity,
    fixed,
    obstacles,
    *,
    x0=None,
    ftol: float = 1e-9,
    maxiter: int = 2000,
    active_tol: float = 1e-7,
    rtol: float = 1e-11,
) -> Equilibrium:
    """Minimise the spring and gravity energy of the free nodes outside every obstacle.

    Args:
        X: rest positions ``(N, 3)`` (the positions of fixed nodes and, unless ``x0``, the start).
        edges: ``(i, j, k, l0)`` arrays ``(E,)`` (:func:`edges_from`).
        mass: node masses ``(N,)`` (kg).
        gravity: ``(3,)`` m/s^2.
        fixed: bool ``(N,)``: nodes held at ``X``.
        obstacles: :class:`Obstacle` list (:func:`sphere`, :func:`half_space`).
        x0: start positions ``(N, 3)`` (default ``X``).
        ftol: SLSQP's tolerance on the scaled objective.
        maxiter: SLSQP iterations.
        active_tol: SLSQP constraints with scaled ``sdf`` below this (fractions of the mean rest
            length) start the active set of the polish.
        rtol: stationarity, feasibility and complementarity tolerance relative to the force scale
            ``max(k l0, |m g|)`` (and to the mean rest length for distances).

    Raises:
        RuntimeError: scipy reports a failure, the active-set polish does not settle, or the KKT
            conditions fail at the answer.
    """
    with one_blas_thread():
        return _solve(X, edges, mass, gravity, fixed, obstacles, x0, ftol, maxiter, active_tol, rtol)


def _solve(X, edges, mass, gravity, fixed, obstacles, x0, ftol, maxiter, active_tol, rtol):
    X = np.asarray(X, dtype=np.float64)
    N = len(X)
    mass = np.broadcast_to(np.asarray(mass, dtype=np.float64), (N,)).copy()
    gravity = np.asarray(gravity, dtype=np.float64)
    fixed = np.asarray(fixed, dtype=bool)
    free = np.flatnonzero(~fixed)
    F, O = len(free), len(obstacles)
    _i, _j, k, l0 = _edges(edges)
    L = float(np.mean(l0))  # length unit
    kref = float(np.mean(k))
    Escale = kref * L * L  # energy unit
    force_scale = max(float(np.max(k * l0)), float(np.max(np.abs(mass[:, None] * gravity[None]))))
    base = X.copy() if x0 is None else np.asarray(x0, dtype=np.float64).copy()
    base[fixed] = X[fixed]

    def full(z):
        x = base.copy()
        x[free] = base[free] + L * z.reshape(F, 3)
        return x

    # ---- 1. SLSQP on the scaled problem: z = (x_free - x0_free) / L, f = E / (k L^2), c = sdf / L
    def fun(z):
        return energy(full(z), edges, mass, gravity) / Escale

    def jac(z):
        return gradient(full(z), edges, mass, gravity)[free].ravel() * (L / Escale)

    def cfun(z):
        return _constraints(obstacles, full(z)[free])[0] / L

    def cjac(z):
        return _constraints(obstacles, full(z)[free])[1].reshape(O * F, 3 * F)

    res = scipy.optimize.minimize(
        fun,
        np.zeros(3 * F),
        jac=jac,
        method="SLSQP",
        constraints=[{"type": "ineq", "fun": cfun, "jac": cjac}] if O else [],
        options={"ftol": ftol, "maxiter": maxiter},
    )
    if not res.success:
        raise RuntimeError(f"SLSQP failed: {res.message} (status {res.status}, {res.nit} iterations)")
    x_slsqp = full(res.x)

    # ---- 2. Newton on the KKT system of the active set, corrected until consistent
    c0 = cfun(res.x)
    active = c0 < active_tol
    y = x_slsqp[free].copy()
    lam = np.zeros(O * F)
    for _ in range(4 * O * F + 10):
        y, lam_a = _newton_kkt(y, active, free, base, edges, mass, gravity, obstacles, force_scale, L)
        lam = np.zeros(O * F)
        lam[active] = lam_a
        x = base.copy()
        x[free] = y
        c, _ = _constraints(obstacles, y)
        neg = active & (lam < -rtol * force_scale)
        viol = ~active & (c < -rtol * L)
        if not neg.any() and not viol.any():
            break
        if neg.any():  # drop the most negative multiplier
            active[np.argmin(np.where(neg, lam, np.inf))] = False
        else:  # add the most violated constraint
            active[np.argmin(np.where(viol, c, np.inf))] = True
    else:
        raise RuntimeError("active-set polish did not settle")

    # ---- 3. independent KKT check
    out = Equilibrium(
        x=x,
        multipliers=np.zeros((N, O)),
        active=np.zeros((N, O), dtype=bool),
        sdf=np.full((N, O), np.inf),
        stationarity=np.nan,
        force_scale=force_scale,
        reduced_hessian_min=np.nan,
        slsqp_x=x_slsqp,
        slsqp=res,
        energy=energy(x, edges, mass, gravity),
    )
    out.multipliers[free] = lam.reshape(O, F).T
    out.active[free] = active.reshape(O, F).T
    out.sdf[free] = np.stack([o.sdf(y) for o in obstacles], 1) if O else np.zeros((F, 0))
    check_kkt(out, X, edges, mass, gravity, fixed, obstacles, rtol=rtol)
    return out


def _newton_kkt(y, active, free, X, edges, mass, gravity, obstacles, force_scale, L, iters=50):
    """Solve ``grad E = J_A^T lambda``, ``c_A = 0`` for the free positions ``y`` ``(F, 3)`` and ``lambda_A``."""
    F, O = len(free), len(obstacles)
    A = np.flatnonzero(active)
    lam = np.zeros(len(A))
    x = X.copy()
    for it in range(iters):
        x[free] = y
        g = gradient(x, edges, mass, gravity)[free].ravel()
        c, J = _constraints(obstacles, y)
        J = J.reshape(O * F, 3 * F)[A]
        if it == 0 and len(A):  # least-squares multipliers to start
            lam = np.linalg.lstsq(J.T, g, rcond=None)[0]
        r = np.concatenate([g - J.T @ lam, c[A]])
        if (
            it > 0
            and np.max(np.abs(r[: 3 * F])) < 1e-14 * force_scale
            and (not len(A) or np.max(np.abs(c[A])) < 1e-15 * L)
        ):
            break
        H = hessian(x, edges).reshape(len(x), 3, len(x), 3)[free][:, :, free].reshape(3 * F, 3 * F)
        H = H - _constraint_hessian(obstacles, y, A, lam)
        K = np.block([[H, -J.T], [J, np.zeros((len(A), len(A)))]])
        step = np.linalg.solve(K, -r)
        y = y + step[: 3 * F].reshape(F, 3)
        lam = lam + step[3 * F :]
    x[free] = y
    return y, lam


def _constraint_hessian(obstacles, y, A, lam):
    """``sum_a lambda_a d^2 c_a / dy^2`` ``(3F, 3F)`` (block diagonal: each constraint reads one node)."""
    F = len(y)
    out = np.zeros((F, 3, F, 3))
    for a, la in zip(A, lam):
        o, node = divmod(int(a), F)
        out[node, :, node, :] += la * obstacles[o].hess(y[node : node + 1])[0]
    return out.reshape(3 * F, 3 * F)


def check_kkt(eq: Equilibrium, X, edges, mass, gravity, fixed, obstacles, rtol: float = 1e-11) -> None:
    """Check the KKT and second-order conditions of ``eq``; fill in ``stationarity`` and ``reduced_hessian_min``.

    Raises:
        RuntimeError: naming the condition that fails.
    """
    X = np.asarray(X, dtype=np.float64)
    N = len(X)
    mass = np.broadcast_to(np.asarray(mass, dtype=np.float64), (N,))
    gravity = np.asarray(gravity, dtype=np.float64)
    fixed = np.asarray(fixed, dtype=bool)
    free = np.flatnonzero(~fixed)
    F = len(free)
    L = float(np.mean(_edges(edges)[3]))
    x = eq.x
    if np.max(np.abs(x[fixed] - X[fixed]), initial=0.0) != 0:
        raise RuntimeError("a fixed node moved")
    # stationarity: grad E = sum_o lambda_o grad sdf_o at every free node
    g = gradient(x, edges, mass, gravity)[free]
    contact = np.zeros((F, 3))
    for o, obs in enumerate(obstacles):
        contact += eq.multipliers[free, o][:, None] * obs.grad(x[free])
    eq.stationarity = float(np.max(np.abs(g - contact)))
    if eq.stationarity > rtol * eq.force_scale:
        raise RuntimeError(f"stationarity residual {eq.stationarity:.3g} N > {rtol * eq.force_scale:.3g} N")
    sdf = np.stack([o.sdf(x[free]) for o in obstacles], 1) if obstacles else np.zeros((F, 0))
    if sdf.size and sdf.min() < -rtol * L:
        raise RuntimeError(f"infeasible: a free node is {-sdf.min():.3g} m inside an obstacle")
    lam = eq.multipliers[free]
    if lam.size and lam.min() < -rtol * eq.force_scale:
        raise RuntimeError(f"negative contact force {lam.min():.3g} N (the obstacle would pull)")
    if lam.size and np.max(np.abs(lam * sdf)) > rtol * eq.force_scale * L:
        raise RuntimeError("complementarity fails: a contact force on a node off the surface")
    # second order: the Lagrangian's Hessian on the tangent space of the strongly active constraints
    H = hessian(x, edges).reshape(N, 3, N, 3)[free][:, :, free].reshape(3 * F, 3 * F)
    rows = []
    for o, obs in enumerate(obstacles):
        nrm = obs.grad(x[free])
        hs = obs.hess(x[free])
        for a in np.flatnonzero(eq.active[free, o]):
            H[3 * a : 3 * a + 3, 3 * a : 3 * a + 3] -= lam[a, o] * hs[a]
            if lam[a, o] > rtol * eq.force_scale:
                r = np.zeros(3 * F)
                r[3 * a : 3 * a + 3] = nrm[a]
                rows.append(r)
    if rows:
        Jc = np.array(rows)
        _, s, vt = np.linalg.svd(Jc)
        Z = vt[int(np.sum(s > 1e-12 * s.max())) :].T  # null space of the active normals
    else:
        Z = np.eye(3 * F)
    eq.reduced_hessian_min = float(np.linalg.eigvalsh(Z.T @ H @ Z).min()) if Z.shape[1] else np.inf
    if not eq.reduced_hessian_min > 0:
        raise RuntimeError(f"not a strict local minimum: reduced Hessian eigenvalue {eq.reduced_hessian_min:.3g} N/m")
