"""The fit of the 3-D chain to recordings and DEFORM's evaluation protocol (diffdlo/chain3d/fit.py) and the command
benchmarks/real_cable.py, on synthetic recordings only (DEFORM's recordings are never in the repository)."""
import dataclasses
import json
import math
import pickle

import numpy as np
import pytest
import torch

from benchmarks import real_cable
from diffdlo.chain3d import chain as chain3d, deform, fit

F64 = torch.float64
HELD = (0, 1, -2, -1)


pytestmark = pytest.mark.usefixtures("one_thread")     # tests/conftest.py: one torch thread, restored after


def synthetic(values, n=8, batch=4, frames=60, link=0.1, mass_per_length=0.05, marker=4e-4, seed=0, substeps=5,
              amplitude=0.15, settle=100, gravity=9.81, hold_bent=False):
    """(batch, frames, n, 3) recordings of a chain with ``values`` (FIT_NAMES) under ``gravity`` swung by its two held
    ends: it first settles ``settle`` frames (with 20x the drag) from straight and level at 0.5 m, its ends drawn 20 %
    together and its middle bent out of line (``hold_bent``: the held nodes kept where the bend puts them, else where
    they were before it); then each end pair moves on its own random sinusoid (amplitude up to ``amplitude`` [m],
    0.5-1.5 Hz) from rest."""
    g = torch.Generator().manual_seed(seed)
    held_idx = [h % n for h in HELD]
    mask = torch.zeros(n, dtype=torch.bool)
    mask[held_idx] = True
    x0 = torch.zeros(batch, n, 3, dtype=F64)
    x0[..., 0] = torch.arange(n, dtype=F64) * link * 0.8
    x0[..., 2] = 0.5
    params = chain3d.ChainParams(rest_lengths=torch.full((n - 1,), link, dtype=F64), mass_per_length=mass_per_length,
                                 point_mass=marker, gravity=gravity, **values)
    if settle:
        bend = 0.02 * torch.sin(math.pi * torch.arange(n, dtype=F64) / (n - 1))            # out of line
        x0[:, :, 2] += bend if hold_bent else 0.0
        still = x0[:, held_idx].unsqueeze(0).expand(settle, -1, -1, -1).contiguous()
        x0[:, :, 2] += 0.0 if hold_bent else bend
        x0 = chain3d.rollout(x0, None, mask, still, dataclasses.replace(params, drag=20 * values["drag"]),
                             substeps)[-1]
    t = torch.arange(frames, dtype=F64) * deform.DT
    amp = amplitude * torch.rand(batch, 2, 3, generator=g, dtype=F64)
    freq = 0.5 + torch.rand(batch, 2, 3, generator=g, dtype=F64)
    phase = 2 * math.pi * torch.rand(batch, 2, 3, generator=g, dtype=F64)
    move = amp * (torch.sin(2 * math.pi * freq * t.view(-1, 1, 1, 1) + phase) - torch.sin(phase))   # (T, B, 2, 3)
    move = torch.stack([move[:, :, 0], move[:, :, 0], move[:, :, 1], move[:, :, 1]], 2)               # per held node
    path = x0[:, held_idx].unsqueeze(0) + move
    out = chain3d.rollout(x0, None, mask, path, params, substeps)
    return out.transpose(0, 1).contiguous()


TRUE = {"EI": 2e-3, "EA": 30.0, "drag": 0.05, "axial_damping": 2e-3, "bending_damping": 2e-6}


# ============================================================================ the metric and the protocol
def test_l1_error_and_score_on_a_hand_made_case():
    T, n = 6, 5
    rec = torch.zeros(2, T, n, 3, dtype=F64)
    pred = torch.zeros(2, T - 2, n, 3, dtype=F64)
    pred[0, :, 2, 0] = 0.03                     # recording 0: one marker 3 cm off in x on every frame
    pred[1, 1, 3] = torch.tensor([0.01, -0.02, 0.03], dtype=F64)   # recording 1: one marker off on one frame
    s = fit.score(pred, rec)
    e0 = 0.03 / (n * 3)
    e1 = 0.06 / ((T - 2) * n * 3)
    assert s["per_recording_m"]["0"] == pytest.approx(e0, rel=1e-12)
    assert s["per_recording_m"]["1"] == pytest.approx(e1, rel=1e-12)
    assert s["l1_m"] == pytest.approx((e0 + e1) / 2, rel=1e-12)
    assert s["deform_convention_m"] == pytest.approx(s["l1_m"] * (T - 2) / T, rel=1e-12)
    assert s["frames"] == T - 2 and len(s["per_frame_m"]) == T - 2
    assert s["per_frame_m"][1] == pytest.approx((0.03 / (n * 3) + 0.06 / (n * 3)) / 2, rel=1e-12)
    with pytest.raises(fit.FitError, match="shape"):
        fit.score(pred[:, :-1], rec)


def test_frozen_baseline_keeps_free_markers_at_frame_one_and_drives_the_held_ones():
    rec = torch.randn(3, 7, 6, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    pred = fit.frozen_prediction(rec, HELD)
    assert pred.shape == (3, 5, 6, 3)
    held = [0, 1, 4, 5]
    assert torch.equal(pred[:, :, held], rec[:, 2:, held])
    assert torch.equal(pred[:, :, 2:4], rec[:, 1:2, 2:4].expand(-1, 5, -1, -1))
    # by hand: the free markers' error is |x_t - x_1|, the held ones' zero
    want = (rec[:, 2:, 2:4] - rec[:, 1:2, 2:4]).abs().sum(dim=(1, 2, 3)) / (5 * 6 * 3)
    assert torch.allclose(fit.l1_error(pred, rec[:, 2:]), want, rtol=1e-12)


def test_predict_starts_at_frame_one_with_the_finite_difference_velocity():
    """A recording the model makes itself from frame 1 (frame 0 set so that (x1 - x0) / dt is its velocity) is
    reproduced to rounding: the frames and the held path are aligned as DEFORM's protocol has them."""
    n, T = 8, 40
    rec = synthetic(TRUE, n=n, batch=2, frames=T, seed=3)
    m = fit.cable_model(rec, HELD, mass=0.05 * 0.7, length=0.7, bounds={"EA": (5.0, 30.0)})
    x1 = rec[:, 5]
    v1 = (rec[:, 5] - rec[:, 4]) / deform.DT
    path = rec[:, 5:, [0, 1, n - 2, n - 1]].transpose(0, 1).contiguous()
    own = fit.simulate(m, TRUE, x1, v1, path).transpose(0, 1)            # frames 5.. of the model's own motion
    made = torch.cat([(x1 - deform.DT * v1).unsqueeze(1), own], 1)       # frame 0 behind frame 1 by v1 dt
    # held markers of the new frame 0 must be on the path's own finite difference
    made[:, 0, [0, 1, n - 2, n - 1]] = own[:, 0, [0, 1, n - 2, n - 1]] - deform.DT * (path[1] - path[0]) / deform.DT
    pred = fit.predict(m, TRUE, made)
    assert pred.shape == (2, made.shape[1] - 2, n, 3)
    assert torch.equal(pred[:, :, [0, 1, n - 2, n - 1]], made[:, 2:, [0, 1, n - 2, n - 1]])
    assert float(fit.score(pred, made)["l1_m"]) < 1e-10


# ============================================================================ the fit
def test_the_fit_recovers_a_synthetic_cables_stiffness_and_drag():
    """Noiseless recordings of a chain with known EI and drag (the other parameters at their true values, the rest
    lengths given), fitted from a start 2x off in each over 20-frame windows. The loss's optimum is the truth up to
    the start velocity's error: each window starts from (x_s - x_{s-1}) / dt, the mean velocity over the frame
    before, not the chain's velocity at frame s (the loss at the truth is 0.2 mm, not 0). Measured: EI within 2 %,
    drag within 6 % (and EI 4 %, drag 0.1 % with 30-frame windows); the tolerances are 10 % and 20 %."""
    n = 6
    true = dict(TRUE, drag=0.2)
    rec = synthetic(true, n=n, batch=4, frames=50, seed=1)
    start = dict(true, EI=true["EI"] * 2, drag=true["drag"] / 2)
    bounds = {k: (v, v) for k, v in true.items() if k not in ("EI", "drag")}
    result = fit.fit_cable(rec, HELD, mass=0.05 * 0.5, length=0.5, window=20, iterations=45, batch=4, lr=0.15,
                           scan_points=0, bootstrap=0, start=start, bounds=bounds, names=("EI", "drag"),
                           rest_lengths=[0.1] * (n - 1), progress=False)
    assert result.values["EI"] == pytest.approx(true["EI"], rel=0.1)
    assert result.values["drag"] == pytest.approx(true["drag"], rel=0.2)
    assert result.history[-1] < 0.2 * result.history[0]
    assert result.values["EA"] == true["EA"]          # the others stayed where they were put


def test_the_fit_is_deterministic_and_reports_a_bootstrap_spread():
    rec = synthetic(TRUE, n=6, batch=3, frames=30, seed=2)
    kw = dict(mass=0.05 * 0.5, length=0.5, window=10, iterations=4, batch=2, scan_points=3, bootstrap=2,
              bootstrap_iterations=2, progress=False, seed=7)
    a = fit.fit_cable(rec, HELD, **kw)
    b = fit.fit_cable(rec, HELD, **kw)
    assert a.values == b.values and a.spread == b.spread and a.history == b.history
    assert len(a.bootstrap) == 2 and all(a.spread[k] >= 0 for k in fit.FIT_NAMES)
    c = fit.fit_cable(rec, HELD, **dict(kw, seed=8))
    assert c.values != a.values
    d = a.to_dict()
    assert set(d["values"]) == set(fit.FIT_NAMES) and d["model"]["substeps"] == a.model.substeps


def test_cable_model_masses_and_rest_lengths():
    rec = synthetic(TRUE, n=6, batch=2, frames=20, seed=4)
    m = fit.cable_model(rec, HELD, mass=0.02, length=0.5)
    assert m.mass_per_length == pytest.approx(0.04)
    assert torch.allclose(m.point_mass, torch.full((6,), deform.MARKER_MASS, dtype=F64))
    gaps = (rec[:, :, 1:] - rec[:, :, :-1]).norm(dim=-1).reshape(-1, 5)       # every frame of every recording
    for k in range(5):
        assert float(m.rest_lengths[k]) == float(gaps[:, k].median())
    given = fit.cable_model(rec, HELD, mass=0.02, length=0.5, rest_lengths=[0.1] * 5)
    assert torch.equal(given.rest_lengths, torch.full((5,), 0.1, dtype=F64))
    with pytest.raises(fit.FitError, match="rest_lengths"):
        fit.cable_model(rec, HELD, mass=0.02, length=0.5, rest_lengths=[0.1] * 4)
    assert m.held == (0, 1, 4, 5)
    inc = fit.cable_model(rec, HELD, mass=0.02, length=0.5, markers_in_mass=True)
    assert inc.mass_per_length == pytest.approx((0.02 - 6 * deform.MARKER_MASS) / 0.5)
    assert m.stability({k: hi for k, (lo, hi) in fit.DEFAULT_BOUNDS.items()}) < fit.STABILITY_TARGET


@pytest.mark.parametrize("bad, match", [
    ({"held": (0, 0, 5)}, "twice"), ({"held": (0, 9)}, "not an integer in"), ({"mass": -1.0}, "mass must be"),
    ({"window": 0}, "window must be"), ({"window": 50}, "window 50 needs"), ({"names": ("EI", "foo")}, "names must"),
    ({"bounds": {"EI": (1.0, 0.1)}}, "bounds"), ({"start": {"EI": -1.0}}, "start"),
])
def test_fit_refuses_bad_input_naming_the_value(bad, match):
    rec = synthetic(TRUE, n=6, batch=2, frames=20, seed=4)
    kw = dict(mass=0.02, length=0.5, window=5, iterations=1, batch=1, scan_points=0, bootstrap=0, progress=False)
    held = bad.pop("held", HELD)
    kw.update(bad)
    with pytest.raises(fit.FitError, match=match):
        fit.fit_cable(rec, held, **kw)


def test_recordings_are_checked():
    with pytest.raises(fit.FitError, match="empty"):
        fit.as_recordings({})
    with pytest.raises(fit.FitError, match="share T and n"):
        fit.as_recordings([torch.zeros(5, 6, 3), torch.zeros(6, 6, 3)])
    with pytest.raises(fit.FitError, match="non-finite"):
        fit.as_recordings({"a": torch.full((5, 6, 3), math.nan)})
    with pytest.raises(fit.FitError, match=r"\(T, n, 3\)"):
        fit.as_recordings([torch.zeros(5, 3, 6)])


# ============================================================================ the command
def write_fake_dataset(root, cable=2, train=3, evals=2, frames=24):
    """DEFORM's layout and format: data_set/DLO<k>/{train,eval}/<id>.pkl, each a pickled (T, 3, n) nested list."""
    n = deform.CABLES[cable].n_markers
    rec = synthetic(TRUE, n=n, batch=train + evals, frames=frames, link=0.09, seed=5)
    for i in range(train + evals):
        split = "train" if i < train else "eval"
        folder = root / "data_set" / f"DLO{cable}" / split
        folder.mkdir(parents=True, exist_ok=True)
        with open(folder / f"{100 + i}.pkl", "wb") as f:
            pickle.dump(rec[i].transpose(1, 2).tolist(), f)
    return root / "data_set", n


def test_the_command_fits_scores_and_writes_predictions(tmp_path, capsys):
    data, n = write_fake_dataset(tmp_path)
    out = tmp_path / "out"
    assert real_cable.main(["--data", str(data), "--out", str(out), "--cables", "2", "--quick", "--no-progress",
                            "--threads", "1"]) == 0
    res = json.loads((out / "results.json").read_text())
    c = res["cables"]["DLO2"]
    assert c["ours"]["frames"] == 22 and c["ours"]["recordings"] == 2
    assert math.isfinite(c["ours"]["l1_m"]) and c["ours"]["time_per_frame_s"] > 0
    assert set(c["parameters"]) == set(fit.FIT_NAMES)
    assert c["paper_cm"]["DEFORM"] == 0.97 and "--quick" in res["command"]
    for key in ("103", "104"):
        with np.load(out / "predictions" / "DLO2" / f"{key}.npz") as z:
            assert z["positions"].shape == (22, n, 3)
    assert "DLO2" in capsys.readouterr().out
    # an existing OUT is refused without --overwrite
    with pytest.raises(SystemExit) as e:
        real_cable.main(["--data", str(data), "--out", str(out), "--cables", "2", "--quick", "--no-progress"])
    assert e.value.code == 2
    assert str(out) in capsys.readouterr().err


@pytest.mark.parametrize("args, named", [
    (["--data", "/no/such/folder"], "/no/such/folder"),
    (["--cables", "7"], "7"),
    (["--cables", "2", "--jobs", "0"], "--jobs"),
])
def test_the_command_refuses_bad_input_naming_the_value(tmp_path, capsys, args, named):
    data, _ = write_fake_dataset(tmp_path)
    argv = ["--data", str(data), "--out", str(tmp_path / "o"), "--quick"]
    argv = argv[:0] + args + [a for i, a in enumerate(argv) if not (argv[i] in args[::2] or
                                                                       (i and argv[i - 1] in args[::2]))]
    with pytest.raises(SystemExit) as e:
        real_cable.main(argv)
    assert e.value.code == 2
    assert named in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_the_command_names_a_missing_split(tmp_path, capsys):
    data, _ = write_fake_dataset(tmp_path)
    with pytest.raises(SystemExit):
        real_cable.main(["--data", str(data), "--out", str(tmp_path / "o"), "--cables", "3", "--quick"])
    assert "DLO3" in capsys.readouterr().err


def test_the_residual_command_trains_on_a_physics_run_and_reports_both(tmp_path, capsys):
    """benchmarks.real_cable_residual: the physics values from a benchmarks.real_cable folder, the residual
    trained and saved, both errors reported, predictions written; a --physics folder without a fit is named."""
    from benchmarks import real_cable_residual
    from diffdlo.chain3d import residual
    data, n = write_fake_dataset(tmp_path)
    phys = tmp_path / "phys"
    assert real_cable.main(["--data", str(data), "--out", str(phys), "--cables", "2", "--quick", "--no-progress",
                            "--threads", "1"]) == 0
    out = tmp_path / "resid"
    assert real_cable_residual.main(["--data", str(data), "--physics", str(phys), "--out", str(out), "--cables", "2",
                                     "--quick", "--no-progress", "--threads", "1"]) == 0
    res = json.loads((out / "results.json").read_text())
    c = res["cables"]["DLO2"]
    physics = json.loads((phys / "results.json").read_text())["cables"]["DLO2"]
    assert c["physics_only"]["l1_m"] == pytest.approx(physics["ours"]["l1_m"], rel=1e-9)   # the same physics
    assert math.isfinite(c["ours"]["l1_m"]) and c["training"]["validation_ids"]
    assert set(c["training"]["validation_ids"]).isdisjoint(c["training"]["train_ids"])
    net = residual.load(out / "DLO2_residual.pt")
    assert net.config.n == n
    with np.load(out / "predictions" / "DLO2" / "103.npz") as z:
        assert z["positions"].shape == (22, n, 3)
    assert "DLO2" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        real_cable_residual.main(["--data", str(data), "--physics", str(tmp_path), "--out", str(tmp_path / "o"),
                                  "--cables", "2", "--quick"])
    assert e.value.code == 2 and "holds no results.json" in capsys.readouterr().err
