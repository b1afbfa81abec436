"""Planners and learners are evaluated on the same episodes: episode i of seed s is what one rope's
``env.reset(seed=s + i)`` draws (its start shape and, on a family, its target), whether a planner runs it
(planners/common.run_episode, one rope, one episode at a time) or a learner's evaluation does (agents/evaluation.
evaluate, several ropes per wave). The comparison pairs its rows on that rule (benchmarks/compare.yaml)."""
from __future__ import annotations

import pytest
import torch

from agents.common.evaluation import evaluate
from diffdlo.envs import BatchedShapeControl
from diffdlo.planar.params import load_params
from planners.common import build_run, run_episode
from planners.greedy import GreedyPlanner

SEED, EPISODES = 12000, 5


def _planner_episodes(target):
    env, planner, _ = build_run(GreedyPlanner, load_params("cable"), load_params("cable"), target, max_steps=1,
                                success_tol=None, device="cpu", seed=SEED, options={})
    return [run_episode(env, planner, SEED + i, progress=False) for i in range(EPISODES)]


def _learner_episodes(target, num_envs):
    """What a learner's evaluation sees: a batched env reset in waves (ropes per wave < episodes, so the second wave's
    seeds are exercised too), a policy that records the start shape of each rope at its first move."""
    env = BatchedShapeControl(num_envs, target=target, max_steps=1)
    starts = []

    def policy(obs, deterministic):
        state = env.get_state(generators=False)
        starts.append((state.pos.clone(), state.target.clone()))
        return torch.full((num_envs, env.action_dim), 0.5)

    result = evaluate(policy, env, EPISODES, seed=SEED)
    pos = torch.cat([p for p, _ in starts])[:EPISODES]
    tgt = torch.cat([t for _, t in starts])[:EPISODES]
    return result["episodes"], pos, tgt


@pytest.mark.parametrize("target", ["random", "random_curve", "planners/targets/arc.npy"])
def test_planners_and_learners_see_the_same_episodes(target):
    planned = _planner_episodes(target)
    learned, pos, tgt = _learner_episodes(target, num_envs=3)
    for i, (p, q) in enumerate(zip(planned, learned)):
        torch.testing.assert_close(p["frames"][0], pos[i].to(p["frames"].dtype), rtol=0, atol=1e-12,
                                   msg=f"episode {i}: other start shape")
        torch.testing.assert_close(p["target_points"], tgt[i].to(p["target_points"].dtype), rtol=0, atol=1e-12,
                                   msg=f"episode {i}: other target")
        assert p["target_name"] == q["target_name"]
        assert p["start_error"] == pytest.approx(q["start_error"], abs=1e-12)     # what the report pairs on
    if target == "random":                       # the family really draws: not one target for every episode
        assert len({e["target_name"] for e in planned}) > 1
    assert len({round(e["start_error"], 9) for e in planned}) == EPISODES          # five different episodes


def test_a_planners_episode_does_not_depend_on_the_episodes_before_it():
    """The planner's generator is re-seeded with the episode's seed: episode 3 run alone equals episode 3 run
    after episodes 0-2 (so a cell's episodes can be rerun, split or paired one by one)."""
    from planners.cem import CEMPlanner

    options = {"horizon": 1, "candidates": 8, "elites": 2, "iterations": 1, "running_weight": 0.5}

    def episodes(first, n):
        env, planner, _ = build_run(CEMPlanner, load_params("cable"), load_params("cable"), "random", max_steps=2,
                                    success_tol=None, device="cpu", seed=first, options=options)
        return [run_episode(env, planner, first + i, progress=False) for i in range(n)]

    after, alone = episodes(SEED, 4)[3], episodes(SEED + 3, 1)[0]
    torch.testing.assert_close(after["frames"], alone["frames"], rtol=0, atol=0)
