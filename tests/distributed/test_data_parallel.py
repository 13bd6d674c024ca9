"""Data-parallel learning (torchdeform.distributed.data_parallel): the window split, a sharded
loss against the plain loss in one process, and fits over 2 and 3 ranks (torchrun, gloo on this
machine) against the same fits in one process with plain window losses, to 1e-12 in float64."""

from __future__ import annotations

import functools
import importlib.util
import json
import operator
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.distributed import data_parallel_fits as fits
from torchdeform import learn
from torchdeform.distributed.data_parallel import ShardedLoss, is_main, parallel_loss, process_group, shard
from torchdeform.errors import ConfigError

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def load(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def torchrun(n: int, *argv, timeout: float = 90) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc-per-node n ARGV`` (a free port on this machine), bounded in time.

    Past ``timeout``: SIGTERM to torchrun (it stops its workers), then SIGKILL, and the test fails."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(n), *map(str, argv)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.terminate()
        try:
            out, err = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
        pytest.fail(f"torchrun with {n} ranks ran past {timeout} s:\n{err[:3000]}")
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def unhex(values: dict) -> dict:
    return {k: [float.fromhex(v) for v in vs] for k, vs in values.items()}


def cube(steps=60):
    return learn.radetzky_cube(springs=70, steps=steps)


def params_of(series, k=12.0, c=0.08):
    return fits.shared(series, k, c)


def value_and_grad(loss, params, windows=None):
    for p in params.parameters():
        p.grad = None
    v = loss(params, windows=windows)
    v.backward()
    return float(v.detach()), [p.grad.clone() for p in params.parameters()]


# ------------------------------------------------------------------ the split
def test_split_covers_every_window_exactly_once():
    for n in range(0, 30):
        for world in range(1, 6):
            blocks = [list(shard(n, r, world)) for r in range(world)]
            assert functools.reduce(operator.iadd, blocks, []) == list(range(n))  # in order, each once
            sizes = [len(b) for b in blocks]
            assert max(sizes) - min(sizes) <= 1
    s = cube(100)  # 10 windows
    loss = learn.WindowLoss(s, window=10)
    subset = [7, 2, 9, 0, 4]
    got = [ShardedLoss(loss, rank=r, world=3).windows(windows=subset) for r in range(3)]
    assert got == [[7, 2], [9, 0], [4]]
    both = [ShardedLoss([loss, loss], rank=r, world=3).windows() for r in range(3)]
    assert functools.reduce(operator.iadd, both, []) == list(range(20)) and [len(b) for b in both] == [7, 7, 6]
    with pytest.raises(ConfigError, match="rank"):
        shard(4, 3, 3)
    with pytest.raises(ConfigError, match="windows"):
        ShardedLoss(loss).windows(windows=[10])


# ------------------------------------------------------------------ one process
def test_sharded_loss_on_one_process_is_the_plain_loss():
    s = cube()
    loss = learn.WindowLoss(s, window=10)
    p = params_of(s)
    sharded = ShardedLoss(loss)
    assert (sharded.rank, sharded.world, sharded.num_windows) == (0, 1, 6)
    for windows in (None, torch.tensor([4, 1, 3])):
        v, g = value_and_grad(loss, p, windows)
        w, h = value_and_grad(sharded, p, windows)
        assert w == v and all(torch.equal(a, b) for a, b in zip(g, h))
    assert parallel_loss(loss) is loss
    with process_group() as (rank, world):
        assert (rank, world) == (0, 1) and is_main() and not torch.distributed.is_initialized()


def test_rank_parts_add_up_to_the_loss_and_its_gradient():
    """Every rank's part (no communication), added over the ranks: the loss of all windows, of a
    subset, of two series, and their gradients, to rounding."""
    a, b = cube(100), learn.radetzky_cube(springs=70, steps=50, noise=0.01, seed=1)
    la, lb = learn.WindowLoss(a, window=10), learn.WindowLoss(b, window=10)
    p = params_of(a)
    reference = fits.SumOfLosses([la, lb])
    for windows in (None, torch.tensor([12, 3, 0, 9, 14, 6])):
        v, g = value_and_grad(reference, p, windows)
        for world in (2, 3, 4):
            total, grads = 0.0, [torch.zeros_like(x) for x in g]
            for r in range(world):
                part, pg = value_and_grad(ShardedLoss([la, lb], rank=r, world=world).partial, p, windows)
                total += part
                grads = [x + y for x, y in zip(grads, pg)]
            assert total == pytest.approx(v, rel=1e-14, abs=0)
            for x, y in zip(grads, g):
                torch.testing.assert_close(x, y, rtol=1e-13, atol=0)


def test_several_ranks_need_a_process_group():
    s = cube(20)
    with pytest.raises(ConfigError, match="process group"):
        ShardedLoss(learn.WindowLoss(s, window=10), rank=0, world=2)(params_of(s))


# ------------------------------------------------------------------ over ranks
@pytest.fixture(scope="module")
def single_process():
    """The fits in this process with plain window losses (the independent reference)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return {case: fits.reference(case) for case in fits.CASES}
    finally:
        torch.set_num_threads(n)


@pytest.mark.parametrize("ranks", [3])  # an odd count of ranks; 2 ranks run the same code
@pytest.mark.slow
def test_data_parallel_fits_equal_the_single_process_fits(tmp_path, ranks, single_process):
    """L-BFGS on one series and Adam on random window subsets of two series (stopped half-way,
    checkpointed by rank 0, resumed on every rank): the learned values of every rank equal the
    one-process fits to 1e-12, the loss histories to 1e-12 relative."""
    out = tmp_path / "result.json"
    res = torchrun(ranks, HERE / "data_parallel_fits.py", out)
    assert res.returncode == 0, res.stderr[:3000] + " ... " + res.stderr[-1500:]
    got = json.loads(out.read_text())
    assert got["world"] == ranks
    for case in fits.CASES:
        want = single_process[case]
        learned, reference = unhex(got[case]["learned"]), unhex(want["learned"])
        assert learned.keys() == reference.keys()
        for name in reference:
            assert learned[name] == pytest.approx(reference[name], abs=1e-12, rel=0), (case, name)
        losses = [float.fromhex(x) for x in got[case]["losses"]]
        assert losses == pytest.approx([float.fromhex(x) for x in want["losses"]], rel=1e-12, abs=0)
    assert got["same_on_all_ranks"]
    assert got["saves"] == [1] + [0] * (ranks - 1)  # the checkpoint: rank 0 only
    # a rollout that fails on the last rank only: every rank raises the same error (none hangs)
    assert len(set(got["seen"])) == 1 and got["seen"][0].startswith("ConfigError: rollout")
    # 2 windows over 3 ranks: a rank without windows adds zero, to value and gradient
    s = cube(20)
    v, g = value_and_grad(learn.WindowLoss(s, window=10), params_of(s))
    assert float.fromhex(got["few"]["value"]) == pytest.approx(v, rel=1e-14, abs=0)
    assert [float.fromhex(x) for x in got["few"]["grad"]] == pytest.approx([float(x) for x in g], rel=1e-13, abs=0)


@pytest.mark.slow
def test_fit_cube_script_under_torchrun_equals_one_process(tmp_path):
    """training/fit_cube.py on 2 ranks: rank 0 alone writes and prints; learned values equal the
    one-process script's to 1e-12."""
    argv = ["--runs", "3", "--iterations", "3", "--quiet"]
    res = torchrun(2, ROOT / "training" / "fit_cube.py", *argv, "--out", tmp_path / "two")
    assert res.returncode == 0, res.stderr[:3000] + " ... " + res.stderr[-1500:]
    assert res.stdout.count("run 3:") == 1
    mod = load(ROOT / "training" / "fit_cube.py", "fit_cube")
    assert mod.main([*argv, "--out", str(tmp_path / "one")]) == 0
    two = json.loads((tmp_path / "two" / "result.json").read_text())
    one = json.loads((tmp_path / "one" / "result.json").read_text())
    assert two["ranks"] == 2 and one["ranks"] == 1
    a, b = two["runs"]["3"], one["runs"]["3"]
    assert a["learned"] == pytest.approx(b["learned"], abs=1e-12, rel=0)
    assert a["iterations"] == b["iterations"] and a["initial_loss"] == pytest.approx(b["initial_loss"], rel=1e-14)
    assert (tmp_path / "two" / "run3_loss.png").is_file()
