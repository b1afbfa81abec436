import dataclasses

import pytest
import torch

import diffdlo


@pytest.fixture(scope="session")
def params():
    return diffdlo.load_params("cable")


@pytest.fixture
def sim64(params):
    return diffdlo.Simulator(params, dtype=torch.float64)


def small_params(params, **changes):
    """A cheap variant for gradcheck-sized problems."""
    return dataclasses.replace(params, **changes)


def crumpled(batch, params, sigma=1.4, seed=0, dtype=torch.float64):
    """Random shapes with large turning angles (beyond 90 degrees at some nodes)."""
    p = dataclasses.replace(params, sigma=sigma)
    return diffdlo.random_shape(batch, p, torch.Generator().manual_seed(seed), dtype=dtype)
