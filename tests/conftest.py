import dataclasses
import os

import pytest
import torch

import diffdlo

# Under pytest-xdist (the README's test command: -n 2) each worker gets its share of the cores, so that two workers
# do not run four torch threads on a 2-core machine
if os.environ.get("PYTEST_XDIST_WORKER_COUNT"):
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))


@pytest.fixture
def one_thread():
    """One torch thread for the test (planning loops are faster so on a shared 2-core machine), restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def params():
    return diffdlo.load_params("cable")


@pytest.fixture(scope="session")
def small():
    """6 nodes, 0.15 m: a move costs a few ms."""
    return dataclasses.replace(diffdlo.load_params("cable"), n_nodes=6, length=0.15, max_speed=1.0,
                               settle_max_substeps=30, settle_check_every=10)


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


def cli_error(main, argv, capsys) -> str:
    """The stderr of a command-line entry point ``main(argv)`` that must refuse its arguments: exit code 2 (returned
    or raised by argparse) and a message."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.strip(), "no message"
    return err
