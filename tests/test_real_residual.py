"""The learned residual correction to the 3-D chain (diffdlo/chain3d/residual.py), on synthetic recordings only
(DEFORM's recordings are never in the repository)."""
import dataclasses
import functools
import math

import pytest
import torch

from diffdlo.chain3d import chain as chain3d, deform, fit, residual

from test_real_fit import HELD, TRUE, synthetic as fit_synthetic     # the held nodes, the true values, the chain

F64 = torch.float64
N = 6
LINK = 0.1

pytestmark = pytest.mark.usefixtures("one_thread")     # tests/conftest.py: one torch thread, restored after


def synthetic(values, **kw):
    """_synthetic's recordings (a copy: they are made once per set of arguments)."""
    return _synthetic(tuple(sorted(values.items())), **kw).clone()


@functools.lru_cache(maxsize=None)
def _synthetic(values, batch=4, frames=40, gravity=9.81, seed=0, substeps=5, amplitude=0.15, settle=60):
    """tests/test_real_fit.py's recordings of a chain of N nodes under ``gravity``, its held nodes kept bent."""
    return fit_synthetic(dict(values), n=N, batch=batch, frames=frames, link=LINK, seed=seed, substeps=substeps,
                         amplitude=amplitude, settle=settle, gravity=gravity, hold_bent=True)


def cable(rec):
    """The cable model of the synthetic chain (its true rest lengths, 5 substeps)."""
    m = fit.cable_model(rec, HELD, mass=0.05 * LINK * (N - 1), length=LINK * (N - 1), rest_lengths=[LINK] * (N - 1),
                        bounds={"EA": (5.0, 30.0)})
    return dataclasses.replace(m, substeps=5)


def random_last_layer(net, scale=0.3, seed=0):
    g = torch.Generator().manual_seed(seed)
    last = net.net[-1]
    with torch.no_grad():
        last.weight.copy_(scale * torch.randn(last.weight.shape, generator=g, dtype=F64).to(last.weight.dtype))
        last.bias.copy_(scale * torch.randn(last.bias.shape, generator=g, dtype=F64).to(last.bias.dtype))


# ============================================================================ the untrained correction is nothing
def test_an_untrained_correction_is_exactly_the_physics_only_model():
    rec = synthetic(TRUE, batch=3, frames=30, seed=1)
    m = cable(rec)
    net = residual.ResidualNet(residual.ResidualConfig(n=N, held=m.held), seed=3).double()
    want = fit.predict(m, TRUE, rec)
    assert torch.equal(residual.predict(m, TRUE, net, rec), want)
    assert torch.equal(residual.predict(m, TRUE, None, rec), want)
    x, v = rec[:, 5], (rec[:, 5] - rec[:, 4]) / deform.DT
    assert torch.equal(net(x, v), torch.zeros_like(x))
    # float32 states and a float32 network: the same model to float32's rounding
    pred32 = residual.predict(m, TRUE, residual.ResidualNet(net.config), rec, dtype=torch.float32)
    assert pred32.dtype == torch.float32 and float((pred32.double() - want).abs().max()) < 1e-4


def test_the_correction_is_translation_and_yaw_equivariant_and_spares_the_held_nodes():
    rec = synthetic(TRUE, batch=2, frames=12, seed=2)
    net = residual.ResidualNet(residual.ResidualConfig(n=N, held=(0, 1, N - 2, N - 1))).double()
    random_last_layer(net, 1.0)
    x, v = rec[:, 6], (rec[:, 6] - rec[:, 5]) / deform.DT
    c, s = math.cos(0.7), math.sin(0.7)
    R = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)      # a turn about the vertical
    shift = torch.tensor([0.3, -1.2, 0.4], dtype=F64)
    flip = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=F64))                 # upside down
    with torch.no_grad():
        a = net(x, v)
        moved = net(x @ R.T + shift, v @ R.T)
        flipped = net(x @ flip, v @ flip)
    assert float(a.abs().max()) > 1e-3 and float(a.abs().max()) <= net.config.max_accel * math.sqrt(2) + 1e-12
    assert torch.equal(a[:, [0, 1, N - 2, N - 1]], torch.zeros_like(a[:, :4]))
    assert torch.allclose(moved, a @ R.T, atol=1e-12)
    # z is not like x and y (gravity): turning the chain over changes the correction
    assert not torch.allclose(flipped, a @ flip, atol=1e-6)


# ============================================================================ training
def test_training_through_the_rollout_learns_a_missing_force():
    """Recordings of a chain under 1.5 g with 3x the drag, modelled with 1 g and 1x the drag: the missing weight and
    drag are an extra force the correction must learn. Trained on 6-frame windows of 6 recordings, judged on
    10-frame windows and open loop (DEFORM's protocol, 38 frames) on 3 others. Measured (training seeds 0-3): window
    loss 0.147 -> 0.062-0.078 cm (its floor is the start's finite-difference velocity), held-out 0.27 -> 0.06-0.09
    cm."""
    truth = dict(TRUE, drag=3 * TRUE["drag"])
    rec = synthetic(truth, batch=9, frames=40, gravity=1.5 * 9.81, seed=4)
    train, held_out = rec[:6], rec[6:]
    m = cable(train)
    result = residual.fit_residual(m, TRUE, train, iterations=30, window=6, batch=4, lr=3e-2, hidden=16,
                                   max_accel=8.0, seed=0, progress=False)
    f, s = fit._windows(train, 8, 10, torch.Generator().manual_seed(99))
    with torch.no_grad():
        before = float(fit.window_loss(m, TRUE, train, f, s, 10))
        after = float(residual.window_loss(m, TRUE, result.net, train, f, s, 10))
    physics = fit.score(fit.predict(m, TRUE, held_out), held_out)["l1_m"]
    learned = fit.score(residual.predict(m, TRUE, result.net, held_out), held_out)["l1_m"]
    assert after < 0.65 * before
    assert learned < 0.5 * physics
    assert len(result.history) == 30 and result.skipped == 0 and result.best_step == 30 and not result.validation
    assert result.to_dict()["config"]["n"] == N


def test_training_is_deterministic_and_validation_keeps_the_best_state():
    rec = synthetic(TRUE, batch=4, frames=25, gravity=1.2 * 9.81, seed=5)
    m = cable(rec)
    kw = dict(iterations=6, window=5, batch=2, hidden=8, seed=7, progress=False)
    a = residual.fit_residual(m, TRUE, rec[:3], **kw)
    b = residual.fit_residual(m, TRUE, rec[:3], **kw)
    assert a.history == b.history
    assert all(torch.equal(a.state_dict[k], b.state_dict[k]) for k in a.state_dict)
    c = residual.fit_residual(m, TRUE, rec[:3], **dict(kw, seed=8))
    assert c.history != a.history
    # validation from step 0 (physics only) every 3 steps; the kept state is the best one seen
    v = residual.fit_residual(m, TRUE, rec[:3], validation=rec[3:], eval_every=3, **kw)
    assert [s for s, _ in v.validation] == [0, 3, 6]
    best_step, best_err = min(v.validation, key=lambda t: (t[1], t[0]))
    assert v.best_step == best_step
    assert fit.score(residual.predict(m, TRUE, v.net, rec[3:]), rec[3:])["l1_m"] == pytest.approx(best_err, rel=1e-12)
    assert v.validation[0][1] == pytest.approx(fit.score(fit.predict(m, TRUE, rec[3:]), rec[3:])["l1_m"], rel=1e-12)


def test_gradients_flow_through_the_rollout_to_every_weight():
    rec = synthetic(TRUE, batch=2, frames=12, seed=6)
    m = cable(rec)
    net = residual.ResidualNet(residual.ResidualConfig(n=N, held=m.held, hidden=8)).double()
    f, s = torch.tensor([0, 1]), torch.tensor([1, 2])
    loss = residual.window_loss(m, TRUE, net, rec, f, s, 8)
    loss.backward()
    last = net.net[-1]
    assert float(last.weight.grad.abs().sum()) > 0           # the zero last layer is where training starts
    random_last_layer(net, 0.3)
    net.zero_grad()
    residual.window_loss(m, TRUE, net, rec, f, s, 8).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()) and float(p.grad.abs().sum()) > 0, name
    # the gradient is the loss's derivative: a directional finite difference along it
    params = list(net.parameters())
    d = [p.grad.clone() for p in params]
    slope = sum(float((g * g).sum()) for g in d)
    eps = 1e-4 / math.sqrt(slope)

    def at(t):
        with torch.no_grad():
            for p, g in zip(params, d):
                p.add_(t * g)
            out = float(residual.window_loss(m, TRUE, net, rec, f, s, 8))
            for p, g in zip(params, d):
                p.sub_(t * g)
        return out
    fd = (at(eps) - at(-eps)) / (2 * eps)
    assert fd == pytest.approx(slope, rel=1e-3)


def test_a_learned_correction_keeps_the_chain_stable():
    """A random (untrained) correction at its bound does not make the chain diverge over a long rollout, and a
    rollout that does diverge still raises chain3d's error naming the frame."""
    rec = synthetic(TRUE, batch=2, frames=80, seed=7)
    m = cable(rec)
    net = residual.ResidualNet(residual.ResidualConfig(n=N, held=m.held, max_accel=5.0)).double()
    random_last_layer(net, 3.0)
    pred = residual.predict(m, TRUE, net, rec)
    assert bool(torch.isfinite(pred).all()) and float(pred.abs().max()) < 5.0
    with pytest.raises(chain3d.ChainDivergedError, match="frame"):
        residual.simulate(m, dict(TRUE, EA=1e5), net, rec[:, 1], (rec[:, 1] - rec[:, 0]) / deform.DT,
                          rec[:, 1:, list(m.held)].transpose(0, 1).contiguous(), substeps=1)


def test_training_in_float32():
    rec = synthetic(TRUE, batch=3, frames=20, gravity=1.2 * 9.81, seed=10)
    m = cable(rec)
    result = residual.fit_residual(m, TRUE, rec, iterations=3, window=5, batch=2, hidden=8, dtype=torch.float32,
                                   progress=False)
    assert result.net.dtype == torch.float32 and len(result.history) == 3
    assert all(v.dtype == torch.float32 for v in result.state_dict.values())
    pred = residual.predict(m, TRUE, result.net, rec, dtype=torch.float32)
    assert pred.dtype == torch.float32 and bool(torch.isfinite(pred).all())
    # the same network on float64 states: the same prediction to float32's rounding
    assert float((residual.predict(m, TRUE, result.net, rec).float() - pred).abs().max()) < 1e-4


# ============================================================================ checkpoints
def test_save_and_load_round_trip_as_data_only(tmp_path):
    rec = synthetic(TRUE, batch=3, frames=20, gravity=1.2 * 9.81, seed=8)
    m = cable(rec)
    result = residual.fit_residual(m, TRUE, rec, iterations=3, window=5, batch=2, hidden=8, progress=False)
    path = residual.save(result, tmp_path / "residual.pt", meta={"cable": "synthetic"})
    ck = torch.load(path, weights_only=True)
    assert ck["format"] == residual.FORMAT and ck["meta"]["cable"] == "synthetic"
    net = residual.load(path)
    assert net.config == result.net.config and net.dtype == F64
    assert net.meta["values"] == {k: float(TRUE[k]) for k in fit.FIT_NAMES}
    assert torch.equal(residual.predict(m, TRUE, net, rec), residual.predict(m, TRUE, result.net, rec))
    for k, v in result.net.state_dict().items():
        assert torch.equal(net.state_dict()[k], v), k
    # float32 networks round-trip as float32
    residual.save(residual.ResidualNet(net.config), tmp_path / "r32.pt")
    assert residual.load(tmp_path / "r32.pt").dtype == torch.float32


def test_load_refuses_what_is_not_a_residual_checkpoint(tmp_path):
    with pytest.raises(residual.ResidualError, match="not found"):
        residual.load(tmp_path / "missing.pt")
    torch.save({"format": "something else"}, tmp_path / "other.pt")
    with pytest.raises(residual.ResidualError, match="not a residual checkpoint"):
        residual.load(tmp_path / "other.pt")

    marker = tmp_path / "ran"

    class Evil:                  # unpickling it would create ``marker``: a stand-in for any code a file could run
        def __reduce__(self):
            return (open, (str(marker), "w"))
    torch.save({"format": residual.FORMAT, "x": Evil()}, tmp_path / "evil.pt")
    with pytest.raises(residual.ResidualError, match="cannot be read"):
        residual.load(tmp_path / "evil.pt")
    assert not marker.exists()
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(residual.ResidualError, match="junk.pt"):
        residual.load(tmp_path / "junk.pt")


# ============================================================================ refused inputs
@pytest.mark.parametrize("bad, match", [
    ({"iterations": -1}, "iterations must be"), ({"window": 0}, "window must be"),
    ({"window": 30}, "window 30 needs"), ({"batch": 0}, "batch must be"), ({"lr": 0.0}, "lr must be"),
    ({"lr": math.nan}, "lr must be"), ({"hidden": 0}, "hidden must be"), ({"kernel": 2}, "kernel must be odd"),
    ({"max_accel": -1.0}, "max_accel must be"), ({"eval_every": 0}, "eval_every must be"),
    ({"dtype": torch.int64}, "dtype must be"), ({"clip": 0}, "clip must be"),
    ({"validation": torch.zeros(2, 20, N + 1, 3, dtype=F64)}, "validation recordings have 7 markers"),
    ({"values": {"EI": 1.0}}, "values must map"), ({"train": {}}, "empty"),
    ({"train": torch.zeros(2, 20, N + 1, 3, dtype=F64)}, "train_recordings have 7 markers"),
    ({"model": "DLO2"}, "model must be a fit.CableModel"),
])
def test_fit_residual_refuses_bad_input_naming_the_value(bad, match):
    rec = synthetic(TRUE, batch=2, frames=20, seed=9)
    m = cable(rec)
    model, values, train = bad.pop("model", m), bad.pop("values", TRUE), bad.pop("train", rec)
    with pytest.raises(residual.ResidualError, match=match):
        residual.fit_residual(model, values, train, **dict(dict(iterations=1, window=5, batch=1, progress=False),
                                                            **bad))


def test_predict_refuses_bad_input_naming_the_value():
    rec = synthetic(TRUE, batch=2, frames=20, seed=9)
    m = cable(rec)
    other = residual.ResidualNet(residual.ResidualConfig(n=N + 1, held=(0, 1, N - 1, N)))
    with pytest.raises(residual.ResidualError, match="for 7 nodes"):
        residual.predict(m, TRUE, other, rec)
    with pytest.raises(residual.ResidualError, match="net must be a ResidualNet"):
        residual.predict(m, TRUE, "net", rec)
    net = residual.ResidualNet(residual.ResidualConfig(n=N, held=m.held))
    with pytest.raises(residual.ResidualError, match="start must be"):
        residual.predict(m, TRUE, net, rec, start=0)
    with pytest.raises(residual.ResidualError, match="dtype must be"):
        residual.predict(m, TRUE, net, rec, dtype=torch.float16)
    with pytest.raises(residual.ResidualError, match="held must be"):
        residual.ResidualConfig(n=N, held=(0, N)).check()
    with pytest.raises(residual.ResidualError, match=r"shape \(B, 6, 3\)"):
        net(rec[:, 0, :4].float(), rec[:, 0, :4].float())
