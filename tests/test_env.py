"""DiffDLO/ShapeControl-v0: gymnasium/SB3 API checks, rewards, episode ends, vectorization, images, bad input."""
import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

import diffdlo
from diffdlo.envs import ACTION_TYPES, ENV_ID, OBS_TYPES, BatchedShapeControl, ShapeControlVectorEnv
from diffdlo.tasks.rewards import PEG_REWARDS

ZERO_DRAG = [0.0, 0.5, 0.5]          # node 0, dx = dy = 0


def make(small, **kw):
    return gym.make(ENV_ID, params=small, **kw)


# every reward but those that need a route's pegs (route_side_gain: tests/test_routing_env.py, tests/test_rewards.py)
FREE_ROPE_REWARDS = [r for r in diffdlo.REWARDS if r not in PEG_REWARDS]


def straight(p, angle_deg=0.0, shift=(0.0, 0.0)):
    from diffdlo.planar.shapes import straight_shape
    return (straight_shape(angle_deg, p) + torch.tensor(shift, dtype=torch.float64)).to(torch.float32)


@pytest.mark.parametrize("reward", FREE_ROPE_REWARDS)
@pytest.mark.parametrize("action_type", ACTION_TYPES)
@pytest.mark.parametrize("obs_type", [o for o in OBS_TYPES if o != "perceived"])   # perceived: test_perception.py
def test_gymnasium_check_env_without_warnings(small, obs_type, action_type, reward):
    env = make(small, obs_type=obs_type, action_type=action_type, reward=reward, render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)


@pytest.mark.parametrize("obs_type,action_type", [("points", "node"), ("distance", "pixel"), ("image", "node"),
                                                  ("image_single", "pixel")])
def test_sb3_check_env(small, obs_type, action_type):
    sb3_check_env = pytest.importorskip("stable_baselines3.common.env_checker").check_env
    env = make(small, obs_type=obs_type, action_type=action_type)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")            # advisory warnings (the [0, 1] action box) are fine
        sb3_check_env(env)


def test_spaces_and_registration(small):
    env = make(small)
    n = small.n_nodes
    assert env.action_space == gym.spaces.Box(0, 1, (3,), np.float32)
    assert set(env.observation_space.spaces) == {"node_poses", "target_poses"}
    assert env.observation_space["node_poses"].shape == (n, 2)
    assert make(small, action_type="pixel").action_space.shape == (4,)
    assert make(small, obs_type="distance").observation_space.shape == (n, 2)
    img = make(small, obs_type="image", image_size=32).observation_space
    assert img["image"].shape == (32, 32, 3) and img["image"].dtype == np.uint8 and "target_image" in img.spaces
    assert set(make(small, obs_type="image_single").observation_space.spaces) == {"image"}


def test_reset_is_deterministic_under_a_seed(small):
    a, b = make(small), make(small)
    oa, ia = a.reset(seed=3)
    ob, ib = b.reset(seed=3)
    for k in oa:
        np.testing.assert_array_equal(oa[k], ob[k])
    assert ia == ib and ia["node"] == -1 and ia["substeps"] > 0
    oc, _ = b.reset(seed=4)
    assert not np.array_equal(oa["node_poses"], oc["node_poses"])
    # random targets: over a few seeds more than one of the four named targets shows up
    targets = {tuple(np.round(a.reset(seed=s)[0]["target_poses"][0], 4)) for s in range(8)}
    assert len(targets) > 1


def test_reset_options_target(small):
    env = make(small)
    obs, _ = env.reset(seed=0, options={"target": "vertical"})
    np.testing.assert_allclose(obs["target_poses"], diffdlo.target_shape("vertical", small).numpy(), atol=1e-7)
    obs, _ = env.reset()                                         # the target spec is kept
    np.testing.assert_allclose(obs["target_poses"], diffdlo.target_shape("vertical", small).numpy(), atol=1e-7)


def _set(env, pos, target, steps=0):
    env.unwrapped.core.set_state(pos=pos.unsqueeze(0), target=target, steps=steps)


@pytest.mark.parametrize("reward", FREE_ROPE_REWARDS)
def test_rewards_hand_computed(small, reward):
    """Straight horizontal rope at rest, vertical target, a zero drag: the rope stays put."""
    env = make(small, target="vertical", reward=reward)
    env.reset(seed=0)
    rope, target = straight(small, 0.0), straight(small, 90.0)
    _set(env, rope, target)
    obs, r, terminated, truncated, info = env.step(np.array(ZERO_DRAG, np.float32))
    np.testing.assert_allclose(obs["node_poses"], rope.numpy(), atol=1e-5)
    s = rope[:, 0].numpy()                                       # node i at (s_i, 0), target node i at (0, s_i)
    expect = {"abs_diff": -math.sqrt(2) * np.abs(s).sum(),
              "delta_gain": 0.0,
              "shape_gain": 0.0,                                 # the rope stays put: no error removed
              "route_gain": 0.0,
              # P = 0 (both straight, same links); O: angle(rope) = pi, angle(target) = -pi/2 -> |3pi/2| wrapped
              "position_orientation": -math.pi / 2}[reward]
    assert r == pytest.approx(expect, abs=1e-4)
    assert not terminated and not truncated
    assert info["orientation_error"] == pytest.approx(math.pi / 2, abs=1e-5)
    assert info["node"] == 0


def test_rewards_match_formulas_after_a_real_move(small):
    rewards = {}
    for kind in FREE_ROPE_REWARDS:
        env = make(small, reward=kind)
        prev, _ = env.reset(seed=11)
        obs, rewards[kind], *_ = env.step(np.array([0.4, 0.9, 0.2], np.float32))
    x0, x, y = prev["node_poses"].astype(np.float64), obs["node_poses"].astype(np.float64), obs["target_poses"]
    absd = lambda a: np.linalg.norm(a - y, axis=-1).sum()
    pair = lambda a: np.linalg.norm(a[:, None] - a[None], axis=-1)
    ang = lambda a: math.atan2(a[0, 1] - a[-1, 1], a[0, 0] - a[-1, 0])
    o = abs((ang(x) - ang(y) + math.pi) % (2 * math.pi) - math.pi)
    assert rewards["abs_diff"] == pytest.approx(-absd(x), abs=1e-4)
    assert rewards["delta_gain"] == pytest.approx(absd(x0) - absd(x), abs=1e-4)
    assert rewards["position_orientation"] == pytest.approx(-np.abs(pair(x) - pair(y)).sum() - o, abs=1e-3)


def test_success_terminates_with_bonus(small):
    env = make(small, target="horizontal")
    env.reset(seed=0)
    _set(env, straight(small, 0.0, shift=(0.1, -0.2)), straight(small, 0.0))   # the shape error ignores shifts
    _, r, terminated, truncated, info = env.step(np.array(ZERO_DRAG, np.float32))
    assert terminated and not truncated
    assert r == small.success_bonus == 20.0
    assert info["is_success"] and info["shape_error"] < small.success_tol


def test_truncation_at_max_steps(small):
    env = make(small, max_steps=3)
    env.reset(seed=1)
    ends = [env.step(np.array([0.5, 0.55, 0.5], np.float32))[2:4] for _ in range(3)]
    assert ends == [(False, False), (False, False), (False, True)]


def test_truncation_when_the_rope_leaves_the_workspace(small):
    env = make(small, target="horizontal")
    env.reset(seed=0)
    _set(env, straight(small, 0.0, shift=(0.9, 0.0)), straight(small, 90.0))   # last node at x = 0.975
    obs, _, terminated, truncated, _ = env.step(np.array([1.0, 1.0, 0.5], np.float32))   # drag it +0.1 in x
    assert truncated and not terminated
    assert obs["node_poses"][:, 0].max() > 1.0
    assert env.observation_space.contains(obs)


def test_image_observations_change_when_the_rope_moves(small):
    env = make(small, obs_type="image", target="diagonal")
    obs0, _ = env.reset(seed=2)
    obs1, *_ = env.step(np.array([1.0, 1.0, 1.0], np.float32))
    assert obs0["image"].shape == (64, 64, 3) and obs0["image"].dtype == np.uint8
    assert (obs0["image"] != obs1["image"]).any()
    np.testing.assert_array_equal(obs0["target_image"], obs1["target_image"])
    single = make(small, obs_type="image_single")
    img = single.reset(seed=2)[0]["image"]
    assert (img != 255).any(-1).sum() > 20
    core = single.unwrapped.core                                 # cached target layer == a fresh render
    np.testing.assert_array_equal(img, core.render_images(core.get_state().pos, core.get_state().target)[0].numpy())


def test_render_rgb_array(small):
    env = make(small, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (256, 256, 3) and frame.dtype == np.uint8


def test_pixel_action_grasps_the_nearest_node(small):
    env = make(small, action_type="pixel", target="horizontal")
    env.reset(seed=0)
    rope = straight(small, 0.0)
    _set(env, rope, straight(small, 0.0))
    view = env.unwrapped.core.view_size
    for k in (0, 3, 5):
        x, y = rope[k].tolist()
        _set(env, rope, straight(small, 0.0))
        a = np.array([x / view + 0.5, 0.5 - (y + 0.004) / view, 0.5, 0.5], np.float32)   # 4 mm above node k
        assert env.step(a)[4]["node"] == k


def test_actions_outside_the_box_are_clipped(small):
    a, b = make(small), make(small)
    a.reset(seed=5)
    b.reset(seed=5)
    oa, ra, *_ = a.step(np.array([1.7, -3.0, 9.0], np.float32))
    ob, rb, *_ = b.step(np.array([1.0, 0.0, 1.0], np.float32))
    np.testing.assert_array_equal(oa["node_poses"], ob["node_poses"])
    assert ra == rb


@pytest.mark.parametrize("action,match", [([np.nan, 0.5, 0.5], "nan"), ([0.1, np.inf, 0.5], "inf"),
                                          ([0.5, 0.5], r"shape \(3,\)"), ([[0.5, 0.5, 0.5]], r"shape \(3,\)")])
def test_bad_actions_raise(small, action, match):
    env = make(small)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.unwrapped.step(np.array(action))


@pytest.mark.parametrize("kw,bad,allowed", [
    ({"obs_type": "pixels"}, "pixels", "points"), ({"action_type": "joint"}, "joint", "node"),
    ({"reward": "dense"}, "dense", "position_orientation"), ({"target": "zigzag"}, "zigzag", "random"),
    ({"render_mode": "ansi"}, "ansi", "rgb_array")])
def test_bad_kwargs_raise(small, kw, bad, allowed):
    with pytest.raises(ValueError, match=bad) as exc:
        diffdlo.envs.ShapeControlEnv(params=small, **kw)
    assert allowed in str(exc.value)
    with pytest.raises(ValueError, match=bad):
        gym.make_vec(ENV_ID, num_envs=2, params=small, **kw)


def test_vector_env_metadata_and_spaces(small):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        venv = gym.make_vec(ENV_ID, num_envs=4, params=small)
    assert isinstance(venv.unwrapped, ShapeControlVectorEnv)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert venv.action_space.shape == (4, 3)
    obs, info = venv.reset(seed=0)
    assert obs["node_poses"].shape == (4, small.n_nodes, 2) and info["shape_error"].shape == (4,)
    with pytest.raises(ValueError, match=r"shape \(4, 3\)"):
        venv.step(np.zeros((3, 3)))


@pytest.mark.parametrize("obs_type,action_type", [("points", "node"), ("image_single", "pixel")])
def test_vector_env_equals_single_envs_with_autoreset(small, obs_type, action_type):
    """Sub-env i seeded s + i, same actions, NEXT_STEP autoreset; max_steps=2 forces autoresets."""
    b, seed, kw = 3, 7, dict(obs_type=obs_type, action_type=action_type, max_steps=2)
    venv = gym.make_vec(ENV_ID, num_envs=b, params=small, **kw)
    envs = [make(small, **kw) for _ in range(b)]
    vobs, vinfo = venv.reset(seed=seed)
    sobs = [e.reset(seed=seed + i) for i, e in enumerate(envs)]
    rng = np.random.default_rng(0)
    done = [False] * b

    def compare(vobs, vinfo, singles):
        for i, (o, info) in enumerate(singles):
            for k in o:
                np.testing.assert_allclose(vobs[k][i], o[k], atol=1e-5 if o[k].dtype != np.uint8 else 1)
            assert vinfo["node"][i] == info["node"] and vinfo["substeps"][i] == info["substeps"]

    compare(vobs, vinfo, sobs)
    n_resets = 0
    for _ in range(5):
        actions = rng.uniform(0, 1, (b, venv.single_action_space.shape[0])).astype(np.float32)
        vobs, vrew, vterm, vtrunc, vinfo = venv.step(actions)
        singles = []
        for i, e in enumerate(envs):
            if done[i]:                              # next-step autoreset: action ignored, reward 0
                o, info = e.reset()
                r, te, tr = 0.0, False, False
                n_resets += 1
            else:
                o, r, te, tr, info = e.step(actions[i])
            done[i] = te or tr
            singles.append((o, info))
            assert vrew[i] == pytest.approx(r, abs=1e-4) and vterm[i] == te and vtrunc[i] == tr
        compare(vobs, vinfo, singles)
    assert n_resets >= b


def test_torch_native_interface(small):
    core = BatchedShapeControl(num_envs=4, params=small, target="random", obs_type="points")
    obs, info = core.reset(seed=0)
    assert all(torch.is_tensor(v) and v.device == core.sim.device for v in obs.values())
    assert obs["node_poses"].shape == (4, small.n_nodes, 2) and obs["node_poses"].dtype == torch.float32
    actions = torch.rand(4, 3, generator=torch.Generator().manual_seed(0))
    obs, reward, terminated, truncated, info = core.step(actions)
    for t in (reward, terminated, truncated, *info.values()):
        assert torch.is_tensor(t) and t.device == core.sim.device and t.shape == (4,)
    assert terminated.dtype == torch.bool and torch.isfinite(obs["node_poses"]).all()
    # partial step: masked-out envs keep their state and get reward 0
    before = core.get_state().pos.clone()
    _, reward, *_ = core.step(actions, mask=[True, False, True, False])
    assert torch.equal(core.get_state().pos[1], before[1]) and reward[1] == 0 and not torch.equal(core.get_state().pos[0], before[0])
    # sub-env i of a batch seeded s is a single env seeded s + i
    single = BatchedShapeControl(num_envs=1, params=small)
    one, _ = single.reset(seed=2)
    many, _ = core.reset(seed=0)
    assert torch.allclose(one["node_poses"][0], many["node_poses"][2], atol=1e-6)


def test_sb3_sac_multi_input_runs(small):
    """The README's SAC snippet, on the small rope."""
    SAC = pytest.importorskip("stable_baselines3").SAC
    env = make(small, target="horizontal")
    model = SAC("MultiInputPolicy", env, learning_starts=4, batch_size=8, buffer_size=100, seed=0)
    model.learn(total_timesteps=8)
    obs, _ = env.reset(seed=1)
    action, _ = model.predict(obs, deterministic=True)
    assert env.action_space.contains(action)
    assert np.isfinite(env.step(action)[1])
