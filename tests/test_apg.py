"""agents.apg: the policy gradient through the simulator against finite differences, the node's gradient, a tiny task
learned, bad input named, exact resume, the trained policy loaded."""
import dataclasses
import json

import numpy as np
import pytest
import torch

import diffdlo
from diffdlo.envs import BatchedShapeControl
from agents import apg
from agents.common.config import load_config
from agents.common.logs import read_csv

PO = dict(n_nodes=6, length=0.15, max_speed=1.0, settle_max_substeps=30, settle_check_every=10)
TINY = "param_overrides={n_nodes: 6, length: 0.15, max_speed: 1.0, settle_max_substeps: 30, settle_check_every: 10}"


@pytest.fixture
def p():
    return dataclasses.replace(diffdlo.load_params(), **PO)


def ropes(p, batch, seed=0, dtype=torch.float64):
    sim = diffdlo.Simulator(p, dtype=dtype)
    start = sim.settle(sim.random_shape(batch, torch.Generator().manual_seed(seed)))
    target = sim.target_shape("horizontal").expand(batch, -1, -1)
    return sim, start, target


class LinearPolicy(torch.nn.Module):
    """A float64 stand-in for the actor: drag = tanh(W x + b) from the rope's target-relative offsets."""

    def __init__(self, n):
        super().__init__()
        self.lin = torch.nn.Linear(2 * n, 2, dtype=torch.float64)
        torch.nn.init.normal_(self.lin.weight, std=0.5)

    def forward(self, pos, target):
        diff = (pos - pos.mean(1, keepdim=True)) - (target - target.mean(1, keepdim=True))
        return torch.tanh(self.lin(diff.flatten(1) / 0.15))


@pytest.mark.parametrize("horizon", [1, 2])
def test_policy_gradient_through_moves_matches_finite_differences(p, horizon):
    """d J / d theta, J the summed shape_gain of H chained moves whose drags come from the policy (the later move's
    observation depends on the earlier move), through the kernel's adjoint in float64: central differences agree."""
    sim, start, target = ropes(p, 3)
    assert sim.engine == "kernel"
    torch.manual_seed(0)
    pol = LinearPolicy(p.n_nodes)
    node = torch.tensor([5, 0, 2])

    def J():
        pos, total = start, 0.0
        for _ in range(horizon):
            _, pos_new, r = apg.move_graph(sim, p, pos, target, node, pol(pos, target), "shape_gain")
            pos, total = pos_new, total + r.sum()
        return total

    pol.zero_grad()
    J().backward()
    params = [pol.lin.weight, pol.lin.bias]
    analytic = torch.cat([x.grad.flatten() for x in params])
    numeric = []
    with torch.no_grad():
        for x in params:
            flat = x.view(-1)
            for i in range(flat.numel()):
                keep = flat[i].item()
                flat[i] = keep + 1e-6
                up = float(J())
                flat[i] = keep - 1e-6
                down = float(J())
                flat[i] = keep
                numeric.append((up - down) / 2e-6)
    numeric = torch.tensor(numeric, dtype=torch.float64)
    assert analytic.abs().max() > 1e-2                              # a gradient worth checking
    assert torch.allclose(analytic, numeric, rtol=1e-4, atol=1e-6), (analytic, numeric)


def test_the_graph_move_is_the_env_move(p):
    """The differentiable move decodes the action as the env does: the same rope, bit for bit (float32)."""
    env = BatchedShapeControl(4, target="horizontal", params=p, reward="shape_gain")
    env.reset(seed=3)
    s = env.get_state(generators=False)
    drag = torch.tensor([[0.3, -0.7], [1.0, 0.2], [-0.5, -0.5], [0.0, 0.9]]).requires_grad_(True)
    node = torch.tensor([0, 5, 2, 3])
    action, new, r = apg.move_graph(env.sim, p, s.pos, s.target, node, drag, "shape_gain")
    _, reward, *_ = env.step(action.detach())
    assert torch.equal(env.get_state(generators=False).pos, new.detach())
    assert torch.equal(reward, r.detach())


def test_the_node_score_function_gives_a_descent_direction(p):
    """Node "score": the estimator (sampled nodes, pathwise drag gradient + REINFORCE with a batch-mean baseline,
    normalized as in training) is finite, non-zero and points downhill on the exact expected loss, computed by
    moving every node: F(theta) = -mean_s sum_k pi(k|s) r(s, k, d_k(s))."""
    torch.manual_seed(0)
    cfg = load_config(apg.APGConfig, "apg", dict(param_overrides=PO, node="score", hidden=[32], ent_coef=0.0))
    sim, start, target = ropes(p, 4, seed=1, dtype=torch.float32)
    obs = apg.graph_obs("points", start, target)
    actor = apg.Actor(obs, cfg, p.length, p.n_nodes)
    actor.net.feat(obs, update_norm=True)
    n, reps = p.n_nodes, 64
    params = [x for x in actor.parameters()]

    def exact():
        log_pk, drags = actor.dist(obs)
        b = len(start)
        node = torch.arange(n).repeat(b)
        rows = torch.arange(b).repeat_interleave(n)
        _, _, r = apg.move_graph(sim, p, start[rows], target[rows], node, drags[rows, node], "shape_gain")
        return -(log_pk.exp() * r.view(b, n)).sum(1).mean()

    F0 = exact()
    g_exact = torch.autograd.grad(F0, params)
    pos, tgt = start.repeat(reps, 1, 1), target.repeat(reps, 1, 1)
    o = apg.graph_obs("points", pos, tgt)
    log_pk, drags = actor.dist(o)
    node = actor.choose(o, log_pk, deterministic=False)
    rows = torch.arange(len(pos))
    _, _, r = apg.move_graph(sim, p, pos, tgt, node, drags[rows, node], "shape_gain")
    adv = r.detach().view(1, -1)
    adv = adv - adv.mean(1, keepdim=True)
    path_loss, node_loss = apg.actor_losses(r.view(1, -1), log_pk[rows, node].view(1, -1),
                                            -(log_pk.exp() * log_pk).sum(-1).view(1, -1), adv, cfg)
    g_path = torch.autograd.grad(path_loss, params, retain_graph=True, allow_unused=True)
    g_node = torch.autograd.grad(node_loss, params, allow_unused=True)
    flat = lambda gs: torch.cat([(g if g is not None else torch.zeros_like(x)).flatten() for g, x in zip(gs, params)])
    ge, gp, gn = flat(g_exact), flat(g_path), flat(g_node)
    for g in (gp, gn):
        assert torch.isfinite(g).all() and g.norm() > 0
    est = gp + gn * (gp.norm() / gn.norm())                     # each part's direction, equally weighted
    assert torch.dot(gn, ge) > 0 and torch.dot(gp, ge) > 0 and torch.dot(est, ge) > 0
    with torch.no_grad():
        for x, g in zip(params, torch.split(est, [x.numel() for x in params])):
            x -= 1e-3 * g.view_as(x) / est.norm()
    assert exact() < F0


def easy(tmp_path, p):
    """One good move solves it: the target straight, its end node dragged 10 cm sideways; tolerance 2 cm."""
    sim = diffdlo.Simulator(p)
    start = sim.move(sim.target_shape("horizontal")[None], torch.tensor([5]), torch.tensor([[0.0, 0.1]]))[0]
    np.save(tmp_path / "start.npy", start.numpy())
    return dict(target="horizontal", start=str(tmp_path / "start.npy"), param_overrides=PO, max_steps=3,
                success_tol=0.02, num_envs=8, eval_episodes=8, checkpoint_every=10**9, hidden=[64, 64])


def test_a_tiny_task_learns_in_a_few_updates(tmp_path, p):
    """The one-move task: the error left after the first move falls clearly within 40 updates of 8 ropes."""
    cfg = load_config(apg.APGConfig, "apg", dict(easy(tmp_path, p), node="greedy", total_steps=320, eval_every=320,
                                                 lr=3e-3))
    res = apg.train(cfg, tmp_path / "run", progress=False)
    rows = read_csv(tmp_path / "run" / "train.csv")
    objective = [float(r["objective"]) for r in rows]
    first, last = np.mean(objective[:5]), np.mean(objective[-5:])
    assert last > first + 1.0, (first, last)                    # cm removed per move: up by more than 1 cm
    assert all(float(r["grad_norm"]) > 0 for r in rows)
    assert res["success_rate"] == 1.0 and res["mean_length"] == 1.0
    assert res["env_steps"] == 320 and res["sim_backward"] == 320 and res["n_updates"] == 40


def argv(out, total, *extra):
    return ["--out", str(out), "--total-steps", str(total), "--num-envs", "8", "--set", TINY, "--max-steps", "8",
            "--eval-every", "128", "--eval-episodes", "8", "--checkpoint-every", "128", "--set", "hidden=[32,32]",
            "--no-progress", *extra]


@pytest.mark.parametrize("bad,message", [(["--set", "node=softmax"], "unknown node 'softmax'"),
                                         (["--set", "horizon=0"], "horizon"),
                                         (["--set", "objective=speed"], "unknown objective"),
                                         (["--set", "max_grad_norm=-1"], "max_grad_norm"),
                                         (["--obs", "image", "--set", "features=raw", "--set", "normalize_obs=false"],
                                          "needs obs"),
                                         (["--action", "pixel"], "needs action 'node'"),
                                         (["--set", "critic=maybe"], "critic must be true or false")])
def test_bad_cli_values_are_named(bad, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        apg.main(argv(tmp_path, 64, *bad))
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("extra", [[], ["--set", "node=score", "--set", "critic=true", "--set", "horizon=2",
                                         "--set", "max_grad_norm=0.05"],
                                   ["--set", "node=gain", "--set", "gain_replay=0"]])
def test_a_killed_run_resumes_exactly(extra, tmp_path, monkeypatch):
    """Killed right after its checkpoint at 128 of 256 steps, resumed: every CSV row and the results equal the
    uninterrupted run's (lr schedule, normalizer, critic, sampled nodes)."""
    a, b = tmp_path / "a", tmp_path / "b"
    assert apg.main(argv(a, 256, *extra)) == 0
    from agents.common import run as run_module
    real_save = run_module.save_checkpoint

    def save_then_die(path, state):
        real_save(path, state)
        if state["step"] >= 128:
            raise KeyboardInterrupt

    monkeypatch.setattr(run_module, "save_checkpoint", save_then_die)
    assert apg.main(argv(b, 256, *extra)) == 130     # reported as a shell reports Ctrl-C, not a traceback
    monkeypatch.setattr(run_module, "save_checkpoint", real_save)
    assert apg.main(["--out", str(b), "--resume", "--total-steps", "256", "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv"):
        assert (a / name).read_text() == (b / name).read_text(), name
    ra, rb = (json.loads((d / "results.json").read_text()) for d in (a, b))
    assert ra["episodes"] == rb["episodes"] and ra["sim_backward"] == rb["sim_backward"] == 256
    assert rb["env_steps"] == 256
    rows = read_csv(a / "train.csv")
    if "max_grad_norm=0.05" in extra:                 # clipping is a setting, and every update says whether it clipped
        assert any(r["clipped"] == "1.0" for r in rows)
        assert rb["clipped_updates"] == sum(float(r["clipped"]) for r in rows)
        assert all(float(r["grad_norm_node"]) > 0 and float(r["critic_loss"]) >= 0 for r in rows)
    else:
        assert rb["clipped_updates"] == 0 and all(r["clipped"] == "0.0" for r in rows)


def test_load_policy_acts_as_the_run_evaluated(tmp_path):
    from agents import load_policy
    from agents.common.evaluation import evaluate
    out = tmp_path / "run"
    assert apg.main(argv(out, 64)) == 0
    pol = load_policy(out)
    env = pol.make_env()
    res = evaluate(pol.batched(env), env, 8, seed=pol.config.run.eval_seed)
    saved = json.loads((out / "results.json").read_text())["episodes"]
    assert [e["final_error"] for e in res["episodes"]] == pytest.approx([e["final_error"] for e in saved])
    obs, _ = __import__("gymnasium").make("DiffDLO/ShapeControl-v0", **pol.env_kwargs()).reset(seed=0)
    assert pol(obs).shape == (3,)


def test_the_comparison_grid_runs_apg_tuned_and_its_ablations(tmp_path):
    from benchmarks import compare
    cells = compare.build_cells(compare.load_grid(), tmp_path, methods=["apg"], targets=["random"], seeds=[0])
    by = {c["variant"]: c["argv"] for c in cells}
    assert set(by) == {"tuned", "h4", "h4_critic", "score", "greedy"}
    assert all(a[:2] == ["-m", "agents.apg"] and a[a.index("--total-steps") + 1] == "5000" for a in by.values())
    assert "horizon=4" in by["h4"] and {"horizon=4", "critic=True"} <= set(by["h4_critic"])
    assert "node=score" in by["score"] and "node=greedy" in by["greedy"]


def test_the_gain_node_head_learns_which_node_to_move(tmp_path, p):
    """Node "gain": G(s, k) regresses the reward of the node moved (its loss falls), and on the one-move task the
    argmax node it learns is the displaced end (node 5), so the evaluation solves it in one move."""
    torch.manual_seed(0)
    for replay in (0, 640):                                     # online regression, and replayed minibatches
        cfg = load_config(apg.APGConfig, "apg", dict(easy(tmp_path, p), node="gain", total_steps=640,
                                                     eval_every=640, lr=3e-3, gain_explore=1.0, gain_replay=replay))
        res = apg.train(cfg, tmp_path / f"run{replay}", progress=False)
        loss = [float(r["gain_loss"]) for r in read_csv(tmp_path / f"run{replay}" / "train.csv")][1:]
        assert np.isfinite(loss).all()
        if replay == 0:                                         # the same samples' error, before and after
            assert np.mean(loss[-10:]) < 0.25 * np.mean(loss[:10]), (loss[:10], loss[-10:])
        assert res["success_rate"] == 1.0 and res["mean_length"] == 1.0, replay
