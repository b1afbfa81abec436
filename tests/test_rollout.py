"""Acting by policy rollouts through the simulator (agents/common/rollout.py): the ranking, the rollouts' bookkeeping on a
hand-built case, and the policy-improvement property on real episodes (never more moves than the base policy)."""
import json
import math

import pytest
import torch

from agents.common.envs import TrainEnv
from agents.common.evaluation import evaluate
from agents.common.rollout import PolicyRollouts, moves_to_success, rank
from diffdlo.envs import BatchedShapeControl
from diffdlo.planar.params import load_params
from diffdlo.tasks.task import encode_node_action, greedy_drags

P = load_params("cable")
TASK = dict(target="random", obs_type="points", action_type="node", reward="shape_gain", success_bonus=5.0,
            on_exit="fail", exit_penalty=5.0)


def greedy_policy(noise: float = 0.3):
    """A deterministic base policy from the observation (drag the farthest node toward its place); sampled: the
    greedy drag plus Gaussian noise in the action box, on a node drawn near the farthest one."""
    def policy(obs, deterministic=True):
        pos, target = obs["node_poses"].double(), obs["target_poses"].double()
        drags, dist = greedy_drags(pos, target, P.max_disp)
        node = dist.argmax(-1)
        if not deterministic:
            node = (node + torch.randint(-2, 3, node.shape)).clamp(0, P.n_nodes - 1)
        drag = drags[torch.arange(len(node)), node]
        a = encode_node_action(node, drag, P.n_nodes, P.action_scale)
        if not deterministic:
            a[:, 1:] = (a[:, 1:] + noise * torch.randn(a[:, 1:].shape)).clamp(0, 1)
        return a.float()
    return policy


def test_rank_prefers_fewest_moves_then_the_policys_own_move_then_the_lowest_error():
    inf = math.inf
    moves = torch.tensor([[3.0, 2.0, 2.0, inf],        # two samples save a move: the lower final error of the two
                          [inf, inf, inf, inf],        # none reaches it: the lowest final error
                          [4.0, 4.0, 5.0, 4.0]])       # the policy's own move is among the fewest: it, whatever the
    error = torch.tensor([[0.001, 0.009, 0.004, 0.0],   # errors of the others
                          [0.30, 0.10, 0.20, 0.15],
                          [0.005, 0.002, 0.001, 0.005]], dtype=torch.float64)
    assert rank(moves, error).tolist() == [2, 1, 0]


def test_moves_to_success_counts_the_first_move_and_never_continues_an_ended_rope():
    core = BatchedShapeControl(3, **TASK)
    core.reset(seed=4)
    s = core.get_state(generators=False)
    target = s.target[0].expand(3, -1, -1)
    start = s.pos.clone()
    start[0] = target[0]                                 # rope 0: on its target (ended by success after move 1)
    core.set_state(pos=start, target=target, steps=0)
    env = TrainEnv(core)
    before = core.get_state(generators=False).pos.clone()
    success = torch.tensor([True, False, False])
    ended = torch.tensor([True, True, False])           # rope 1: ended without success (say it left the table)
    calls = []

    def policy(obs, deterministic=True):
        calls.append(obs["node_poses"].shape[0])
        return greedy_policy()(obs, True)

    moves, error, evals = moves_to_success(env, policy, success, ended, moves=3)
    after = core.get_state(generators=False).pos
    assert moves[0] == 1.0 and math.isinf(moves[1])
    assert torch.equal(after[0], before[0]) and torch.equal(after[1], before[1])   # ended ropes never move again
    assert not torch.equal(after[2], before[2])
    assert evals == 3                                    # only rope 2 moved, 3 times (greedy needs more than 4)
    assert math.isinf(moves[2]) and float(error[2]) > P.success_tol


def test_acting_by_rollouts_never_needs_more_moves_than_its_policy_and_here_fewer():
    def run(policy, n=3):
        env = TrainEnv(BatchedShapeControl(n, max_steps=60, **TASK))
        return evaluate(policy, env, n, seed=10000)
    base = greedy_policy()
    alone = run(base)
    acting = PolicyRollouts(base, {**TASK, "max_steps": 60}, candidates=6, moves=60, seed=0)
    improved = run(acting)
    assert all(e["success"] for e in alone["episodes"]) and all(e["success"] for e in improved["episodes"])
    for a, b in zip(alone["episodes"], improved["episodes"]):
        assert a["start_error"] == b["start_error"]                  # the same episodes
        assert b["steps"] <= a["steps"]
    assert sum(e["steps"] for e in improved["episodes"]) < sum(e["steps"] for e in alone["episodes"])
    stats = acting.stats()
    assert stats["rollout_candidates"] == 6 and stats["sim_evals_per_move"] > 6


def test_the_same_observations_give_the_same_moves():
    core = BatchedShapeControl(2, **TASK)
    obs, _ = core.reset(seed=7)
    one, two = (PolicyRollouts(greedy_policy(), TASK, candidates=5, moves=4, seed=3) for _ in range(2))
    assert torch.equal(one(obs), two(obs))


@pytest.mark.parametrize("bad, match", [(dict(candidates=0), "candidates must be >= 1"),
                                        (dict(moves=-1), "moves must be >= 0")])
def test_bad_rollout_options_are_named(bad, match):
    with pytest.raises(ValueError, match=match):
        PolicyRollouts(greedy_policy(), TASK, **bad)


def test_rollouts_need_an_observation_that_shows_the_rope():
    with pytest.raises(ValueError, match="needs obs \\['points'\\], got 'image'"):
        PolicyRollouts(greedy_policy(), {**TASK, "obs_type": "image"})


def test_a_learner_acting_by_rollouts_keeps_its_policy_alone_result(tmp_path):
    from agents import ppo
    from agents.common.config import from_flat
    cfg = from_flat(ppo.PPOConfig, {"total_steps": 512, "num_envs": 32, "n_steps": 16, "batch_size": 256,
                                    "max_steps": 12, "eval_episodes": 2, "rollout_candidates": 3,
                                    "rollout_moves": 2, "policy": "hybrid", "features": "relative",
                                    "reward": "shape_gain"})
    ppo.train(cfg, tmp_path / "run", progress=False)
    r = json.loads((tmp_path / "run" / "results.json").read_text())
    assert r["rollout_candidates"] == 3 and r["acting"].startswith("policy rollouts")
    assert len(r["policy_alone"]["episodes"]) == 2
    starts = [e["start_error"] for e in r["episodes"]]
    assert starts == [e["start_error"] for e in r["policy_alone"]["episodes"]]
    # any run's checkpoint acts by rollouts from the command line; a bad count is named
    from agents.tools.evaluate import main
    assert main([str(tmp_path / "run"), "--rollouts", "2", "--rollout-moves", "1", "--episodes", "2", "--no-gif",
                 "--out", str(tmp_path / "ev")]) == 0
    ev = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert ev["rollout_candidates"] == 2 and [e["start_error"] for e in ev["episodes"]] == starts
    assert main([str(tmp_path / "run"), "--rollouts", "-1"]) == 2


def test_planet_refuses_to_act_by_rollouts(tmp_path):
    from agents import planet
    from agents.common.config import from_flat
    cfg = from_flat(planet.PlaNetConfig, {"total_steps": 64, "rollout_candidates": 4})
    with pytest.raises(ValueError, match="PlaNet already plans"):
        planet.train(cfg, tmp_path / "run", progress=False)


def test_the_value_lookahead_never_bootstraps_an_ended_move():
    """benchmarks/studies/value_lookahead.py's score by hand: a move that ended the episode scores its reward alone, however
    large the critic's value of the state it reached."""
    from benchmarks.studies.value_lookahead import one_move_score
    reward = torch.tensor([5.0, 1.0, 0.5], dtype=torch.float64)      # success bonus, a gain, a gain
    ended = torch.tensor([True, False, False])
    value = torch.tensor([100.0, 3.0, 4.0], dtype=torch.float64)
    score = one_move_score(reward, ended, value, gamma=0.5)
    assert score.tolist() == [5.0, 1.0 + 0.5 * 3.0, 0.5 + 0.5 * 4.0]
    assert int(score.argmax()) == 0
