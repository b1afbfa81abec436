"""Gymnasium conventions of DiffDLO/ShapeControl-v0: autoreset modes, episode limits, action_scale, and clear errors
for coincident or non-finite nodes in targets, start shapes and simulator states."""
import dataclasses
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

import diffdlo
from diffdlo import TargetError
from diffdlo.envs import ENV_ID, BatchedShapeControl, ShapeControlVectorEnv
from diffdlo.planar.shapes import straight_shape

ZERO_DRAG = [0.0, 0.5, 0.5]          # node 0, dx = dy = 0


def make_vec(small, num_envs=2, **kw):
    return gym.make_vec(ENV_ID, num_envs=num_envs, vectorization_mode="vector_entry_point", params=small, **kw)


def episode_length(env, action, limit=200):
    """Steps of ``action`` until the first end of a single env (reset with seed 0)."""
    env.reset(seed=0)
    for t in range(1, limit + 1):
        _, _, terminated, truncated, _ = env.step(np.asarray(action, dtype=np.float32))
        if terminated or truncated:
            return t
    return None


def straight(p, dtype=torch.float64):
    return straight_shape(0.0, p).to(dtype)


# ---------------------------------------------------------------------------------------------- autoreset modes
@pytest.mark.parametrize("mode,expected", [(AutoresetMode.NEXT_STEP, AutoresetMode.NEXT_STEP),
                                           (AutoresetMode.SAME_STEP, AutoresetMode.SAME_STEP),
                                           ("SameStep", AutoresetMode.SAME_STEP)])
def test_make_vec_accepts_autoreset_mode_and_max_episode_steps(small, mode, expected):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        venv = make_vec(small, autoreset_mode=mode, max_episode_steps=4)
    assert isinstance(venv.unwrapped, ShapeControlVectorEnv)
    assert venv.metadata["autoreset_mode"] == expected and venv.unwrapped.autoreset_mode == expected
    assert ShapeControlVectorEnv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP     # per instance
    assert venv.unwrapped.core.max_steps == 4


@pytest.mark.parametrize("mode", [AutoresetMode.DISABLED, "Disabled", "sometimes"])
def test_unsupported_autoreset_mode_is_named(small, mode):
    with pytest.raises(ValueError, match="autoreset_mode") as exc:
        make_vec(small, autoreset_mode=mode)
    assert repr(mode) in str(exc.value) and "SAME_STEP" in str(exc.value)


def assert_obs_equal(a, b):
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_same_step_equals_next_step_shifted_by_the_reset_step(small):
    """Both sub-envs end at step 2. SAME_STEP returns the new episodes' first observation at once, with the ending
    observation and info in final_obs/final_info; NEXT_STEP returns the ending observation and resets one step later
    (ignoring that step's action). After that the two envs run in lockstep."""
    kw = dict(max_episode_steps=2)
    same = make_vec(small, autoreset_mode=AutoresetMode.SAME_STEP, **kw)
    nxt = make_vec(small, autoreset_mode=AutoresetMode.NEXT_STEP, **kw)
    assert_obs_equal(same.reset(seed=3)[0], nxt.reset(seed=3)[0])
    rng = np.random.default_rng(0)
    actions = rng.uniform(0, 1, (4, 2, 3)).astype(np.float32)

    so, sr, ste, str_, si = same.step(actions[0])
    no, nr, nte, ntr, ni = nxt.step(actions[0])
    assert_obs_equal(so, no)
    assert "final_obs" not in si and "final_info" not in si               # nobody ended: no final entries

    so, sr, ste, str_, si = same.step(actions[1])
    no, nr, nte, ntr, ni = nxt.step(actions[1])
    assert (str_ == ntr).all() and str_.all() and (ste == nte).all()
    np.testing.assert_array_equal(sr, nr)
    assert si["_final_obs"].tolist() == [True, True] and si["_final_info"].tolist() == [True, True]
    for i in range(2):
        for k in no:
            np.testing.assert_array_equal(si["final_obs"][i][k], no[k][i])     # the step's observation
    for k in ("shape_error", "orientation_error", "is_success", "node", "substeps"):
        np.testing.assert_array_equal(si["final_info"][k], ni[k])             # the step's info
        assert si["final_info"][f"_{k}"].tolist() == [True, True]
    assert (si["node"] == -1).all()                                           # the new episodes' reset info

    no, nr, nte, ntr, ni = nxt.step(actions[2])                               # NEXT_STEP's reset step
    assert_obs_equal(so, no)
    assert (nr == 0).all() and not nte.any() and not ntr.any()
    for k in ("shape_error", "node", "substeps"):
        np.testing.assert_array_equal(si[k], ni[k])

    so, sr, *_ = same.step(actions[3])
    no, nr, *_ = nxt.step(actions[3])
    assert_obs_equal(so, no)
    np.testing.assert_array_equal(sr, nr)


def test_same_step_info_layout_matches_sync_vector_env(small):
    """Sub-envs that end at different steps (a partial reset staggers them) give SyncVectorEnv's SAME_STEP layout:
    final_obs an object array with None for the running sub-envs, final_info and every mask marking the ended."""
    b, kw = 3, dict(params=small, max_steps=2)
    native = make_vec(small, num_envs=b, autoreset_mode=AutoresetMode.SAME_STEP, max_steps=2)
    sync = gym.make_vec(ENV_ID, num_envs=b, vectorization_mode="sync",
                        vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP}, **kw)
    rng = np.random.default_rng(1)
    native.reset(seed=5)
    sync.reset(seed=5)
    ends = 0
    for t in range(5):
        actions = rng.uniform(0, 1, (b, 3)).astype(np.float32)
        if t == 1:
            mask = np.array([True, False, False])
            for env in (native, sync):
                env.reset(options={"reset_mask": mask})
        no, nr, nte, ntr, ni = native.step(actions)
        so, sr, ste, str_, si = sync.step(actions)
        for k in so:
            np.testing.assert_allclose(no[k], so[k], atol=1e-5)
        np.testing.assert_allclose(nr, sr, atol=1e-4)
        assert (nte == ste).all() and (ntr == str_).all()
        assert set(ni) == set(si)
        if "final_obs" in si:
            ends += int(si["_final_obs"].sum())
            np.testing.assert_array_equal(ni["_final_obs"], si["_final_obs"])
            np.testing.assert_array_equal(ni["_final_info"], si["_final_info"])
            assert set(ni["final_info"]) == set(si["final_info"])
            for i in range(b):
                if si["final_obs"][i] is None:
                    assert ni["final_obs"][i] is None
                else:
                    for k in so:
                        np.testing.assert_allclose(ni["final_obs"][i][k], si["final_obs"][i][k], atol=1e-5)
            for k, v in si["final_info"].items():
                np.testing.assert_allclose(ni["final_info"][k].astype(np.float64), v.astype(np.float64), atol=1e-5)
        for k in ("node", "substeps", "_node"):
            np.testing.assert_array_equal(ni[k], si[k])
    assert ends >= 4


# ---------------------------------------------------------------------------------------------- episode limits
def test_registered_spec_max_episode_steps_is_the_params_default():
    assert gym.spec(ENV_ID).max_episode_steps == 100 == diffdlo.load_params("cable").max_episode_steps


def test_make_time_limit_and_the_envs_truncation_agree(small):
    env = gym.make(ENV_ID, params=small)
    assert env.spec.max_episode_steps == 100 and env.unwrapped.core.max_steps == 100
    env.reset(seed=0)
    for t in range(1, 101):                       # one truncation, at step 100: the env's and TimeLimit's
        _, _, terminated, truncated, _ = env.step(np.asarray(ZERO_DRAG, dtype=np.float32))
        assert not terminated and truncated == (t == 100)
    assert episode_length(gym.make(ENV_ID, params=small, max_steps=3), ZERO_DRAG) == 3
    assert episode_length(gym.make(ENV_ID, params=small, max_episode_steps=3), ZERO_DRAG) == 3
    longer = gym.make(ENV_ID, params=small, max_steps=103, max_episode_steps=103)
    assert episode_length(longer, ZERO_DRAG) == 103


@pytest.mark.parametrize("kw,length", [({}, 100), ({"max_episode_steps": 3}, 3), ({"max_steps": 3}, 3),
                                       ({"max_steps": 4, "max_episode_steps": 6}, 4)])
def test_make_vec_episode_length_is_makes(small, kw, length):
    venv = make_vec(small, **kw)
    assert venv.unwrapped.core.max_steps == length
    venv.reset(seed=0)
    for t in range(1, length + 1):
        _, _, terminated, truncated, _ = venv.step(np.tile(ZERO_DRAG, (2, 1)).astype(np.float32))
        assert not terminated.any() and truncated.all() == (t == length) and truncated.any() == (t == length)


def test_max_steps_cut_by_max_episode_steps_warns(small):
    with pytest.warns(UserWarning, match="max_episode_steps=3.*max_steps=5"):
        venv = make_vec(small, max_steps=5, max_episode_steps=3)
    assert venv.unwrapped.core.max_steps == 3
    with pytest.raises(ValueError, match="max_episode_steps must be a positive integer.*got 0"):
        make_vec(small, max_episode_steps=0)


# ---------------------------------------------------------------------------------------------- action_scale
def test_action_scale_sets_the_drag(small):
    start = straight(small)
    core = BatchedShapeControl(params=small, action_scale=0.05, target="horizontal", start=start,
                               dtype=torch.float64)
    assert core.params.action_scale == 0.05 and core.sim.params.action_scale == 0.05
    core.reset(seed=0)
    action = torch.tensor([[0.0, 1.0, 0.5]], dtype=torch.float64)       # node 0, a = 1 in x, 0.5 in y
    node, drag = core.decode(action)
    assert node.tolist() == [0] and drag.tolist() == [[0.05, 0.0]]
    core.step(action)
    expected = core.sim.move(start[None], torch.zeros(1, dtype=torch.int64),
                             torch.tensor([[0.05, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(core.get_state().pos, expected, rtol=0, atol=0)
    default = BatchedShapeControl(params=small, target="horizontal", start=start, dtype=torch.float64)
    assert default.decode(action)[1].tolist() == [[small.action_scale, 0.0]]
    env = gym.make(ENV_ID, params=small, action_scale=0.05)
    assert env.unwrapped.core.params.action_scale == 0.05


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), True, "0.1"])
def test_bad_action_scale_is_named(small, bad):
    with pytest.raises(ValueError, match="action_scale must be a positive number") as exc:
        BatchedShapeControl(params=small, action_scale=bad)
    assert repr(bad) in str(exc.value)


# ---------------------------------------------------------------------------------------------- coincident nodes
def with_node_near_its_neighbour(p, gap, node=3):
    """A straight rope whose ``node`` lies ``gap`` m from node - 1."""
    s = straight(p).clone()
    s[node] = s[node - 1] + torch.tensor([gap, 0.0], dtype=torch.float64)
    return s


@pytest.mark.parametrize("gap,shown", [(0.0, "0 m"), (1e-9, "1e-09 m")])
def test_coincident_target_nodes_are_named(params, gap, shown):
    shape = with_node_near_its_neighbour(params, gap)
    with pytest.raises(TargetError, match=f"nodes 2 and 3 are {shown} apart"):
        diffdlo.target_shape(shape.numpy(), params)
    with pytest.raises(TargetError, match=f"nodes 2 and 3 are {shown} apart"):
        BatchedShapeControl(params=params, target=shape.numpy())


def test_target_links_shorter_than_a_tenth_of_the_rest_length_are_rejected(params):
    short = with_node_near_its_neighbour(params, 0.05 * params.rest_length)
    with pytest.raises(TargetError, match="nodes 2 and 3 are 0.00132 m apart"):
        diffdlo.target_shape(short.numpy(), params)


def test_nan_target_is_named(small):
    nan = straight(small).numpy().copy()
    nan[3, 1] = np.nan
    with pytest.raises(TargetError, match=r"NaN or inf: node 3 is \[.*, nan\]"):
        diffdlo.target_shape(nan, small)
    with pytest.raises(TargetError, match=r"node 3 is \[.*, nan\]"):
        gym.make(ENV_ID, params=small, target=nan)
    core = BatchedShapeControl(num_envs=2, params=small, dtype=torch.float64)
    core.reset(seed=0)
    with pytest.raises(ValueError, match=r"target contains NaN or inf: rope 0, node 3 is \[.*, nan\]"):
        core.set_state(target=nan)
    assert torch.isfinite(core.get_state().info["shape_error"]).all()          # the state is unchanged
    with pytest.raises(ValueError, match="target: rope 0: nodes 2 and 3 are 0 m apart"):
        core.set_state(target=with_node_near_its_neighbour(small, 0.0))


@pytest.mark.parametrize("gap,shown", [(0.0, "0 m"), (1e-9, "1e-09 m")])
def test_coincident_start_nodes_are_named(small, gap, shown):
    with pytest.raises(ValueError, match=f"start shape: nodes 2 and 3 are {shown} apart"):
        BatchedShapeControl(params=small, start=with_node_near_its_neighbour(small, gap).numpy())


def test_nan_start_is_named(small):
    start = straight(small).numpy().copy()
    start[4, 0] = np.inf
    with pytest.raises(ValueError, match=r"start shape contains NaN or inf: node 4 is \[inf, .*\]"):
        BatchedShapeControl(params=small, start=start)
    with pytest.raises(ValueError, match=r"start shape must have shape \(6, 2\).*got \(5, 2\)"):
        BatchedShapeControl(params=small, start=start[:5])


@pytest.mark.parametrize("gap,shown", [(0.0, "0 m"), (1e-9, "1e-09 m")])
def test_coincident_simulator_inputs_are_named(small, gap, shown):
    sim = diffdlo.Simulator(small, dtype=torch.float64)
    pos = torch.stack([straight(small), with_node_near_its_neighbour(small, gap)])
    node, drag = torch.zeros(2, dtype=torch.int64), torch.zeros(2, 2, dtype=torch.float64)
    match = f"pos: rope 1: nodes 2 and 3 are {shown} apart"
    with pytest.raises(ValueError, match=match):
        sim.move(pos, node, drag)
    with pytest.raises(ValueError, match=match):
        sim.settle(pos)
    core = BatchedShapeControl(num_envs=2, params=small, dtype=torch.float64)
    core.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        core.set_state(pos=pos)


def test_simulator_accepts_ropes_after_hard_moves(small):
    """Fast 0.1 m drags with no settling keep every link far above the simulator's 1% threshold."""
    p = dataclasses.replace(small, settle_max_substeps=0)
    sim = diffdlo.Simulator(p, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    pos = sim.random_shape(64, generator=gen)
    for _ in range(3):
        node = torch.randint(0, p.n_nodes, (64,), generator=gen)
        drag = (torch.rand(64, 2, generator=gen, dtype=torch.float64) * 2 - 1) * p.max_disp
        pos = sim.move(pos, node, drag)                       # each move checks its input
    links = (pos[:, 1:] - pos[:, :-1]).norm(dim=-1)
    assert links.min() > 0.05 * p.rest_length


# ---------------------------------------------------------------------------------------------- torchrl
@pytest.mark.ecosystem    # run by .ci/run after installing the optional extras
def test_torchrl_rollout_of_the_native_vector_env(small):
    pytest.importorskip("torchrl")
    from torchrl.envs import GymWrapper
    venv = make_vec(small, autoreset_mode=AutoresetMode.SAME_STEP, max_episode_steps=3, obs_type="distance")
    env = GymWrapper(venv)
    rollout = env.rollout(6, break_when_any_done=False)
    assert rollout.batch_size == torch.Size([2, 6])
    assert torch.isfinite(rollout["next", "observation"]).all()
    assert rollout["next", "truncated"].any()
