"""Options and fixtures shared by every test (the independent oracles live in :mod:`tests.oracles`).

Two tiers: ``pytest`` runs everything not marked ``slow`` (the developer's loop); ``pytest --runslow``
adds the slow tests (compiles, torchrun ranks, the browser, fuzz campaigns, bench smoke runs, long
fits). ``--device cuda`` builds the device-aware tests on the GPU (they are skipped where CUDA is
absent); tests that are CPU-only by nature (the C kernel, file IO, the CLI) ignore the option.
"""

import functools
import os

import numpy as np
import pytest
import torch

from tests import helpers

if os.environ.get("PYTEST_XDIST_WORKER"):  # two workers on two cores: one thread each, no spinning
    torch.set_num_threads(1)
    # and so do the processes the tests start (the CLI, scripts, torchrun ranks), unless a test asks
    os.environ.setdefault("OMP_NUM_THREADS", "1")


@pytest.fixture
def one_thread():
    """One torch thread for the test: small tensors run several times faster on one thread than on
    two when another process holds a core (OpenMP threads spinning at barriers, DESIGN.md)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="also run the tests marked slow")
    parser.addoption(
        "--device", action="store", default="cpu", choices=("cpu", "cuda"), help="device of the device-aware tests"
    )


#: modules whose tests run first: their long tests (a whole inductor compile in a fresh process,
#: about 40 s on 2 cores; fuzz campaigns) would otherwise come last in the collection and run alone at the end,
#: with the other worker idle
FIRST = ("tests/test_compile.py", "tests/test_fuzz.py")


def pytest_collection_modifyitems(config, items):
    # every test that takes the device fixture is device-aware: `-m device` selects them (the GPU check)
    for item in items:
        if "device" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.device)
    items.sort(key=lambda item: item.nodeid.split("::")[0] not in FIRST)  # stable: the rest keep their order
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow: pass --runslow")
    for item in items:
        if item.get_closest_marker("slow") is not None:
            item.add_marker(skip_slow)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)


@pytest.fixture(scope="session")
def device(request) -> torch.device:
    """The device of the device-aware tests (``--device``); they are skipped when it is absent."""
    if request.config.getoption("--device") == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        pytest.skip("--device cuda: CUDA is not available on this machine")
    return torch.device("cuda", torch.cuda.current_device())  # equal to the .device of the tensors made on it


@pytest.fixture(params=helpers.DTYPES, ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    """Each dtype in turn: float32 (the default) and float64 (the accuracy dtype)."""
    return request.param


@pytest.fixture
def make_grid():
    """:func:`tests.helpers.make_grid`: a small grid factory."""
    return helpers.make_grid


@pytest.fixture
def make_model(device):
    """:func:`tests.helpers.make_model` bound to the device of the run."""
    return functools.partial(helpers.make_model, device=device)
