"""The spring kernels (torchdeform.sim.native: C on the CPU, Triton on CUDA) against the grid-layout model's shifted-slice springs.

The oracle is :meth:`Model.spring_forces` (shifted slices, itself tested against the numpy edge
list in test_stencil / test_physics) and :meth:`SymplecticEuler.step` on the grid layout. Kernels
are built by the system C compiler (on CUDA by Triton); without one the tests that need a kernel
are skipped with the reason, and the fall-back is tested instead. The tests that take the
``kernel_device`` fixture run on the suite's ``--device``.
"""

import ctypes
import time

import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.sim import native, native_cuda
from torchdeform.sim.compiled import CompiledStep
from torchdeform.sim.packed import PackedModel

needs_cc = pytest.mark.skipif(native.unavailable() is not None, reason=f"no C kernel here: {native.unavailable()}")


@pytest.fixture
def kernel_device(device):
    """The run's device, where its spring kernel can run (C on the CPU, Triton on CUDA); else the test skips."""
    why = native.unavailable() if device.type == "cpu" else native_cuda.unavailable()
    if why:
        pytest.skip(f"no spring kernel on {device.type}: {why}")
    return device


def _body(
    topology=26,
    damping=0.05,
    mode="projected",
    dtype=F64,
    batch=1,
    per_spring=False,
    decay=None,
    box=False,
    device="cpu",
):
    node_mask = torch.ones(6, 5, 7, dtype=torch.bool)
    if not box:
        node_mask[4:, 3:, :3] = False  # an L-shaped body: holes in `inside`
    grid = td.Grid((6, 5, 7), spacing=(0.01, 0.011, 0.012), topology=topology, node_mask=node_mask)
    g = torch.Generator().manual_seed(topology + batch)
    k = 40 * (1 + torch.rand(((batch,) if per_spring else ()) + (grid.S,) + grid.shape, generator=g, dtype=F64))
    if not per_spring:
        k = 40.0
    model = td.Model(
        grid,
        stiffness=k,
        damping=damping,
        damping_mode=mode,
        density=1000.0,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom") & grid.nodes(),
        decay=decay,
        dtype=dtype,
        device=device,
    )
    x = model.X + 2e-4 * torch.randn((batch, 3) + grid.shape, generator=g, dtype=F64).to(dtype=dtype, device=device)
    v = 1e-2 * torch.randn((batch, 3) + grid.shape, generator=g, dtype=F64).to(dtype=dtype, device=device)
    inside = grid.nodes().to(device)
    return model, td.State(x * inside, v * inside, t=0.0)


def _close(a, b, dtype):
    tol = 1e-12 if dtype == F64 else 2e-6
    return torch.allclose(a, b, rtol=tol, atol=tol * float(b.abs().max()))


@pytest.mark.parametrize("topology,dtype", [(6, torch.float32), (14, F64), (18, F64), (26, torch.float32), (26, F64)])
@pytest.mark.parametrize("damping,mode", [(None, "projected"), (0.05, "projected"), (0.05, "unprojected")])
def test_kernel_forces_equal_the_grid_springs(topology, damping, mode, dtype, kernel_device):
    """Every topology and damping mode; both dtypes on the 26-neighbour stencil (each case is a
    kernel built once per machine, ~1.5 s: the dtype changes only the C type)."""
    model, state = _body(topology, damping, mode, dtype, batch=2, device=kernel_device)
    pm = PackedModel(model)
    ps = pm.pack_state(state)
    f = native.spring_forces(pm, ps.x, ps.v)
    assert f.shape == ps.x.shape
    assert _close(pm.unpack(f), model.spring_forces(state.x, state.v), dtype)
    # zero on the halo and outside the core range, as every packed field
    assert torch.equal(f, pm.pack(pm.unpack(f)))


@pytest.mark.parametrize("share", [True, ("stiffness", "rest_length", "damping")])
@pytest.mark.parametrize("mode", ["projected", "unprojected"])
def test_kernel_with_fields_per_spring_and_per_batch_entry(share, mode, kernel_device):
    """Stiffness per spring and per batch entry (``Bp = B = 2``), cut springs (stiffness 0: their
    damping gated out where the damping is per direction), rest lengths per spring. A box: on an
    L-shaped body every spring field is per spring already (the missing springs masked)."""
    model, state = _body(26, 0.05, mode, F64, batch=2, per_spring=True, box=True, device=kernel_device)
    model.stiffness[:, 3, 2, 1:4] = 0.0  # cut springs
    pm = PackedModel(model, share=share)  # model's fields: views of pm's
    if "rest_length" in pm.source.shared:
        model.rest_length.mul_(1.02)  # in place: the packed field sees it
    var = native.variant_of(pm)
    # gated where the stiffness has more values than the damping (per spring and batch against per direction,
    # or per spring and batch against per spring)
    assert var.k_per_spring and var.gate and var.l0_per_spring == (share is not True)
    ps = pm.pack_state(state)
    assert _close(pm.unpack(native.spring_forces(pm, ps.x, ps.v)), model.spring_forces(state.x, state.v), F64)


@needs_cc
@pytest.mark.parametrize("threads", [1, 2, 3])
def test_kernel_is_the_same_on_any_thread_count(threads):
    """Threads split the core range (each its own ring warm-up): the sums are the same bit for bit."""
    model, state = _body(26, 0.05, "projected", torch.float32)
    pm = PackedModel(model)
    ps = pm.pack_state(state)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = native.spring_forces(pm, ps.x, ps.v)
        torch.set_num_threads(threads)
        assert torch.equal(native.spring_forces(pm, ps.x, ps.v), one)
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("damping", [None, 0.05])
def test_fused_symplectic_step_equals_the_eager_step(dtype, damping, kernel_device):
    model, state = _body(26, damping, "projected", dtype, batch=2, decay=50.0, device=kernel_device)
    state = model.start(state)
    pm = PackedModel(model)
    assert native.fused_blocker(pm, td.SymplecticEuler()) is None
    ps = pm.pack_state(state)
    x, v = native.symplectic_step(pm, ps.x, ps.v, 2e-4)
    ref = td.SymplecticEuler().step(model, state, 2e-4)
    assert _close(pm.unpack(x), ref.x, dtype) and _close(pm.unpack(v), ref.v, dtype)
    # halo nodes stay where they are
    assert torch.equal(x, pm.pack(pm.unpack(x)) + (ps.x - pm.pack(pm.unpack(ps.x))))


@pytest.mark.parametrize("shape,batch", [((5, 40, 30), 1), ((4, 5, 6), 3)], ids=["large-planes", "small-batch"])
def test_every_launch_shape_makes_the_same_step(shape, batch, kernel_device):
    """The Triton kernel's launch shapes (block, planes walked, bit words), on
    planes larger than a block and on a batch of small bodies: the grid-layout step."""
    if kernel_device.type == "cpu":
        pytest.skip("launch shapes are the Triton kernel's (CUDA); the CPU runs the C kernel")
    grid = td.Grid(shape, spacing=0.01, topology=26)
    model = td.Model(grid, 40.0, damping=0.05, density=1000.0, gravity=(-9.81, 0, 0), device=kernel_device)
    g = torch.Generator().manual_seed(1)
    x = model.X + 2e-4 * torch.randn((batch, 3, *shape), generator=g, dtype=F64).to(kernel_device, model.dtype)
    v = 1e-2 * torch.randn((batch, 3, *shape), generator=g, dtype=F64).to(kernel_device, model.dtype)
    state = td.State(x, v, t=0.0)
    ref = td.SymplecticEuler().step(model, state, 2e-4)
    pm = PackedModel(model)
    ps = pm.pack_state(state)
    var = native.fused_variant(pm)
    _D, H, W = shape
    shapes = [*native_cuda.CONFIGS, native_cuda.Config(512, 1, 4)]  # each one compiled by Triton (~10 s)
    for cfg in shapes:
        xo, vo = torch.empty_like(ps.x), torch.empty_like(ps.v)
        native_cuda.launch(
            var, ps.x, ps.v, xo, vo, pm.inside, pm.stiffness, pm.rest_length, pm.damping, pm.offset_table,
            pm.inv_mass, pm.mass, G=pm.G, plane=(H + 2) * (W + 2), scalars=(-9.81, 0.0, 0.0, 2e-4, 1.0), config=cfg,
        )  # fmt: skip
        assert _close(pm.unpack(xo), ref.x, model.dtype) and _close(pm.unpack(vo), ref.v, model.dtype), cfg


def test_tuning_keeps_the_fastest_launch_shape_and_leaves_out_one_that_fails(monkeypatch):
    """Launch shapes timed by the clock (off a GPU): one that cannot launch is left out, its time None."""
    shapes = (native_cuda.Config(256, 1, 2), native_cuda.Config(512, 1, 2), native_cuda.Config(1024, 1, 2))
    monkeypatch.setattr(native_cuda, "CONFIGS", shapes)
    monkeypatch.setattr(native_cuda, "timings", {})
    cost = {shapes[0]: 3e-3, shapes[2]: 1e-3}

    def run(cfg):
        if cfg == shapes[1]:
            raise RuntimeError("out of resources")
        time.sleep(cost[cfg])

    assert native_cuda._tune(run, "key", torch.device("cpu")) == shapes[2]
    times = dict(native_cuda.timings["key"])
    assert times[shapes[1]] is None and times[shapes[0]] > times[shapes[2]] >= 1.0  # ms
    monkeypatch.setattr(native_cuda, "CONFIGS", shapes[1:2])
    with pytest.raises(RuntimeError, match="out of resources"):
        native_cuda._tune(run, "other", torch.device("cpu"))


def test_neighbour_bits_say_which_springs_exist():
    """The GPU kernel's one word per node against both ends' node mask, node by node (an L-shaped body)."""
    model, _ = _body(26)
    pm = PackedModel(model)
    bits = native_cuda.neighbour_bits(pm.inside, pm.offset_table)
    assert native_cuda.neighbour_bits(pm.inside, pm.offset_table) is bits  # kept on the mask
    inside, words, P = pm.inside.tolist(), bits.tolist(), pm.P
    for i in range(P):
        for s, o in enumerate(pm.offsets):
            for sign, j in ((0, i + o), (1, i - o)):
                exists = 0 <= j < P and inside[i] > 0 and inside[j] > 0
                assert bool(words[i] >> (2 * s + sign) & 1) == exists, (i, s, sign)


def test_fused_step_is_only_for_what_it_computes():
    model, _ = _body(6)
    pm = PackedModel(model)
    assert "rk4" in native.fused_blocker(pm, td.RK4())
    assert native.fused_blocker(pm, td.SymplecticEuler(), loads=torch.zeros(1)) == "loads"
    law = td.Model(model.grid, stiffness=40.0, mass=1e-3, law=td.Exponential(stiffening=5.0))
    assert "Exponential law" in native.supports(PackedModel(law))


@needs_cc
def test_a_nan_reaches_the_neighbours():
    model, state = _body(26, 0.05, "unprojected", torch.float32)
    state.x[0, 1, 2, 2, 3] = float("nan")
    pm = PackedModel(model)
    ps = pm.pack_state(state)
    f = pm.unpack(native.spring_forces(pm, ps.x, ps.v))
    assert not torch.isfinite(f[0, :, 2, 2, 3]).all() and not torch.isfinite(f[0, :, 1, 1, 2]).all()
    assert torch.isfinite(f[0, :, 5, 0, 6]).all()  # far away: untouched


@needs_cc
def test_kernels_are_cached_on_disk(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHDEFORM_CACHE_DIR", str(tmp_path))
    var = native.Variant(S=3, dtype="double", damping=2, l0_per_spring=True)
    native._kernels.pop(native.name_of(var), None)
    native.kernel(var)
    built = sorted(native.cache_dir().glob("springs-*.so"))
    assert len(built) == 1
    native._kernels.pop(native.name_of(var))
    stamp = built[0].stat().st_mtime_ns
    native.kernel(var)  # loaded, not built again
    assert sorted(native.cache_dir().glob("springs-*.so")) == built and built[0].stat().st_mtime_ns == stamp


def test_a_failed_build_names_the_kernel_and_keeps_the_compilers_words(tmp_path, monkeypatch):
    """A C source that does not compile: the error names the kernel and quotes the compiler; a
    source that does gives its function typed for ctypes (it runs)."""
    if native.unavailable():
        pytest.skip(native.unavailable())
    monkeypatch.setenv("TORCHDEFORM_CACHE_DIR", str(tmp_path))
    with pytest.raises(native.NativeBuildError, match=r"(?s)could not build the probe kernel: .*error"):
        native.entry("int probe(int a) { return a + ; }\n", "probe", [ctypes.c_int], what="the probe kernel")
    fn = native.entry("int probe(int a) { return 3 * a; }\n", "probe", [ctypes.c_int], what="the probe kernel")
    assert fn(14) == 42 and fn.restype is ctypes.c_int


def test_no_compiler_says_why_and_the_compiled_step_uses_inductors_forms(monkeypatch):
    monkeypatch.setenv("TORCHDEFORM_NATIVE", "0")
    native.unavailable.cache_clear()
    try:
        assert native.unavailable() == "TORCHDEFORM_NATIVE=0"
        model, _ = _body(6)
        step = CompiledStep(td.SymplecticEuler(), model, 1e-4, enable=False)
        assert (
            step.force_form in ("gather", "reduction")
            and "TORCHDEFORM_NATIVE=0" in step.packed.traced(step.trace).native_why
        )
        with pytest.raises(native.NativeBuildError, match="TORCHDEFORM_NATIVE=0"):
            CompiledStep(td.SymplecticEuler(), model, 1e-4, enable=False, force_form="native")
        with pytest.raises(td.ConfigError, match="native"):
            td.simulate(model, model.rest_state(), 1e-4, 3, engine="native")
    finally:
        monkeypatch.delenv("TORCHDEFORM_NATIVE")
        native.unavailable.cache_clear()


def test_source_is_one_block_per_spring_and_direction():
    for S in (3, 7, 9, 13):
        src = native.source(native.Variant(S=S, dtype="float", damping=1, update=True))
        assert src.count("{ /* forward */") == S and src.count("{ /* backward */") == S
        assert "sqrtf(" in src and "U0[i] = u0 * keep" in src


@needs_cc
def test_compiled_module_imports_without_inductor():
    """The native engine needs no torch.compile: importing the compiled-step module must not load
    inductor (3 s); the first compile loads it."""
    import subprocess
    import sys

    code = (
        "import sys, torchdeform.sim.compiled, torchdeform.sim.engine; print('torch._inductor.lowering' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


@pytest.mark.slow
@needs_cc
def test_compiled_step_around_the_kernel_equals_the_eager_step():
    """torch.compile of an explicit step with the kernel as one external call (a few seconds)."""
    model, state = _body(26, 0.05, "projected", F64, batch=1, decay=20.0)
    state = model.start(state)
    step = CompiledStep(td.SymplecticEuler(), model, 1e-4)
    assert step.force_form == "native" and step.compiled
    out = step.run(state, 5)
    ref = state
    for _ in range(5):
        ref = td.SymplecticEuler().step(model, ref, 1e-4)
    assert step.compiled and _close(out.x, ref.x, F64) and _close(out.v, ref.v, F64)
