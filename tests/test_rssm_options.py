"""agents.models.rssm's diagnosis options (issue 47): the centroid frame, the residual decoder and DreamerV3's KL.
Each builds, gives a finite loss, and does what it claims; the defaults are PlaNet's model."""
from __future__ import annotations

import copy

import pytest
import torch

from agents import planet
from agents.common.envs import make_env
from agents.models import openloop
from agents.models.rssm import RSSM, free_nats_kl

from test_planet import collect, tiny_cfg   # the tiny rope and RSSM of the PlaNet tests, random moves

pytestmark = pytest.mark.usefixtures("one_thread")


def setup(rows=12, seed=0, **kw):
    """A tiny config, a model built from it, random-move chunks and the last observation."""
    cfg = tiny_cfg(**kw)
    rb, obs = collect(cfg, rows, seed)
    env = make_env(cfg.task, cfg.run, cfg.task.cable_params(), cfg.run.num_envs)   # its core: the action layout
    torch.manual_seed(seed)
    model = planet.build_model(cfg, obs, env.core.action_dim, cfg.task.cable_params())
    return cfg, model, rb, obs, env


def loss_on(model, rb, seed=0):
    s = rb.sample_sequences(5, 4, torch.Generator().manual_seed(seed))
    return model.loss(s["obs"], s["action"], s["reward"], s["mask"])


def test_defaults_are_planets_model():
    cfg, m, *_ = setup()
    assert (cfg.rssm_frame, cfg.rssm_residual, cfg.kl_balance) == ("world", False, "planet")
    assert not m.carries and m.centroid_net is None
    assert "x" not in m.initial(2) and "c" not in m.initial(2)


@pytest.mark.parametrize("opts", [dict(rssm_frame="centroid"), dict(rssm_residual=True),
                                  dict(kl_balance="dreamerv3", free_nats=1.0),
                                  dict(rssm_frame="centroid", rssm_residual=True),
                                  dict(rssm_residual=True, obs="distance", action="pixel")])
def test_option_builds_trains_and_evaluates(opts):
    cfg, m, rb, obs, env = setup(**opts)
    L = loss_on(m, rb)
    assert all(torch.isfinite(L[k]) for k in ("loss", "recon", "kl", "kl_loss", "reward_loss"))
    L["loss"].backward()
    assert all(torch.isfinite(p.grad).all() for p in m.parameters() if p.grad is not None)
    m.eval()
    ol = openloop.open_loop_eval(m, cfg, n_episodes=3, context=1, horizons=(1, 2))
    assert all(torch.isfinite(torch.tensor(ol[f"pred_err_{k}"])) for k in (1, 2))
    plan_cfg = tiny_cfg(**opts, candidates=8, elites=2, iterations=1, horizon=2,
                        plan_objective="shape" if cfg.task.obs == "points" else "reward")
    action = planet.make_planner(m, plan_cfg, env.core, 0)(obs)
    assert action.shape == (cfg.run.num_envs, env.core.action_dim) and torch.isfinite(action).all()


def translated(obs, d):
    return {k: v + d for k, v in obs.items()}


def test_centroid_frame_is_translation_invariant():
    cfg, m, _, obs, _ = setup(rssm_frame="centroid")
    d = torch.tensor([0.37, -0.21])
    assert torch.allclose(m.embed(translated(obs, d)), m.embed(obs), atol=1e-5)
    acts = torch.rand(cfg.run.num_envs, 3, 3, generator=torch.Generator().manual_seed(1))
    preds = []
    for o in (obs, translated(obs, d)):
        st, _ = m.obs_step(None, None, m.embed(o), sample=False, obs=o)
        preds.append(m.decode_traj(m.imagine(st, acts))["node_poses"] / m.scale)
    assert torch.allclose(preds[1] - preds[0], d.expand_as(preds[0]), atol=1e-5)   # same shape, moved by d
    assert not torch.allclose(preds[1], preds[0], atol=1e-3)
    # the world frame is not invariant: the check above can fail
    _, w, *_ = setup()
    assert not torch.allclose(w.embed(translated(obs, d)), w.embed(obs), atol=1e-3)


def zero_decoder(model):
    last = [mod for mod in model.float_dec.modules() if isinstance(mod, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()


@pytest.mark.parametrize("residual", [True, False])
def test_residual_decoder_with_zero_output_predicts_the_previous_rope(residual):
    cfg, m, rb, obs, _ = setup(rssm_residual=residual)
    zero_decoder(m)
    st, _ = m.obs_step(None, None, m.embed(obs), sample=False, obs=obs)
    acts = torch.rand(cfg.run.num_envs, 3, 3, generator=torch.Generator().manual_seed(1))
    pred = m.decode_traj(m.imagine(st, acts))
    target = m.obs_target(obs)
    for k in m.float_keys:                      # every open-loop step: the last observed rope ("nothing moves")
        same = torch.allclose(pred[k], target[k][:, None].expand_as(pred[k]), atol=1e-6)
        assert same == residual
    # in training the zero decoder predicts o_{t-1} (o_0 at t = 0): recon is exactly the "nothing moves" one
    s = rb.sample_sequences(5, 4, torch.Generator().manual_seed(0))
    recon = m.loss(s["obs"], s["action"], s["reward"], s["mask"])["recon"]
    o = m.obs_target(s["obs"])
    base = 0
    for k in m.float_keys:
        prev = torch.cat([o[k][:, :1], o[k][:, :-1]], 1)
        base = base + 0.5 * ((prev - o[k]) / m.obs_std).square().sum((2, 3))
    mask = s["mask"].float()
    expected = (base * mask).sum() / mask.sum()
    assert torch.isclose(recon, expected, rtol=1e-5) == residual


def test_dreamerv3_kl_weights_the_prior_by_half():
    cfg, m, rb, *_ = setup(free_nats=0.0)
    d = copy.deepcopy(m)
    d.kl_balance = "dreamerv3"
    grads, values = [], []
    for model in (m, d):
        torch.manual_seed(3)                    # the same posterior samples in both
        L = loss_on(model, rb)
        model.zero_grad()
        L["kl_loss"].backward()
        grads.append(torch.cat([p.grad.flatten() for p in model.prior_net.parameters()]))
        values.append((L["kl_loss"].detach(), L["kl"].detach()))
    (planet_kl, kl), (dreamer_kl, kl2) = values
    assert torch.isclose(kl, kl2) and torch.isclose(planet_kl, kl)          # free_nats 0: kl_loss is the KL
    assert torch.isclose(dreamer_kl, 0.6 * kl, rtol=1e-5)                    # 0.5 dynamics + 0.1 representation
    assert grads[0].abs().max() > 0
    assert torch.allclose(grads[1], 0.5 * grads[0], rtol=1e-4, atol=1e-7)    # the prior learns from the dynamics term


def test_dreamerv3_free_bits_clamp_each_term():
    kl = torch.tensor([[0.5, 2.0]])
    assert torch.isclose(free_nats_kl(kl, 1.0), torch.tensor(1.5))


@pytest.mark.parametrize("opts,msg", [(dict(rssm_frame="centroid", obs="distance", action="pixel"), "centroid"),
                                      (dict(rssm_residual=True, obs="image"), "rssm_residual")])
def test_options_refused_where_they_cannot_work(opts, msg):
    with pytest.raises(ValueError, match=msg):
        tiny_cfg(**opts).check()


def test_carrying_model_needs_the_observation():
    _, m, _, obs, _ = setup(rssm_residual=True)
    with pytest.raises(ValueError, match="pass obs"):
        m.obs_step(None, None, m.embed(obs))
    assert isinstance(m, RSSM)
