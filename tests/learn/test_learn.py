"""Learning parameters from series (torchdeform.learn): transforms, parameter sharing, the
window loss against hand-written losses and finite differences, recovery of known true
parameters, identifiability report, checkpoint/resume (bitwise), the training scripts."""

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchdeform import fuzzy, learn
from torchdeform.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def cube(steps=100, **kw):
    return learn.radetzky_cube(springs=kw.pop("springs", 70), steps=steps, **kw)


def shared(series, k, c, mass=None, device=None):
    return learn.Parameters(
        series,
        learn.SpringParameter.like(series, init=k),
        learn.SpringParameter.like(series, init=c),
        series.truth["mass"] if mass is None else mass,
        device=device,
    )


# ------------------------------------------------------------------ parameters
@pytest.mark.parametrize("transform", ["log", "softplus"])
def test_transforms_roundtrip_and_positive(transform):
    v = torch.tensor([1e-4, 0.3, 1.0, 7.0, 50.0], dtype=torch.float64)
    assert torch.allclose(learn.from_raw(learn.to_raw(v, transform), transform), v, rtol=1e-12)
    raw = torch.linspace(-40, 40, 9, dtype=torch.float64)
    assert (learn.from_raw(raw, transform) > 0).all()
    p = learn.Positive(v, transform=transform)
    assert torch.allclose(p(), v, rtol=1e-12)
    with pytest.raises(ConfigError, match="init"):
        learn.Positive(torch.tensor([1.0, -1.0]), transform=transform)


def test_sharing_modes(device):
    g, _ = learn.cube_grid(n=4, spacing=0.01, springs=None, topology=26)
    mask = g.spring_mask()
    k = learn.SpringParameter(g, spring_mask=None, init=3.0, sharing="shared").to(device)()
    assert k.device == device
    k = k.cpu()
    assert torch.allclose(k, 3.0 * mask.to(k.dtype), rtol=1e-14, atol=0)
    c = learn.SpringParameter(g, spring_mask=None, init=torch.tensor([1.0, 2.0, 3.0]), sharing="class").to(device)()
    c = c.cpu()
    for s, cls in enumerate(g.direction_class()):
        expect = {"axis": 1.0, "face": 2.0, "body": 3.0}[cls]
        assert torch.allclose(c[s][mask[s]], torch.tensor(expect, dtype=c.dtype))
    lab = learn.layered_regions(g, layers=2)
    r = learn.SpringParameter(g, spring_mask=None, init=torch.tensor([2.0, 8.0]), sharing="region", regions=lab)
    r = r.to(device)().cpu()
    # oracle: harmonic mean of the two end nodes' region values, spring by spring
    vals = np.array([2.0, 8.0])[lab]
    for s, d in enumerate(g.directions):
        for i, j, l in zip(*np.nonzero(mask[s].numpy())):
            a, b = vals[i, j, l], vals[i + d[0], j + d[1], l + d[2]]
            assert r[s, i, j, l].item() == pytest.approx(2 * a * b / (a + b))
    n = int(mask.sum())
    sp = learn.SpringParameter(g, spring_mask=None, init=torch.arange(1.0, n + 1), sharing="spring").to(device)
    out = sp()
    assert torch.equal(sp.per_spring(out), sp.values()) and (out.cpu()[~mask] == 0).all()
    m = learn.NodeParameter(g, init=torch.arange(1.0, g.num_nodes + 1), sharing="node").to(device)()
    assert m.device == device
    assert torch.allclose(m.cpu().reshape(-1), torch.arange(1.0, g.num_nodes + 1, dtype=m.dtype), rtol=1e-14, atol=0)
    with pytest.raises(ConfigError, match="init"):
        learn.SpringParameter(g, spring_mask=None, init=torch.ones(3), sharing="spring")
    with pytest.raises(ConfigError, match="sharing"):
        learn.SpringParameter(g, spring_mask=None, init=1.0, sharing="per-node")


# ------------------------------------------------------------------ the loss
def test_loss_is_zero_at_truth_and_matches_hand_written_full_rollout(device):
    s = cube(60)
    k0, c0 = s.meta["truth"]["stiffness"], s.meta["truth"]["damping"]
    for window in (1, 10, None):
        assert float(learn.WindowLoss(s, window=window)(shared(s, k0, c0, device=device)).detach()) < 1e-26
    # full rollout: mean squared error of a plain simulation over free, observed coordinates / ref^2
    p = shared(s, 1.2 * k0, c0, device=device)
    loss = learn.WindowLoss(s, window=None)(p)
    assert loss.device == device
    loss = float(loss.detach())
    with torch.no_grad():
        x = s.simulate(s.model(1.2 * k0, c0, s.truth["mass"]))[:, 0].numpy()
    free = ~s.constrained()
    X = s.grid.rest_positions(dtype=torch.float64)[0].numpy()
    err = ((x[1:] - s.positions[1:]) ** 2)[:, :, free]
    ref2 = np.mean(((s.positions - X) ** 2)[:, :, free])
    assert loss == pytest.approx(err.sum() / (err.size * (61 / 60)) / ref2, rel=1e-10)


def test_gradient_matches_finite_differences(device):
    s = cube(40)
    L = learn.WindowLoss(s, window=8)
    p = shared(s, 14.0, 0.07, device=device)
    L(p).backward()
    for name in ("stiffness", "damping"):
        raw = p.learned[name].value.raw
        h = 1e-6
        with torch.no_grad():
            raw += h
            up = float(L(p))
            raw -= 2 * h
            down = float(L(p))
            raw += h
        assert raw.grad.item() == pytest.approx((up - down) / (2 * h), rel=1e-5)


def test_checkpointing_gives_the_same_loss_and_gradient(device):
    s = learn.cube_series(n=3, load="sine", steps=30, period=0.1)
    grads = []
    for ckpt in (None, 7):
        p = shared(s, 13.0, 0.2, device=device)
        loss = learn.WindowLoss(s, window=None, checkpoint=ckpt)(p)
        loss.backward()
        grads.append((float(loss.detach()), [q.grad.clone() for q in p.parameters()]))
    assert grads[0][0] == pytest.approx(grads[1][0], rel=1e-13)
    for a, b in zip(grads[0][1], grads[1][1]):
        assert torch.allclose(a, b, rtol=1e-11)


def test_missing_data_is_ignored(device):
    observe = np.ones((3, 3, 3), dtype=bool)
    observe[2, 0, 0] = False
    s = cube(60, observe=observe)
    p = shared(s, 12.0, 0.08, device=device)
    before = float(learn.WindowLoss(s, window=None)(p).detach())
    s.positions[:, :, 2, 0, 0] = 123.0  # garbage where nothing was seen
    assert float(learn.WindowLoss(s, window=None)(p).detach()) == before
    # carrying the simulation through unobserved nodes still recovers the truth exactly
    truth = shared(s, 10.0, 0.1, device=device)
    assert float(learn.WindowLoss(s, window=10, velocity="carry")(truth).detach()) < 1e-26


# ------------------------------------------------------------------ recovery
def test_shared_recovery_from_offset_start(device):
    s = cube(150)
    p = shared(s, 30.0, 0.04, device=device)  # 3x and 1/2.5x the truth
    tr = learn.Trainer(
        p, learn.WindowLoss(s, window=10), optimizer="lbfgs", iterations=20, patience=3, tol=1e-24, progress=False
    )
    tr.run()
    got = p.summary()
    assert learn.relative_error(got["stiffness"], 10.0) < 1e-3
    assert learn.relative_error(got["damping"], 0.1) < 1e-3


def test_shared_recovery_with_one_percent_noise(device):
    s = learn.radetzky_cube(springs=70, noise=0.01, seed=2)
    p = shared(s, 30.0, 0.04, device=device)
    tr = learn.Trainer(
        p, learn.WindowLoss(s, window=50, smooth=10), optimizer="lbfgs", iterations=10, patience=3, progress=False
    )
    tr.run()
    got = p.summary()
    assert learn.relative_error(got["stiffness"], 10.0) < 0.02
    assert learn.relative_error(got["damping"], 0.1) < 0.02


def test_per_spring_fit_loss_falls_and_report_flags_undetermined_springs(device):
    s = cube(100, springs=54)
    g = torch.Generator().manual_seed(0)
    k = learn.SpringParameter.like(s, init=1.0, sharing="spring")
    n = int(k.mask.sum())
    true = k.per_spring(torch.as_tensor(s.truth["stiffness"]))
    init = true * torch.exp(torch.empty(n, dtype=torch.float64).uniform_(math.log(0.2), math.log(5), generator=g))
    k = learn.SpringParameter.like(s, init=init, sharing="spring")
    p = learn.Parameters(s, k, s.truth["damping"], s.truth["mass"], device=device)
    L = learn.WindowLoss(s, window=10)
    first = float(L(p).detach())
    tr = learn.Trainer(p, L, optimizer="lbfgs", iterations=6, patience=3, progress=False)
    tr.run()
    assert tr.final_loss() < first / 100
    active = learn.active_springs(s)[k.mask.cpu()]
    assert int((~active).sum()) == 12  # the 12 springs among the 9 fixed nodes
    v = k.values().detach().cpu()
    assert torch.allclose(v[~active], init[~active], rtol=1e-14)  # no data ever touches them
    rep = learn.spread_report(v[active], true[active])
    assert rep["n"] == 42 and rep["ratio"]["min"] <= rep["ratio"]["median"] <= rep["ratio"]["max"]
    r = (v[active] / true[active]).numpy()
    assert rep["within_10pct"] == pytest.approx(np.mean(np.abs(r - 1) <= 0.1))
    curv = learn.curvature_report(p, L)
    assert curv["n"] == 54 and curv["undetermined"] >= 12


def test_spread_report_verdicts():
    t = torch.linspace(1, 2, 50, dtype=torch.float64)
    assert learn.spread_report(t * 1.001, t)["verdict"] == "recovered"
    bad = learn.spread_report(t * torch.linspace(0.5, 2, 50, dtype=torch.float64), t)
    assert bad["verdict"] == "not determined by the data" and bad["max_rel_error"] == pytest.approx(1.0)


@pytest.mark.slow
def test_sparse_snapshots_recover_stiffness():
    s = learn.balloon_series()
    k0 = s.meta["truth"]["stiffness"]
    p = learn.Parameters(s, learn.SpringParameter.like(s, init=k0 / 3), s.truth["damping"], s.truth["mass"])
    tr = learn.Trainer(
        p, learn.WindowLoss(s, window=1, velocity="zero"), optimizer="lbfgs", iterations=5, patience=2, progress=False
    )
    tr.run()
    assert learn.relative_error(p.summary()["stiffness"], k0) < 0.05


def test_fuzzy_slider_recovers_target_stiffness_and_viscosity(device):
    fis = fuzzy.load_preset("susilap_g").double()
    target = {k: float(v) for k, v in fis.evaluate(consistency=5.5).items()}
    s = cube(100, stiffness=target["spring_const"], damping=target["viscosity"], mass=0.2)
    fs = learn.FuzzySprings(
        fuzzy.load_preset("susilap_g"), {"consistency": 5.1}, grid=s.grid, spring_mask=s.spring_mask_tensor()
    )
    p = learn.Parameters(s, fs.part("stiffness"), fs.part("damping"), s.truth["mass"], device=device)
    learn.Trainer(p, learn.WindowLoss(s, window=10), optimizer="lbfgs", iterations=10, patience=3, progress=False).run()
    got = {k: float(v.detach()) for k, v in fs().items()}
    assert learn.relative_error(got["stiffness"], target["spring_const"]) < 0.01
    assert learn.relative_error(got["damping"], target["viscosity"]) < 0.01


# ------------------------------------------------------------------ training machinery
@pytest.mark.parametrize("optimizer", ["adam", "lbfgs"])
def test_resume_is_bitwise_identical(tmp_path, optimizer):
    s = cube(60)
    kw = dict(
        optimizer=optimizer,
        iterations=6,
        progress=False,
        patience=100,
        min_delta=0.0,
        windows_per_step=2 if optimizer == "adam" else None,
        seed=7,
        lbfgs_inner=3,
    )

    def fresh():
        p = shared(s, 25.0, 0.05)
        return p, learn.Trainer(p, learn.WindowLoss(s, window=10), **kw)

    p1, t1 = fresh()
    t1.run()
    _p2, t2 = fresh()
    t2.run(stop_after=3)
    t2.save(tmp_path / "ckpt.pt")
    p3, t3 = fresh()
    t3.load(tmp_path / "ckpt.pt")
    assert t3.iteration == 3
    t3.run()
    for a, b in zip(p1.parameters(), p3.parameters()):
        assert torch.equal(a, b)
    assert [r.loss for r in t1.history] == [r.loss for r in t3.history]
    with pytest.raises(ConfigError, match="checkpoint"):
        t3.load(tmp_path / "nope.pt")


def test_divergence_stops_with_finite_parameters():
    s = cube(60)
    p = shared(s, 10.0, 0.1)
    tr = learn.Trainer(
        p, learn.WindowLoss(s, window=None), optimizer="adam", lr=40.0, iterations=10, clip=None, progress=False
    )
    with pytest.warns(UserWarning, match=r"training stopped at iteration \d+: the loss went non-finite"):
        tr.run()
    assert tr.stopped == "non-finite loss"
    assert all(bool(torch.isfinite(q).all()) for q in p.parameters())


def test_early_stopping_and_plot(tmp_path):
    s = cube(60)
    p = shared(s, 10.0, 0.1)  # already at the optimum
    tr = learn.Trainer(
        p, learn.WindowLoss(s, window=10), optimizer="adam", lr=1e-6, iterations=100, patience=4, progress=False
    )
    tr.run()
    assert tr.iteration < 100 and "no improvement" in tr.stopped
    png = learn.plot_history(tr.history, tmp_path / "curve.png")
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_loss_argument_errors():
    s = cube(20)
    with pytest.raises(ConfigError, match="window"):
        learn.WindowLoss(s, window=0)
    with pytest.raises(ConfigError, match="velocity"):
        learn.WindowLoss(s, velocity="guess")
    s.steps = np.array([0, 1, 3] + list(range(4, 21)))[: len(s.steps)]
    with pytest.raises(ConfigError, match="evenly"):
        learn.WindowLoss(s)


# ------------------------------------------------------------------ scripts
@pytest.mark.parametrize("script", ["fit_cube.py", "fit_fuzzy.py", "fit_sparse.py"])
def test_scripts_have_help(script):
    r = subprocess.run(
        [sys.executable, str(ROOT / "training" / script), "--help"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
    )
    assert r.returncode == 0 and "--out" in r.stdout


def test_fit_cube_script_writes_result(tmp_path):
    spec = importlib.util.spec_from_file_location("fit_cube", ROOT / "training" / "fit_cube.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--runs", "3", "--iterations", "15", "--out", str(tmp_path), "--quiet"]) == 0
    res = json.loads((tmp_path / "result.json").read_text())
    run = res["runs"]["3"]
    assert run["relative_error"]["stiffness"] < 1e-3 and run["relative_error"]["damping"] < 1e-3
    assert run["true"] == {"stiffness": 10.0, "damping": 0.1} and run["history"]
    assert (tmp_path / "run3_loss.png").is_file()


@pytest.mark.slow
def test_fit_cube_recovers_a_stiff_cube_through_implicit_euler(tmp_path):
    """--integrator implicit: a 1000x stiffer cube stepped by implicit Euler at 50x the explicit bound;
    shared stiffness and damping come back from 3x and 0.4x the truth to < 0.1 % (adjoint gradients).
    L-BFGS's first step (up to 20 evaluations) reaches the truth to about 1e-7; a second shows the fit
    stays there, without the further steps that early stopping would wait for."""
    spec = importlib.util.spec_from_file_location("fit_cube", ROOT / "training" / "fit_cube.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    argv = ["--integrator", "implicit", "--runs", "3", "--iterations", "2", "--out", str(tmp_path), "--quiet"]
    assert mod.main(argv) == 0
    res = json.loads((tmp_path / "result.json").read_text())
    assert res["series"]["dt_over_bound"] == 50 and res["series"]["explicit_bound"] > 0
    run = res["runs"]["3"]
    assert run["iterations"] == 2
    assert run["true"] == pytest.approx({"stiffness": 1e4, "damping": 0.1 * 1000**0.5})
    assert run["relative_error"]["stiffness"] < 1e-3 and run["relative_error"]["damping"] < 1e-3


def test_checkpointed_loss_with_a_scalar_mass_equals_the_whole_graph(device):
    """A scalar mass goes through the checkpoint's model rebuild."""
    s = learn.radetzky_cube(springs=54, steps=40)

    def value_and_grads(checkpoint):
        k, c = learn.SpringParameter.like(s, init=12.0), learn.SpringParameter.like(s, init=0.1)
        p = learn.Parameters(s, k, c, 0.01, device=device)
        loss = learn.WindowLoss(s, window=None, checkpoint=checkpoint)(p)
        loss.backward()
        return loss.detach(), [q.grad.clone() for q in p.parameters() if q.grad is not None]

    whole, g_whole = value_and_grads(None)
    ckpt, g_ckpt = value_and_grads(10)
    assert torch.allclose(ckpt, whole, rtol=1e-12) and len(g_ckpt) == len(g_whole) > 0
    for a, b in zip(g_ckpt, g_whole):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-14)
