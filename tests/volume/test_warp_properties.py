"""Property tests (hypothesis) of :func:`torchdeform.volume.warp` against numpy slicing.

* identity: zero offsets give back the volume, bit for bit (every mode, padding, order and
  node grid), and to rounding when the offsets require a gradient (the interpolating path);
* uniform shift: the same integer offset ``d`` at every node moves the content by ``d`` voxels:
  ``out[p] = vol[p - d]`` wherever ``p - d`` lies inside the volume (``fill`` elsewhere with
  zero padding);
* composition: warping by ``d1`` and then by ``d2`` equals the numpy shift by ``d1 + d2`` where
  both steps read inside the volume.

The identity and the uniform shift run on the device of the run (``--device``).
"""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from torchdeform.volume import warp

SHAPES = st.tuples(*[st.integers(2, 9)] * 3)


@st.composite
def volumes(draw, shape=None):
    shape = draw(SHAPES) if shape is None else shape
    return draw(hnp.arrays(np.float64, shape, elements=st.floats(-1e3, 1e3, allow_subnormal=False)))


@st.composite
def node_shapes(draw, shape):
    return tuple(draw(st.integers(1, min(n, 5))) for n in shape)


def shifted(vol: np.ndarray, d) -> tuple[np.ndarray, np.ndarray]:
    """``(out, inside)``: ``out[p] = vol[p - d]`` where ``inside[p]`` (``p - d`` in the volume), else 0."""
    out, inside = np.zeros_like(vol), np.zeros(vol.shape, dtype=bool)
    dst = [np.array([p for p in range(n) if 0 <= p - k < n], dtype=np.int64) for k, n in zip(d, vol.shape)]
    out[np.ix_(*dst)] = vol[np.ix_(*[p - k for p, k in zip(dst, d)])]
    inside[np.ix_(*dst)] = True
    return out, inside


def uniform(d, nodes, dtype=torch.float64) -> torch.Tensor:
    return torch.tensor(d, dtype=dtype).view(3, 1, 1, 1).expand(3, *nodes).contiguous()


def test_shifted_oracle():
    vol = np.arange(24.0).reshape(2, 3, 4)
    out, inside = shifted(vol, (0, 1, -2))
    assert out[0, 1, 0] == vol[0, 0, 2] and inside[0, 1, 0] and not inside[0, 0, 0] and not inside[0, 1, 2]
    assert inside.sum() == 2 * 2 * 2
    assert not shifted(vol, (0, 0, 4))[1].any() and not shifted(vol, (-3, 0, 0))[1].any()


@settings(max_examples=60, deadline=None)
@given(
    data=st.data(),
    mode=st.sampled_from(["deform", "knoche", "carve"]),
    padding=st.sampled_from(["border", "zeros"]),
    order=st.sampled_from(["linear", "bspline"]),
    inverse_iters=st.integers(0, 3),
    dtype=st.sampled_from([torch.float32, torch.float64]),
)
def test_zero_offsets_are_the_identity(data, mode, padding, order, inverse_iters, dtype, device):
    vol = torch.from_numpy(data.draw(volumes())).to(dtype=dtype, device=device)
    nodes = data.draw(node_shapes(vol.shape))
    out = warp(
        vol,
        torch.zeros((3,) + nodes, dtype=dtype, device=device),
        mode=mode,
        padding=padding,
        order=order,
        inverse_iters=inverse_iters,
    )
    assert out.shape == vol.shape and out.dtype == vol.dtype and out.device == vol.device
    assert torch.equal(out, vol)


@settings(max_examples=40, deadline=None)
@given(data=st.data(), padding=st.sampled_from(["border", "zeros"]), order=st.sampled_from(["linear", "bspline"]))
def test_zero_offsets_with_gradient_interpolate_the_voxels(data, padding, order):
    vol = data.draw(volumes())
    nodes = data.draw(node_shapes(vol.shape))
    u = torch.zeros((3,) + nodes, dtype=torch.float64, requires_grad=True)
    out = warp(torch.from_numpy(vol), u, padding=padding, order=order)
    np.testing.assert_allclose(out.detach().numpy(), vol, rtol=0, atol=1e-9 * (1 + np.abs(vol).max()))


OFFSET = st.tuples(*[st.integers(-3, 3)] * 3)


@settings(max_examples=80, deadline=None)
@given(
    data=st.data(),
    d=OFFSET,
    mode=st.sampled_from(["deform", "knoche"]),
    padding=st.sampled_from(["border", "zeros"]),
    fill=st.floats(-5, 5),
)
def test_uniform_integer_offset_shifts_the_volume(data, d, mode, padding, fill, device):
    vol = data.draw(volumes())
    nodes = data.draw(node_shapes(vol.shape))
    out = warp(
        torch.from_numpy(vol).to(device),
        uniform(d, nodes).to(device),
        mode=mode,
        padding=padding,
        fill=fill,
        check=False,
    )
    out = out.cpu().numpy()
    ref, inside = shifted(vol, d)
    tol = 1e-9 * (1 + np.abs(vol).max())
    np.testing.assert_allclose(out[inside], ref[inside], rtol=0, atol=tol)
    if padding == "zeros" and mode == "deform":
        np.testing.assert_allclose(out[~inside], fill, rtol=0, atol=tol)


@settings(max_examples=60, deadline=None)
@given(data=st.data(), d1=OFFSET, d2=OFFSET, padding=st.sampled_from(["border", "zeros"]))
def test_two_uniform_shifts_compose(data, d1, d2, padding):
    vol = data.draw(volumes())
    n1, n2 = data.draw(node_shapes(vol.shape)), data.draw(node_shapes(vol.shape))
    once = warp(torch.from_numpy(vol), uniform(d1, n1), padding=padding, check=False)
    twice = warp(once, uniform(d2, n2), padding=padding, check=False).numpy()
    ref, inside = shifted(vol, tuple(a + b for a, b in zip(d1, d2)))
    _, inside2 = shifted(vol, d2)
    _, inside1 = shifted(vol, d1)
    both = inside & inside2 & shifted(inside1, d2)[0].astype(bool)  # p - d2 and p - d2 - d1 inside
    np.testing.assert_allclose(twice[both], ref[both], rtol=0, atol=1e-9 * (1 + np.abs(vol).max()))
