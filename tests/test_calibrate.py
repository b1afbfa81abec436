"""Calibration (diffdlo.calibrate) on a tiny synthetic recording: the fit recovers what positions over time can
identify (the stiffness-to-damping ratios) and the curvature says the absolute values are not identifiable."""
import dataclasses
import math

import pytest
import torch

import diffdlo
from diffdlo import calibrate


@pytest.fixture(scope="module")
def case():
    p = dataclasses.replace(diffdlo.load_params(), n_nodes=5, length=0.12, max_speed=1.0, settle_max_substeps=40,
                            settle_check_every=4, settle_threshold=0.0)
    sim = diffdlo.Simulator(p, dtype=torch.float64, backend="torch")
    g = torch.Generator().manual_seed(0)
    m, k = 4, 4
    start = sim.settle(diffdlo.random_shape(m, dataclasses.replace(p, sigma=0.6), g, dtype=torch.float64))
    node = torch.randint(0, p.n_nodes, (m,), generator=g)
    delta = (torch.rand(m, 2, generator=g, dtype=torch.float64) * 2 - 1) * 0.02
    _, info = sim.move(start, node, delta, return_info=True, record_every=k)
    f = 1 + int(info.substeps.max()) // k
    blank = calibrate.Moves(start, node, delta, torch.zeros(m, f, p.n_nodes, 2, dtype=torch.float64),
                            torch.ones(m, f, p.n_nodes, dtype=torch.bool), k)
    true = torch.log(torch.tensor([1.3, 0.7, 1.2, 1.5], dtype=torch.float64))        # the hidden rope's factors
    with torch.no_grad():
        frames = calibrate.simulated_frames(sim, blank, true[None])[0]
    return sim, dataclasses.replace(blank, frames=frames), true


def test_the_fit_recovers_the_identifiable_ratios_and_says_what_it_cannot(case):
    sim, moves, true = case
    result = calibrate.fit(sim, moves, starts=2, iterations=80)
    assert result.rms < 1e-5 and result.history[-1] < result.history[0]       # from ~mm to ~um
    report = calibrate.identifiability(sim, moves, result.theta)
    truth = torch.exp(true) * calibrate.nominal_values(sim)
    for name in ("k_s/k_d", "k_b/k_d"):
        c = torch.tensor(calibrate.COMBINATIONS[name], dtype=torch.float64)
        expected = float(torch.exp((c * torch.log(truth)).sum()))
        got = report["combinations"][name]
        assert got["identifiable"] and got["fitted"] == pytest.approx(expected, rel=0.01), name
    for name in ("k_s", "k_b", "k_d", "mass"):                                  # one common scale is invisible
        assert not report["combinations"][name]["identifiable"]
        assert math.isinf(report["combinations"][name]["std"])
    assert report["eigenvalues"][0] < 1e-12 * report["eigenvalues"][-1]
    null = torch.tensor(report["eigenvectors"][0], dtype=torch.float64)
    torch.testing.assert_close(null.abs(), torch.full((4,), 0.5, dtype=torch.float64), rtol=0, atol=1e-3)


def test_the_position_error_depends_only_on_the_ratios(case):
    sim, moves, true = case
    scaled = true + math.log(2.0)                                               # every parameter doubled
    with torch.no_grad():
        a, b = calibrate.residuals(sim, moves, torch.stack([true, scaled]))
    torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    assert a.abs().max() < 1e-12                                                 # the data were made with `true`
