"""The task's rules (diffdlo/tasks/task.py), the env's one state object and its one autoreset, and the composed
configs."""
import dataclasses

import numpy as np
import pytest
import torch

import diffdlo
from agents.common import config
from agents import sac
from diffdlo.tasks import task
from diffdlo.envs import BatchedShapeControl, EnvOptions


@pytest.fixture
def small():
    p = diffdlo.load_params("cable")
    return dataclasses.replace(p, n_nodes=6, length=0.15, max_speed=1.0, settle_max_substeps=30,
                               max_drag_steps=200)


def test_node_action_decodes_as_eq_2_6_and_encodes_back(small):
    a = torch.tensor([[0.0, 0.5, 1.0], [0.49, 0.0, 0.25], [1.3, -0.2, 0.75]], dtype=torch.float64)
    node, drag = task.decode_node_action(a, small)
    assert node.tolist() == [0, 2, 5]                                   # round(a0 (N - 1)), a0 clipped to [0, 1]
    s = small.action_scale
    torch.testing.assert_close(drag, torch.tensor([[0.0, s], [-s, -s / 2], [-s, s / 2]], dtype=torch.float64))
    back = task.decode_node_action(task.encode_node_action(node, drag, small.n_nodes, s), small)
    assert torch.equal(back[0], node) and torch.allclose(back[1], drag)


def test_pixel_action_grasps_the_node_nearest_to_the_point(small):
    pos = torch.zeros(1, 6, 2, dtype=torch.float64)
    pos[0, :, 0] = torch.linspace(-0.25, 0.25, 6)
    point = torch.tensor([[0.75, 0.5]], dtype=torch.float64)           # x = 0.25 m, y = 0 in a 1 m view
    assert task.decode_pixel_node(point, pos, 1.0).tolist() == [5]
    assert task.decode_pixel_node(torch.tensor([[0.25, 0.5]]).double(), pos, 1.0).tolist() == [0]


def test_greedy_drags_point_at_the_aligned_target_capped_in_length(small):
    pos = torch.zeros(6, 2, dtype=torch.float64)
    target = torch.zeros(6, 2, dtype=torch.float64)
    target[5] = torch.tensor([0.6, 0.0])                               # node 5 is far from its (aligned) place
    drags, dist = task.greedy_drags(pos, target, max_disp=0.1)
    assert int(dist.argmax()) == 5
    assert float(drags.norm(dim=-1).max()) <= 0.1 + 1e-12
    torch.testing.assert_close(drags[5] / drags[5].norm(), torch.tensor([1.0, 0.0], dtype=torch.float64))


def test_step_outcome_scores_success_exit_and_time_limit():
    rules = EnvOptions(reward="shape_gain", success_tol=0.01, max_steps=3, success_bonus=20.0,
                       step_penalty=0.5, on_exit="fail", exit_penalty=7.0).resolve()
    target = torch.zeros(3, 2, 2)
    target[:, 1, 0] = 0.1
    prev = target + torch.tensor([0.0, 0.05])
    prev[:, 1] -= 0.04                                                 # 2 cm shape error before the move
    new = prev.clone()
    new[0] = target[0]                                                 # rope 0 solved
    new[1] = prev[1] + 5.0                                             # rope 1 left the workspace
    r, term, trunc, success = task.step_outcome(rules, prev, new, target, torch.tensor([1, 1, 3]))
    assert success.tolist() == [True, False, False]
    assert term.tolist() == [True, True, False] and trunc.tolist() == [False, False, True]
    assert r[0] == 20.0 and r[1] == -7.0 and r[2] == pytest.approx(-0.5)   # no progress: the step penalty


def test_a_rope_on_the_route_but_round_a_peg_on_the_wrong_side_neither_ends_the_episode_nor_succeeds():
    """The route success rule, once: a rope of the route's shape (mean node error 2 mm, within the 1 cm) passing a
    peg on the other side from the route is not terminated, gets no bonus and is not info["is_success"]; the same
    rope with the peg on the route's side is all three. Both paths (step_outcome, task_metrics) read task_success."""
    p = diffdlo.load_params("cable")
    rules = EnvOptions(target="route", reward="route_gain", success_tol=0.01, success_bonus=20.0).resolve()
    x = (torch.arange(p.n_nodes, dtype=torch.float64) - (p.n_nodes - 1) / 2) * p.rest_length
    route = torch.stack([x, torch.zeros_like(x)], -1)                 # straight, along y = 0
    radius = 0.005
    below = torch.tensor([[0.0, -(radius + p.rope_radius + 0.001), radius]], dtype=torch.float64)
    above = below * torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)
    over = route.clone()
    over[[9, 10], 1] = 0.022                                          # nodes 9-10 lifted over a peg at y = +11 mm
    assert float((over - route).norm(dim=-1).mean()) < 0.01
    rope = over[None].repeat(2, 1, 1)
    pegs = torch.stack([above, below])                                # rope 0: the peg between rope and route
    prev = rope + 0.05
    r, term, trunc, success = task.step_outcome(rules, prev, rope, route[None].expand(2, -1, -1),
                                                torch.tensor([1, 1]), pegs)
    metrics = task.task_metrics(rope, route[None].expand(2, -1, -1), 0.01, None, pegs)
    assert metrics["sides_kept"].tolist() == [False, True]
    assert success.tolist() == [False, True] and term.tolist() == [False, True]
    assert float(r[0]) != rules.success_bonus and float(r[1]) == rules.success_bonus
    assert metrics["is_success"].tolist() == [False, True]


def test_draw_target_names_what_it_drew(small):
    named = {n: diffdlo.target_shape(n, small) for n in diffdlo.TARGET_NAMES}
    rng = np.random.default_rng(3)
    names = [task.draw_target("random", rng, small, named)[1] for _ in range(20)]
    assert set(names) <= set(diffdlo.TARGET_NAMES) and len(set(names)) > 1
    assert task.draw_target(named["vertical"], rng, small, named)[1] == "vertical"
    curve, name = task.draw_target("random_curve", rng, small, named)
    assert name == "random_curve" and curve.shape == (6, 2)
    with pytest.raises(diffdlo.TargetError, match="allowed"):
        task.resolve_target("spiral", small)


def test_get_state_is_a_copy_and_set_state_restores_the_episode_exactly(small):
    env = BatchedShapeControl(3, target="random", params=small)
    env.reset(seed=5)
    state = env.get_state()
    state.pos += 1.0                                                   # a copy: the env does not change
    assert not torch.equal(state.pos, env.get_state().pos)
    saved = env.get_state()
    a = torch.rand(3, 3, generator=torch.Generator().manual_seed(0))
    first = [env.step(a, autoreset="same_step") for _ in range(3)]
    env.set_state(saved)
    again = [env.step(a, autoreset="same_step") for _ in range(3)]
    for (o1, r1, *_), (o2, r2, *_) in zip(first, again):
        assert torch.equal(r1, r2) and torch.equal(o1["node_poses"], o2["node_poses"])
    reader = env.get_state(generators=False)                           # cheap: no generators to copy
    assert reader.rngs is None and torch.equal(reader.pos, env.get_state().pos)
    with pytest.raises(ValueError, match="generators=False"):
        env.set_state(reader)
    fresh = BatchedShapeControl(3, target="random", params=small)
    fresh.reset(seed=5)
    assert saved.target_names == fresh.get_state().target_names
    assert set(saved.target_names) <= set(diffdlo.TARGET_NAMES)


def test_same_step_autoreset_returns_the_steps_info_and_final_obs(small):
    env = BatchedShapeControl(2, target="horizontal", params=small, max_steps=1)
    env.reset(seed=0)
    before = env.get_state()
    obs, _, term, trunc, info = env.step(torch.full((2, 3), 0.5), autoreset="same_step")
    assert bool((term | trunc).all())                                  # max_steps 1: both episodes end
    plain = BatchedShapeControl(2, target="horizontal", params=small, max_steps=1)
    plain.reset(seed=0)
    moved = plain.step(torch.full((2, 3), 0.5))[0]                    # no autoreset: the step's own observation
    assert torch.equal(info["final_obs"]["node_poses"], moved["node_poses"])
    assert int(info["node"][0]) >= 0                                   # the move's info, not the reset's (-1)
    assert torch.equal(env.get_state().steps, torch.zeros(2, dtype=torch.int64))   # reset in the same call
    assert not torch.equal(obs["node_poses"], info["final_obs"]["node_poses"])
    assert not torch.equal(before.pos, env.get_state().pos)


def test_composed_config_takes_flat_names_and_names_unknown_ones():
    cfg = config.from_flat(sac.SACConfig, {"target": "diagonal", "seed": 3, "features": "relative", "lr": 1e-3})
    assert (cfg.task.target, cfg.run.seed, cfg.inputs.features, cfg.lr) == ("diagonal", 3, "relative", 1e-3)
    assert config.replace(cfg, seed=4).run.seed == 4 and cfg.run.seed == 3
    old_flat = {k: v for part in ("task", "run", "inputs") for k, v in dataclasses.asdict(getattr(cfg, part)).items()}
    assert config.from_flat(sac.SACConfig, {**old_flat, "lr": 1e-3}) == cfg      # a flat (older) checkpoint config
    with pytest.raises(ValueError, match=r"unknown config keys \['lrr'\]"):
        config.from_flat(sac.SACConfig, {"lrr": 1.0})
