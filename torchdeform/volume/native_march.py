r"""A native (C, OpenMP) ray marcher for perspective views: virtual endoscopy and overviews, no gradient.

The fast path of :func:`~torchdeform.volume.interior.render_endoscope` (``engine="native"``, or
``"auto"`` without gradient). One C function marches every ray of an image front to back with
emission-absorption compositing, built by the system C compiler with the spring kernels' flags and
disk cache (:func:`~torchdeform.sim.native.load_library`) and called through ``ctypes``.

Per ray (eye ``e``, unit direction ``d``, interval ``[t0, t1]`` already clipped to the volume's box
and to the near/far planes, voxels):

* segments of ``step`` from ``t0`` to ``t1`` (the last one shorter), one sample per segment at its
  midpoint ``t``, point ``p = e + t d``;
* through node offsets ``u`` (``(3, n_d, n_h, n_w)`` voxels, the node grid spanning the volume as
  :class:`~torchdeform.volume.DisplacementField` with ``order="linear"``: node ``a`` at voxel
  ``a (N - 1) / (n - 1)``, trilinear, clamped to the node box) the sample reads the volume at
  ``X = p - u(p)``; without offsets ``X = p``;
* ``v = V(X)``, trilinear with the edge voxels repeated (``sample(..., padding="border")``);
* ``(c, sigma)`` from the transfer-function table ``(R, 4)`` over ``[lo, hi]``, exactly as
  :meth:`~torchdeform.volume.TransferFunction.lookup`: index ``x = (v - lo) (R - 1) / (hi - lo)``
  clamped to ``[0, R - 1]``, linear between the two entries around it;
* with ``light`` (a two-sided headlight) the colour is scaled by
  ``ambient + diffuse |g . d| / |g|``, ``g`` the central differences of trilinear samples at
  ``X +- 1`` voxel along each axis (edges repeated), or by ``ambient + diffuse`` where
  ``|g| < 1e-6 (hi - lo)``;
* ``alpha = 1 - exp(-sigma l)`` for the segment's length ``l``; ``C += T alpha c``,
  ``T *= 1 - alpha``; the ray stops once ``T < stop`` (early ray termination; ``stop = 0``: never).

Output: the image ``(B, 4, h, w)``, premultiplied RGB and ``alpha = 1 - T``, zero where ``valid``
is False; and the depth ``(B, h, w)``: the ``t`` at which the accumulated alpha first exceeds 1/2,
exact inside the segment where it happens (constant extinction there: ``t_s + ln(2 T_s) / sigma``
for the segment's start ``t_s`` and the transmittance ``T_s`` before it; ``inf`` where it never
does). These are the rules of :func:`~torchdeform.volume.render_endoscope`'s torch engine, which
calls :func:`render_endoscope_native` for ``engine="auto"`` without gradient.

Speed
-----
* **The sample.** The volume is kept with its edges repeated (2 voxels before, 3 after each axis),
  so a sample clamps its coordinate to ``[-1, N]`` and reads without bounds checks. The value is
  the 4 bilinear samples of two slices; the gradient (only where ``sigma > 0``) reuses the
  same fractions: along D, ``g_D = ((1 - f) (B_{i+1} - B_{i-1}) + f (B_{i+2} - B_i)) / 2`` with
  ``B_k`` the bilinear sample of slice ``k`` (likewise along H and W).
* **Empty-space leaping.** The volume is cut into blocks of ``block`` voxels (default 2); each
  block keeps the range of the voxels its samples can read (the block and a 1-voxel apron). A
  block is occupied when the transfer function's extinction is non-zero anywhere over the table
  entries of that range (conservative). Each block stores its Chebyshev distance ``e`` (in blocks,
  capped at 15) to the nearest occupied block, so the ``(2e - 1)^3`` blocks around it are empty;
  a ray whose sample falls in such a block jumps to the first sample lattice point
  ``t0 + (k + 1/2) step`` past that box's exit. Samples on the lattice are never moved, so the
  image is the same as without leaping. Through offsets the occupancy is dilated by
  ``ceil(max |u| / block)`` blocks (``e`` reduced by as much): a sample reads within ``max |u|``
  of its point.
* **Threads.** Tiles of 8 x 8 pixels (neighbouring rays read the same cache lines), dynamically
  scheduled over ``torch.get_num_threads()`` OpenMP threads (at the call).
* The volume's padded copy and block ranges are cached per volume tensor (its storage, shape and
  version counter; the cache holds the tensor, so its memory is not reused while cached); the
  occupancy is remade per call (a few hundred microseconds: it depends on the table and offsets).

* :func:`render`: the image and depth of a batch of volumes for given rays;
* :func:`render_endoscope_native`: a :func:`~torchdeform.volume.render_endoscope` plan by the kernel
  (the hook of its ``auto`` engine);
* :func:`render_axis_native`: an axis view of :func:`~torchdeform.volume.render` by the kernel
  (its ``"native"`` and ``"auto"`` engines): parallel rays, each from its own origin on the face
  the view enters, sampled on the slabs the ``grid_sample`` engine samples;
* :func:`clip_rays`: ``t0, t1`` of rays clipped to the volume's box and to near/far;
* :func:`unavailable`: why the kernel cannot be built here (no C compiler ...), or None;
* :func:`source`: the C source.

Example:
    >>> import torch
    >>> from torchdeform.volume import native_march, TransferFunction
    >>> vol = torch.zeros(8, 8, 8); vol[4:] = 100.0               # opaque past D = 3.5
    >>> tf = TransferFunction([0.0, 100.0], [[1, 1, 1], [1, 1, 1]], [0.0, 5.0])
    >>> eye = torch.tensor([-2.0, 3.5, 3.5]); dirs = torch.tensor([1.0, 0.0, 0.0]).view(3, 1, 1)
    >>> t0, t1 = native_march.clip_rays(eye, dirs, (8, 8, 8))
    >>> if native_march.unavailable() is None:
    ...     img, depth = native_march.render(vol, tf.table(), 0.0, 100.0, eye, dirs, t0=t0, t1=t1, light=False, stop=0)
    ...     print(tuple(img.shape), round(float(img[0, 3, 0, 0]), 4), round(float(depth[0, 0, 0]), 3))
    ... else:
    ...     print((1, 4, 1, 1), 1.0, 5.518)
    (1, 4, 1, 1) 1.0 5.518
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import math
from collections import OrderedDict

import torch
import torch.nn.functional as F

from ..sim import native

__all__ = [
    "render",
    "render_endoscope_native",
    "render_axis_native",
    "axis_blocker",
    "clip_rays",
    "unavailable",
    "source",
    "BLOCK",
    "TILE",
    "MAX_LEAP",
]

#: voxels per side of an empty-space block
BLOCK = 2
#: pixels per side of a tile (the unit of work of a thread)
TILE = 8
#: the largest leap distance stored (blocks)
MAX_LEAP = 31
#: edge voxels repeated before and after each axis of the kernel's copy of the volume
_PAD_LO, _PAD_HI = 2, 3

_SOURCE = r"""
/* torchdeform native ray marcher (virtual endoscopy), float32 */
#include <stdint.h>
#include <stdlib.h>
#include <math.h>
#ifdef _OPENMP
#include <omp.h>
#endif

typedef struct {
  const float* vol; int64_t sD, sH; float ND, NH, NW;       /* padded volume: origin at voxel (0,0,0) */
  const float* tab; float lo, tscale, rmax; int64_t R;     /* (R, 4) table, index = (v - lo) * tscale */
  const float* nodes; int nd, nh, nw; int64_t nsD, nsH;    /* (nd, nh, nw, 4) node offsets or NULL */
  float ncD, ncH, ncW;                                     /* node coordinate = p * nc */
  int64_t odD, odH, odW;                                   /* node strides to the next node (0 on 1-node axes) */
  const uint8_t* leap; float bs, inv_bs; int BD, BH, BW;   /* leap distances per block or NULL */
  int dil;                                                 /* blocks of dilation (offsets) */
  int light; float amb, dif, gtiny2;
  float step, stop;
} Ctx;

static inline float lerp(float a, float b, float f) { return a + f * (b - a); }

static inline float bil(const float* p, int64_t sa, int64_t sb, float fa, float fb) {
  return lerp(lerp(p[0], p[sb], fb), lerp(p[sa], p[sa + sb], fb), fa);
}

static inline float clampf(float x, float a, float b) { return x < a ? a : (x > b ? b : x); }

/* u(p) from the node grid: trilinear, clamped to the node box */
static inline void offset_at(const Ctx* c, float p0, float p1, float p2, float* u) {
  float q0 = clampf(p0 * c->ncD, 0.f, (float)(c->nd - 1));
  float q1 = clampf(p1 * c->ncH, 0.f, (float)(c->nh - 1));
  float q2 = clampf(p2 * c->ncW, 0.f, (float)(c->nw - 1));
  int i0 = (int)q0, i1 = (int)q1, i2 = (int)q2;
  if (i0 > c->nd - 2) i0 = c->nd > 1 ? c->nd - 2 : 0;
  if (i1 > c->nh - 2) i1 = c->nh > 1 ? c->nh - 2 : 0;
  if (i2 > c->nw - 2) i2 = c->nw > 1 ? c->nw - 2 : 0;
  const float f0 = q0 - i0, f1 = q1 - i1, f2 = q2 - i2;
  const float* b = c->nodes + ((int64_t)i0 * c->nsD + (int64_t)i1 * c->nsH + (int64_t)i2) * 4;
  const int64_t a = c->odD * 4, h = c->odH * 4, w = c->odW * 4;
  for (int k = 0; k < 3; k++) {
    const float* q = b + k;
    u[k] = lerp(lerp(lerp(q[0], q[w], f2), lerp(q[h], q[h + w], f2), f1),
                lerp(lerp(q[a], q[a + w], f2), lerp(q[a + h], q[a + h + w], f2), f1), f0);
  }
}

/* leaving the box of blocks [b - r, b + r] (r = e - 1) along the ray: its exit t */
static inline float box_exit(const Ctx* c, const float* e, const float* d, const int* b, int r) {
  float t = INFINITY;
  for (int k = 0; k < 3; k++) {
    float bound;
    if (d[k] > 0.f) bound = (b[k] + r + 1) * c->bs - 0.5f;
    else if (d[k] < 0.f) bound = (b[k] - r) * c->bs - 0.5f;
    else continue;
    const float tk = (bound - e[k]) / d[k];
    if (tk < t) t = tk;
  }
  return t;
}

static void ray(const Ctx* c, const float* e, const float* d, float t0, float t1, float* rgba, float* dep) {
  float C0 = 0.f, C1 = 0.f, C2 = 0.f, T = 1.f, depth = INFINITY;
  const float len = t1 - t0, step = c->step, inv_step = 1.0f / step;
  const int64_t sD = c->sD, sH = c->sH;
  float t_known = -INFINITY;             /* samples before this t are in an occupied block already looked up */
  int64_t k = 0;
  while (1) {
    const float s0 = (float)k * step;
    float sl = len - s0;
    if (!(sl > 0.f)) break;
    if (sl > step) sl = step;
    const float t = (t0 + s0) + 0.5f * sl;
    const float p0 = e[0] + d[0] * t, p1 = e[1] + d[1] * t, p2 = e[2] + d[2] * t;
    if (c->leap && t >= t_known) {
      int b[3];
      b[0] = (int)floorf((p0 + 0.5f) * c->inv_bs); b[0] = b[0] < 0 ? 0 : (b[0] >= c->BD ? c->BD - 1 : b[0]);
      b[1] = (int)floorf((p1 + 0.5f) * c->inv_bs); b[1] = b[1] < 0 ? 0 : (b[1] >= c->BH ? c->BH - 1 : b[1]);
      b[2] = (int)floorf((p2 + 0.5f) * c->inv_bs); b[2] = b[2] < 0 ? 0 : (b[2] >= c->BW ? c->BW - 1 : b[2]);
      const int lp = (int)c->leap[((int64_t)b[0] * c->BH + b[1]) * c->BW + b[2]] - c->dil;
      if (lp > 0) {
        const float tx = box_exit(c, e, d, b, lp - 1);
        int64_t kn = (int64_t)ceilf((tx - t0) * inv_step - 0.5f);
        if (!(tx < INFINITY)) break;
        k = kn > k ? kn : k + 1;
        continue;
      }
      t_known = box_exit(c, e, d, b, 0);
    }
    float X0 = p0, X1 = p1, X2 = p2;
    if (c->nodes) {
      float u[3];
      offset_at(c, p0, p1, p2, u);
      X0 -= u[0]; X1 -= u[1]; X2 -= u[2];
    }
    X0 = clampf(X0, -1.f, c->ND); X1 = clampf(X1, -1.f, c->NH); X2 = clampf(X2, -1.f, c->NW);
    const float fl0 = floorf(X0), fl1 = floorf(X1), fl2 = floorf(X2);
    const float fd = X0 - fl0, fh = X1 - fl1, fw = X2 - fl2;
    const float* q = c->vol + (int64_t)fl0 * sD + (int64_t)fl1 * sH + (int64_t)fl2;
    const float B0 = bil(q, sH, 1, fh, fw), B1 = bil(q + sD, sH, 1, fh, fw);
    const float v = lerp(B0, B1, fd);
    float x = (v - c->lo) * c->tscale;
    x = clampf(x, 0.f, c->rmax);
    int64_t i = (int64_t)x;
    if (i > c->R - 2) i = c->R - 2;
    const float f = x - (float)i;
    const float* tb = c->tab + 4 * i;
    const float sigma = lerp(tb[3], tb[7], f);
    if (sigma > 0.f) {
      float shade = 1.f;
      if (c->light) {
        const float Bm = bil(q - sD, sH, 1, fh, fw), B2 = bil(q + 2 * sD, sH, 1, fh, fw);
        const float gd = 0.5f * ((1.f - fd) * (B1 - Bm) + fd * (B2 - B0));
        const float Hm = bil(q - sH, sD, 1, fd, fw), H0 = bil(q, sD, 1, fd, fw);
        const float H1 = bil(q + sH, sD, 1, fd, fw), H2 = bil(q + 2 * sH, sD, 1, fd, fw);
        const float gh = 0.5f * ((1.f - fh) * (H1 - Hm) + fh * (H2 - H0));
        const float Wm = bil(q - 1, sD, sH, fd, fh), W0 = bil(q, sD, sH, fd, fh);
        const float W1 = bil(q + 1, sD, sH, fd, fh), W2 = bil(q + 2, sD, sH, fd, fh);
        const float gw = 0.5f * ((1.f - fw) * (W1 - Wm) + fw * (W2 - W0));
        const float gg = gd * gd + gh * gh + gw * gw;
        if (gg < c->gtiny2) shade = c->amb + c->dif;
        else shade = c->amb + c->dif * fabsf(gd * d[0] + gh * d[1] + gw * d[2]) / sqrtf(gg);
      }
      const float ex = expf(-sigma * sl);
      const float wgt = T * (1.f - ex) * shade;
      C0 += wgt * lerp(tb[0], tb[4], f);
      C1 += wgt * lerp(tb[1], tb[5], f);
      C2 += wgt * lerp(tb[2], tb[6], f);
      const float Tb = T;
      T *= ex;
      if (T < 0.5f && Tb >= 0.5f) depth = (t0 + s0) + logf(2.f * Tb) / sigma;  /* inside the segment */
      if (T < c->stop) break;
    }
    k++;
  }
  rgba[0] = C0; rgba[1] = C1; rgba[2] = C2; rgba[3] = 1.f - T; *dep = depth;
}

int march(const float* vol, int64_t D, int64_t H, int64_t W,
          const float* tab, int64_t R, float lo, float tscale,
          const float* eye, const float* orgs, const float* dirs, const uint8_t* valid, const float* t0s, const float* t1s,
          float near, float far, int64_t h, int64_t w, float step, float stop,
          const float* nodes, int64_t nd, int64_t nh, int64_t nw, float ncD, float ncH, float ncW,
          const uint8_t* leap, int64_t bs, int64_t BD, int64_t BH, int64_t BW, int64_t dil,
          int light, float ambient, float diffuse, float gtiny,
          float* out, float* depth, int nt, int64_t tile) {
  Ctx c;
  c.sH = W + 5; c.sD = (H + 5) * (W + 5);
  c.vol = vol + 2 * c.sD + 2 * c.sH + 2;
  c.ND = (float)D; c.NH = (float)H; c.NW = (float)W;
  c.tab = tab; c.R = R; c.lo = lo; c.tscale = tscale; c.rmax = (float)(R - 1);
  c.nodes = nodes; c.nd = (int)nd; c.nh = (int)nh; c.nw = (int)nw; c.nsH = nw; c.nsD = nh * nw;
  c.ncD = ncD; c.ncH = ncH; c.ncW = ncW;
  c.odD = nd > 1 ? c.nsD : 0; c.odH = nh > 1 ? c.nsH : 0; c.odW = nw > 1 ? 1 : 0;
  c.dil = (int)dil; c.leap = leap; c.bs = (float)bs; c.inv_bs = 1.0f / (float)bs; c.BD = (int)BD; c.BH = (int)BH; c.BW = (int)BW;
  c.light = light; c.amb = ambient; c.dif = diffuse; c.gtiny2 = gtiny * gtiny;
  c.step = step; c.stop = stop;
  const int64_t th = (h + tile - 1) / tile, tw = (w + tile - 1) / tile, P = h * w;
  #pragma omp parallel for schedule(dynamic, 2) num_threads(nt)
  for (int64_t ti = 0; ti < th * tw; ti++) {
    const int64_t y0 = (ti / tw) * tile, x0 = (ti % tw) * tile;
    const int64_t y1 = y0 + tile < h ? y0 + tile : h, x1 = x0 + tile < w ? x0 + tile : w;
    for (int64_t y = y0; y < y1; y++) {
      for (int64_t x = x0; x < x1; x++) {
        const int64_t px = y * w + x;
        float rgba[4] = {0.f, 0.f, 0.f, 0.f}, dp = INFINITY;
        if (!valid || valid[px]) {
          const float d[3] = {dirs[px], dirs[P + px], dirs[2 * P + px]};
          float eo[3];                             /* this ray's origin: its own (orgs) or the eye */
          const float* e = eye;
          if (orgs) { eo[0] = orgs[px]; eo[1] = orgs[P + px]; eo[2] = orgs[2 * P + px]; e = eo; }
          float t0, t1;
          if (t0s) { t0 = t0s[px]; t1 = t1s[px]; }
          else {                                   /* the box [-0.5, N - 0.5] and [max(near, 0), far] */
            float tin = -INFINITY, tout = INFINITY;
            const float hi[3] = {D - 0.5f, H - 0.5f, W - 0.5f};
            for (int k = 0; k < 3; k++) {
              float a, b;
              if (fabsf(d[k]) < 1e-12f) {
                const int in = e[k] >= -0.5f && e[k] <= hi[k];
                a = in ? -INFINITY : INFINITY; b = in ? INFINITY : -INFINITY;
              } else {
                const float inv = 1.0f / d[k], ta = (-0.5f - e[k]) * inv, tb = (hi[k] - e[k]) * inv;
                a = ta < tb ? ta : tb; b = ta < tb ? tb : ta;
              }
              if (a > tin) tin = a;
              if (b < tout) tout = b;
            }
            const float nr = near > 0.f ? near : 0.f;
            t0 = tin > nr ? tin : nr; t1 = tout < far ? tout : far;
          }
          ray(&c, e, d, t0, t1, rgba, &dp);
        }
        out[px] = rgba[0]; out[P + px] = rgba[1]; out[2 * P + px] = rgba[2]; out[3 * P + px] = rgba[3];
        depth[px] = dp;
      }
    }
  }
  return 0;
}
"""


def source() -> str:
    """The C source of ``march(...)`` (see the module docstring).

    Examples:
        >>> "int march(" in source()
        True
    """
    return _SOURCE


def unavailable() -> str | None:
    """Why the kernel cannot be built here (no C compiler, not POSIX, ``TORCHDEFORM_NATIVE=0``), or None."""
    return native.unavailable()


@functools.cache
def _function():
    i64, ptr, f32, cint = ctypes.c_int64, ctypes.c_void_p, ctypes.c_float, ctypes.c_int
    argtypes = (
        [ptr, i64, i64, i64]  # volume
        + [ptr, i64, f32, f32]  # table
        + [ptr, ptr, ptr, ptr, ptr, ptr, f32, f32]  # eye, origins, dirs, valid, t0, t1, near, far
        + [i64, i64, f32, f32]  # h, w, step, stop
        + [ptr, i64, i64, i64, f32, f32, f32]  # nodes
        + [ptr, i64, i64, i64, i64, i64]  # leap
        + [cint, f32, f32, f32]  # light
        + [ptr, ptr, cint, i64]  # out, depth, threads, tile
    )
    return native.entry(_SOURCE, "march", argtypes, what="the ray-marching kernel")


# ------------------------------------------------------------------ per-volume data (cached)
class _Prepared:
    """The kernel's copy of a volume (edges repeated) and the value range of each block (with its apron)."""

    def __init__(self, vol: torch.Tensor, block: int):
        v = vol.detach().to(dtype=torch.float32, device="cpu").contiguous()
        D, H, W = v.shape
        self.shape = (D, H, W)
        v5 = v[None, None]
        self.padded = F.pad(v5, (_PAD_LO, _PAD_HI) * 3, mode="replicate")[0, 0].contiguous()
        nb = [max(1, math.ceil(n / block)) for n in (D, H, W)]
        extra = [b * block - n for b, n in zip(nb, (D, H, W))]
        ap = F.pad(v5, (1, extra[2] + 1, 1, extra[1] + 1, 1, extra[0] + 1), mode="replicate")
        k = block + 2
        self.bmax = F.max_pool3d(ap, k, stride=block)[0, 0].double()
        self.bmin = -F.max_pool3d(-ap, k, stride=block)[0, 0].double()
        self.block = block
        self.leaps: dict = {}  # leap distances per transfer-function table (:func:`_leap`)


_CACHE: OrderedDict = OrderedDict()
_CACHE_SIZE = 2


def _prepared(vol: torch.Tensor, block: int) -> _Prepared:
    key = (vol.data_ptr(), vol.device.type, vol.dtype, tuple(vol.shape), tuple(vol.stride()), vol._version, block)
    hit = _CACHE.get(key)
    if hit is not None:
        _CACHE.move_to_end(key)
        return hit[1]
    prep = _Prepared(vol, block)
    _CACHE[key] = (vol, prep)  # holds the tensor: its storage (the key's pointer) is not reused while cached
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return prep


def _leap(prep: _Prepared, table: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    """Leap distances per block ``(BD, BH, BW)`` uint8: Chebyshev distance (blocks) to an occupied block, capped.

    Cached on the prepared volume per table (its bytes) and range: a deforming volume reuses it (the
    kernel subtracts the offsets' dilation).
    """
    key = (hashlib.sha1(table.numpy().tobytes()).hexdigest(), lo, hi)
    hit = prep.leaps.get(key)
    if hit is not None:
        return hit
    R = table.shape[0]
    nz = torch.cumsum((table[:, 3].double() > 0).to(torch.int64), 0)
    nz = torch.cat([nz.new_zeros(1), nz])  # nz[i] = entries < i with sigma > 0
    scale = (R - 1) / (hi - lo)
    ilo = ((prep.bmin - lo) * scale).floor().clamp(0, R - 1).long() - 1  # one entry of margin for rounding
    ihi = ((prep.bmax - lo) * scale).ceil().clamp(0, R - 1).long() + 1
    ilo, ihi = ilo.clamp(0, R - 1), ihi.clamp(0, R - 1)
    occ = (nz[ihi + 1] - nz[ilo]) > 0
    o = occ.float()[None, None]
    dist = torch.zeros(o.shape, dtype=torch.uint8)
    for _ in range(MAX_LEAP):
        empty = o == 0
        if not bool(empty.any()):
            break
        dist += empty.to(torch.uint8)
        o = F.max_pool3d(o, 3, stride=1, padding=1)
    dist = dist[0, 0].contiguous()
    if len(prep.leaps) >= 4:
        prep.leaps.clear()
    prep.leaps[key] = dist
    return dist


# ------------------------------------------------------------------ rays
def clip_rays(eye, dirs, shape, *, near: float = 0.0, far: float = math.inf):
    """``(t0, t1)``: where rays enter and leave the volume's box, kept within ``[max(near, 0), far]``.

    Args:
        eye: ``(3,)`` voxel coordinates ``(D, H, W)``.
        dirs: ``(3, *S)`` unit directions (``S``: e.g. ``(h, w)``).
        shape: the volume ``(D, H, W)``; its box is ``[-0.5, N - 0.5]`` per axis.
        near: the start of the range of ``t`` (voxels along the ray) to keep.
        far: its end.

    Returns:
        ``t0``, ``t1`` of shape ``S`` (float32); a ray that misses the box (or the range) has
        ``t1 <= t0``. A direction component below 1e-12 is parallel to that pair of faces: the
        whole line when the eye is between them, nothing otherwise (as
        :func:`~torchdeform.volume.render_endoscope`).
    """
    d = torch.as_tensor(dirs).detach().to(dtype=torch.float32, device="cpu")
    S = d.shape[1:]
    d = d.reshape(3, -1)
    e = torch.as_tensor(eye).detach().to(dtype=torch.float32, device="cpu").reshape(3, 1)
    lo_b = torch.full((3, 1), -0.5)
    hi_b = torch.tensor([float(n) - 0.5 for n in shape]).view(3, 1)
    small = d.abs() < 1e-12
    inv = 1.0 / torch.where(small, torch.full_like(d, 1e-12), d)
    ta, tb = (lo_b - e) * inv, (hi_b - e) * inv
    between = (e >= lo_b) & (e <= hi_b)
    t_in = torch.where(small, torch.where(between, -math.inf, math.inf), torch.minimum(ta, tb))
    t_out = torch.where(small, torch.where(between, math.inf, -math.inf), torch.maximum(ta, tb))
    t0 = t_in.amax(0).clamp(min=max(float(near), 0.0))
    t1 = t_out.amin(0).clamp(max=float(far))
    return t0.reshape(S), t1.reshape(S)


def _as_rays(dirs, h: int, w: int) -> torch.Tensor:
    """``(3, h w)`` float32 contiguous (no copy when it already is) from ``(3, h, w)``, ``(3, h w)`` or ``(h, w, 3)``."""
    d = torch.as_tensor(dirs).detach().to(dtype=torch.float32, device="cpu")
    P = h * w
    if tuple(d.shape) in ((3, h, w), (3, P)):
        return d.reshape(3, P).contiguous()
    if tuple(d.shape) in ((h, w, 3), (P, 3)):
        return d.reshape(P, 3).t().contiguous()
    raise ValueError(f"ray directions of shape (3, {h}, {w}) or ({P}, 3), got {tuple(d.shape)}")


def _light_flag(light) -> bool:
    if light in (None, False, "none", "off", "flat"):
        return False
    if light in (True, "headlight", "on"):
        return True
    raise ValueError(f'light: "headlight", None, True or False, got {light!r}')


def render(
    volume,
    table,
    lo: float,
    hi: float,
    eye,
    dirs,
    *,
    t0=None,
    t1=None,
    valid=None,
    origins=None,
    near: float = 0.0,
    far: float = math.inf,
    step: float = 0.5,
    stop: float = 1e-3,
    offsets=None,
    light="headlight",
    ambient: float = 0.2,
    diffuse: float = 0.8,
    skip_empty: bool = True,
    block: int = BLOCK,
    threads: int | None = None,
):
    """Image and depth of rays through a volume, by the C kernel (no gradient; CPU, float32 inside).

    Args:
        volume: ``(D, H, W)`` or ``(B, 1, D, H, W)``.
        table: the transfer function's table ``(R, 4)`` (RGB, sigma per voxel) over ``[lo, hi]``
            (:meth:`~torchdeform.volume.TransferFunction.table`, ``tf.range(volume=...)``).
        lo: the value of the table's first entry (volume units).
        hi: the value of its last entry.
        eye: ``(3,)`` voxel coordinates: where every ray starts (a perspective view).
        origins: ``(3, h, w)`` voxel coordinates, each ray's own start (an orthographic view: the
            same direction from a plane of origins), or None (every ray starts at ``eye``).
        dirs: unit directions ``(3, h, w)`` (or ``(3, h w)``, ``(h, w, 3)``, ``(h w, 3)`` with ``valid``
            or ``t0`` giving ``(h, w)``); ``(3, h, w)`` float32 contiguous is read without a copy.
        t0: ``(h, w)`` where the rays start, in voxels (:func:`clip_rays`), or None: the kernel clips
            each ray to the volume's box and to ``[max(near, 0), far]`` itself (as :func:`clip_rays`).
        t1: ``(h, w)`` where they end, or None (with ``t0``).
        near: the start of the range along the rays when ``t0`` and ``t1`` are None.
        far: its end.
        valid: ``(h, w)`` bool, or None (all); invalid pixels get zeros and depth ``inf``.
        step: segment length (voxels).
        stop: early ray termination once the transmittance is below this (0: never).
        offsets: node offsets ``(3, n_d, n_h, n_w)`` or ``(B or 1, 3, ...)`` in voxels, or None.
        light: ``"headlight"``/True (two-sided, ``ambient + diffuse |g.d|/|g|``) or None/False.
        ambient: the headlight's ambient term.
        diffuse: its diffuse term.
        skip_empty: empty-space leaping (same image; off only to compare).
        block: voxels per side of a leaping block.
        threads: OpenMP threads (default ``torch.get_num_threads()``).

    Returns:
        ``(image (B, 4, h, w), depth (B, h, w))`` float32: premultiplied RGB and alpha; the ``t``
        where alpha first exceeds 1/2 (``inf`` if never; the module docstring).

    Raises:
        NativeBuildError: no C compiler (see :func:`unavailable`) or the build failed.
    """
    fn = _function()
    vol = torch.as_tensor(volume)
    if vol.dim() == 3:
        vol = vol[None, None]
    if vol.dim() != 5 or vol.shape[1] != 1:
        raise ValueError(f"volume of shape (D, H, W) or (B, 1, D, H, W), got {tuple(vol.shape)}")
    B, shape = vol.shape[0], tuple(int(n) for n in vol.shape[2:])
    if (t0 is None) != (t1 is None):
        raise ValueError("t0 and t1 both, or neither (the kernel clips the rays)")
    if t0 is not None:
        t0 = torch.as_tensor(t0).detach().to(dtype=torch.float32, device="cpu").contiguous()
        t1 = torch.as_tensor(t1).detach().to(dtype=torch.float32, device="cpu").contiguous()
    if valid is not None:
        valid = torch.as_tensor(valid).detach().to(device="cpu")
    ref = valid if valid is not None else (t0 if t0 is not None else torch.as_tensor(dirs)[0])
    if ref.dim() != 2:
        raise ValueError(f"t0 / valid / dirs[0] of shape (h, w), got {tuple(ref.shape)}")
    h, w = int(ref.shape[0]), int(ref.shape[1])
    if t0 is not None and (tuple(t0.shape) != (h, w) or tuple(t1.shape) != (h, w)):
        raise ValueError(f"t0 and t1 of shape ({h}, {w}), got {tuple(t0.shape)} and {tuple(t1.shape)}")
    d = _as_rays(dirs, h, w)
    e = torch.as_tensor(eye).detach().to(dtype=torch.float32, device="cpu").reshape(3).contiguous()
    orgs = None
    if origins is not None:
        orgs = torch.as_tensor(origins).detach().to(dtype=torch.float32, device="cpu").contiguous()
        if tuple(orgs.shape) != (3, h, w):
            raise ValueError(f"origins of shape (3, {h}, {w}), got {tuple(orgs.shape)}")
    tab = torch.as_tensor(table).detach().to(dtype=torch.float32, device="cpu").contiguous()
    if tab.dim() != 2 or tab.shape[1] != 4 or tab.shape[0] < 2:
        raise ValueError(f"a transfer-function table (R >= 2, 4), got {tuple(tab.shape)}")
    lo, hi = float(lo), float(hi)
    if not hi > lo:
        raise ValueError(f"a value range lo < hi, got {(lo, hi)}")
    v8 = None if valid is None else valid.to(torch.uint8).contiguous()
    u = None
    if offsets is not None:
        u = torch.as_tensor(offsets).detach().to(dtype=torch.float32, device="cpu")
        u = u[None] if u.dim() == 4 else u
        if u.dim() != 5 or u.shape[1] != 3:
            raise ValueError(f"node offsets (3, n_d, n_h, n_w) or (B, 3, ...), got {tuple(u.shape)}")
        B = max(B, u.shape[0])
    nt = int(threads or torch.get_num_threads())
    light_on = _light_flag(light)
    images = torch.empty(B, 4, h, w, dtype=torch.float32)
    depths = torch.empty(B, h, w, dtype=torch.float32)
    null = ctypes.c_void_p(None)
    for bi in range(B):
        vb = vol[bi if vol.shape[0] > 1 else 0, 0]
        prep = _prepared(vb, int(block))
        nodes, nn, nc, dil = null, (1, 1, 1), (0.0, 0.0, 0.0), 0
        if u is not None:
            ub = u[bi if u.shape[0] > 1 else 0]
            nn = tuple(int(n) for n in ub.shape[1:])
            nodes_t = F.pad(ub.permute(1, 2, 3, 0), (0, 1)).contiguous()  # (nd, nh, nw, 4)
            nodes = nodes_t.data_ptr()
            nc = tuple((n - 1) / max(N - 1, 1) for n, N in zip(nn, shape))
            umax = float(ub.abs().max()) if ub.numel() else 0.0
            dil = math.ceil(math.ceil(umax) / block) if umax > 0 else 0
        leap_t = _leap(prep, tab, lo, hi) if skip_empty else None
        BD, BH, BW = prep.bmax.shape
        rc = fn(
            prep.padded.data_ptr(),
            *shape,
            tab.data_ptr(),
            tab.shape[0],
            lo,
            (tab.shape[0] - 1) / (hi - lo),
            e.data_ptr(),
            null if orgs is None else orgs.data_ptr(),
            d.data_ptr(),
            null if v8 is None else v8.data_ptr(),
            null if t0 is None else t0.data_ptr(),
            null if t1 is None else t1.data_ptr(),
            float(near),
            float(far),
            h,
            w,
            float(step),
            float(stop),
            nodes,
            *nn,
            *nc,
            null if leap_t is None else leap_t.data_ptr(),
            int(block),
            BD,
            BH,
            BW,
            dil,
            int(light_on),
            float(ambient),
            float(diffuse),
            1e-6 * (hi - lo),
            images[bi].data_ptr(),
            depths[bi].data_ptr(),
            nt,
            TILE,
        )
        if rc:
            raise RuntimeError(f"native ray marcher failed ({rc})")
    return images, depths


def render_endoscope_native(plan):
    """:func:`~torchdeform.volume.render_endoscope`'s resolved ``plan`` by the kernel: ``(image, depth)`` or None.

    The hook its ``engine="auto"`` calls when no gradient is needed. None (the caller falls back to
    torch) where the kernel does not apply: no C compiler, a volume not float32 or not on the CPU
    (float64 stays on the exact path), a gradient needed. The camera's rays are clipped to the box
    and to ``[near, far]`` (:func:`clip_rays`), then to the first opaque surface, whose headlit colour
    is composited behind the volume with the remaining transmittance (as the torch engine does).

    Returns:
        ``image (B, 4, h, w)``, ``depth (B, h, w)``, float32 on the CPU.
    """
    vol = plan.volume
    if plan.needs_grad or vol.dtype != torch.float32 or vol.device.type != "cpu" or unavailable() is not None:
        return None
    cam, light = plan.camera, plan.light
    eye, dirs, valid = plan.eye.detach(), plan.dirs.detach(), plan.valid
    h, w = valid.shape
    t0 = t1 = None  # the kernel clips the rays to the box and [near, far]
    d_all = dirs.reshape(3, -1)
    t_hit = s_rgb = None
    if plan.surfaces:
        t0, t1 = clip_rays(eye, dirs, tuple(vol.shape[2:]), near=float(cam.near), far=float(cam.far))
        t_hit, s_rgb = plan.surface_hits(eye, d_all)
        t_hit = t_hit.view(h, w)
        t1 = torch.minimum(t1, t_hit)
    kw = dict(light=None) if light is None else dict(light=True, ambient=light.ambient, diffuse=light.diffuse)
    img, depth = render(
        vol,
        plan.table,
        plan.lo,
        plan.hi,
        eye,
        dirs,
        t0=t0,
        t1=t1,
        valid=valid,
        near=float(cam.near),
        far=float(cam.far),
        step=plan.step,
        stop=plan.stop,
        offsets=None if plan.field is None else plan.field.nodes,
        skip_empty=plan.skip_empty,
        **kw,
    )
    if t_hit is not None:
        hit = (torch.isfinite(t_hit) & valid.to(torch.bool))[None]  # (1, h, w)
        T = 1 - img[:, 3]
        rgb = s_rgb.view(3, h, w)[None] * T[:, None]
        img[:, :3] = torch.where(hit[:, None], img[:, :3] + rgb, img[:, :3])
        depth = torch.where(hit & (T >= 0.5) & torch.isinf(depth), t_hit.expand_as(depth), depth)
        img[:, 3] = torch.where(hit, torch.ones_like(T), img[:, 3])
    if img.shape[0] != plan.batch:
        img, depth = img.expand(plan.batch, *img.shape[1:]), depth.expand(plan.batch, *depth.shape[1:])
    return img, depth


# ------------------------------------------------------------------ axis views of render()
def axis_blocker(plan) -> str | None:
    """Why the kernel cannot render :func:`~torchdeform.volume.render`'s resolved ``plan``, or None.

    It renders ``dvr`` axis views of float32 CPU volumes, directly or through linear node offsets
    (``warp_mode="deform"``, ``inverse_iters=0``) with the edge voxels repeated
    (``padding="border"``), no cut pieces, no gradient.
    """
    from .plan import AXIS_VIEWS

    field, vol = plan.field, plan.volume
    if not (isinstance(plan.view, str) and plan.view in AXIS_VIEWS):
        return "the kernel renders axis views (an OrbitCamera takes grid_sample)"
    if plan.mode != "dvr":
        return f"the kernel composites dvr (mode {plan.mode!r} takes grid_sample)"
    if plan.pieces is not None:
        return "a cut body's pieces take grid_sample"
    if field is not None and (field.order != "linear" or field.cell_centred or plan.inverse_iters):
        return "the kernel reads linear offsets, warp_mode='deform', inverse_iters=0"
    if plan.padding != "border":
        return "the kernel repeats the edge voxels (padding='border')"
    if vol.device.type != "cpu" or vol.dtype != torch.float32:
        return f"the kernel takes a float32 volume on the CPU (this one is {vol.dtype} on {vol.device.type})"
    needs = [vol, plan.table] + ([field.nodes] if field is not None else [])
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in needs):
        return "a gradient is needed (the kernel has none)"
    return unavailable()


def render_axis_native(plan) -> torch.Tensor:
    """An axis view of :func:`~torchdeform.volume.render`'s resolved ``plan`` by the kernel: ``(B, 4, h, w)``.

    Parallel rays along the view's axis, one per pixel, each from its pixel's point on the face of
    the box ``[-0.5, N - 0.5]`` the view enters; ``step`` the slab thickness of
    :meth:`~torchdeform.volume.plan.RenderPlan.axis_samples`, so the kernel's midpoint samples are
    the slab centres the ``grid_sample`` engine reads. Early ray termination is per ray (the
    torch engines stop a chunk of slabs once every ray is below ``stop``): pixels differ by at most
    ``stop`` in alpha. Call :func:`axis_blocker` first.
    """
    lat = plan.axis_samples()
    shape, h, w = plan.shape, *lat.img_shape
    N = shape[lat.axis]
    grid = torch.meshgrid(lat.pix[0].float(), lat.pix[1].float(), indexing="ij")
    origins = torch.empty(3, h, w, dtype=torch.float32)
    origins[lat.others[0]], origins[lat.others[1]] = grid
    origins[lat.axis] = N - 0.5 if lat.reverse else -0.5
    dirs = torch.zeros(3, h, w, dtype=torch.float32)
    dirs[lat.axis] = -1.0 if lat.reverse else 1.0
    t0, t1 = torch.zeros(h, w), torch.full((h, w), float(N))
    assert plan.table is not None and plan.lo is not None and plan.hi is not None  # dvr
    image, _ = render(
        plan.volume,
        plan.table,
        plan.lo,
        plan.hi,
        torch.zeros(3),
        dirs,
        t0=t0,
        t1=t1,
        origins=origins,
        step=lat.dt,
        stop=plan.stop,
        offsets=None if plan.field is None else plan.field.nodes,
        light=None,
    )
    return image
