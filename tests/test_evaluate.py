"""agents.load_policy and python -m agents.tools.evaluate: a trained run's checkpoint acts on the gymnasium env, reproduces
the run's own final evaluation, is evaluated and watched from the command line; broken checkpoints are named."""
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import agents
from agents.tools import evaluate as evaluate_cli
from agents import planet, ppo, sac
from agents.common.checkpoints import CHECKPOINT
from agents.common.config import load_config
from agents.common.evaluation import evaluate
from conftest import cli_error

pytestmark = pytest.mark.usefixtures("one_thread")

PO = dict(n_nodes=6, length=0.15, max_speed=1.0, settle_max_substeps=30, settle_check_every=10)
TASK = dict(param_overrides=PO, max_steps=4, num_envs=4, eval_episodes=6, checkpoint_every=10**9, eval_every=10**9)
TINY = {   # a few seconds each; one evaluation, at the end (evaluations in between would move PlaNet's CEM generators)
    "sac": (sac, sac.SACConfig, "sac", dict(total_steps=64, hidden=[16, 16], head_hidden=8, batch_size=16,
                                            learning_starts=32, buffer_size=256)),
    "sac-gaussian": (sac, sac.SACConfig, "sac-sb3-default", dict(total_steps=64, hidden=[16, 16], batch_size=16,
                                                                  learning_starts=32, buffer_size=256)),
    "ppo": (ppo, ppo.PPOConfig, "ppo", dict(total_steps=64, hidden=[16, 16], n_steps=8, batch_size=16,
                                            n_epochs=1)),
    "planet": (planet, planet.PlaNetConfig, "planet", dict(total_steps=48, members=2, model_hidden=[16, 16],
                                                            horizon=1, candidates=8, elites=2, iterations=2,
                                                            seed_episodes=2, train_every=16, updates_per_train=2,
                                                            batch_size=8, openloop_episodes=2,
                                                            openloop_context=1)),
    "planet-latent": (planet, planet.PlaNetConfig, "planet-latent", dict(total_steps=48, latent_dim=8,
                                                                          latent_hidden=[16, 16], chunk_length=2,
                                                                          horizon=1, candidates=8, elites=2,
                                                                          iterations=2, seed_episodes=2,
                                                                          train_every=16, updates_per_train=2,
                                                                          batch_size=8, openloop_episodes=2,
                                                                          openloop_context=1)),
    "planet-rssm": (planet, planet.PlaNetConfig, "planet-rssm", dict(total_steps=48, deter=8, stoch=4, hidden=8,
                                                                      embed=8, horizon=1, candidates=8, elites=2,
                                                                      iterations=2, seed_episodes=2, train_every=16,
                                                                      updates_per_train=2, batch_size=4,
                                                                      chunk_length=2, plan_objective="shape",
                                                                      openloop_episodes=2, openloop_context=1)),
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """name -> the folder of a finished tiny run."""
    torch.set_num_threads(1)
    out = {}
    for name, (module, cls, preset, kw) in TINY.items():
        folder = tmp_path_factory.mktemp(name)
        module.train(load_config(cls, preset, {**TASK, **kw}), folder, progress=False)
        out[name] = folder
    return out


@pytest.mark.parametrize("name", list(TINY))
def test_loaded_policy_acts_on_a_gym_observation_and_reproduces_the_runs_evaluation(name, runs):
    policy = agents.load_policy(runs[name])
    assert policy.algo == name.split("-")[0] and policy.step == TINY[name][3]["total_steps"]
    env = gym.make("DiffDLO/ShapeControl-v0", **policy.env_kwargs())
    obs, _ = env.reset(seed=3)
    policy.reset()
    for _ in range(2):
        action = policy(obs)
        assert action.dtype == np.float32 and action.shape == env.action_space.shape
        assert np.all((action >= 0) & (action <= 1))
        obs, *_ = env.step(action)
    if not name.startswith("planet"):                        # deterministic: the same observation, the same action
        assert np.array_equal(policy(obs), policy(obs))

    own = json.loads((runs[name] / "results.json").read_text())
    cfg = policy.config
    eval_env = policy.make_env()
    again = evaluate(policy.batched(eval_env), eval_env, cfg.run.eval_episodes, seed=cfg.run.eval_seed)
    assert again["success_rate"] == own["success_rate"]
    for mine, theirs in zip(again["episodes"], own["episodes"], strict=True):
        assert (mine["success"], mine["steps"], mine["target_name"]) == \
               (theirs["success"], theirs["steps"], theirs["target_name"])
        assert mine["final_error"] == pytest.approx(theirs["final_error"], abs=1e-6)


def test_wrong_observation_and_planet_without_env_are_named(runs):
    with pytest.raises(ValueError, match="does not fit the run's task"):
        agents.load_policy(runs["sac"])(np.zeros((6, 2), np.float32))
    with pytest.raises(ValueError, match="pass it"):
        agents.load_policy(runs["planet"]).batched()


@pytest.mark.parametrize("name", ["sac", "planet"])
def test_evaluate_command_writes_results_pictures_and_refuses_to_overwrite(name, runs, tmp_path, capsys):
    out = tmp_path / "eval"
    argv = [str(runs[name]), "--episodes", "3", "--target", "diagonal", "--seed", "5", "--out", str(out),
            "--gif-episodes", "2"]
    assert evaluate_cli.main(argv) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["method"] == name and res["step"] == TINY[name][3]["total_steps"] and res["target"] == "diagonal"
    assert len(res["episodes"]) == 3 and 0 <= res["success_rate"] <= 1
    assert {e["target_name"] for e in res["episodes"]} == {"diagonal"}
    assert set(res["episodes"][0]) == {"success", "steps", "final_error", "start_error", "target_name", "errors",
                                       "worst_errors"}
    for e in res["episodes"]:                                  # the errors after the reset and after every move
        assert len(e["errors"]) == len(e["worst_errors"]) == e["steps"] + 1
        assert e["errors"][-1] == pytest.approx(e["final_error"]) and e["worst_errors"][-1] >= e["final_error"]
    assert (out / "eval_episodes.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "episodes.gif").read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    assert "success rate" in capsys.readouterr().out

    assert evaluate_cli.main(argv) == 2                       # an earlier evaluation is kept
    err = capsys.readouterr().err
    assert "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert evaluate_cli.main(argv + ["--overwrite", "--no-gif"]) == 0


def test_evaluate_command_default_out_and_bad_flags(runs, capsys):
    assert evaluate_cli.main([str(runs["ppo"]), "--no-gif"]) == 0
    cfg = agents.load_policy(runs["ppo"]).config
    assert (runs["ppo"] / f"evaluate-random-s{cfg.run.eval_seed}" / "results.json").exists()
    capsys.readouterr()
    for bad, named in ((["--episodes", "0"], "'0'"), (["--target", "zigzag"], "zigzag"), (["--seed", "x"], "'x'"),
                       (["--bogus"], "--bogus"), (["--success-tol", "-0.01"], "'-0.01'"),
                       (["--success-tol", "nan"], "'nan'"), (["--success-worst-tol", "inf"], "'inf'"),
                       (["--success-worst-tol", "0"], "'0'"), (["--max-steps", "0"], "'0'")):
        assert evaluate_cli.main([str(runs["ppo"]), *bad]) == 2, bad
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and named in err, err


def test_broken_checkpoints_give_one_clear_error(runs, tmp_path, capsys):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        agents.load_policy(tmp_path / "nothing")
    good = (runs["sac"] / CHECKPOINT).read_bytes()
    truncated = tmp_path / "truncated" / CHECKPOINT
    truncated.parent.mkdir()
    truncated.write_bytes(good[: len(good) // 2])
    with pytest.raises(ValueError, match="not a readable checkpoint") as exc:
        agents.load_policy(truncated.parent)
    assert str(truncated) in str(exc.value)

    ck = torch.load(runs["sac"] / CHECKPOINT, weights_only=False)
    for change, message in (({"algo": "dqn"}, "unknown algo 'dqn'"), ({"algo": "ppo"}, "without \\['agent'\\]"),
                            ({"config": {"lr": 1e-3, "warp": 9}}, "does not fit"),
                            ({"config": {**ck["config"], "hidden": [8]}}, "'actor' weights do not fit")):
        folder = tmp_path / next(iter(change))
        folder.mkdir(exist_ok=True)
        torch.save({**ck, **change}, folder / CHECKPOINT)
        with pytest.raises(ValueError, match=message):
            agents.load_policy(folder)
    assert evaluate_cli.main([str(truncated.parent)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a readable checkpoint" in err


def test_evaluate_at_another_tolerance_continues_the_runs_own_episodes(runs, capsys):
    """PlaNet's planner does not look at the tolerance: evaluated until 2 mm over 6 moves, each episode begins with
    the run's own final-evaluation episode (until 1 cm, 4 moves), move for move."""
    cfg = agents.load_policy(runs["planet"]).config
    assert evaluate_cli.main([str(runs["planet"]), "--success-tol", "0.002", "--success-worst-tol", "0.005",
                              "--max-steps", "6", "--no-gif"]) == 0
    assert "at 2 mm (5 mm worst node)" in capsys.readouterr().out
    res = json.loads((runs["planet"] / f"evaluate-random-s{cfg.run.eval_seed}-tol2mm-worst5mm" / "results.json")
                     .read_text())
    assert (res["success_tol"], res["success_worst_tol"], res["max_steps"]) == (0.002, 0.005, 6)
    own = json.loads((runs["planet"] / "results.json").read_text())["episodes"]
    for mine, theirs in zip(res["episodes"], own, strict=True):
        assert mine["success"] == (mine["final_error"] < 0.002 and mine["worst_errors"][-1] < 0.005)
        assert mine["success"] or mine["steps"] == 6
        assert mine["steps"] >= theirs["steps"]
        assert mine["errors"][:len(theirs["errors"])] == pytest.approx(theirs["errors"], abs=1e-6)


def test_tolerance_ladder_is_exact_at_every_rung_and_agrees_with_the_runs_own_success(runs, tmp_path, capsys):
    from benchmarks.compare.stats import success_move
    from benchmarks.studies import tolerance_ladder
    assert tolerance_ladder.group_of(Path("runs/compare/pets/precise/random/seed3")) == \
        ("runs/compare/pets/precise/random", "seed3")
    out = tmp_path / "ladder"
    assert tolerance_ladder.main([str(runs["planet"]), "--until", "0.002", "--out", str(out)]) == 0
    assert "< 2 mm" in capsys.readouterr().out
    (row,) = json.loads((out / "results.json").read_text())["rows"]
    assert [r["tol"] for r in row["ladder"]] == [0.02, 0.01, 0.005, 0.002]
    assert not any(r["lower_bound"] for r in row["ladder"])
    (evaluation,) = out.glob("*/run/results.json")
    assert json.loads(evaluation.read_text())["success_tol"] == 0.002
    own = json.loads((runs["planet"] / "results.json").read_text())["episodes"]     # ran until 1 cm: exact there
    at_1cm = next(r for r in row["ladder"] if r["tol"] == 0.01)
    assert at_1cm["success"] == np.mean([success_move(e["errors"], None, 0.01) is not None for e in own])
    assert tolerance_ladder.main([str(runs["planet"]), "--out", str(out)]) == 2       # kept without --overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert "--until must be a positive number [m], got -1.0" in cli_error(
        tolerance_ladder.main, [str(runs["planet"]), "--until", "-1", "--out", str(tmp_path / "x")], capsys)


# ---------------------------------------------------------------- benchmarks.studies.model_error (issue 50)
@pytest.mark.parametrize("name", ["planet", "planet-latent"])
def test_model_error_study_records_every_move_and_a_perfect_predictor_misses_nothing(name, runs):
    from benchmarks.studies import model_error
    from diffdlo.planar.simulator import Simulator
    res = model_error.closed_loop_moves(runs[name], episodes=3, seed=5)
    task = agents.load_policy(runs[name]).config.task
    tol = res["success_tol"]
    assert tol == 0.01 and res["success_worst_tol"] is None           # the env's defaults: Table 2.1's 1 cm
    per_episode = [sum(m["episode"] == i for m in res["moves"]) for i in range(3)]
    assert all(1 <= n <= task.max_steps for n in per_episode)
    for i, n in enumerate(per_episode):          # an episode stops at its first success, or at max_steps
        errors = [m["error_after"] for m in res["moves"] if m["episode"] == i]
        assert all(e >= tol for e in errors[:-1]) and (errors[-1] < tol or n == task.max_steps)
    assert all(0 < m["miss_mean"] <= m["miss_worst"] for m in res["moves"])     # a learned model is never exact
    assert sum(r["moves"] for r in res["buckets"]) == len(res["moves"])
    # the simulator as the predictor: the moves are predicted exactly, so the bookkeeping is right
    sim = Simulator(task.cable_params(), dtype=torch.float64)
    exact = model_error.closed_loop_moves(runs[name], episodes=3, seed=5,
                                          predict=lambda rope, node, drag, pegs, pin: sim.move(rope.double(), node,
                                                                                               drag.double()))
    assert [m["error_before"] for m in exact["moves"]] == [m["error_before"] for m in res["moves"]]
    assert max(m["miss_worst"] for m in exact["moves"]) < 1e-5
    assert all(abs(m["predicted_error_after"] - m["error_after"]) < 1e-5 for m in exact["moves"])


def test_model_error_study_refuses_a_run_without_a_model_of_node_positions(runs, capsys):
    from benchmarks.studies import model_error
    err = cli_error(model_error.main, [str(runs["sac"]), "--episodes", "2"], capsys)
    assert str(runs["sac"]) in err and "sac" in err
    err = cli_error(model_error.main, [str(runs["planet-rssm"])], capsys)
    assert "'rssm'" in err
    assert "--episodes must be at least 1, got 0" in cli_error(model_error.main, [str(runs["planet"]), "--episodes", "0"],
                                                               capsys)
