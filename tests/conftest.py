"""Fixtures shared by every test (the independent oracles live in :mod:`tests.oracles`)."""
import numpy as np
import pytest
import torch


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)
