"""Precision: the worst node's error beside the mean, a worst-node tolerance for the task (off by default), both
recorded after every move of a planner's and a learner's episode, kept by the comparison's records, and an episode's
success at another tolerance read back from them."""
import math

import gymnasium as gym
import numpy as np
import pytest
import torch

import diffdlo
from agents import sac
from agents.common.config import load_config
from agents.common.evaluation import episode_records, evaluate
from benchmarks.compare.records import _episode, as_results, floor_error, make_record
from benchmarks.compare.stats import row_stats, success_move
from diffdlo.tasks import task
from diffdlo.envs import BatchedShapeControl, EnvOptions
from planners import greedy
from planners.common import build_run, run_episode
from planners.greedy import GreedyPlanner
from tests.conftest import cli_error

pytestmark = pytest.mark.usefixtures("one_thread")

ZERO_DRAG = [0.0, 0.5, 0.5]          # node 0, no drag: a straight rope at rest stays where it is

# ---------------------------------------------------------------------- the worst node's error
TARGET3 = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]], dtype=torch.float64)
ROPE3 = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.3]]], dtype=torch.float64)


def test_worst_node_error_against_a_hand_computed_rope():
    # centroids (1, 0.1) and (1, 0): centred rope (-1, -0.1), (0, -0.1), (1, 0.2) against (-1, 0), (0, 0), (1, 0):
    # node distances 0.1, 0.1, 0.2 -> mean 0.4 / 3, worst 0.2
    torch.testing.assert_close(diffdlo.node_errors(ROPE3, TARGET3),
                               torch.tensor([[0.1, 0.1, 0.2]], dtype=torch.float64))
    assert diffdlo.shape_error(ROPE3, TARGET3).item() == pytest.approx(0.4 / 3, abs=1e-12)
    assert diffdlo.worst_node_error(ROPE3, TARGET3).item() == pytest.approx(0.2, abs=1e-12)
    assert diffdlo.worst_node_error(ROPE3, TARGET3[0]).item() == pytest.approx(0.2, abs=1e-12)   # (N, 2) target
    # a rigid shift of the target is no error, for either figure
    shifted = TARGET3 + torch.tensor([0.3, -0.7], dtype=torch.float64)
    assert diffdlo.worst_node_error(shifted, TARGET3).item() == pytest.approx(0.0, abs=1e-12)
    assert diffdlo.shape_error(shifted, TARGET3).item() == pytest.approx(0.0, abs=1e-12)


def test_worst_is_never_below_the_mean_and_equals_it_when_every_node_is_as_far(small):
    gen = torch.Generator().manual_seed(0)
    ropes = diffdlo.random_shape(64, small, gen, dtype=torch.float64)
    target = diffdlo.target_shape("diagonal", small).double()
    mean, worst = diffdlo.shape_error(ropes, target), diffdlo.worst_node_error(ropes, target)
    assert (worst >= mean).all() and (worst > mean + 1e-3).any()
    # a two-node rope against its reversal: both nodes are equally far from their places, so worst == mean
    two = torch.tensor([[[0.0, 0.0], [0.1, 0.0]]], dtype=torch.float64)
    flipped = two.flip(1)
    assert diffdlo.worst_node_error(flipped, two).item() == pytest.approx(diffdlo.shape_error(flipped, two).item())
    assert diffdlo.worst_node_error(flipped, two).item() == pytest.approx(0.1)
    # the mean is the old formula, bit for bit (default behaviour unchanged)
    a = ropes - ropes.mean(-2, keepdim=True)
    b = target - target.mean(-2, keepdim=True)
    assert torch.equal(diffdlo.shape_error(ropes, target), (a - b).norm(dim=-1).mean(-1))


def test_within_tolerance_on_tensors_and_floats():
    mean, worst = torch.tensor([0.005, 0.005, 0.012]), torch.tensor([0.008, 0.015, 0.02])
    assert diffdlo.within_tolerance(mean, worst, 0.01).tolist() == [True, True, False]
    assert diffdlo.within_tolerance(mean, worst, 0.01, 0.01).tolist() == [True, False, False]
    assert diffdlo.within_tolerance(0.005, None, 0.01) is True        # no worst tolerance: the worst is not read
    assert diffdlo.within_tolerance(0.005, 0.012, 0.01, 0.01) is False
    assert bool(diffdlo.is_success(ROPE3, TARGET3, tol=0.2)) and not bool(diffdlo.is_success(ROPE3, TARGET3, 0.2, 0.2))
    assert bool(diffdlo.is_success(ROPE3, TARGET3, 0.2, 0.21))


def test_task_metrics_report_the_worst_node_error():
    m = task.task_metrics(ROPE3, TARGET3, 0.2)
    assert m["worst_node_error"].item() == pytest.approx(0.2) and bool(m["is_success"][0])
    m = task.task_metrics(ROPE3, TARGET3, 0.2, 0.15)
    assert m["shape_error"].item() == pytest.approx(0.4 / 3) and not bool(m["is_success"][0])


# ---------------------------------------------------------------------- the env's success test
def hooked_target(p):
    """A straight target whose last link is turned by ~35 degrees: its last node is 0.018 m off the straight line, so
    a straight rope is about 5 mm from it on the mean and 15 mm at its worst node."""
    straight = diffdlo.target_shape("horizontal", p).double()
    link = straight[-1] - straight[-2]
    turn = 2 * math.asin(0.018 / 2 / float(link.norm()))
    c, s = math.cos(turn), math.sin(turn)
    bent = straight.clone()
    bent[-1] = straight[-2] + torch.stack([c * link[0] - s * link[1], s * link[0] + c * link[1]])
    return straight, bent


@pytest.mark.parametrize("worst_tol,succeeds", [(None, True), (0.01, False), (0.02, True)])
def test_env_succeeds_only_when_the_mean_and_the_worst_node_are_within(small, worst_tol, succeeds):
    straight, target = hooked_target(small)
    env = BatchedShapeControl(1, target="horizontal", params=small, dtype=torch.float64, success_worst_tol=worst_tol,
                              max_steps=5)
    env.reset(seed=0)
    env.set_state(pos=straight[None], target=target, steps=0)
    info = env.info()
    assert 0.004 < float(info["shape_error"][0]) < 0.006 and 0.014 < float(info["worst_node_error"][0]) < 0.016
    assert bool(info["is_success"][0]) == succeeds                         # the figures after set_state
    _, r, term, trunc, info = env.step(torch.tensor([ZERO_DRAG], dtype=torch.float64))
    assert float(info["shape_error"][0]) < small.success_tol               # the mean passes in every case
    assert bool(info["is_success"][0]) == succeeds and bool(term[0]) == succeeds and not bool(trunc[0])
    assert (float(r[0]) == small.success_bonus) == succeeds
    assert float(info["worst_node_error"][0]) == pytest.approx(
        float(diffdlo.worst_node_error(env.get_state().pos, target)[0]), abs=1e-12)


def test_step_outcome_reads_the_worst_tolerance():
    rope, target = ROPE3 / 10, TARGET3 / 10                  # inside the workspace: mean 1.33 cm, worst 2 cm
    rules = EnvOptions(target="horizontal", success_tol=0.02, success_worst_tol=0.015, max_steps=9).resolve()
    r, term, trunc, success = task.step_outcome(rules, rope, rope, target, torch.tensor([1]))
    assert not bool(success[0]) and not bool(term[0]) and not bool(trunc[0]) and float(r[0]) != rules.success_bonus
    loose = EnvOptions(target="horizontal", success_tol=0.02, max_steps=9).resolve()
    assert loose.success_worst_tol is None
    r, term, trunc, success = task.step_outcome(loose, rope, rope, target, torch.tensor([1]))
    assert bool(success[0]) and bool(term[0]) and float(r[0]) == loose.success_bonus


def test_gym_env_reports_the_worst_node_error(small):
    env = gym.make("DiffDLO/ShapeControl-v0", params=small, target="diagonal", success_worst_tol=0.02)
    _, info = env.reset(seed=0)
    assert info["worst_node_error"] >= info["shape_error"] > 0
    _, _, _, _, info = env.step(np.array(ZERO_DRAG, dtype=np.float32))
    assert info["worst_node_error"] >= info["shape_error"] > 0
    assert env.unwrapped.core.options.success_worst_tol == 0.02


def test_a_state_saved_before_the_worst_error_was_reported_loads(small):
    env = BatchedShapeControl(2, target="diagonal", params=small)
    env.reset(seed=1)
    old = env.get_state()
    want = old.info.pop("worst_node_error")              # as an older checkpoint holds it
    env.reset(seed=5)
    env.set_state(old)
    torch.testing.assert_close(env.info()["worst_node_error"], want)
    env.step(torch.tensor([ZERO_DRAG, ZERO_DRAG]))       # and steps on


# ---------------------------------------------------------------------- bad tolerances are refused, named
BAD = [(-0.01, "-0.01"), (0.0, "0.0"), (math.nan, "nan"), (math.inf, "inf")]


@pytest.mark.parametrize("name", ["success_tol", "success_worst_tol"])
@pytest.mark.parametrize("value,shown", BAD, ids=[s for _, s in BAD])
def test_env_options_and_gym_make_refuse_a_bad_tolerance(name, value, shown, small):
    with pytest.raises(ValueError, match=rf"{name} must be a positive finite number \[m\].*, got {shown}"):
        EnvOptions(**{name: value})
    with pytest.raises(ValueError, match=rf"{name} must be a positive finite number \[m\].*, got {shown}"):
        gym.make("DiffDLO/ShapeControl-v0", params=small, **{name: value})


def test_env_options_take_a_worst_tolerance_and_none(small):
    assert EnvOptions(success_worst_tol=0.005).resolve().success_worst_tol == 0.005
    assert EnvOptions(success_worst_tol=None).resolve().success_worst_tol is None
    assert EnvOptions().resolve().success_tol == 0.01                              # Table 2.1's 1 cm stays
    with pytest.raises(ValueError, match="success_worst_tol must be a positive finite number .m. or None, got '1cm'"):
        EnvOptions(success_worst_tol="1cm")


@pytest.mark.parametrize("flag", ["--success-tol", "--success-worst-tol"])
@pytest.mark.parametrize("value,shown", [("-0.01", "-0.01"), ("0", "0.0"), ("nan", "nan"), ("inf", "inf")])
def test_planner_cli_refuses_a_bad_tolerance(flag, value, shown, tmp_path, capsys):
    err = cli_error(greedy.main, ["--out", str(tmp_path / "run"), "--quiet", "--no-gif", flag, value], capsys)
    assert f"{flag} must be in (0, inf), got {shown}" in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("name", ["success_tol", "success_worst_tol"])
@pytest.mark.parametrize("value,shown", [("-0.01", "-0.01"), ("0", "0"), (".nan", "nan"), (".inf", "inf")])
def test_learner_config_and_cli_refuse_a_bad_tolerance(name, value, shown, tmp_path, capsys):
    import yaml
    with pytest.raises(ValueError, match=rf"{name} must be in \(0, inf\), got {shown}"):
        load_config(sac.SACConfig, "sac", {name: yaml.safe_load(value)}).check()
    err = cli_error(sac.main, ["--out", str(tmp_path / "run"), "--no-progress", "--set", f"{name}={value}"], capsys)
    assert f"{name} must be in (0, inf), got {shown}" in err, err
    assert not (tmp_path / "run").exists()


def test_learner_config_carries_the_worst_tolerance_to_its_env():
    cfg = load_config(sac.SACConfig, "sac", {"success_worst_tol": 0.004})
    assert cfg.task.env_options().resolve().success_worst_tol == 0.004
    assert load_config(sac.SACConfig, "sac", {}).task.env_options().success_worst_tol is None


# ---------------------------------------------------------------------- the episodes record both errors per move
def test_planner_episode_records_the_mean_and_worst_error_after_every_move(small):
    env, planner, _ = build_run(GreedyPlanner, small, small, "diagonal", max_steps=3, success_tol=None, device="cpu",
                                seed=0, options={}, success_worst_tol=0.003)
    assert env.options.success_worst_tol == 0.003
    ep = run_episode(env, planner, seed=4, progress=False)
    n = ep["steps"] + 1
    assert ep["steps"] >= 1 and len(ep["errors"]) == len(ep["worst_errors"]) == len(ep["frames"]) == n
    want = diffdlo.worst_node_error(ep["frames"].double(), ep["target_points"].double())
    np.testing.assert_allclose(ep["worst_errors"], want.numpy(), rtol=0, atol=1e-6)
    assert all(w > m for m, w in zip(ep["errors"], ep["worst_errors"]))
    assert ep["errors"][0] == ep["start_error"] and ep["errors"][-1] == ep["final_error"]
    assert ep["success"] == diffdlo.within_tolerance(ep["errors"][-1], ep["worst_errors"][-1], 0.01, 0.003)


def test_planner_cli_writes_worst_errors(tmp_path, capsys):
    out = tmp_path / "g"
    assert greedy.main(["--target", "diagonal", "--max-steps", "2", "--episodes", "2", "--out", str(out), "--quiet",
                        "--no-gif", "--success-worst-tol", "0.02"]) == 0
    import json
    r = json.loads((out / "results.json").read_text())
    assert r["config"]["success_worst_tol"] == 0.02
    for ep in r["episodes"]:
        assert len(ep["worst_errors"]) == len(ep["errors"]) == ep["steps"] + 1


def test_learner_evaluation_records_the_mean_and_worst_error_after_every_move(small):
    env = BatchedShapeControl(3, target="random", params=small, max_steps=3)
    gen = torch.Generator().manual_seed(0)

    def policy(obs, deterministic):
        return torch.rand(3, 3, generator=gen)

    res = evaluate(policy, env, 5, seed=7)                       # two waves of three ropes
    eps = res["episodes"]
    assert len(eps) == 5
    for i, e in enumerate(eps):
        assert len(e["errors"]) == len(e["worst_errors"]) == e["steps"] + 1, e
        assert e["errors"][0] == pytest.approx(e["start_error"]) and e["errors"][-1] == pytest.approx(e["final_error"])
        assert all(w >= m for m, w in zip(e["errors"], e["worst_errors"]))
        assert e["worst_errors"][-1] == pytest.approx(
            float(diffdlo.worst_node_error(res["ropes"][i], res["targets"][i])), abs=1e-6)
    kept = episode_records(eps)
    assert kept[0]["worst_errors"] == eps[0]["worst_errors"] and "return" not in kept[0]
    old = [{k: v for k, v in e.items() if k not in ("errors", "worst_errors")} for e in eps]
    assert episode_records(old)[0] == {k: old[0][k] for k in ("success", "steps", "final_error", "start_error",
                                                              "target_name")}   # a checkpoint's older evaluation


# ---------------------------------------------------------------------- the comparison's records
CELL = {"method": "greedy", "variant": "default", "target": "diagonal", "seed": 0, "kind": "planner",
        "argv": ["-m", "planners.greedy", "--target", "diagonal"]}


def planner_results(with_worst: bool) -> dict:
    eps = [{"success": True, "steps": 2, "final_error": 0.00999999977648, "start_error": 0.05,
            "target_name": "diagonal", "errors": [0.05, 0.0150000006, 0.00999999977648],
            "worst_errors": [0.09, 0.03, 0.0181234567]},
           {"success": False, "steps": 3, "final_error": 0.012, "start_error": 0.04, "target_name": "diagonal",
            "errors": [0.04, 0.03, 0.02, 0.012], "worst_errors": [0.07, 0.05, 0.04, 0.03]}]
    if not with_worst:
        for e in eps:
            del e["worst_errors"]
    return {"episodes": eps, "env_steps": 5, "wall_s": 1.0, "sim_evals": 0, "plan_s_per_step": 0.01}


def test_records_keep_both_errors_rounded_down_and_old_records_summarise_as_before():
    rec = make_record(CELL, planner_results(True), {})
    ep = rec["episodes"][0]
    assert ep["errors"] == [0.05, 0.015, 0.00999] and ep["worst_errors"] == [0.09, 0.03, 0.01812]
    old = make_record(CELL, planner_results(False), {})
    assert "worst_errors" not in old["episodes"][0] and old["episodes"][0]["errors"] == ep["errors"]
    assert repr(row_stats([as_results(old)])) == repr(row_stats([as_results(rec)]))     # nan != nan: by repr
    st = row_stats([as_results(old)])
    assert st["s1"][0] == 0.5 and st["moves"] == (2.0, 1) and st["moves2"] == pytest.approx(2.0)   # under 2 cm at 1, 3
    assert _episode({"success": True, "steps": 0, "final_error": 0.1}) == {"success": True, "steps": 0,
                                                                           "final_error": 0.1}


def test_rounding_down_keeps_every_10_micrometre_tolerance_exact():
    rng = np.random.default_rng(0)
    for tol in (0.02, 0.01, 0.005, 0.002):
        near = tol + rng.normal(0, 1e-7, 2000)
        xs = np.concatenate([near, near.astype(np.float32), [tol, np.nextafter(tol, 0), np.nextafter(tol, 1)]])
        assert [floor_error(x) < tol for x in xs] == [x < tol for x in xs]
        assert all(0 <= x - floor_error(x) < 1e-5 + 1e-15 for x in xs)
    assert floor_error(0.0123456) == 0.01234 and floor_error(0.01) == 0.01


def test_success_move_at_other_tolerances():
    errors = [0.05, 0.021, 0.015, 0.009, 0.004]
    worst = [0.09, 0.05, 0.025, 0.019, 0.006]
    assert success_move(errors, worst, 0.02) == 2 and success_move(errors, None, 0.02) == 2
    assert success_move(errors, worst, 0.01) == 3
    assert success_move(errors, worst, 0.01, 0.02) == 3
    assert success_move(errors, worst, 0.01, 0.01) == 4                 # the worst node holds it back a move
    assert success_move(errors, worst, 0.005) == 4
    assert success_move(errors, worst, 0.005, 0.005) is None            # never within both
    assert success_move(errors, worst, 0.002) is None
    assert success_move(errors, worst, 0.1) == 0                        # the start already within
    with pytest.raises(ValueError, match="worst node errors"):
        success_move(errors, None, 0.01, 0.005)
    with pytest.raises(ValueError, match="5 and 4"):
        success_move(errors, worst[:4], 0.01, 0.005)
    # a recorded episode ended at its own success: read back at its own tolerance, at its last move
    rec = make_record(CELL, planner_results(True), {})
    for e in rec["episodes"]:
        assert success_move(e["errors"], e["worst_errors"], 0.01) == (e["steps"] if e["success"] else None)
