"""Contact between two deformable bodies as a small C kernel: the nodes of one body in the other.

The eager resolution of :class:`~torchdeform.interact.bodies.BodyContact` spends its time in a few
hundred small tensor operations per step (Newton's iterations for every candidate, then one
pass per colour of constraints that share no corner). Here the same physics runs as one C loop
over the nodes of body ``a`` (built by the system C compiler on first use and cached on disk,
as the spring kernels: :func:`torchdeform.sim.native.load_library`):

1. the deformed bounding box of body ``b``'s nodes;
2. for each node ``p`` of ``a`` inside it: the rest point of ``b``'s lattice it lies at, by
   Newton's method on the trilinear map of its cell (started from ``b``'s least-squares affine
   map, at most ``newton`` iterations, each clamped to 4 cells), and whether it is inside
   (the cell solid, ``phi < 0``, the point reproduced to 1e-3 of a spacing), with its depth and
   normal;
3. the constraints resolved colour by colour as the tensor code orders them (cells of one parity
   along the three axes; the k-th constraint of a cell in the k-th round), each with the impulse
   of the module docstring of :mod:`~torchdeform.interact.bodies` (normal ``j_n = -d / (W dt)``
   with the depth corrected by how far the earlier colours moved ``b``'s corners, Coulomb friction
   up to ``mu j_n``, velocities and positions changed together, equal and opposite on ``b``'s
   corners).

Constraints of one colour share no corner, so resolving them one after another is resolving them
together: the kernel and the tensor code give the same states up to rounding.

Single-threaded (a few hundred constraints per step: microseconds). ``float`` or ``double``.

Example (the two engines on one step of a block pressed into another):
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact.bodies import Bodies, Body
    >>> def stack(engine):
    ...     lower = td.Model(td.Grid((4, 4, 4), spacing=0.01), stiffness=50.0, mass=1e-3, fixed="bottom", dtype=torch.float64)
    ...     upper = td.Model(td.Grid((3, 3, 3), spacing=0.01, origin=(0.028, 0.005, 0.005)), stiffness=50.0,
    ...                      mass=1e-3, dtype=torch.float64)
    ...     return Bodies([Body("lower", lower), Body("upper", upper)], friction=0.5, engine=engine)
    >>> a, b = stack("torch"), stack("auto")
    >>> b.contact.engine_for(torch.zeros(1, dtype=torch.float64))  # "torch" where no C compiler works
    'native'
    >>> sa, sb = a.step(a.rest_states(), 1e-3), b.step(b.rest_states(), 1e-3)
    >>> float(sa[1].readings["lower/upper.contacts"][0]), float((sa[1].x - sb[1].x).abs().max()) < 1e-15
    (12.0, True)
"""

from __future__ import annotations

import ctypes
import functools

import torch

from ..sim import native

__all__ = ["source", "unavailable", "supports", "resolve_pair"]

#: Newton iterations at most per located point (quadratic convergence: 5 are plenty)
NEWTON = 5


def source(T: str) -> str:
    """C source of ``contact(...)`` for ``T`` (``"float"`` or ``"double"``); arguments in :func:`resolve_pair`.

    Example:
        >>> "int contact(" in source("double")
        True
    """
    return _SOURCE.replace("@REAL@", T)


_SOURCE = """/* torchdeform: nodes of body a inside body b, located, then resolved colour by colour */
#include <stdint.h>
#include <stdlib.h>
#include <math.h>
typedef @REAL@ real;

static int solve3(const real J[9], const real r[3], real out[3]) {
  /* J row-major, J[3 i + j] = dx_i / ds_j; out = J^-1 r by cofactors; 1 when singular */
  const real c00 = J[4] * J[8] - J[5] * J[7], c01 = J[5] * J[6] - J[3] * J[8], c02 = J[3] * J[7] - J[4] * J[6];
  const real det = J[0] * c00 + J[1] * c01 + J[2] * c02;
  if (!(fabs((double)det) > 0) || !isfinite((double)det)) return 1;
  const real inv = (real)1 / det;
  const real i00 = c00, i01 = J[2] * J[7] - J[1] * J[8], i02 = J[1] * J[5] - J[2] * J[4];
  const real i10 = c01, i11 = J[0] * J[8] - J[2] * J[6], i12 = J[2] * J[3] - J[0] * J[5];
  const real i20 = c02, i21 = J[1] * J[6] - J[0] * J[7], i22 = J[0] * J[4] - J[1] * J[3];
  out[0] = (i00 * r[0] + i01 * r[1] + i02 * r[2]) * inv;
  out[1] = (i10 * r[0] + i11 * r[1] + i12 * r[2]) * inv;
  out[2] = (i20 * r[0] + i21 * r[1] + i22 * r[2]) * inv;
  return 0;
}

typedef struct {
  int64_t D, H, W, N;
  const real *x0, *x1, *x2;
  const real *origin, *h;
} lattice;

/* cell (clamped into the grid) and cell coordinates s of rest point X */
static void cell_of(const lattice* L, const real X[3], int64_t c[3], real s[3]) {
  const int64_t top[3] = {L->D - 2, L->H - 2, L->W - 2};
  for (int k = 0; k < 3; k++) {
    const real g = (X[k] - L->origin[k]) / L->h[k];
    real f = floor(g);
    if (f < 0) f = 0;
    if (f > (real)top[k]) f = (real)top[k];
    c[k] = (int64_t)f;
    s[k] = g - f;
  }
}

/* x(s), J = dx/ds (row-major), the 8 corner indices, weights and weight gradients */
static void trilinear(const lattice* L, const int64_t c[3], const real s[3], real xs[3], real J[9],
                      int64_t idx[8], real w[8], real dw[8][3]) {
  const int64_t sD = L->H * L->W, sH = L->W;
  const int64_t base = c[0] * sD + c[1] * sH + c[2];
  for (int k = 0; k < 3; k++) xs[k] = 0;
  for (int k = 0; k < 9; k++) J[k] = 0;
  for (int q = 0; q < 8; q++) {
    const int od = q >> 2, oh = (q >> 1) & 1, ow = q & 1;
    const real fd = od ? s[0] : 1 - s[0], fh = oh ? s[1] : 1 - s[1], fw = ow ? s[2] : 1 - s[2];
    const real gd = od ? 1 : -1, gh = oh ? 1 : -1, gw = ow ? 1 : -1;
    const int64_t i = base + od * sD + oh * sH + ow;
    idx[q] = i;
    w[q] = fd * fh * fw;
    dw[q][0] = gd * fh * fw; dw[q][1] = gh * fd * fw; dw[q][2] = gw * fd * fh;
    const real p[3] = {L->x0[i], L->x1[i], L->x2[i]};
    for (int k = 0; k < 3; k++) {
      xs[k] += w[q] * p[k];
      J[3 * k + 0] += dw[q][0] * p[k]; J[3 * k + 1] += dw[q][1] * p[k]; J[3 * k + 2] += dw[q][2] * p[k];
    }
  }
}

/* Nodes of a (Na, member_a) inside b (D, H, W nodes, member_b, solid cells, phi at rest).
   x*, v*: planar (3, N) positions and velocities, changed in place. wa, wb: inverse masses per
   node. Ainv, bvec: b's affine map x = X A + b, as X = (p - b) Ainv. out: force a exerts on b
   (3, the impulses over dt), the count of constraints, the deepest penetration. Returns 0, or 1
   when memory ran out.
   1. every node of a in b's deformed box is located in b's lattice (Newton on its cell);
   2. the constraints are resolved colour by colour (cells of one parity along the three axes, the
      k-th constraint of a cell in the k-th round), each seeing how far the earlier colours moved
      b's corners: constraints of one colour share no corner, so this is the tensor code's order. */
typedef struct { int64_t i; int64_t idx[8]; real w[8]; real n[3]; real d, W; int64_t colour; } constraint;

int contact(int64_t Na, const uint8_t* member_a, real* xa, real* va, const real* wa,
            int64_t D, int64_t H, int64_t W, const uint8_t* member_b, real* xb, real* vb, const real* wb,
            const real* phi, const uint8_t* solid, const real* origin, const real* h,
            const real* Ainv, const real* bvec, real dt, real mu, real tol, int newton, real* out) {
  const int64_t Nb = D * H * W;
  lattice L = {D, H, W, Nb, xb, xb + Nb, xb + 2 * Nb, origin, h};
  real lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (int64_t i = 0; i < Nb; i++) {
    if (!member_b[i]) continue;
    const real p[3] = {xb[i], xb[Nb + i], xb[2 * Nb + i]};
    for (int k = 0; k < 3; k++) {
      if (p[k] < lo[k]) lo[k] = p[k];
      if (p[k] > hi[k]) hi[k] = p[k];
    }
  }
  const real hmin = h[0] < h[1] ? (h[0] < h[2] ? h[0] : h[2]) : (h[1] < h[2] ? h[1] : h[2]);
  real *a0 = xa, *a1 = xa + Na, *a2 = xa + 2 * Na, *u0 = va, *u1 = va + Na, *u2 = va + 2 * Na;
  real *b0 = xb, *b1 = xb + Nb, *b2 = xb + 2 * Nb, *v0 = vb, *v1 = vb + Nb, *v2 = vb + 2 * Nb;
  out[0] = out[1] = out[2] = out[3] = out[4] = 0;
  int64_t M = 0, cap = 0;
  for (int64_t i = 0; i < Na; i++)
    if (member_a[i] && a0[i] > lo[0] && a0[i] < hi[0] && a1[i] > lo[1] && a1[i] < hi[1] && a2[i] > lo[2] &&
        a2[i] < hi[2]) cap++;
  if (cap == 0) return 0;
  constraint* C = (constraint*)malloc(cap * sizeof(constraint));
  if (!C) return 1;
  real deepest = 0;
  for (int64_t i = 0; i < Na; i++) {                       /* 1. locate */
    if (!member_a[i]) continue;
    const real p[3] = {a0[i], a1[i], a2[i]};
    if (!(p[0] > lo[0] && p[0] < hi[0] && p[1] > lo[1] && p[1] < hi[1] && p[2] > lo[2] && p[2] < hi[2])) continue;
    real X[3], s[3], xs[3], J[9], w[8], dw[8][3], step[3];
    int64_t c[3], idx[8];
    for (int k = 0; k < 3; k++)
      X[k] = (p[0] - bvec[0]) * Ainv[k] + (p[1] - bvec[1]) * Ainv[3 + k] + (p[2] - bvec[2]) * Ainv[6 + k];
    for (int it = 0; it < newton; it++) {
      cell_of(&L, X, c, s);
      trilinear(&L, c, s, xs, J, idx, w, dw);
      const real r[3] = {p[0] - xs[0], p[1] - xs[1], p[2] - xs[2]};
      if (solve3(J, r, step)) break;                       /* a collapsed cell: no step */
      real big = 0;
      for (int k = 0; k < 3; k++) {
        if (!isfinite((double)step[k])) step[k] = 0;
        if (step[k] > 4) step[k] = 4;
        if (step[k] < -4) step[k] = -4;
        X[k] += step[k] * h[k];
        if (fabs((double)step[k]) > big) big = fabs((double)step[k]);
      }
      if (big < tol) break;
    }
    cell_of(&L, X, c, s);
    trilinear(&L, c, s, xs, J, idx, w, dw);
    if (!solid[(c[0] * (H - 1) + c[1]) * (W - 1) + c[2]]) continue;
    int within = 1;
    for (int k = 0; k < 3; k++) within &= (s[k] >= (real)-1e-9) && (s[k] <= (real)(1 + 1e-9));
    if (!within) continue;
    const real e0 = xs[0] - p[0], e1 = xs[1] - p[1], e2 = xs[2] - p[2];
    if (!(sqrt((double)(e0 * e0 + e1 * e1 + e2 * e2)) <= 1e-3 * (double)hmin)) continue;
    real ph = 0, gs[3] = {0, 0, 0};
    for (int q = 0; q < 8; q++) {
      ph += w[q] * phi[idx[q]];
      for (int k = 0; k < 3; k++) gs[k] += dw[q][k] * phi[idx[q]];
    }
    if (!(ph < 0)) continue;
    const real JT[9] = {J[0], J[3], J[6], J[1], J[4], J[7], J[2], J[5], J[8]};
    real gx[3];
    if (solve3(JT, gs, gx)) continue;
    const real size = sqrt(gx[0] * gx[0] + gx[1] * gx[1] + gx[2] * gx[2]);
    if (!(size > 0) || !isfinite((double)size)) continue;
    real Wt = wa[i];
    for (int q = 0; q < 8; q++) Wt += w[q] * w[q] * wb[idx[q]];
    if (!(Wt > 0)) continue;
    constraint* k = &C[M++];
    k->i = i; k->d = ph / size; k->W = Wt;
    for (int m = 0; m < 3; m++) k->n[m] = gx[m] / size;
    for (int q = 0; q < 8; q++) { k->idx[q] = idx[q]; k->w[q] = w[q]; }
    k->colour = ((c[0] & 1) << 2) | ((c[1] & 1) << 1) | (c[2] & 1);
    if (-k->d > deepest) deepest = -k->d;
  }
  if (M == 0) { free(C); return 0; }
  /* 2. colours: the rank of a constraint among those of its cell (in node order), times 8, plus the parity */
  const int64_t cells = (D - 1) * (H - 1) * (W - 1);
  int32_t* seen = (int32_t*)calloc(cells, sizeof(int32_t));
  real* moved = (real*)calloc(3 * Nb, sizeof(real));      /* how far the resolved constraints moved b's nodes */
  int64_t* order = (int64_t*)malloc(M * sizeof(int64_t));
  if (!seen || !moved || !order) { free(C); free(seen); free(moved); free(order); return 1; }
  int64_t top = 0;
  for (int64_t m = 0; m < M; m++) {
    const int64_t f = C[m].idx[0], cd = f / (H * W), ch = (f / W) % H, cw = f % W;
    C[m].colour += 8 * (int64_t)seen[(cd * (H - 1) + ch) * (W - 1) + cw]++;
    if (C[m].colour > top) top = C[m].colour;
  }
  int64_t* start = (int64_t*)calloc(top + 2, sizeof(int64_t));
  if (!start) { free(C); free(seen); free(moved); free(order); return 1; }
  for (int64_t m = 0; m < M; m++) start[C[m].colour + 1]++;
  for (int64_t c = 0; c <= top; c++) start[c + 1] += start[c];
  for (int64_t m = 0; m < M; m++) order[start[C[m].colour]++] = m;   /* stable: node order within a colour */
  real imp[3] = {0, 0, 0};
  real *m0 = moved, *m1 = moved + Nb, *m2 = moved + 2 * Nb;
  for (int64_t r = 0; r < M; r++) {                        /* 3. resolve, colour after colour */
    const constraint* k = &C[order[r]];
    const int64_t i = k->i;
    real sh[3] = {0, 0, 0}, vr[3] = {u0[i], u1[i], u2[i]};
    for (int q = 0; q < 8; q++) {
      const int64_t t = k->idx[q];
      sh[0] += k->w[q] * m0[t]; sh[1] += k->w[q] * m1[t]; sh[2] += k->w[q] * m2[t];
      vr[0] -= k->w[q] * v0[t]; vr[1] -= k->w[q] * v1[t]; vr[2] -= k->w[q] * v2[t];
    }
    const real* n = k->n;
    const real depth = k->d - (n[0] * sh[0] + n[1] * sh[1] + n[2] * sh[2]);   /* the depth now */
    const real jn = (depth < 0 ? -depth : 0) / (k->W * dt);
    const real vn = vr[0] * n[0] + vr[1] * n[1] + vr[2] * n[2];
    const real tg[3] = {vr[0] - vn * n[0], vr[1] - vn * n[1], vr[2] - vn * n[2]};
    const real speed = sqrt(tg[0] * tg[0] + tg[1] * tg[1] + tg[2] * tg[2]);
    real jt = 0;
    if (mu > 0) {
      jt = speed / k->W;
      if (mu * jn < jt) jt = mu * jn;
    }
    const real sp = speed > 0 ? speed : 1;
    const real j[3] = {jn * n[0] - jt * tg[0] / sp, jn * n[1] - jt * tg[1] / sp, jn * n[2] - jt * tg[2] / sp};
    u0[i] += wa[i] * j[0]; u1[i] += wa[i] * j[1]; u2[i] += wa[i] * j[2];
    a0[i] += dt * wa[i] * j[0]; a1[i] += dt * wa[i] * j[1]; a2[i] += dt * wa[i] * j[2];
    for (int q = 0; q < 8; q++) {
      const int64_t t = k->idx[q];
      const real g = -k->w[q] * wb[t];
      v0[t] += g * j[0]; v1[t] += g * j[1]; v2[t] += g * j[2];
      b0[t] += dt * g * j[0]; b1[t] += dt * g * j[1]; b2[t] += dt * g * j[2];
      m0[t] += dt * g * j[0]; m1[t] += dt * g * j[1]; m2[t] += dt * g * j[2];
    }
    imp[0] += j[0]; imp[1] += j[1]; imp[2] += j[2];
  }
  out[0] = -imp[0] / dt; out[1] = -imp[1] / dt; out[2] = -imp[2] / dt;
  out[3] = (real)M; out[4] = deepest;
  free(C); free(seen); free(moved); free(order); free(start);
  return 0;
}
"""


def unavailable() -> str | None:
    """Why the kernel cannot be built here (no C compiler, ``TORCHDEFORM_NATIVE=0``), or None."""
    return native.unavailable()


def supports(dtype: torch.dtype, device) -> str | None:
    """Why the kernel cannot resolve bodies of ``dtype`` on ``device``, or None when it can."""
    if torch.device(device).type != "cpu":
        return f"the contact kernel runs on the CPU (the bodies are on {torch.device(device).type})"
    if dtype not in native.CTYPE_NAMES:
        return f"the contact kernel takes float32 or float64 (the bodies are {dtype})"
    return unavailable()


@functools.cache
def _function(T: str):
    real = ctypes.c_float if T == "float" else ctypes.c_double
    i64, ptr = ctypes.c_int64, ctypes.c_void_p
    argtypes = [i64, ptr, ptr, ptr, ptr, i64, i64, i64] + [ptr] * 10 + [real, real, real, ctypes.c_int, ptr]
    return native.entry(source(T), "contact", argtypes, what=f"the contact kernel ({T})")


def _planar(t: torch.Tensor) -> torch.Tensor:
    assert t.is_contiguous()
    return t


def resolve_pair(a, b, xa, va, xb, vb, dt: float, mu: float) -> tuple:
    """Nodes of body ``a`` inside body ``b`` (:class:`~torchdeform.interact.bodies.Body`), resolved in place.

    ``xa, va`` ``(3, Na)`` and ``xb, vb`` ``(3, Nb)``: contiguous positions (m) and velocities (m/s)
    of one batch entry, changed in place. Returns ``(force (3,) N that a exerts on b, count,
    deepest penetration (0-d) m)``.
    """
    T = native.CTYPE_NAMES[xa.dtype]
    fn = _function(T)
    affine = b.affine(xb)  # (Ainv (3, 3), bvec (3,)): X = (p - bvec) Ainv
    out = torch.zeros(5, dtype=xa.dtype)
    D, H, W = b.model.grid.shape
    tol = 1e-4 if xa.dtype == torch.float32 else 1e-9
    failed = fn(
        xa.shape[1],
        a._member_u8.data_ptr(),
        _planar(xa).data_ptr(),
        _planar(va).data_ptr(),
        a._inv_mass.data_ptr(),
        D,
        H,
        W,
        b._member_u8.data_ptr(),
        _planar(xb).data_ptr(),
        _planar(vb).data_ptr(),
        b._inv_mass.data_ptr(),
        b.phi.data_ptr(),
        b._solid_u8.data_ptr(),
        b._origin.data_ptr(),
        b._h.data_ptr(),
        affine[0].data_ptr(),
        affine[1].data_ptr(),
        float(dt),
        float(mu),
        tol,
        NEWTON,
        out.data_ptr(),
    )
    if failed:
        raise MemoryError("native contact kernel: could not allocate its constraint lists")
    return out[:3], float(out[3]), out[4]
