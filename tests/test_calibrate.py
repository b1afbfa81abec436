"""Calibration (diffdlo.calibration.calibrate) on a tiny synthetic recording: the fit recovers what positions over time can
identify (the stiffness-to-damping ratios) and the curvature says the absolute values are not identifiable."""
import dataclasses
import math

import pytest
import torch

import diffdlo
from diffdlo.calibration import calibrate


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


def test_adam_through_the_simulators_gradient_lowers_the_error(case):
    sim, moves, true = case
    result = calibrate.fit(sim, moves, starts=2, iterations=15)
    assert result.history[-1] < 0.5 * result.history[0] and result.simulator_calls == 31
    assert result.starts.shape == (2, 4) and result.rms == min(result.start_rms)


def test_the_fit_recovers_the_identifiable_ratios_and_says_what_it_cannot(case):
    sim, moves, true = case
    result = calibrate.fit_gauss_newton(sim, moves, iterations=12, hold=())      # all four probed
    assert result.rms < 1e-9 and result.history[-1] < result.history[0]       # noiseless: to rounding
    assert result.left_out == {} and result.offsets.abs().max() < 1e-8          # exact starts need no correction
    report = calibrate.identifiability(sim, moves, result.theta, result.offsets)
    reused = calibrate.identifiability(sim, moves, result.theta, at_theta=result.at_best)   # the fit's own Jacobian
    assert reused["simulator_calls"] == 0 and reused["eigenvalues"] == pytest.approx(report["eigenvalues"], rel=1e-4)
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


def test_the_block_step_equals_the_dense_gauss_newton_step(case):
    """Eliminating the start shapes move by move (Schur complement) gives the step of the whole dense system."""
    sim, moves, true = case
    m, n = moves.start.shape[:2]
    offsets = 1e-4 * torch.randn(1, m, n, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    lin = calibrate.linearize(sim, moves, torch.zeros(1, 4, dtype=torch.float64), offsets, fit_starts=True)
    d_theta, d_start = lin.step(torch.zeros(1, dtype=torch.float64), hold=(2,))
    d = lin.r.shape[-1]
    dense = torch.zeros(m * d, 3 + m * 2 * n, dtype=torch.float64)             # theta without k_d, then starts
    for i in range(m):
        dense[i * d:(i + 1) * d, :3] = lin.j_theta[0, i][:, [0, 1, 3]]
        dense[i * d:(i + 1) * d, 3 + i * 2 * n:3 + (i + 1) * 2 * n] = lin.j_start[0, i]
    h = dense.T @ dense
    expected = -torch.linalg.solve(h + 1e-12 * torch.eye(h.shape[0], dtype=torch.float64), dense.T @ lin.r[0].flatten())
    torch.testing.assert_close(d_theta[0, [0, 1, 3]], expected[:3], rtol=1e-6, atol=1e-9)
    assert d_theta[0, 2] == 0                                                    # held
    torch.testing.assert_close(d_start[0].flatten(), expected[3:], rtol=1e-6, atol=1e-12)


def test_fitting_the_start_shapes_removes_the_noisy_starts_bias():
    """Replayed from noisy recorded starts the fitted ratios are biased; fitting the starts too removes it, and a
    move the replay cannot follow is left out by name."""
    from diffdlo.calibration.record import make_recording
    p = diffdlo.load_params("cable", n_nodes=8, length=0.2, settle_max_substeps=200, settle_check_every=50)
    scale = {"k_s": 1.4, "k_b": 0.7}
    rec = make_recording(p, 6, seed=0, noise=1e-3, record_every=20, scale=scale)
    sim = diffdlo.Simulator(p, dtype=torch.float64)
    moves = calibrate.moves_from_recording(rec, p.dt)
    errors = {}
    for fit_starts in (False, True):
        r = calibrate.fit_gauss_newton(sim, moves, fit_starts=fit_starts, outlier_factor=None)
        errors[fit_starts] = abs(r.values["k_b"] / r.values["k_d"] / (0.7 * p.k_b / p.k_d) - 1)
    assert errors[True] < 0.5 * errors[False], errors
    broken = dataclasses.replace(moves, frames=moves.frames.clone())
    broken.frames[2, 1:] += 0.02                                               # a move the model cannot follow
    r = calibrate.fit_gauss_newton(sim, broken)
    assert list(r.left_out) == [2] and r.kept.tolist() == [0, 1, 3, 4, 5] and r.offsets.shape[0] == 5


def test_the_position_error_depends_only_on_the_ratios(case):
    sim, moves, true = case
    scaled = true + math.log(2.0)                                               # every parameter doubled
    with torch.no_grad():
        a, b = calibrate.residuals(sim, moves, torch.stack([true, scaled]))
    torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    assert a.abs().max() < 1e-12                                                 # the data were made with `true`


TINY = ["--set", "n_nodes=5", "--set", "length=0.12", "--set", "max_speed=1.0", "--set", "settle_max_substeps=40",
        "--set", "settle_check_every=4", "--set", "settle_threshold=0.0"]


def test_the_command_line_calibrates_a_synthetic_rope_and_writes_its_report(tmp_path, capsys):
    import json
    out = tmp_path / "cal"
    argv = ["--synthetic", "--seed", "3", "--moves", "4", "--noise", "0.0001", "--iterations", "6", "--starts", "1",
            "--record-every", "4", "--out", str(out), *TINY]
    assert calibrate.main(argv) == 0
    res = json.loads((out / "results.json").read_text())
    rows = res["parameters"]
    # the accuracy of the fit is the test above's; here the report: every row, its truth, its error and its verdict
    assert set(rows) == set(calibrate.COMBINATIONS)
    for row in rows.values():
        assert row["rel_error"] == pytest.approx(row["fitted"] / row["true"] - 1) and isinstance(row["identifiable"],
                                                                                                  bool)
    assert not rows["k_d"]["identifiable"] and not rows["mass"]["identifiable"]     # a common scale never is
    assert res["history_rms_m"][-1] < res["history_rms_m"][0]
    assert set(res["true"]) == {"k_s", "k_b", "k_d", "mass"} and res["held"] == ["k_d", "mass"]
    assert res["fit_starts"] and 3 <= res["simulator_calls"] <= 3 * (6 + 1) + 1     # stages stop when converged
    assert (out / "trajectories.png").exists()
    with pytest.raises(SystemExit) as exc:                                      # an earlier result is kept
        calibrate.main(argv)
    assert exc.value.code == 2 and "already holds an earlier calibration" in capsys.readouterr().err


@pytest.mark.parametrize("extra,message", [(["--iterations", "0"], "--iterations must be at least 1, got 0"),
                                           (["--noise", "-1"], "--noise must be >= 0"),
                                           (["--set", "n_nodes"], "--set expects KEY=VALUE"),
                                           (["--params", "nope"], "nope"),
                                           (["--hold", "k_d,stiffness"], "--hold must name some of")])
def test_bad_calibration_flags_are_named(extra, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        calibrate.main(["--synthetic", "--out", str(tmp_path / "cal"), *TINY, *extra])
    assert exc.value.code == 2 and message in capsys.readouterr().err and not (tmp_path / "cal").exists()


def test_a_recording_file_is_calibrated_through_the_same_path(tmp_path):
    from diffdlo.calibration.record import make_recording
    from diffdlo.calibration.recording import save_recording
    p = diffdlo.load_params("cable", n_nodes=5, length=0.12, max_speed=1.0, settle_max_substeps=40,
                            settle_check_every=4, settle_threshold=0.0)
    rec = make_recording(p, 3, seed=1, record_every=4, scale={"k_s": 1.5})
    moves = calibrate.moves_from_recording(rec, p.dt)
    sim = diffdlo.Simulator(p, dtype=torch.float64, backend="torch")
    true = torch.tensor([math.log(1.5), 0.0, 0.0, 0.0], dtype=torch.float64)
    with torch.no_grad():                                # the recording replays exactly under its hidden params
        assert calibrate.residuals(sim, moves, true[None]).abs().max() < 1e-10
        assert calibrate.residuals(sim, moves, torch.zeros(1, 4, dtype=torch.float64)).abs().max() > 1e-5
    save_recording(tmp_path / "rec.npz", rec)
    assert calibrate.main(["--data", str(tmp_path / "rec.npz"), "--iterations", "5", "--starts", "1",
                           "--out", str(tmp_path / "cal"), *TINY]) == 0
