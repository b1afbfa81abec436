"""The tuned learners' pieces on hand-computed cases: the hybrid (node, drag) action, the running normalizer, and the
update rules of SAC and PPO (target-network averaging, temperature step, the expectation over nodes, clipping)."""
import math

import numpy as np
import pytest
import torch

import diffdlo
from agents.common import config
from agents.models import hybrid
from agents import ppo, sac
from agents.common.config import load_config, preset_path
from diffdlo.envs import BatchedShapeControl


# ---------------------------------------------------------------------- hybrid action <-> env action
def test_every_node_and_drag_maps_to_a_valid_env_action_and_back():
    p = diffdlo.load_params()
    env = BatchedShapeControl(1, params=p)
    n = p.n_nodes
    grid = torch.linspace(-1.0, 1.0, 5, dtype=torch.float64)
    drags = torch.cartesian_prod(grid, grid)                                  # (25, 2)
    node = torch.arange(n).repeat_interleave(len(drags))
    drag = drags.repeat(n, 1)
    a = hybrid.to_env_action(node, drag, n)
    assert a.shape == (n * 25, 3) and bool(((a >= 0) & (a <= 1)).all())
    env_node, delta = env.decode(a)                                           # what the env does with it
    assert torch.equal(env_node, node)
    torch.testing.assert_close(delta, drag * p.action_scale)                  # d = +-1 is +-action_scale metres
    back_node, back_drag = hybrid.from_env_action(a, n)
    assert torch.equal(back_node, node)
    torch.testing.assert_close(back_drag, drag)
    stored = hybrid.join(node, drag)                                          # the replay buffer's row (k, dx, dy)
    k, d = hybrid.split(stored.float())
    assert torch.equal(k, node) and torch.allclose(d.double(), drag, atol=1e-6)


def test_drags_beyond_the_range_are_clipped_and_bad_nodes_named():
    a = hybrid.to_env_action(torch.tensor([0, 19]), torch.tensor([[3.0, -7.0], [0.5, 0.0]]), 20)
    torch.testing.assert_close(a, torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.75, 0.5]]))
    with pytest.raises(ValueError, match=r"\[0, 19\], got \[3, 20\]"):
        hybrid.to_env_action(torch.tensor([3, 20]), torch.zeros(2, 2), 20)


def test_relative_features_ignore_where_the_target_is_and_see_the_difference():
    g = torch.Generator().manual_seed(0)
    rope, target = torch.randn(4, 6, 2, generator=g), torch.randn(4, 6, 2, generator=g)
    f = hybrid.relative_features({"node_poses": rope, "target_poses": target}, 0.5)
    assert f.shape == (4, 4 * 6 + 2)
    moved = hybrid.relative_features({"node_poses": rope, "target_poses": target + 3.0}, 0.5)
    torch.testing.assert_close(f, moved)                                      # target translation: no change
    diff = (rope - rope.mean(1, keepdim=True)) - (target - target.mean(1, keepdim=True))
    torch.testing.assert_close(f[:, :12], diff.flatten(1) / 0.5)
    torch.testing.assert_close(f[:, -2:], rope.mean(1) / 0.5)                 # the centroid: workspace edge


def test_running_norm_matches_the_statistics_of_all_batches_and_survives_state_dict():
    g = torch.Generator().manual_seed(1)
    batches = [torch.randn(n, 3, generator=g) * torch.tensor([1.0, 5.0, 0.1]) + 2.0 for n in (7, 50, 1)]
    norm = hybrid.RunningNorm(3)
    for b in batches:
        norm.update(b)
    x = torch.cat(batches).double().numpy()
    np.testing.assert_allclose(norm.mean.numpy(), x.mean(0), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(norm.var.numpy(), x.var(0), rtol=5e-3)     # the prior (count 1e-4, var 1) is all
    copy = hybrid.RunningNorm(3)
    copy.load_state_dict(norm.state_dict())
    torch.testing.assert_close(copy(batches[0]), norm(batches[0]))
    z = norm(torch.cat(batches))
    assert abs(float(z.mean())) < 1e-3 and abs(float(z.std()) - 1) < 0.05


# ---------------------------------------------------------------------- SAC update rules
def test_polyak_update_moves_the_target_a_tau_step_towards_the_online_network():
    online, target = torch.nn.Linear(1, 1), torch.nn.Linear(1, 1)
    with torch.no_grad():
        for p in online.parameters():
            p.fill_(1.0)
        for p in target.parameters():
            p.fill_(0.0)
    sac.polyak_update(online, target, tau=0.1)
    assert all(torch.allclose(p, torch.tensor(0.1)) for p in target.parameters())      # not 0.9: not swapped
    sac.polyak_update(online, target, tau=0.1)
    assert all(torch.allclose(p, torch.tensor(0.19)) for p in target.parameters())


def test_temperature_step_lowers_alpha_while_entropy_is_above_target():
    log_alpha = torch.tensor(0.0, requires_grad=True)
    loss = sac.temperature_loss(log_alpha, torch.tensor([2.0, 4.0]), target_entropy=1.0)
    loss.backward()
    assert float(log_alpha.grad) == pytest.approx(2.0)                        # mean entropy 3 - target 1
    opt = torch.optim.SGD([log_alpha], lr=0.5)
    opt.step()
    assert float(log_alpha.detach()) == pytest.approx(-1.0)
    log_alpha.grad = None
    sac.temperature_loss(log_alpha, torch.tensor([0.0]), target_entropy=1.0).backward()
    assert float(log_alpha.grad) == pytest.approx(-1.0)                        # below target: alpha rises


def test_hybrid_soft_value_is_the_exact_expectation_over_nodes():
    log_pk = torch.log(torch.tensor([[0.25, 0.75]]))
    q, log_pd = torch.tensor([[1.0, 3.0]]), torch.tensor([[0.0, -1.0]])
    v = sac.hybrid_soft_value(log_pk, q, log_pd, alpha_node=torch.tensor(0.2), alpha_drag=torch.tensor(0.5))
    expected = 0.25 * (1.0 - 0.0 - 0.2 * math.log(0.25)) + 0.75 * (3.0 + 0.5 - 0.2 * math.log(0.75))
    assert float(v) == pytest.approx(expected)


def test_hybrid_critic_taken_equals_all_nodes_at_the_taken_node():
    cfg = load_config(sac.SACConfig, "sac", dict(hidden=[16], head_hidden=8))
    obs = {"node_poses": torch.randn(5, 6, 2), "target_poses": torch.randn(5, 6, 2)}
    critic = sac.HybridCritic(obs, cfg, 0.15, 6)
    with torch.no_grad():
        critic.node_embed.normal_()
    z = critic.state(critic.feat(obs))
    node, drag = torch.tensor([0, 5, 2, 2, 3]), torch.rand(5, 2) * 2 - 1
    drags = torch.rand(5, 6, 2) * 2 - 1
    drags[torch.arange(5), node] = drag
    q_all = critic.all_nodes(z, drags)
    assert q_all.shape == (2, 5, 6)
    torch.testing.assert_close(critic.taken(z, node, drag), q_all[:, torch.arange(5), node])
    assert not torch.allclose(q_all[0], q_all[1])                             # two independent critics


def test_hybrid_actor_log_prob_of_the_squashed_drag():
    mean, log_std = torch.tensor([[0.3, -0.2]]), torch.tensor([[-1.0, 0.5]])
    u = torch.tensor([[0.1, 0.4]])
    normal = torch.distributions.Normal(mean, log_std.exp())
    expected = (normal.log_prob(u) - torch.log(1 - torch.tanh(u) ** 2 + 1e-6)).sum(-1)
    torch.testing.assert_close(sac.squashed_log_prob(u, mean, log_std), expected)


# ---------------------------------------------------------------------- PPO
def test_clipped_surrogate_on_hand_computed_ratios():
    new = torch.log(torch.tensor([1.5, 0.5, 1.1, 0.5]))
    adv = torch.tensor([1.0, -1.0, 1.0, 1.0])
    loss, ratio = ppo.clipped_surrogate(new, torch.zeros(4), adv, clip_range=0.2)
    torch.testing.assert_close(ratio, torch.tensor([1.5, 0.5, 1.1, 0.5]))
    # per sample min(r A, clip(r) A): 1.2 (clipped), -0.8 (clipped), 1.1, 0.5 (unclipped: pessimistic side)
    assert float(loss) == pytest.approx(-(1.2 - 0.8 + 1.1 + 0.5) / 4)


def test_ppo_hybrid_distribution_log_prob_entropy_and_mode():
    logits = torch.tensor([[0.0, math.log(3.0)]])                            # p = (0.25, 0.75)
    mean = torch.tensor([[[0.1, 0.2], [-0.3, 0.4]]])
    std = torch.tensor([0.5, 2.0])
    d = ppo.HybridDist(logits, mean, std)
    a = torch.tensor([[1.0, 0.0, 1.0]])
    expected = math.log(0.75) + torch.distributions.Normal(mean[0, 1], std).log_prob(torch.tensor([0.0, 1.0])).sum()
    assert float(d.log_prob(a)) == pytest.approx(float(expected), rel=1e-6)
    h_cat = -(0.25 * math.log(0.25) + 0.75 * math.log(0.75))
    h_drag = float(torch.distributions.Normal(0.0, std).entropy().sum())
    assert float(d.entropy()) == pytest.approx(h_cat + h_drag, rel=1e-6)
    torch.testing.assert_close(d.mode(), torch.tensor([[1.0, -0.3, 0.4]]))
    s = d.sample()
    assert s[0, 0] in (0.0, 1.0)


# ---------------------------------------------------------------------- presets
@pytest.mark.parametrize("algo,cls", [("ppo", ppo.PPOConfig), ("sac", sac.SACConfig)])
def test_presets_tuned_is_the_default_and_sb3_default_keeps_the_old_settings(algo, cls):
    tuned = load_config(cls, preset_path(algo, None))
    assert (tuned.policy, tuned.inputs.features, tuned.task.on_exit, tuned.task.reward) == (
        "hybrid", "relative", "fail", "shape_gain")
    old = load_config(cls, preset_path(algo, "sb3-default"))
    assert (old.policy, old.inputs.features, old.task.on_exit, old.task.reward) == (
        "gaussian", "raw", "truncate", "position_orientation")
    assert old.run.num_envs == 16 and old.gamma == 0.99 and old.task.success_bonus is None
    with pytest.raises(ValueError, match="unknown preset 'fast'.*sb3-default"):
        preset_path(algo, "fast")


@pytest.mark.parametrize("bad,message", [(dict(policy="mixed"), "unknown policy 'mixed'"),
                                         (dict(action="pixel"), "policy 'hybrid' chooses a node"),
                                         (dict(obs="image", features="relative"), "features 'relative' need obs"),
                                         (dict(on_exit="bounce"), "unknown on_exit 'bounce'"),
                                         (dict(features="raw"), "normalize_obs needs features 'relative'")])
def test_bad_tuned_config_values_are_named(bad, message):
    with pytest.raises(ValueError, match=message):
        load_config(ppo.PPOConfig, "ppo", bad)


def test_tiny_config_dataclass_roundtrip():
    cfg = load_config(sac.SACConfig, "sac")
    assert config.from_flat(sac.SACConfig, config.to_dict(cfg)) == cfg
