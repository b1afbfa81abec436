"""The cable model against the literature (docs/SIMULATOR.md "The physics against the literature"): the rod map,
the elastica of Bisshopp & Drucker (1945), exact chain modes, free-free beam modes, conservation, the integrator's
frequency error and the gradient over chained moves. Tolerances come from the convergence measured by
``python -m benchmarks.physics_checks`` (quoted per test), never from the code's own output."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from benchmarks import physics_checks as pc
from conftest import crumpled
from diffdlo.planar.simulator import Simulator
from diffdlo.planar.params import CableParams, ParamsError, load_params
from diffdlo.planar.rod import params_for_rod, rod_properties

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def cable() -> CableParams:
    return load_params("cable")


# ====================================================================== the rod map
def test_table21_as_a_rod(cable):
    rod = rod_properties(cable)
    l0 = 0.5 / 19
    assert rod.EI == pytest.approx(0.01 * l0, rel=1e-12)          # k_b l0
    assert rod.EA == pytest.approx(999.0 * l0, rel=1e-12)         # k_s l0
    assert rod.mass_per_length == pytest.approx(0.4, rel=1e-12)
    assert rod.length == 0.5 and rod.rest_length == pytest.approx(l0)


def test_params_for_rod_inverts_rod_properties(cable):
    got = params_for_rod(2e-3, 500.0, 0.1, 0.8, 33, cable)
    rod = rod_properties(got)
    assert (got.n_nodes, got.length) == (33, 0.8)
    for field, want in (("EI", 2e-3), ("EA", 500.0), ("mass_per_length", 0.1)):
        assert getattr(rod, field) == pytest.approx(want, rel=1e-12)
    assert (got.k_d, got.dt, got.controller) == (cable.k_d, cable.dt, cable.controller)


@pytest.mark.parametrize("field", ["EI", "EA", "mass_per_length", "length"])
@pytest.mark.parametrize("value", [0.0, -1.0, math.nan, math.inf])
def test_params_for_rod_refuses_bad_values(cable, field, value):
    kwargs = dict(EI=1e-3, EA=100.0, mass_per_length=0.2, length=0.5, n_nodes=20)
    kwargs[field] = value
    with pytest.raises(ParamsError, match=rf"'{field}'.*{value!r}"):
        params_for_rod(base=cable, **kwargs)


def test_params_for_rod_refuses_few_nodes(cable):
    with pytest.raises(ParamsError, match="n_nodes.*2"):
        params_for_rod(1e-3, 100.0, 0.2, 0.5, 2, cable)


# ====================================================================== statics
def test_elastica_shooting_reproduces_bisshopp_drucker():
    """The independent reference the convergence is measured against agrees with the printed 5 decimals."""
    for alpha, want in pc.BISSHOPP_DRUCKER.items():
        assert pc.elastica_reference(alpha) == pytest.approx(want, abs=6e-6)


def test_cantilever_n80_matches_bisshopp_drucker():
    """Measured at N = 80 (midpoint clamp): errors <= 4.5e-5 (w, alpha = 5), O(1/N^2); 1e-4 allows that plus the
    table's rounding (5e-6). The naive node clamp is 5e-3 off here, so the test can fail."""
    got = pc.cantilever(80)
    for alpha, (w, u, angle) in pc.BISSHOPP_DRUCKER.items():
        assert got[alpha]["w"] == pytest.approx(w, abs=1e-4)
        assert got[alpha]["u"] == pytest.approx(u, abs=1e-4)
        assert got[alpha]["angle"] == pytest.approx(angle, abs=1e-4)


@pytest.mark.parametrize("clamp, lo, hi", [("midpoint", 1.8, 2.5), ("node", 0.9, 1.15)])
def test_cantilever_convergence_order(clamp, lo, hi):
    """Measured orders at N = 10, 20, 40 (alpha = 1 and 5): 2.2-2.3 in N (2.0-2.1 in the N - 2 bending nodes of
    the rod) with the clamp link's midpoint as the rod's root, 1.0 from the clamp node (its link cannot bend)."""
    ref = {a: pc.elastica_reference(a) for a in (1.0, 5.0)}
    runs = {n: pc.cantilever(n, (1.0, 5.0), clamp) for n in (10, 20, 40)}
    for alpha in (1.0, 5.0):
        errors = {n: runs[n][alpha]["w"] - ref[alpha][0] for n in runs}
        assert lo < pc.order(errors) < hi, errors


def test_end_moment_gives_a_circular_arc():
    """Pure end couple: every turning angle M / k_b and the tip on the regular polygon's circle to solver tolerance
    (measured 1e-14); against the continuous arc the tip is off by exactly 1 - beta / (2 tan(beta / 2)), O(1/N^2)."""
    res = {n: pc.end_moment(n) for n in (10, 20, 40)}
    for r in res.values():
        assert r["beta_spread"] < 1e-10 and r["tip_vs_polygon"] < 1e-10 and r["link_strain"] < 1e-10
        assert r["tip_vs_arc"] == pytest.approx(r["tip_vs_arc_predicted"], rel=1e-6)
    # order in the number of bending nodes N - 2 (the rod is (N - 2) l0): beta^2 / 12 exactly
    assert 1.98 < pc.order({n - 2: r["tip_vs_arc"] for n, r in res.items()}) < 2.02


# ====================================================================== modes
@pytest.mark.parametrize("n", [10, 20, 80])
def test_axial_modes_of_a_fixed_fixed_chain_are_exact(cable, n):
    assert pc.axial_modes_fixed_fixed(dataclasses.replace(cable, n_nodes=n))["max_rel_error"] < 1e-10


def _rod_params(cable, n):
    rod = rod_properties(cable)
    return params_for_rod(rod.EI, rod.EA, rod.mass_per_length, rod.length, n, cable)


def test_free_free_bending_modes_rod_lumped(cable):
    """With a rod's lumped masses the linearised model converges to (beta_n L)^2 sqrt(EI / (mu L^4)) as 1/N^2
    (measured -6.6e-4 and -1.5e-3 at N = 80 for modes 1 and 2); the rigid-body modes are zero."""
    res = {n: pc.bending_modes_free_free(_rod_params(cable, n), "rod") for n in (20, 40, 80)}
    for j, tol in ((0, 1e-3), (1, 2e-3)):
        assert abs(res[80]["rel_error"][j]) < tol
        assert 1.9 < pc.order({n: r["rel_error"][j] for n, r in res.items()}) < 2.2
    assert max(abs(x) for x in res[80]["rigid_omega2"]) < 1e-8


def test_free_free_bending_modes_with_the_models_masses(cable):
    """Departure: mass / N on every node (the thesis's and Lv et al.'s lumping) lowers the frequencies by O(1/N)
    (measured -7.3 % for mode 1 at Table 2.1's N = 20)."""
    res = {n: pc.bending_modes_free_free(_rod_params(cable, n)) for n in (20, 40, 80)}
    assert -0.08 < res[20]["rel_error"][0] < -0.065
    assert 0.9 < pc.order({n: r["rel_error"][0] for n, r in res.items()}) < 1.1


# ====================================================================== through the simulator
def test_momentum_is_conserved_with_the_drag_off(cable):
    res = pc.momentum_undamped(cable)
    assert res["momentum_rel_change"] < 1e-12
    assert res["energy_rel_spread"] < 0.15          # symplectic: bounded (measured 6-9 % up to 20,000 substeps)


def test_energy_only_decreases_with_the_drag_on(cable):
    res = pc.energy_damped(cable)
    assert res["max_rise"] <= 1e-12 and res["left"] < 1.0


def test_integrator_frequency_error(cable):
    """Semi-implicit Euler turns omega into (2 / dt) asin(omega dt / 2): exact for the measured recurrence, +1e-4
    for the slowest free-free axial mode, +1.7 % for the stiffest (omega dt = 0.63)."""
    slow = pc.integrator_frequency(cable, mode=1, substeps=1000)
    stiff = pc.integrator_frequency(cable)
    assert abs(slow["vs_prediction"]) < 1e-9 and abs(stiff["vs_prediction"]) < 1e-9
    assert slow["vs_model"] == pytest.approx((slow["omega"] * cable.dt) ** 2 / 24, rel=0.05)
    assert 0.015 < stiff["vs_model"] < 0.02


def test_settle_cap_leaves_a_bent_rope_bent(cable):
    """Departure: the drag makes the first bending mode relax in k_d / (m omega_1^2) = 2,200 s, so the 1 s settle
    cap leaves a released half circle with most of its bending energy (measured 0.96)."""
    drag = pc.drag_departure(cable)
    assert drag["bending_relaxation_s"] > 1000 and drag["zeta_bending_1"] > 100
    res = pc.settle_cap(cable)
    assert not res["settled"] and 0.9 < res["energy_left"] < 1.0


# ====================================================================== gradients
@pytest.mark.parametrize("horizon", [1, 5, 20, 50])
def test_gradient_of_chained_moves_matches_finite_differences(horizon):
    """Measured relative errors 5e-9 to 2.2e-6 over 16 directions with a 1e-6 m step; no direction crosses a
    substep boundary at that step. 1e-5 leaves room for the FD's truncation."""
    res = pc.gradient_horizon(pc.gradient_params(), horizon)
    assert res["crossed"] == 0
    assert res["rel_error_max"] < 1e-5
    assert 0.01 < res["grad_norm_first"] < 10       # neither vanishing nor exploding over 50 moves


def test_move_is_continuous_across_a_substep_boundary():
    """Regression: before the release within the last substep (control.last_substep_fraction) the settled rope
    jumped by 36 um here (the release velocity fell from max_speed to ~0 and the cap came a substep later)."""
    res = pc.substep_boundary_jump(pc.gradient_params())
    assert res["drag_substeps"][0] != res["drag_substeps"][1]
    assert res["jump"] < 1e-6


# ====================================================================== the command
def test_command_refuses_an_existing_results_json(tmp_path, capsys):
    (tmp_path / "results.json").write_text("{}")
    assert pc.main(["--out", str(tmp_path)]) == 2
    assert "results.json" in capsys.readouterr().err
    assert (tmp_path / "results.json").read_text() == "{}"


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_the_gradient_of_a_drag_of_a_whole_number_of_substeps(backend):
    """Regression: a drag of exactly a whole number of substeps (0.03 m = 300 x max_speed dt) got d(move)/d(drag)
    along the drag as if the path's end stood still (the clamp of the path's share passed its gradient at equality):
    about 0, outside the move's one-sided derivatives there (the release within the last substep makes the move's
    derivative along the drag a sawtooth of period max_speed dt, with its kink at these drags). Now it lies between
    them; across the drag it equals central differences."""
    p = pc.gradient_params()
    sim = Simulator(p, dtype=torch.float64, backend=backend)
    pos = crumpled(1, p, sigma=0.6, seed=2)
    node, delta = torch.tensor([p.n_nodes - 1]), torch.tensor([[0.018, 0.024]], dtype=torch.float64)   # 0.03 m
    weights = torch.randn(pos.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    loss = lambda d: float((sim.move(pos, node, d) * weights).sum())
    d = delta.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad((sim.move(pos, node, d) * weights).sum(), d)
    along, across = delta[0] / delta.norm(), torch.tensor([-0.8, 0.6], dtype=torch.float64)
    h = 1e-9
    right = (loss(delta + h * along) - loss(delta)) / h
    left = (loss(delta) - loss(delta - h * along)) / h
    assert abs(left - right) > 0.1 * abs(left)                          # a kink: the two sides differ
    assert min(left, right) < float(grad[0] @ along) < max(left, right), (left, float(grad[0] @ along), right)
    central = (loss(delta + 1e-7 * across) - loss(delta - 1e-7 * across)) / 2e-7
    assert abs(float(grad[0] @ across) - central) < 1e-5 * abs(central)
