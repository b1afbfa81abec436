"""Task options: random_curve targets, the shape_gain reward, success_bonus / step_penalty, on_exit="fail"."""
import dataclasses
import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import diffdlo
from diffdlo.envs import ENV_ID, BatchedShapeControl
from diffdlo.planar.shapes import CURVE_MAX_TURN_DEG, check_target, random_curve, straight_shape

ZERO_DRAG = [0.0, 0.5, 0.5]          # node 0, dx = dy = 0
EPS_DEG = 1e-7


def turns_deg(pos: torch.Tensor) -> torch.Tensor:
    """(B, N, 2) -> (B, N-2) turning angle at each interior node [deg], wrapped to (-180, 180]."""
    d = pos[:, 1:] - pos[:, :-1]
    a = torch.atan2(d[..., 1], d[..., 0])
    return torch.rad2deg(torch.remainder(a[:, 1:] - a[:, :-1] + math.pi, 2 * math.pi) - math.pi)


def np_shape_error(a, b):
    """Independent numpy shape error: mean node distance after aligning centroids [m]."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.linalg.norm((a - a.mean(0)) - (b - b.mean(0)), axis=-1).mean())


def straight(p, angle_deg=0.0, shift=(0.0, 0.0)):
    return (straight_shape(angle_deg, p) + torch.tensor(shift, dtype=torch.float64)).to(torch.float32)


# ----------------------------------------------------------------------------------------------- random_curve
@pytest.mark.parametrize("n_nodes", [6, 20])
def test_random_curve_geometry(params, n_nodes):
    p = dataclasses.replace(params, n_nodes=n_nodes)
    c = random_curve(300, p, torch.Generator().manual_seed(0), dtype=torch.float64)
    assert c.shape == (300, n_nodes, 2) and c.dtype == torch.float64
    links = (c[:, 1:] - c[:, :-1]).norm(dim=-1)
    assert (links - p.rest_length).abs().max() < 1e-9
    assert c.mean(dim=1).abs().max() < 1e-12
    t = turns_deg(c)
    assert t.abs().max() <= CURVE_MAX_TURN_DEG + EPS_DEG
    assert t.abs().max() > 0.9 * CURVE_MAX_TURN_DEG           # the bound is reached: curves are really curved
    assert t.sum(1).std() > 5.0                               # total turning varies from curve to curve
    first = torch.rad2deg(torch.atan2(c[:, 1, 1] - c[:, 0, 1], c[:, 1, 0] - c[:, 0, 0]))
    assert first.min() < -150 and first.max() > 150          # the first link points anywhere
    for curve in c:
        check_target(curve, p, "curve")


def test_random_curve_seeding(params):
    a = random_curve(4, params, torch.Generator().manual_seed(7), dtype=torch.float64)
    b = random_curve(4, params, torch.Generator().manual_seed(7), dtype=torch.float64)
    other = random_curve(4, params, torch.Generator().manual_seed(8), dtype=torch.float64)
    assert torch.equal(a, b)
    assert (a - other).abs().amax(dim=(1, 2)).min() > 1e-3    # every curve differs
    assert (a[1:] - a[:1]).abs().amax(dim=(1, 2)).min() > 1e-3  # and the curves of one batch differ
    f32 = random_curve(4, params, torch.Generator().manual_seed(7))
    assert f32.dtype == torch.float32 and torch.allclose(f32.double(), a, atol=1e-6)
    with pytest.raises(ValueError, match="batch"):
        random_curve(0, params)


# ------------------------------------------------------------------------------------- env target="random_curve"
def _targets(env):
    return env.get_state().target.detach().clone()


def test_env_random_curve_targets_follow_the_seed(small):
    env = BatchedShapeControl(3, target="random_curve", params=small, dtype=torch.float64)
    env.reset(seed=5)
    t5 = _targets(env)
    env.reset()                                               # a new curve at each reset
    t_next = _targets(env)
    assert (t_next - t5).abs().amax(dim=(1, 2)).min() > 1e-3
    env.reset(seed=5)
    assert torch.equal(_targets(env), t5)                     # same seed, same targets
    env.reset(seed=6)
    assert (_targets(env) - t5).abs().amax(dim=(1, 2)).min() > 1e-3
    assert (t5[1:] - t5[:1]).abs().amax(dim=(1, 2)).min() > 1e-3   # the sub-envs differ
    for i in range(3):                                        # sub-env i of seed 5 == a single env of seed 5 + i
        single = BatchedShapeControl(1, target="random_curve", params=small, dtype=torch.float64)
        single.reset(seed=5 + i)
        assert torch.equal(single.get_state().target[0], t5[i])
        gym_env = gym.make(ENV_ID, params=small, target="random_curve", dtype=torch.float64)
        obs, _ = gym_env.reset(seed=5 + i)
        np.testing.assert_array_equal(obs["target_poses"], t5[i].float().numpy())
    for t in t5:
        check_target(t, small, "env target")
        assert turns_deg(t[None]).abs().max() <= CURVE_MAX_TURN_DEG + EPS_DEG
        assert abs(float(t.mean(0).abs().max())) < 1e-12


def test_env_random_curve_start_shapes_match_single_envs(small):
    env = BatchedShapeControl(2, target="random_curve", params=small, dtype=torch.float64)
    env.reset(seed=11)
    for i in range(2):
        single = BatchedShapeControl(1, target="random_curve", params=small, dtype=torch.float64)
        single.reset(seed=11 + i)
        torch.testing.assert_close(single.get_state().pos[0], env.get_state().pos[i], rtol=0, atol=1e-12)


# -------------------------------------------------------------------------- shape_gain, step_penalty, success_bonus
def _placed(small, **kw):
    env = BatchedShapeControl(1, target="horizontal", params=small, dtype=torch.float64, **kw)
    env.reset(seed=0)
    env.set_state(pos=straight(small, 0.0).double()[None], target=straight(small, 90.0).double(), steps=0)
    return env


ACTION = [[0.4, 0.9, 0.2]]            # node 2 of 6, drag (+0.08, -0.06) m


def test_shape_gain_reward_of_a_real_move(small):
    env = _placed(small, reward="shape_gain")
    prev, target = env.get_state().pos[0].clone(), env.get_state().target[0].clone()
    _, r, term, trunc, info = env.step(torch.tensor(ACTION, dtype=torch.float64))
    new = env.get_state().pos[0]
    assert (new - prev).abs().max() > 0.01                    # the rope really moved
    expect = 100.0 * (np_shape_error(prev, target) - np_shape_error(new, target))
    assert abs(expect) > 0.1                                  # and the error changed by a visible amount
    assert float(r[0]) == pytest.approx(expect, abs=1e-9)
    assert not bool(term[0]) and not bool(trunc[0]) and not bool(info["is_success"][0])
    # the same move under the step penalty pays exactly the penalty less
    pen = _placed(small, reward="shape_gain", step_penalty=0.25)
    _, r_pen, *_ = pen.step(torch.tensor(ACTION, dtype=torch.float64))
    assert torch.equal(pen.get_state().pos, env.get_state().pos)
    assert float(r_pen[0]) == pytest.approx(expect - 0.25, abs=1e-9)


def test_step_penalty_with_the_default_reward(small):
    base = _placed(small)
    pen = _placed(small, step_penalty=1.5)
    _, r0, *_ = base.step(torch.tensor(ACTION, dtype=torch.float64))
    _, r1, *_ = pen.step(torch.tensor(ACTION, dtype=torch.float64))
    assert float(r1[0]) == pytest.approx(float(r0[0]) - 1.5, abs=1e-9)


@pytest.mark.parametrize("reward", ["shape_gain", "position_orientation"])
def test_success_bonus_replaces_the_reward_and_skips_the_penalty(small, reward):
    env = BatchedShapeControl(1, target="horizontal", params=small, dtype=torch.float64, reward=reward,
                              success_bonus=7.5, step_penalty=0.5)
    env.reset(seed=0)
    rope = straight(small, 0.0, shift=(0.1, -0.2)).double()
    noise = 0.003 * torch.randn(small.n_nodes, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    target = straight(small, 0.0).double() + noise            # 1-3 mm away in shape: any tiny move succeeds
    env.set_state(pos=rope[None], target=target, steps=0)
    assert 0 < float(env.info()["shape_error"][0]) < small.success_tol
    _, r, term, trunc, info = env.step(torch.tensor([ZERO_DRAG], dtype=torch.float64))
    assert bool(term[0]) and not bool(trunc[0]) and bool(info["is_success"][0])
    assert float(r[0]) == 7.5
    default = BatchedShapeControl(1, target="horizontal", params=small, dtype=torch.float64, reward=reward)
    default.reset(seed=0)
    default.set_state(pos=rope[None], target=target, steps=0)
    assert float(default.step(torch.tensor([ZERO_DRAG], dtype=torch.float64))[1][0]) == small.success_bonus == 20.0


# ------------------------------------------------------------------------------------------------------ on_exit
DRAG_OUT = [[1.0, 1.0, 0.5]]          # last node, +0.1 m in x


def _near_edge(small, **kw):
    env = BatchedShapeControl(1, target="horizontal", params=small, dtype=torch.float64, reward="shape_gain", **kw)
    env.reset(seed=0)
    assert small.workspace == (2.0, 2.0)
    rope = straight(small, 0.0, shift=(0.9, 0.0)).double()   # last node at x = 0.975 (edge at 1.0)
    env.set_state(pos=rope[None], target=straight(small, 90.0).double(), steps=0)
    return env


def test_on_exit_fail_terminates_with_the_exit_penalty(small):
    env = _near_edge(small, on_exit="fail", exit_penalty=3.0, step_penalty=0.5)
    _, r, term, trunc, info = env.step(torch.tensor(DRAG_OUT, dtype=torch.float64))
    assert float(env.get_state().pos[0, :, 0].max()) > 1.0                # it left the workspace
    assert bool(term[0]) and not bool(trunc[0])
    assert float(r[0]) == -3.0
    assert not bool(info["is_success"][0])


def test_on_exit_truncate_is_the_default_and_keeps_the_reward(small):
    env = _near_edge(small)
    assert env.options.on_exit == "truncate"
    prev, target = env.get_state().pos[0].clone(), env.get_state().target[0].clone()
    _, r, term, trunc, info = env.step(torch.tensor(DRAG_OUT, dtype=torch.float64))
    assert float(env.get_state().pos[0, :, 0].max()) > 1.0
    assert bool(trunc[0]) and not bool(term[0]) and not bool(info["is_success"][0])
    expect = 100.0 * (np_shape_error(prev, target) - np_shape_error(env.get_state().pos[0], target))
    assert float(r[0]) == pytest.approx(expect, abs=1e-9)
    penalised = _near_edge(small, exit_penalty=3.0)           # exit_penalty only applies under on_exit="fail"
    _, r2, *_ = penalised.step(torch.tensor(DRAG_OUT, dtype=torch.float64))
    assert float(r2[0]) == pytest.approx(expect, abs=1e-9)


@pytest.mark.parametrize("on_exit", ["fail", "truncate"])
def test_success_takes_precedence_over_exit(small, on_exit):
    env = BatchedShapeControl(1, target="horizontal", params=small, dtype=torch.float64, on_exit=on_exit,
                              exit_penalty=3.0)
    env.reset(seed=0)
    rope = straight(small, 0.0, shift=(0.95, 0.0)).double()  # last node at x = 1.025: outside, and on target
    env.set_state(pos=rope[None], target=straight(small, 0.0).double(), steps=0)
    _, r, term, trunc, info = env.step(torch.tensor([ZERO_DRAG], dtype=torch.float64))
    assert float(env.get_state().pos[0, :, 0].max()) > 1.0
    assert bool(info["is_success"][0]) and bool(term[0]) and not bool(trunc[0])
    assert float(r[0]) == small.success_bonus


def test_on_exit_fail_in_a_batch_only_ends_the_env_that_left(small):
    env = BatchedShapeControl(2, target="horizontal", params=small, dtype=torch.float64, on_exit="fail",
                              exit_penalty=2.0, reward="shape_gain")
    env.reset(seed=0)
    ropes = torch.stack([straight(small, 0.0, shift=(0.9, 0.0)), straight(small, 0.0)]).double()
    env.set_state(pos=ropes, target=straight(small, 90.0).double(), steps=0)
    _, r, term, trunc, info = env.step(torch.tensor(DRAG_OUT * 2, dtype=torch.float64))
    assert term.tolist() == [True, False] and trunc.tolist() == [False, False]
    assert float(r[0]) == -2.0 and float(r[1]) != -2.0
    assert info["is_success"].tolist() == [False, False]


# ------------------------------------------------------------------------------------------------- bad values
@pytest.mark.parametrize("kw,match", [({"on_exit": "explode"}, "on_exit 'explode'"),
                                      ({"on_exit": None}, "on_exit None"),
                                      ({"success_bonus": float("nan")}, "success_bonus.*nan"),
                                      ({"success_bonus": float("inf")}, "success_bonus.*inf"),
                                      ({"exit_penalty": "x"}, "exit_penalty.*'x'"),
                                      ({"step_penalty": True}, "step_penalty.*True"),
                                      ({"target": "random_curves"}, "random_curves")])
def test_bad_task_options_raise(small, kw, match):
    with pytest.raises(ValueError, match=match):
        BatchedShapeControl(1, params=small, **kw)


def test_gymnasium_make_and_check_env(small):
    env = gym.make(ENV_ID, params=small, target="random_curve", on_exit="fail", reward="shape_gain",
                   step_penalty=0.1, exit_penalty=1.0)
    core = env.unwrapped.core
    assert (core.get_state().target_spec, core.options.on_exit, core.reward_type) == ("random_curve", "fail",
                                                                                      "shape_gain")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
    obs, _ = env.reset(seed=3)
    assert env.observation_space.contains(obs)
    assert turns_deg(torch.as_tensor(obs["target_poses"], dtype=torch.float64)[None]).abs().max() > 1.0


# ------------------------------------------------------------------------------------- held-out target files
def test_held_out_target_files(params):
    hook = diffdlo.target_shape("planners/targets/hook.npy", params, dtype=torch.float64)
    wave = diffdlo.target_shape("planners/targets/wave.yaml", params, dtype=torch.float64)
    for t in (hook, wave):
        assert ((t[1:] - t[:-1]).norm(dim=-1) - params.rest_length).abs().max() < 1e-5
        assert t.mean(0).abs().max() < 1e-6
    th, tw = turns_deg(hook[None])[0], turns_deg(wave[None])[0]
    half = (params.n_nodes - 2) // 2
    assert th[:half].abs().max() < 1e-4                       # straight first half
    torch.testing.assert_close(th[half:], torch.full_like(th[half:], 120.0 / (params.n_nodes - 2 - half)),
                               rtol=0, atol=1e-4)
    assert float(th.sum()) == pytest.approx(120.0, abs=1e-3)
    assert float(tw.sum()) == pytest.approx(0.0, abs=1e-2)            # two whole sine periods: it ends as it began
    assert 19.0 < float(tw.abs().max()) < 21.0                        # 60 sin(20 deg) = 20.5 deg at most per node
    d = wave[1:] - wave[:-1]
    direction = torch.rad2deg(torch.atan2(d[:, 1], d[:, 0]))
    k = torch.arange(params.n_nodes - 1, dtype=torch.float64)
    torch.testing.assert_close(direction, 30.0 * torch.sin(4 * math.pi * k / (params.n_nodes - 2)),
                               rtol=0, atol=0.01)                 # two sine periods, 30 deg (YAML: 1 um)


def test_random_curve_family_width_is_an_env_option(params):
    env = BatchedShapeControl(8, target="random_curve", curve_max_turn_deg=20.0, params=params)
    env.reset(seed=0)
    t = turns_deg(env.get_state().target.double())
    assert t.abs().max() <= 20.0 + 1e-3 and t.abs().max() > CURVE_MAX_TURN_DEG   # wider than the default 12 deg
    narrow = BatchedShapeControl(8, target="random_curve", params=params)
    narrow.reset(seed=0)
    assert turns_deg(narrow.get_state().target.double()).abs().max() <= CURVE_MAX_TURN_DEG + 1e-3
    with pytest.raises(ValueError, match=r"curve_max_turn_deg: .*\[0, 90\], got 120"):
        BatchedShapeControl(1, target="random_curve", curve_max_turn_deg=120, params=params)
