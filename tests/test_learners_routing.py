"""The learners among pegs (issue 60): the pegs in each learner's features and world model, the grasp frame carrying
the pegs, the second gripper in PPO's head and the ensemble, exact resume on routes, and the refusals."""
import dataclasses
import json
import math

import pytest
import torch

from agents import apg, planet, ppo, sac
from agents.common.config import load_config
from agents.common.logs import read_csv
from agents.models import hybrid
from agents.models.ensemble import EnsembleDynamics, ModelObjective, k_step_errors, peg_clearance
from agents.models.networks import Features
from agents.common.config import InputOptions
from benchmarks import compare
from tests.conftest import cli_error
from diffdlo.planar import contact
from diffdlo.envs import BatchedShapeControl
from diffdlo.planar.params import load_params
from diffdlo.planar.simulator import Simulator
from diffdlo.tasks.task import decode_pin, encode_node_action, encode_pin

PO = dict(n_nodes=6, length=0.15, max_speed=1.0, settle_max_substeps=30, settle_check_every=10)
TINY = "param_overrides={n_nodes: 6, length: 0.15, max_speed: 1.0, settle_max_substeps: 30, settle_check_every: 10}"

pytestmark = pytest.mark.usefixtures("one_thread")


def tiny_params():
    return dataclasses.replace(load_params("cable"), **PO)


def straight_route(p, dtype=torch.float64):
    x = torch.linspace(-p.length / 2, p.length / 2, p.n_nodes, dtype=dtype)
    return torch.stack([x, torch.zeros_like(x)], -1)


# ====================================================================== features
def test_route_features_carry_the_pegs_and_the_side_the_rope_passes_them():
    """4N + 2 + 4K numbers: rope - route on the board (not centred), the pegs from the centroid with their radii, and
    each peg's side gap, ~0 where the rope passes a peg as the route does and ~ +-1 where it passes on the other
    side; an empty slot is all zeros."""
    p = tiny_params()
    route = straight_route(p)
    pegs = torch.tensor([[0.0, 0.02, 0.01], [0.0, 0.0, 0.0]], dtype=torch.float64)   # above the route; one empty slot
    over = route + torch.tensor([0.0, 0.045])                                          # the route's shape, above it
    obs = {"node_poses": torch.stack([route, over]).float(), "target_poses": torch.stack([route, route]).float(),
           "pegs": torch.stack([pegs, pegs]).float()}
    f = hybrid.relative_features(obs, p.length)
    n, k = p.n_nodes, 2
    assert f.shape == (2, 4 * n + 2 + 4 * k)
    gap = f[:, -k:]
    assert abs(float(gap[0, 0])) < 1e-6 and abs(abs(float(gap[1, 0])) - 1.0) < 0.2
    assert torch.all(f[:, -k - 1] == 0) and torch.all(f[:, -2 * k - 1] == 0)           # the empty slot's radius, x
    diff = f[:, : 2 * n].view(2, n, 2) * p.length
    assert torch.allclose(diff[1], torch.tensor([0.0, 0.045]).expand(n, 2), atol=1e-6)  # on the board, not centred
    radius = f[:, -2 * k:-k] * p.length
    assert torch.allclose(radius[:, 0], torch.tensor(0.01))
    moved = dict(obs, pegs=obs["pegs"] + torch.tensor([0.03, 0.0, 0.0]))               # a peg moved: features change
    assert not torch.allclose(hybrid.relative_features(moved, p.length), f)


def test_every_model_free_learner_sees_the_pegs_of_a_route_observation():
    env = BatchedShapeControl(num_envs=2, target="route", reward="route_gain", params=tiny_params())
    obs, _ = env.reset(seed=0)
    feats = Features(obs, InputOptions(features="relative"), 0.15)
    without = {k: v for k, v in obs.items() if k != "pegs"}
    assert feats.out_dim == Features(without, InputOptions(features="relative"), 0.15).out_dim + 4 * env.max_pegs
    raw = Features(obs, InputOptions(features="raw"), 0.15)                               # SB3's encoder: flattened
    assert raw.out_dim == 2 * 2 * 6 + 3 * env.max_pegs


# ====================================================================== the second gripper in PPO's head
def test_ppo_pin_head_samples_scores_and_decodes_to_the_env_pin():
    torch.manual_seed(0)
    b, n = 64, 6
    d = ppo.HybridDist(torch.randn(b, n), torch.randn(b, n, 2), torch.tensor([0.5, 0.5]), torch.randn(b, n, n + 1))
    a = d.sample()
    assert a.shape == (b, 4)
    node, choice = a[:, 0].long(), a[:, 3].long()
    # log-prob = log Cat(k) + log N(d) + log Cat(c | k)
    lp = (d.cat.log_prob(node) + torch.distributions.Normal(d.mean[torch.arange(b), node], 0.5).log_prob(a[:, 1:3]).sum(-1)
          + torch.log_softmax(d.pin_logits[torch.arange(b), node], -1)[torch.arange(b), choice])
    assert torch.allclose(d.log_prob(a), lp, atol=1e-5)
    env_a = hybrid.to_env_pin_action(node, a[:, 1:3], choice, n)
    pin = decode_pin(env_a[:, 3], node, n)
    want = torch.where(choice - 1 == node, -1, choice - 1)            # the grasped node held is no pin (the env's rule)
    assert torch.equal(pin, want)
    assert torch.allclose(env_a[:, 3], encode_pin(choice - 1, n))
    # the entropy adds E_k H(pin | k): larger than without the pin
    no_pin = ppo.HybridDist(d.cat.logits, d.mean, d.std)
    assert torch.all(d.entropy() > no_pin.entropy())
    with pytest.raises(ValueError, match="pin choices must lie in"):
        hybrid.to_env_pin_action(node, a[:, 1:3], choice + n + 1, n)


@pytest.mark.parametrize("module, name, message", [
    (sac, "sac", "second gripper's choice is PPO's hybrid head only"),
    (apg, "apg", "it needs action 'node'"),
])
def test_node_pin_is_refused_by_the_learners_without_a_pin_head(module, name, message):
    cfg_cls = {"sac": sac.SACConfig, "apg": apg.APGConfig}[name]
    with pytest.raises(ValueError, match=message):
        load_config(cfg_cls, name, {"target": "route", "reward": "route_gain", "action": "node_pin"})


@pytest.mark.parametrize("kind", ["keypoints", "vector"])
def test_the_latent_world_model_carries_the_pegs_in_its_frame(kind):
    """The latent model among pegs: a rotated and shifted scene (rope, drag, pegs) is predicted rotated and shifted
    (untrained: by construction), the pegs and the pin reach the prediction, and its loss trains on chunks with
    pegs and pins."""
    from agents.models.latent import LatentWorldModel
    p = tiny_params()
    torch.manual_seed(0)
    model = LatentWorldModel(p, latent=16, hidden=[32], augment=[], kind=kind, max_pegs=2, pin=True).double()
    pos, node, drag, pegs, pin = board(p, 8)
    node2, drag2, pin2 = node[:, None].repeat(1, 2), drag[:, None].repeat(1, 2, 1), pin[:, None].repeat(1, 2)
    pred = model.predict(pos, node2, drag2, pegs, pin2)
    shift = torch.tensor([0.3, -0.2], dtype=torch.float64)
    moved = torch.cat([rotate(pegs[..., :2], 0.7, shift), pegs[..., 2:]], -1)
    moved[..., :2] = torch.where(pegs[..., 2:] > 0, moved[..., :2], 0.0)
    pred2 = model.predict(rotate(pos, 0.7, shift), node2, rotate(drag2, 0.7), moved, pin2)
    assert (pred2 - rotate(pred, 0.7, shift)).abs().max() < 1e-9
    nudged = pegs.clone()
    nudged[:, 0, 0] += 0.01
    assert (model.predict(pos, node2, drag2, nudged, pin2) - pred).abs().max() > 1e-7
    assert (model.predict(pos, node2, drag2, pegs, torch.full_like(pin2, -1)) - pred).abs().max() > 1e-7
    with pytest.raises(ValueError, match="takes 2 peg slots"):
        model.predict(pos, node2, drag2, None, pin2)
    act = torch.cat([encode_node_action(node, drag / p.action_scale, p.n_nodes, 1.0),
                     encode_pin(pin, p.n_nodes, torch.float64)[:, None]], -1)[:, None]
    obs = {"node_poses": torch.stack([pos, pred[:, 0]], 1), "pegs": torch.stack([pegs, pegs], 1)}
    model.train()
    out = model.loss(obs, act)
    out["loss"].backward()
    assert torch.isfinite(out["loss"]) and model.dynamics[0].weight.grad.abs().sum() > 0


# ====================================================================== the ensemble among pegs
def board(p, b, seed=0):
    """Ropes near pegs, grasped nodes, drags, pegs (two slots, one empty in half the rows), pins."""
    g = torch.Generator().manual_seed(seed)
    turn = 0.4 * torch.randn(b, p.n_nodes - 1, generator=g, dtype=torch.float64).cumsum(1)
    links = torch.stack([turn.cos(), turn.sin()], -1) * (p.length / (p.n_nodes - 1))
    pos = torch.cat([torch.zeros(b, 1, 2, dtype=torch.float64), links.cumsum(1)], 1)
    node = torch.randint(p.n_nodes, (b,), generator=g)
    drag = (torch.rand(b, 2, generator=g, dtype=torch.float64) * 2 - 1) * p.action_scale
    # a peg 1.2 cm to the side of a middle node (clear of the rope, in reach of the drag), a second far or empty
    mid = pos[:, p.n_nodes // 2]
    normal = torch.stack([-links[:, p.n_nodes // 2 - 1, 1], links[:, p.n_nodes // 2 - 1, 0]], -1)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    c1 = mid + 0.018 * normal
    pegs = torch.zeros(b, 2, 3, dtype=torch.float64)
    pegs[:, 0, :2], pegs[:, 0, 2] = c1, 0.008
    pegs[::2, 1] = torch.tensor([0.5, 0.5, 0.01], dtype=torch.float64)
    pin = torch.randint(-1, p.n_nodes, (b,), generator=g)
    pin = torch.where(pin == node, -1, pin)
    return pos, node, drag, pegs, pin


def rotate(v, angle, shift=None):
    c, s = math.cos(angle), math.sin(angle)
    out = torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)
    return out if shift is None else out + shift


def test_the_grasp_frame_carries_the_pegs_so_the_prediction_is_equivariant():
    """A rotated and shifted scene (rope, drag and pegs together) is predicted rotated and shifted, by an untrained
    model: the symmetry is built in, not learned; the pegs reach the prediction (moving one changes it)."""
    p = tiny_params()
    torch.manual_seed(0)
    model = EnsembleDynamics(p, members=2, hidden=[32], augment=[], max_pegs=2, pin=True).double()
    pos, node, drag, pegs, pin = board(p, 8)
    pred = model(pos, node, drag, pegs, pin)
    shift = torch.tensor([0.3, -0.2], dtype=torch.float64)
    moved = torch.cat([rotate(pegs[..., :2], 0.7, shift), pegs[..., 2:]], -1)
    moved[..., :2] = torch.where(pegs[..., 2:] > 0, moved[..., :2], 0.0)                  # an empty slot stays zeros
    pred2 = model(rotate(pos, 0.7, shift), node, rotate(drag, 0.7), moved, pin)
    assert (pred2 - rotate(pred, 0.7, shift)).abs().max() < 1e-10
    nudged = pegs.clone()
    nudged[:, 0, 0] += 0.01
    assert (model(pos, node, drag, nudged, pin) - pred).abs().max() > 1e-6
    other_pin = torch.where(pin >= 0, -1, (node + 1) % p.n_nodes)
    assert (model(pos, node, drag, pegs, other_pin) - pred).abs().max() > 1e-6
    with pytest.raises(ValueError, match="takes 2 peg slots"):
        model(pos, node, drag, None, pin)
    with pytest.raises(ValueError, match="built without pegs"):
        EnsembleDynamics(p, members=1, hidden=[8]).double()(pos, node, drag, pegs)


@pytest.mark.parametrize("augment", [["rotate"], ["mirror"], ["reverse"], ["rotate", "mirror", "reverse"]])
def test_augmentations_with_pegs_and_pin_are_symmetries_of_the_simulator(augment):
    """A recorded move among pegs with a held node, transformed (the pegs turned with the rope, the held node
    renumbered), is the move the simulator makes from the transformed start."""
    p = tiny_params()
    sim = Simulator(p, dtype=torch.float64)
    model = EnsembleDynamics(p, members=1, hidden=[8], augment=augment, max_pegs=2, pin=True).double()
    pos, node, drag, pegs, pin = board(p, 8, seed=1)
    far = torch.where(pegs[..., 2:] > 0, pegs, torch.tensor([1e3, 1e3, 1e-3], dtype=torch.float64))
    nxt = sim.move(pos, node, drag, far, pin)
    assert (nxt - sim.move(pos, node, drag)).norm(dim=-1).max() > 1e-3      # the pegs and the pin change the move
    torch.manual_seed(3)
    rope, n2, d2, pg2, pin2 = model.transform(torch.stack([pos, nxt], 1), node[:, None], drag[:, None],
                                              torch.stack([pegs, pegs], 1), pin[:, None])
    assert not torch.allclose(rope[:, 0], pos)
    far2 = torch.where(pg2[:, 0, :, 2:] > 0, pg2[:, 0], torch.tensor([1e3, 1e3, 1e-3], dtype=torch.float64))
    again = sim.move(rope[:, 0].contiguous(), n2[:, 0], d2[:, 0].contiguous(), far2.contiguous(), pin2[:, 0])
    assert (again - rope[:, 1]).norm(dim=-1).max() < 1e-6


def test_model_objective_scores_each_rope_on_its_own_board_and_the_error_is_split_near_pegs():
    """The planning cost among pegs is the routing planners' (the error on the board + SIDE_COST per peg on the wrong
    side); k_step_errors splits the open-loop error by the distance to the nearest peg."""
    from planners.objective import route_cost
    p = tiny_params()
    model = EnsembleDynamics(p, members=2, hidden=[16], augment=[], max_pegs=2, pin=True).eval()
    pos, node, drag, pegs, pin = board(p, 3)
    route = pos.float() + torch.tensor([0.0, 0.03])
    obj = ModelObjective(model, pos.float(), route, running_weight=0.0, propagation="mean", pegs=pegs.float())
    act = torch.cat([encode_node_action(node, drag.float() / p.action_scale, p.n_nodes, 1.0),
                     encode_pin(pin, p.n_nodes)[:, None]], -1)
    cost = obj(act[:, None, None])
    with torch.no_grad():
        nxt = model(pos.float(), node, drag.float(), pegs.float(), pin).mean(0)
    want = torch.stack([route_cost(nxt[i], route[i], pegs[i].float()) for i in range(3)])
    assert torch.allclose(cost.flatten(), want, atol=1e-5)
    true = nxt[:, None]
    ks = k_step_errors(model, pos.float(), act[:, None], true, (1,), pegs=pegs.float())
    assert ks["pred_err_1"] < 1e-5
    clear = peg_clearance(true[:, 0], pegs.float())
    assert clear.shape == (3, p.n_nodes) and torch.isfinite(clear).all()
    assert "pred_err_near_1" in ks and "pred_err_far_1" in ks


# ====================================================================== runs on routes
def run_argv(out, total, *extra):
    # the cable's own params: the tiny 6-node rope's coarse substeps can end a move deeper in a peg than its radius,
    # which the next move refuses
    return ["--out", str(out), "--total-steps", str(total), "--num-envs", "8", "--max-steps", "8",
            "--target", "route", "--set", "reward=route_gain", "--eval-every", "128", "--eval-episodes", "4",
            "--checkpoint-every", "128", "--set", "log_every=1", "--no-progress", *extra]


PPO_SMALL = ["--set", "hidden=[32,32]", "--set", "n_steps=16", "--set", "n_epochs=2", "--set", "batch_size=32",
             "--set", "anneal_lr=false", "--set", "action=node_pin"]


def test_ppo_with_the_pin_on_routes_resumes_exactly_and_records_the_side_test(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    few = ["--num-envs", "4", "--eval-every", "64", "--checkpoint-every", "64"]      # two rollouts of 16 x 4
    assert ppo.main(run_argv(a, 128, *PPO_SMALL, *few)) == 0
    assert ppo.main(run_argv(b, 64, *PPO_SMALL, *few)) == 0
    assert ppo.main(["--out", str(b), "--resume", "--total-steps", "128", "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv", "rollout.csv"):
        assert (a / name).read_text() == (b / name).read_text(), name
    ra, rb = json.loads((a / "results.json").read_text()), json.loads((b / "results.json").read_text())
    assert ra["episodes"] == rb["episodes"] and ra["action"] == "node_pin"
    assert ra["shapes"]["pegs"] == ra["episodes"][0]["pegs"]          # the gallery draws the first episode's board
    for e in ra["episodes"]:                       # each episode keeps its board and the side test
        assert isinstance(e["sides_kept"], bool) and 2 <= len(e["pegs"]) <= 4 and len(e["pegs"][0]) == 3
        assert not e["success"] or e["sides_kept"]


def test_the_ensemble_world_model_runs_on_routes_and_its_error_is_split_near_pegs(tmp_path):
    """PlaNet with the ensemble among pegs and the pin (exact resume: the free rope's in tests/test_dynamics.py, with
    pegs PPO's above): the open-loop error and the model-error study split near and far from pegs, the latter exact
    with the simulator as the predictor."""
    small = ["--set", "members=2", "--set", "model_hidden=[32]", "--set", "batch_size=16", "--set", "seed_episodes=4",
             "--set", "train_every=32", "--set", "updates_per_train=4", "--set", "candidates=16",
             "--set", "elites=4", "--set", "iterations=2", "--set", "openloop_episodes=4", "--set", "action=node_pin"]
    a = tmp_path / "a"
    assert planet.main(run_argv(a, 96, *small, "--eval-every", "96", "--checkpoint-every", "96")) == 0
    rows = read_csv(a / "openloop.csv")
    assert "pred_err_near_1" in rows[0] and "pred_err_far_1" in rows[0]
    ra = json.loads((a / "results.json").read_text())
    assert all(isinstance(e["sides_kept"], bool) for e in ra["episodes"])
    # the model-error study among pegs: the model predicts with the board and the pin; the simulator as the
    # predictor (with the same pegs and pin) misses nothing, so its bookkeeping on the board is right
    from benchmarks.studies import model_error
    res = model_error.closed_loop_moves(a, episodes=2, seed=5)
    split = res["near_pegs"]
    assert split is not None and split["moves_near"] + split["moves_far"] >= len(res["moves"])
    sim = Simulator(load_params("cable"), dtype=torch.float64)
    exact = model_error.closed_loop_moves(
        a, episodes=2, seed=5,
        predict=lambda rope, node, drag, pegs, pin: sim.move(rope.double(), node, drag.double(),
                                                             pegs.double(), pin))
    assert max(m["miss_worst"] for m in exact["moves"]) < 1e-4
    assert [m["error_before"] for m in exact["moves"]] == [m["error_before"] for m in res["moves"]]
    # planning with the predictions moved out of the pegs (benchmarks.studies.planet_budget --project-pegs)
    from benchmarks.studies import planet_budget
    assert planet_budget.main(["--run", str(a), "--out", str(tmp_path / "pb"), "--project-pegs", "0", "1",
                               "--episodes", "2", "--candidates", "8", "--iterations", "1"]) == 0
    res_pb = json.loads((tmp_path / "pb" / "results.json").read_text())
    pb = res_pb["rows"]
    assert [r["project_pegs"] for r in pb] == [False, True] and all(len(r["episodes"]) == 2 for r in pb)
    # each run's results carry its seed and each episode its start (what --pool pairs by); the two rows share them
    assert res_pb["seed"] == 0                                  # the run's (RunOptions' default)
    assert [e["start_error"] for e in pb[0]["episodes"]] == [e["start_error"] for e in pb[1]["episodes"]]
    pos, node, drag, pegs, pin = board(load_params("cable"), 4)
    inside = lambda rope, node, drag, pegs=None, pin=None: rope.expand(3, *rope.shape).clone()   # noqa: E731
    deep = pos.clone()
    deep[:, 10] = pegs[:, 0, :2]                              # a node at a peg's centre
    out = planet_budget.projected(inside, 0.005)(deep, node, drag, pegs)
    assert out.shape == (3, 4, *pos.shape[1:])
    assert float(contact.depth(out.reshape(-1, *pos.shape[1:]), pegs.repeat(3, 1, 1), 0.005).max()) <= 1e-3


def test_apg_among_pegs_moves_the_rope_with_the_pegs(tmp_path):
    """APG's differentiable move runs among the route's pegs: its rope is the env's (the same decoded action)."""
    p = tiny_params()
    env = BatchedShapeControl(num_envs=4, target="route", reward="route_gain", params=p, dtype=torch.float64)
    env.reset(seed=2)
    s = env.get_state()
    node = torch.tensor([0, 2, 3, 5])
    drag = torch.full((4, 2), 0.9, dtype=torch.float64)
    action, new, r = apg.move_graph(env.sim, p, s.pos, s.target, node, drag, "route_gain", pegs=s.pegs)
    env.step(action)
    assert torch.allclose(new, env.get_state().pos, atol=1e-9)
    free = apg.move_graph(env.sim, p, s.pos, s.target, node, drag, "route_gain")[1]
    assert r.shape == (4,) and torch.isfinite(r).all()
    obs = apg.graph_obs("points", s.pos, s.target, s.pegs)
    assert torch.equal(obs["pegs"], s.pegs.float())
    # a route's greedy node is the farthest from its place ON THE BOARD (no centroid alignment)
    far = (s.pos - s.target).norm(dim=-1).argmax(-1)
    assert torch.equal(apg.greedy_node(obs), far)
    del free


@pytest.mark.slow
def test_a_tiny_world_model_run_learns_to_route_a_u(tmp_path):
    """The PETS-style model among pegs from 1,200 env steps (10 random episodes, then planning through it) lays the
    rope round the two pegs of u_two_pegs (start beside the board, at most 40 moves) in most of 8 episodes, where
    random moves never do. Run with: pytest -m slow tests/test_learners_routing.py (minutes)."""
    out = tmp_path / "u"
    assert planet.main(["--out", str(out), "--total-steps", "1200", "--num-envs", "8", "--max-steps", "40",
                        "--target", "route:u_two_pegs", "--set", "reward=route_gain", "--set", "seed_episodes=10",
                        "--eval-every", "1200", "--eval-episodes", "8", "--checkpoint-every", "1200",
                        "--no-progress"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["success_rate"] >= 0.75, res["success_rate"]
    assert all(e["sides_kept"] for e in res["episodes"] if e["success"])


def test_the_budget_study_pools_seeds_and_pairs_them_with_the_committed_cells(tmp_path, capsys):
    """planet_budget --pool: a row pooled over the seeds' results and paired, episode by episode, with a grid row's
    committed cells of the same seed and task: two moves more on every episode reads +2.0 moves; an episode whose
    start differs is left out as mismatched; a record without start errors pairs by index, unverified."""
    from benchmarks.compare.records import read_records, record_key
    from benchmarks.studies import planet_budget
    by = {record_key(r): r for r in read_records()}
    budget = dict(horizon=1, candidates=300, iterations=3, propagation="members", project_pegs=False)
    timed = lambda seed: dict(budget, plan_ms_per_env_step=10.0 * (seed + 1))       # noqa: E731
    files = []
    for seed in (0, 1):
        eps = [dict(e, steps=e["steps"] + 2) for e in by[("cem", "route", "route_hook_wrap", seed)]["episodes"]]
        eps[0]["start_error"] += 0.01                                             # another start shape
        row = dict(timed(seed), target="route:hook_wrap", episodes=eps)
        files.append(tmp_path / f"s{seed}.json")
        files[-1].write_text(json.dumps({"seed": seed, "rows": [row]}))
    rows = planet_budget.pooled_pairs(planet_budget.load_pooled([str(f) for f in files]), ["cem/route"],
                                      read_records(), compare.load_grid())
    assert len(rows) == 1 and rows[0]["task"] == "route_hook_wrap" and rows[0]["seeds"] == 2
    assert rows[0]["plan_ms_per_env_step"] == pytest.approx(15.0)                  # the seeds' mean
    p = rows[0]["paired"]["cem/route"]
    assert (p["pairs"], p["mismatched"], p["unverified"]) == (38, 2, 0)
    assert p["dm"] and all(d == 2.0 for d in p["dm"]) and all(d == 0.0 for d in p["ds"])
    # the record form docs/results/ keeps: {"runs": {"seed<N>": results}}, here without start errors
    bare = {f"seed{s}": {"rows": [dict(timed(s), target="route:hook_wrap",
                                       episodes=[{k: e[k] for k in ("success", "steps", "final_error")}
                                                 for e in by[("cem", "route", "route_hook_wrap", s)]["episodes"]])]}
            for s in (0, 1)}
    (tmp_path / "record.json").write_text(json.dumps({"runs": bare}))
    assert planet_budget.main(["--pool", str(tmp_path / "record.json"), "--pair", "cem/route"]) == 0
    out = capsys.readouterr().out
    assert "route_hook_wrap: H=1 candidates=300 iterations=3 members, 2 seeds x 20" in out
    assert "moves +0.0 [+0.0, +0.0]" in out and "pairs 40 (40 unverifiable)" in out and "plan 15 ms" in out
    for argv, message in ((["--pool", str(files[0]), str(files[0])], "seed 0's row {'target': 'route:hook_wrap', "
                                                                     "'horizon': 1, 'candidates': 300, 'iterations': 3, "
                                                                     "'propagation': 'members', 'project_pegs': False, "
                                                                     "'risk': 0.0} is given twice"),
                          (["--pool", str(files[0]), "--pair", "cem/no_such_row"], "no grid row"),
                          (["--pool", str(tmp_path / "missing.json")], "not a readable results file"),
                          (["--pool", str(files[0]), "--run", str(tmp_path)], "without --run and --out"),
                          (["--run", str(tmp_path), "--out", str(tmp_path / "o"), "--pair", "cem/route"],
                           "--pair goes with --pool"),
                          (["--run", str(tmp_path), "--out", str(tmp_path / "o"), "--risks", "1", "-0.5"],
                           "--risks must be >= 0, got [-0.5]")):
        assert message in cli_error(planet_budget.main, argv, capsys)
    (tmp_path / "bad.json").write_text(json.dumps({"runs": {"seedX": {"rows": []}}}))
    assert "neither this study's results.json" in cli_error(planet_budget.main, ["--pool", str(tmp_path / "bad.json")],
                                                             capsys)
    (tmp_path / "s9.json").write_text(json.dumps({"seed": 99, "rows": [dict(timed(0), target="route", episodes=bare["seed0"]["rows"][0]["episodes"])]}))
    assert "no committed cell of cem/route on route seed 99" in cli_error(
        planet_budget.main, ["--pool", str(tmp_path / "s9.json"), "--pair", "cem/route"], capsys)
