"""The ensemble world model (agents/models/ensemble.py): its symmetries hold in the simulator, it learns, its k-step error
and planning cost are what they claim, and PlaNet with it resumes exactly and solves a tiny task."""
import dataclasses
import json

import pytest
import torch

from agents import planet
from agents.common.checkpoints import CHECKPOINT
from agents.common.config import load_config
from agents.common.logs import read_csv
from agents.models.ensemble import EnsembleDynamics, ModelObjective, k_step_errors
from diffdlo.planar.params import load_params
from diffdlo.tasks.rewards import shape_error
from diffdlo.planar.simulator import Simulator
from diffdlo.tasks.task import decode_node_action, encode_node_action

PO = dict(n_nodes=6, length=0.15, max_speed=1.0, settle_max_substeps=30, settle_check_every=10)
TINY = "param_overrides={n_nodes: 6, length: 0.15, max_speed: 1.0, settle_max_substeps: 30, settle_check_every: 10}"


pytestmark = pytest.mark.usefixtures("one_thread")


def tiny_params():
    return dataclasses.replace(load_params("cable"), **PO)


def random_ropes(p, b, seed=0):
    g = torch.Generator().manual_seed(seed)
    turn = 0.6 * torch.randn(b, p.n_nodes - 1, generator=g, dtype=torch.float64).cumsum(1)
    links = torch.stack([turn.cos(), turn.sin()], -1) * (p.length / (p.n_nodes - 1))
    pos = torch.cat([torch.zeros(b, 1, 2, dtype=torch.float64), links.cumsum(1)], 1)
    node = torch.randint(p.n_nodes, (b,), generator=g)
    drag = (torch.rand(b, 2, generator=g, dtype=torch.float64) * 2 - 1) * p.action_scale
    return pos + torch.rand(b, 1, 2, generator=g, dtype=torch.float64), node, drag


@pytest.mark.parametrize("augment", [["rotate"], ["mirror"], ["reverse"], ["rotate", "mirror", "reverse"]])
def test_augmentations_are_symmetries_of_the_simulator(augment):
    """Transforming a recorded move gives the move the simulator makes from the transformed start: the augmented
    chunks are true data, not an approximation."""
    p = tiny_params()
    sim = Simulator(p, dtype=torch.float64)
    model = EnsembleDynamics(p, members=1, hidden=[8], augment=augment).double()
    pos, node, drag = random_ropes(p, 8)
    nxt = sim.move(pos, node, drag)
    torch.manual_seed(3)
    rope, n2, d2 = model.transform(torch.stack([pos, nxt], 1), node[:, None], drag[:, None])[:3]
    assert not torch.allclose(rope[:, 0], pos)                          # the transform did something
    again = sim.move(rope[:, 0].contiguous(), n2[:, 0], d2[:, 0].contiguous())
    assert (again - rope[:, 1]).norm(dim=-1).max() < 1e-6               # [m]: far below the 1 cm task tolerance


def test_transform_is_off_in_eval_mode_and_keeps_shapes():
    p = tiny_params()
    model = EnsembleDynamics(p, members=2, hidden=[8])
    pos, node, drag = random_ropes(p, 4)
    chunk = torch.stack([pos, pos], 1).float()
    model.eval()
    r, n, d = model.transform(chunk, node[:, None], drag[:, None].float())[:3]
    assert r is chunk and torch.equal(n, node[:, None])
    model.train()
    r, n, d = model.transform(chunk, node[:, None].expand(4, 3), drag[:, None].float().expand(4, 3, 2))[:3]
    assert r.shape == chunk.shape and n.shape == (4, 3) and d.shape == (4, 3, 2)


def test_members_are_independent_networks_and_the_ensemble_learns():
    """Each member fits its own slice of the batch; a few hundred steps on a fixed set of moves cut the one-step error
    well below "nothing moves"."""
    p = tiny_params()
    sim = Simulator(p)
    pos, node, drag = random_ropes(p, 64, seed=1)
    pos, drag = pos.float(), drag.float()
    nxt = sim.move(pos, node, drag)
    action = encode_node_action(node, drag, p.n_nodes, p.action_scale)
    model = EnsembleDynamics(p, members=2, hidden=[64, 64], augment=[])
    out = model(pos, node, drag)
    assert out.shape == (2, 64, 6, 2) and not torch.allclose(out[0], out[1])
    obs = {"node_poses": torch.stack([pos, nxt], 1).repeat(2, 1, 1, 1)}
    acts = action[:, None].repeat(2, 1, 1)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    torch.manual_seed(0)
    first = model.loss(obs, acts)
    for _ in range(300):
        L = model.loss(obs, acts)
        opt.zero_grad()
        L["loss"].backward()
        opt.step()
    base = float((nxt - pos).norm(dim=-1).mean()) * 100
    assert float(L["err_cm"]) < 0.3 * base and float(L["err_cm"]) < 0.5 * float(first["err_cm"])
    with pytest.raises(ValueError, match="split evenly"):
        model.loss({"node_poses": obs["node_poses"][:3]}, acts[:3])


def zero_model(p, members=2):
    """A model that predicts "nothing moves" exactly (last layer zero)."""
    model = EnsembleDynamics(p, members=members, hidden=[8])
    with torch.no_grad():
        model.weights[-1].zero_()
        model.biases[-1].zero_()
    return model


def test_k_step_errors_on_a_hand_checked_case():
    p = tiny_params()
    sim = Simulator(p)
    pos, node, drag = random_ropes(p, 5, seed=2)
    pos, drag = pos.float(), drag.float()
    a = encode_node_action(node, drag, p.n_nodes, p.action_scale)
    one = sim.move(pos, node, drag)
    two = sim.move(one, node, -drag)
    true = torch.stack([one, two], 1)
    acts = torch.stack([a, encode_node_action(node, -drag, p.n_nodes, p.action_scale)], 1)
    r = k_step_errors(zero_model(p), pos, acts, true, (1, 2))
    assert r["pred_err_1"] == pytest.approx(r["base_err_1"]) and r["pred_err_2"] == pytest.approx(r["base_err_2"])
    assert r["base_err_1"] == pytest.approx(float((one - pos).norm(dim=-1).mean()), rel=1e-5)
    alive = torch.tensor([True, False, False, False, False])
    r1 = k_step_errors(zero_model(p), pos, acts, true, (1,), alive)
    assert r1["base_err_1"] == pytest.approx(float((one[0] - pos[0]).norm(dim=-1).mean()), rel=1e-5)


@pytest.mark.parametrize("propagation", ["members", "mean"])
def test_model_objective_is_the_planners_cost(propagation):
    """Through a model that predicts "nothing moves", every candidate costs (1 + w) x the current shape error; the
    cost has one row per rope and one column per candidate."""
    p = tiny_params()
    ropes, _, _ = random_ropes(p, 3, seed=4)
    targets, _, _ = random_ropes(p, 3, seed=5)
    obj = ModelObjective(zero_model(p), ropes.float(), targets.float(), running_weight=0.5, propagation=propagation)
    cost = obj(torch.rand(3, 7, 2, 3))
    want = 1.5 * shape_error(ropes.float(), targets.float())
    assert cost.shape == (3, 7)
    assert torch.allclose(cost, want[:, None].expand(3, 7), rtol=1e-5)
    with pytest.raises(ValueError, match="propagation"):
        ModelObjective(zero_model(p), ropes, targets, propagation="nope")


def test_the_risk_adds_the_members_spread_of_the_cost():
    """risk r: each candidate costs the members' mean cost plus r x their standard deviation (hand-computed from
    each member's rollout); risk 0 is the plain mean; a bad risk, or one with nothing to spread, is refused."""
    p = tiny_params()
    torch.manual_seed(0)
    model = EnsembleDynamics(p, members=3, hidden=[8]).eval()
    ropes, _, _ = random_ropes(p, 2, seed=4)
    targets, _, _ = random_ropes(p, 2, seed=5)
    actions = torch.rand(2, 5, 2, 3, generator=torch.Generator().manual_seed(1))
    node, drag = decode_node_action(actions, p)
    per_member = []
    for e in range(3):
        pos = ropes.float()[:, None].expand(2, 5, p.n_nodes, 2).reshape(10, p.n_nodes, 2)
        errs = []
        for t in range(2):
            pos = model(pos, node.reshape(10, 2)[:, t], drag.reshape(10, 2, 2)[:, t])[e]
            errs.append(shape_error(pos, targets.float()[:, None].expand(2, 5, p.n_nodes, 2).reshape(10, -1, 2)))
        per_member.append(errs[1] + 0.5 * errs[0])                # the last error + w x the mean intermediate one
    per_member = torch.stack(per_member).view(3, 2, 5)
    for risk in (0.0, 1.5):
        cost = ModelObjective(model, ropes.float(), targets.float(), 0.5, "members", risk=risk)(actions)
        want = per_member.mean(0) + risk * per_member.std(0)
        assert torch.allclose(cost, want, rtol=1e-4, atol=1e-7), (risk, cost, want)
    assert not torch.allclose(per_member.std(0), torch.zeros(2, 5))          # the members differ: risk matters
    for kwargs, message in (({"risk": -1.0}, "risk must be a number >= 0"),
                            ({"risk": 1.0, "propagation": "mean"}, "needs propagation 'members'")):
        with pytest.raises(ValueError, match=message):
            ModelObjective(model, ropes, targets, **kwargs)
    with pytest.raises(ValueError, match="no members to spread"):
        ModelObjective(zero_model(p, members=1), ropes, targets, risk=1.0)
    with pytest.raises(ValueError, match="model 'latent' has no members"):
        load_config(planet.PlaNetConfig, "planet-latent", {"risk": 1.0})


def argv(out, total, *extra):
    return ["--out", str(out), "--total-steps", str(total), "--num-envs", "4", "--set", TINY, "--max-steps", "8",
            "--eval-every", "64", "--eval-episodes", "4", "--checkpoint-every", "64", "--no-progress",
            "--set", "members=2", "--set", "model_hidden=[16,16]", "--set", "horizon=2", "--set", "candidates=12",
            "--set", "elites=3", "--set", "iterations=2", "--set", "seed_episodes=4", "--set", "train_every=32",
            "--set", "updates_per_train=4", "--set", "batch_size=8", "--set", "log_every=2",
            "--set", "openloop_episodes=4", "--set", "openloop_context=2", *extra]


def test_ensemble_planet_resume_equals_uninterrupted(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert planet.main(argv(a, 128)) == 0
    assert planet.main(argv(b, 64)) == 0
    assert planet.main(["--out", str(b), "--resume", "--total-steps", "128", "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv", "openloop.csv"):
        assert (a / name).read_text() == (b / name).read_text(), name
    ra, rb = json.loads((a / "results.json").read_text()), json.loads((b / "results.json").read_text())
    assert ra["episodes"] == rb["episodes"] and rb["env_steps"] == 128
    row = read_csv(a / "openloop.csv")[-1]
    assert {"pred_err_1", "base_err_1", "pred_err_2", "pred_err_10"} <= set(row)
    assert "err_cm" in read_csv(a / "train.csv")[-1]
    assert ra["plan_ms_per_step"] > 0 and (a / CHECKPOINT).exists()


def test_heldout_targets_are_evaluated_after_training(tmp_path):
    assert planet.main(argv(tmp_path, 64, "--set", "eval_targets=[horizontal, vertical]")) == 0
    held = json.loads((tmp_path / "results.json").read_text())["heldout"]
    assert set(held) == {"horizontal", "vertical"} and len(held["vertical"]["episodes"]) == 4


def test_ensemble_needs_points_and_node_actions(tmp_path):
    with pytest.raises(ValueError, match="needs obs 'points'"):
        load_config(planet.PlaNetConfig, "planet", {"obs": "image"})
    with pytest.raises(ValueError, match="augment"):
        load_config(planet.PlaNetConfig, "planet", {"augment": ["shear"]})
    with pytest.raises(ValueError, match="propagation"):
        load_config(planet.PlaNetConfig, "planet", {"propagation": "ts9"})


def test_tiny_task_is_solved_by_planning_through_the_learned_model(tmp_path):
    """A 6-node rope, the diagonal target, 8 moves: after 640 env steps PlaNet (ensemble) succeeds in most
    evaluation episodes (measured: 8/8 in about 4 moves); planning through the untrained model (lr 1e-12) succeeds
    in none."""
    extra = ["--target", "diagonal", "--set", "seed_episodes=20", "--set", "model_hidden=[64,64]",
             "--set", "updates_per_train=40", "--set", "batch_size=32", "--set", "candidates=64",
             "--set", "elites=8", "--set", "iterations=3", "--eval-every", "640",
             "--eval-episodes", "8", "--checkpoint-every", "640"]
    assert planet.main(argv(tmp_path, 640, *extra)) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["success_rate"] >= 0.75, res["success_rate"]
    from benchmarks.studies import planet_budget
    budget = tmp_path / "budget"
    assert planet_budget.main(["--run", str(tmp_path), "--out", str(budget), "--candidates", "64", "8",
                               "--iterations", "3", "--propagations", "members", "mean", "--episodes", "4"]) == 0
    rows = json.loads((budget / "results.json").read_text())["rows"]
    assert [(r["candidates"], r["propagation"]) for r in rows] == [(64, "members"), (64, "mean"), (8, "members"),
                                                                   (8, "mean")]
    assert all(0 <= r["success_rate"] <= 1 and r["plan_ms_per_env_step"] > 0 for r in rows)
    with pytest.raises(SystemExit):                       # never replaces a result without --overwrite
        planet_budget.main(["--run", str(tmp_path), "--out", str(budget)])
    own = tmp_path / "own"                                # no budget given: the run's own
    assert planet_budget.main(["--run", str(tmp_path), "--out", str(own), "--episodes", "2"]) == 0
    row = json.loads((own / "results.json").read_text())["rows"][0]
    assert (row["horizon"], row["candidates"], row["iterations"], row["propagation"]) == (2, 64, 3, "members")
    held = tmp_path / "held"
    assert planet_budget.main(["--run", str(tmp_path), "--out", str(held), "--targets", "horizontal", "random",
                               "--candidates", "16", "--iterations", "1", "--episodes", "2"]) == 0
    assert [r["target"] for r in json.loads((held / "results.json").read_text())["rows"]] == ["horizontal", "random"]
    with pytest.raises(SystemExit):
        planet_budget.main(["--run", str(tmp_path), "--out", str(tmp_path / "x"), "--targets", "no_such_shape"])
