"""MATLAB's remaining membership functions and fuzzylite's extra terms against independent oracles.

Oracles (none of them produced by torchdeform):

* ``skfuzzy.membership`` (scikit-fuzzy 0.5) for zmf, smf, pimf, dsigmf, psigmf and gauss2mf,
  with its own parameter orders (sigmoids ``(center, slope)``, gauss2mf ``(mean1, sigma1,
  mean2, sigma2)``); dsigmf compared in absolute value, as MATLAB's dsigmf.m and fuzzylite's
  SigmoidDifference compute it (scikit-fuzzy's is signed);
* the published formulas written out in numpy below for the kinds scikit-fuzzy lacks: MATLAB's
  linsmf, linzmf (MathWorks documentation) and gauss2mf with ``c1 > c2`` (MATLAB's gauss2mf.m:
  the product of both one-sided Gaussians); fuzzylite's Ramp, Rectangle, Concave, Cosine, Spike,
  Binary and Discrete (fuzzylite's documentation; Discrete is ``numpy.interp``);
* finite differences (``torch.autograd.gradcheck``) for gradients, at points away from kinks.

Tolerance: 1e-6 in float64 on seeded random parameters and points.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import skfuzzy as fuzz
import torch
from torch.func import functional_call

from tests.helpers import F64
from tests.oracles.fuzzy import default_dtype
from torchdeform.errors import ConfigError
from torchdeform.fuzzy import (
    KINDS,
    Binary,
    Concave,
    Cosine,
    DiffSigmoid,
    Discrete,
    Gaussian2,
    LinS,
    LinZ,
    PiShape,
    ProdSigmoid,
    Ramp,
    Rectangle,
    Spike,
    SShape,
    ZShape,
)
from torchdeform.fuzzy.membership import make

NEW = (
    "zshape",
    "sshape",
    "pishape",
    "dsigmoid",
    "psigmoid",
    "gaussian2",
    "lins",
    "linz",
    "ramp",
    "rectangle",
    "concave",
    "cosine",
    "spike",
    "binary",
    "discrete",
)
TRIALS = 40


def _rng(kind: str) -> np.random.Generator:
    return np.random.default_rng(sum(map(ord, kind)) * 7919)


def _random_params(kind: str, rng: np.random.Generator) -> list:
    """Sensible random parameters of ``kind`` in our (= the .fis) order, on a universe near [-10, 10]."""
    if kind in ("zshape", "sshape", "lins", "linz", "rectangle"):
        return sorted(rng.uniform(-8, 8, 2).tolist())
    if kind == "pishape":
        return sorted(rng.uniform(-8, 8, 4).tolist())
    if kind in ("dsigmoid", "psigmoid"):
        a1, a2 = rng.uniform(0.3, 4.0, 2) * rng.choice([-1.0, 1.0], 2)
        c1, c2 = rng.uniform(-6, 6, 2)
        return [float(a1), float(c1), float(a2), float(c2)]
    if kind == "gaussian2":
        s1, s2 = rng.uniform(0.3, 3.0, 2)
        c1, c2 = rng.uniform(-6, 6, 2)
        return [float(s1), float(c1), float(s2), float(c2)]
    if kind in ("ramp", "concave", "binary"):
        a, b = rng.uniform(-8, 8, 2)
        return [float(a), float(b)]
    if kind in ("cosine", "spike"):
        return [float(rng.uniform(-6, 6)), float(rng.uniform(0.5, 8.0))]
    if kind == "discrete":
        n = int(rng.integers(1, 7))
        xs = np.sort(rng.uniform(-8, 8, n))
        ys = rng.uniform(0, 1, n)
        return np.stack([xs, ys], 1).reshape(-1).tolist()
    raise AssertionError(kind)


def _points(rng: np.random.Generator, n: int = 301) -> np.ndarray:
    return np.sort(rng.uniform(-12, 12, n))


def _mf(kind: str, params: list):
    """``make(kind, *params)`` with its parameters made in float64 (not rounded to float32 first)."""
    with default_dtype(F64):
        return make(kind, *params)


def _torch(mf, x: np.ndarray) -> np.ndarray:
    return mf(torch.tensor(x, dtype=F64)).detach().numpy()


# ----------------------------------------------------------------- numpy oracles (published formulas)


def np_linsmf(x, a, b):
    """MATLAB linsmf: 0 for x < a, (x - a)/(b - a) on [a, b], 1 for x > b; a == b: 1 for x >= a."""
    if a == b:
        return (x >= a).astype(float)
    return np.where(x < a, 0.0, np.where(x > b, 1.0, (x - a) / (b - a)))


def np_linzmf(x, a, b):
    """MATLAB linzmf: 1 for x < a, (b - x)/(b - a) on [a, b], 0 for x > b; a == b: 1 for x < a."""
    if a == b:
        return (x < a).astype(float)
    return np.where(x < a, 1.0, np.where(x > b, 0.0, (b - x) / (b - a)))


def np_gauss2mf_matlab(x, s1, c1, s2, c2):
    """MATLAB gauss2mf.m: (left Gaussian where x <= c1, else 1) * (right Gaussian where x >= c2, else 1)."""
    y1 = np.where(x <= c1, np.exp(-((x - c1) ** 2) / (2 * s1**2)), 1.0)
    y2 = np.where(x >= c2, np.exp(-((x - c2) ** 2) / (2 * s2**2)), 1.0)
    return y1 * y2


def np_ramp(x, start, end):
    """fuzzylite Ramp: rising (start < end) 0 at/below start, 1 at/above end; falling mirrored."""
    if start < end:
        return np.where(x <= start, 0.0, np.where(x >= end, 1.0, (x - start) / (end - start)))
    return np.where(x >= start, 0.0, np.where(x <= end, 1.0, (start - x) / (start - end)))


def np_rectangle(x, start, end):
    """fuzzylite Rectangle: 1 for start <= x <= end."""
    return ((x >= start) & (x <= end)).astype(float)


def np_concave(x, i, e):
    """fuzzylite Concave: increasing (i <= e) (e - i)/(2e - i - x) for x < e; decreasing (i - e)/(i - 2e + x) for x > e; else 1."""
    out = np.ones_like(x)
    if i <= e:
        m = x < e
        out[m] = (e - i) / (2 * e - i - x[m])
    else:
        m = x > e
        out[m] = (i - e) / (i - 2 * e + x[m])
    return out


def np_cosine(x, c, w):
    """fuzzylite Cosine: 0 outside [c - w/2, c + w/2], else 0.5 (1 + cos(2 pi (x - c) / w))."""
    inside = (x >= c - 0.5 * w) & (x <= c + 0.5 * w)
    return np.where(inside, 0.5 * (1 + np.cos(2.0 / w * np.pi * (x - c))), 0.0)


def np_spike(x, c, w):
    """fuzzylite Spike: exp(-|10 / w (x - c)|)."""
    return np.exp(-np.abs(10.0 / w * (x - c)))


def np_binary(x, start, direction):
    """fuzzylite Binary: 1 where direction > start and x >= start, or direction < start and x <= start."""
    return (((direction > start) & (x >= start)) | ((direction < start) & (x <= start))).astype(float)


def np_discrete(x, *xy):
    """fuzzylite Discrete on distinct ascending x: linear interpolation, end values held outside."""
    xs, ys = np.asarray(xy[0::2]), np.asarray(xy[1::2])
    return np.interp(x, xs, ys)


def oracle(kind: str, x: np.ndarray, p: list) -> np.ndarray:
    """The independent value of ``kind`` with parameters ``p`` (our order) at ``x``."""
    if kind == "zshape":
        return fuzz.zmf(x, p[0], p[1])
    if kind == "sshape":
        return fuzz.smf(x, p[0], p[1])
    if kind == "pishape":
        return fuzz.pimf(x, *p)
    if kind == "dsigmoid":  # skfuzzy: (center, slope) pairs; MATLAB/fuzzylite: absolute value
        return np.abs(fuzz.dsigmf(x, p[1], p[0], p[3], p[2]))
    if kind == "psigmoid":
        return fuzz.psigmf(x, p[1], p[0], p[3], p[2])
    if kind == "gaussian2":
        if p[1] <= p[3]:  # skfuzzy: (mean1, sigma1, mean2, sigma2), mean1 <= mean2 only
            return fuzz.gauss2mf(x, p[1], p[0], p[3], p[2])
        return np_gauss2mf_matlab(x, *p)
    fn = {
        "lins": np_linsmf,
        "linz": np_linzmf,
        "ramp": np_ramp,
        "rectangle": np_rectangle,
        "concave": np_concave,
        "cosine": np_cosine,
        "spike": np_spike,
        "binary": np_binary,
        "discrete": np_discrete,
    }[kind]
    return fn(x, *p)


# ----------------------------------------------------------------- values


@pytest.mark.parametrize("kind", NEW)
def test_against_oracle(kind):
    """Every new kind equals its oracle to 1e-6 on random parameters and points (float64)."""
    rng = _rng(kind)
    for _ in range(TRIALS):
        p = _random_params(kind, rng)
        x = _points(rng)
        if kind in ("rectangle", "binary"):  # the breakpoints themselves: the boundary convention
            x = np.concatenate([x, p[:1], p[-1:] if kind == "rectangle" else []])
        np.testing.assert_allclose(_torch(_mf(kind, p), x), oracle(kind, x, p), atol=1e-6, err_msg=f"{kind} {p}")


def test_gaussian2_overlap_peaks_below_one():
    """gauss2mf with c1 > c2: the product of both sides is below 1 in the middle (MATLAB), peak() at its maximum."""
    mf = Gaussian2(1.0, 2.0, 2.0, -1.0).to(F64)
    x = np.linspace(-8, 8, 16001)
    y = _torch(mf, x)
    np.testing.assert_allclose(y, np_gauss2mf_matlab(x, 1.0, 2.0, 2.0, -1.0), atol=1e-12)
    assert y.max() < 1.0
    assert mf.peak() == pytest.approx(x[np.argmax(y)], abs=2e-3)


def test_matlab_step_cases():
    """a == b: smf/linsmf are 1 from a on, zmf 1 up to and including a, linzmf 1 only below a (MATLAB)."""
    x = torch.tensor([-1.0, 2.0, 3.0], dtype=F64)
    assert SShape(2.0, 2.0).to(F64)(x).tolist() == [0.0, 1.0, 1.0]
    assert ZShape(2.0, 2.0).to(F64)(x).tolist() == [1.0, 1.0, 0.0]
    assert LinS(2.0, 2.0).to(F64)(x).tolist() == [0.0, 1.0, 1.0]
    assert LinZ(2.0, 2.0).to(F64)(x).tolist() == [1.0, 0.0, 0.0]
    assert PiShape(0.0, 0.0, 2.0, 2.0).to(F64)(x).tolist() == [0.0, 1.0, 0.0]


def test_fuzzylite_boundary_conventions():
    """Rectangle includes both ends, Binary includes start, Discrete holds its end values (fuzzylite)."""
    x = torch.tensor([0.999, 1.0, 2.0, 3.0, 3.001], dtype=F64)
    assert Rectangle(1.0, 3.0).to(F64)(x).tolist() == [0.0, 1.0, 1.0, 1.0, 0.0]
    assert Binary(1.0, 5.0).to(F64)(x).tolist() == [0.0, 1.0, 1.0, 1.0, 1.0]
    assert Binary(1.0, -math.inf).to(F64)(x).tolist() == [1.0, 1.0, 0.0, 0.0, 0.0]
    assert Binary(1.0, math.inf).values() == [1.0, 2.0]  # fuzzylite writes the direction as +-inf
    d = Discrete(1.0, 0.2, 2.0, 1.0, 3.0, 0.4).to(F64)
    assert d(torch.tensor([-5.0, 1.5, 2.5, 50.0], dtype=F64)).tolist() == pytest.approx([0.2, 0.6, 0.7, 0.4])
    # a vertical jump: the first point's y at the repeated x, the last one's to the right
    j = Discrete(0.0, 0.0, 1.0, 0.2, 1.0, 0.9, 2.0, 1.0).to(F64)
    assert j(torch.tensor([1.0, 1.5], dtype=F64)).tolist() == pytest.approx([0.2, 0.95])
    assert Concave(0.0, 1.0).to(F64)(torch.tensor([0.0, 1.0, 5.0], dtype=F64)).tolist() == [0.5, 1.0, 1.0]
    assert Concave(1.0, 0.0).to(F64)(torch.tensor([1.0, 0.0, -5.0], dtype=F64)).tolist() == [0.5, 1.0, 1.0]


@pytest.mark.parametrize("kind", NEW)
def test_degrees_in_unit_interval_any_shape(kind):
    """Degrees lie in [0, 1], keep the input's shape and stay finite, also for float32."""
    rng = _rng(kind)
    for _ in range(10):
        mf = make(kind, *_random_params(kind, rng))
        x = torch.tensor(rng.uniform(-1e3, 1e3, (3, 4, 5)), dtype=torch.float32)
        y = mf(x)
        assert y.shape == x.shape and y.dtype == x.dtype
        assert torch.isfinite(y).all() and (y >= 0).all() and (y <= 1).all()


# ----------------------------------------------------------------- gradients and constraints


def _kinks(kind: str, p: list) -> list:
    """Points where the degree has a kink or a jump (gradcheck stays away from them)."""
    if kind == "discrete":
        return p[0::2]
    if kind in ("dsigmoid", "psigmoid"):
        return []
    if kind == "gaussian2":
        return [p[1], p[3]]
    if kind == "cosine":
        return [p[0] - p[1] / 2, p[0] + p[1] / 2]
    if kind == "spike":
        return [p[0]]
    if kind == "concave":
        return [p[1]]
    if kind == "binary":
        return [p[0]]
    out = list(p)
    if kind in ("zshape", "sshape", "pishape"):
        out += [(p[0] + p[1]) / 2, (p[-2] + p[-1]) / 2]
    return out


@pytest.mark.parametrize("kind", NEW)
def test_gradcheck_raw(kind):
    """Analytic gradients with respect to ``raw`` match finite differences (float64, away from kinks)."""
    rng = _rng(kind)
    for _ in range(3):
        p = _random_params(kind, rng)
        mf = _mf(kind, p)
        x = _points(rng, 200)
        kinks = np.asarray(_kinks(kind, p) or [np.inf])
        x = torch.tensor(x[np.min(np.abs(x[:, None] - kinks[None, :]), axis=1) > 1e-3], dtype=F64)
        if kind == "dsigmoid":  # |f1 - f2| has a kink where f1 == f2
            f1 = torch.sigmoid(p[0] * (x - p[1]))
            f2 = torch.sigmoid(p[2] * (x - p[3]))
            x = x[(f1 - f2).abs() > 1e-4]
        raw = mf.raw.detach().clone().requires_grad_(True)
        f = lambda r, mf=mf, x=x: functional_call(mf, {"raw": r}, (x,))
        assert torch.autograd.gradcheck(f, (raw,), eps=1e-7, atol=1e-5)


@pytest.mark.parametrize("kind", NEW)
def test_gradients_finite_everywhere(kind):
    """Gradients are finite at every point, kinks and breakpoints included."""
    rng = _rng(kind)
    p = _random_params(kind, rng)
    mf = _mf(kind, p).requires_grad_()
    x = torch.tensor(np.concatenate([_points(rng), np.asarray(_kinks(kind, p) + p)]), dtype=F64, requires_grad=True)
    y = mf(x)
    if kind in ("rectangle", "binary"):  # steps: no gradient at all, as for a singleton
        assert not y.requires_grad
        return
    y.sum().backward()
    assert torch.isfinite(mf.raw.grad).all() and torch.isfinite(x.grad).all()


ORDERED = {
    "zshape": (ZShape, (1.0, 2.0)),
    "sshape": (SShape, (1.0, 2.0)),
    "pishape": (PiShape, (0.0, 1.0, 2.0, 3.0)),
    "lins": (LinS, (1.0, 2.0)),
    "linz": (LinZ, (1.0, 2.0)),
    "rectangle": (Rectangle, (1.0, 2.0)),
}


@pytest.mark.parametrize("kind", sorted(ORDERED))
def test_order_kept_after_a_breaking_step(kind):
    """A gradient step that pushes the points out of order leaves the effective points ordered."""
    cls, p = ORDERED[kind]
    mf = cls(*p).to(F64).requires_grad_()
    push = torch.linspace(1.0, -1.0, len(p), dtype=F64)  # the first point up, the last down
    (mf.raw * push).sum().neg().backward()
    with torch.no_grad():
        mf.raw -= 10.0 * mf.raw.grad
    assert (mf.raw.diff() < 0).any()
    assert (mf.params.diff() >= 0).all()
    y = mf(torch.linspace(-20, 20, 401, dtype=F64))
    assert torch.isfinite(y).all() and (y >= 0).all() and (y <= 1).all()


def test_discrete_and_width_constraints_after_a_breaking_step():
    """Discrete keeps x ascending and y in [0, 1]; widths and sigmas stay positive; ramps never divide by 0."""
    d = Discrete(0.0, 0.1, 1.0, 0.9, 2.0, 0.5).to(F64)
    with torch.no_grad():
        d.raw.copy_(torch.tensor([3.0, -0.5, 1.0, 1.7, 2.0, 0.5], dtype=F64))
    p = d.params
    assert (p[0::2].diff() >= 0).all() and (p[1::2] >= 0).all() and (p[1::2] <= 1).all()
    assert torch.isfinite(d(torch.linspace(-5, 5, 101, dtype=F64))).all()
    for mf, idx in ((Gaussian2(1.0, 0.0, 1.0, 1.0), (0, 2)), (Cosine(0.0, 1.0), (1,)), (Spike(0.0, 1.0), (1,))):
        mf = mf.to(F64)
        with torch.no_grad():
            for i in idx:
                mf.raw[i] = 0.0
        assert all(float(mf.params[i]) > 0 for i in idx)
        assert torch.isfinite(mf(torch.linspace(-5, 5, 101, dtype=F64))).all()
    for mf in (Ramp(0.0, 1.0), Concave(0.0, 1.0)):
        mf = mf.to(F64).requires_grad_()
        with torch.no_grad():
            mf.raw[1] = mf.raw[0]
        y = mf(torch.linspace(-5, 5, 101, dtype=F64))
        y.sum().backward()
        assert torch.isfinite(y).all() and torch.isfinite(mf.raw.grad).all()


# ----------------------------------------------------------------- checks, registry, support and peak

REFUSED = [
    ("dsigmoid", (1.0, 2.0, 3.0)),
    ("psigmoid", (1.0, 2.0, 3.0, 4.0, 5.0)),
    ("zshape", (3.0, 1.0)),
    ("sshape", (3.0, 1.0)),
    ("pishape", (0.0, 2.0, 1.0, 3.0)),
    ("lins", (2.0, 1.0)),
    ("linz", (2.0, 1.0)),
    ("rectangle", (2.0, 1.0)),
    ("gaussian2", (0.0, 1.0, 1.0, 2.0)),
    ("gaussian2", (1.0, 1.0, 0.0, 2.0)),
    ("ramp", (1.0, 1.0)),
    ("concave", (1.0, 1.0)),
    ("cosine", (0.0, 0.0)),
    ("cosine", (0.0, -1.0)),
    ("spike", (0.0, 0.0)),
    ("binary", (1.0, 1.0)),
    ("discrete", ()),
    ("discrete", (0.0, 0.5, 1.0)),
    ("discrete", (1.0, 0.5, 0.0, 0.5)),
    ("discrete", (0.0, 1.5, 1.0, 0.5)),
    ("discrete", (0.0, -0.1)),
    ("spike", (0.0, math.nan)),
    ("ramp", (0.0, math.inf)),
    ("binary", (math.inf, 1.0)),
    ("binary", (0.0, math.nan)),
]


@pytest.mark.parametrize(("kind", "params"), REFUSED, ids=[f"{k}-{i}" for i, (k, _) in enumerate(REFUSED)])
def test_check_refuses(kind, params):
    """Nonsense parameters raise ConfigError naming the kind."""
    with pytest.raises(ConfigError, match=kind):
        make(kind, *params)


def test_registry_names_and_orders():
    """KINDS maps every new kind to its class; parameter names follow the .fis (fuzzylite) order."""
    expected = {
        "zshape": ("a", "b"),
        "sshape": ("a", "b"),
        "pishape": ("a", "b", "c", "d"),
        "dsigmoid": ("a1", "c1", "a2", "c2"),
        "psigmoid": ("a1", "c1", "a2", "c2"),
        "gaussian2": ("sigma1", "c1", "sigma2", "c2"),
        "lins": ("a", "b"),
        "linz": ("a", "b"),
        "ramp": ("start", "end"),
        "rectangle": ("start", "end"),
        "concave": ("inflection", "end"),
        "cosine": ("center", "width"),
        "spike": ("center", "width"),
        "binary": ("start", "direction"),
    }
    for kind, names in expected.items():
        assert KINDS[kind].names == names and KINDS[kind].kind == kind
    assert KINDS["dsigmoid"] is DiffSigmoid and KINDS["psigmoid"] is ProdSigmoid
    d = make("discrete", 0.0, 0.0, 1.0, 1.0)
    assert d.names == ("x1", "y1", "x2", "y2") and d.values() == [0.0, 0.0, 1.0, 1.0]
    assert repr(d) == "Discrete(x1=0, y1=0, x2=1, y2=1)"
    assert repr(make("gaussian2", -2.0, 1.0, 3.0, 4.0)) == "Gaussian2(sigma1=2, c1=1, sigma2=3, c2=4)"


@pytest.mark.parametrize("kind", NEW)
def test_support_and_peak(kind):
    """support() is an ordered finite interval; peak() is finite and reaches the largest degree (within 1e-2)."""
    rng = _rng(kind)
    for _ in range(10):
        p = _random_params(kind, rng)
        if kind == "dsigmoid":  # a bump: same slope signs, c1 < c2
            p = [abs(p[0]), min(p[1], p[3]), abs(p[2]), max(p[1], p[3])]
        mf = _mf(kind, p)
        lo, hi = mf.support()
        assert math.isfinite(lo) and math.isfinite(hi) and lo <= hi
        pk = mf.peak()
        assert math.isfinite(pk)
        span = max(hi - lo, 1.0)
        x = torch.linspace(lo - span, hi + span, 20001, dtype=F64)
        best = float(mf(x).max())
        assert float(mf(torch.tensor([pk], dtype=F64))) >= best - 1e-2, (kind, p, pk)
