"""Planners: objective vs env, CEM, gradient planner (finite differences), greedy, CLIs and their outputs."""
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

import diffdlo
from diffdlo.envs import BatchedShapeControl
from diffdlo.tasks.task import decode_node_action, encode_node_action
from planners import SimObjective
from planners import cem as cem_mod, gradient as grad_mod, greedy as greedy_mod
from planners.cem import CEM, CEMPlanner
from planners.gradient import GradientPlanner
from planners.greedy import GreedyPlanner


def _start(env_b=1, seed=0, target="diagonal", dtype=torch.float32):
    env = BatchedShapeControl(env_b, target=target, dtype=dtype)
    env.reset(seed=seed)
    return env


def test_objective_matches_env_steps():
    env = _start(3, seed=2)
    start, target = env.get_state().pos[0].clone(), env.get_state().target[0].clone()
    actions = torch.rand(3, 2, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    actions[0, 0, 1] = 1.3                                        # clipped like the env clips
    obj = SimObjective(env.sim, start, target)
    cost = obj(actions)
    assert obj.sim_evals == 6 and obj.calls == 2
    env.set_state(pos=start.expand(3, -1, -1), target=target, steps=0)
    for t in range(2):
        node_env, delta_env = env.decode(actions[:, t].clamp(0, 1).to(env.dtype))
        node, delta = decode_node_action(actions[:, t], env.params)
        assert torch.equal(node, node_env) and torch.allclose(delta.float(), delta_env)
        _, _, _, _, info = env.step(actions[:, t])
    torch.testing.assert_close(cost, info["shape_error"].to(cost.dtype), rtol=0, atol=1e-7)


def test_encode_decode_roundtrip(params):
    node = torch.tensor([0, 7, 19])
    delta = torch.tensor([[0.1, -0.1], [0.03, 0.0], [-0.05, 0.07]], dtype=torch.float64)
    n, d = decode_node_action(encode_node_action(node, delta, params.n_nodes, params.action_scale), params)
    assert torch.equal(n, node) and torch.allclose(d, delta)


def test_cem_generic_discrete_quadratic():
    # optimum: category 3 of 5 (a0 = 0.75) with the continuous dims at 0.2 / 0.9 -- a cheap sanity problem
    def objective(x):
        return (x[..., 0] - 0.75).abs().sum(-1) * 10 + ((x[..., 1:] - torch.tensor([0.2, 0.9], dtype=x.dtype)) ** 2
                                                        ).sum((-1, -2))
    cem = CEM(3, 2, candidates=200, elites=20, iterations=8, discrete={0: 5},
              generator=torch.Generator().manual_seed(0))
    best, cost = cem.optimize(objective)
    assert torch.allclose(best[:, 0], torch.full((2,), 0.75, dtype=best.dtype))
    assert cost < 1e-2
    bests = [h["best"] for h in cem.history]
    assert all(a >= b for a, b in zip(bests, bests[1:]))


def test_cem_state_dict_restores_the_next_optimisation_exactly():
    def objective(x):
        return ((x[..., 1:] - 0.3) ** 2).sum((-1, -2)) + x[..., 0].sum(-1)
    cem = CEM(3, 2, candidates=40, elites=5, iterations=3, discrete={0: 5}, generator=torch.Generator().manual_seed(1))
    cem.optimize(objective)
    cem.shift()
    saved = cem.state_dict()
    first, cost = cem.optimize(objective)
    other = CEM(3, 2, candidates=40, elites=5, iterations=3, discrete={0: 5},
                generator=torch.Generator().manual_seed(99))
    other.load_state_dict(saved)
    again, cost_again = other.optimize(objective)
    assert torch.equal(first, again) and cost == cost_again
    with pytest.raises(ValueError, match="horizon"):
        CEM(3, 4, candidates=40, elites=5, discrete={0: 5}).load_state_dict(saved)


def test_optimize_together_equals_each_cem_alone():
    goals = torch.tensor([[0.2, 0.7], [0.9, 0.1], [0.5, 0.5]], dtype=torch.float64)

    def one(x, g):                                   # (n, H, A) -> (n,)
        return ((x[..., 1:] - g) ** 2).sum((-1, -2)) + (x[..., 0] - g[0]).abs().sum(-1)

    def make(seed):
        return CEM(3, 2, candidates=30, elites=4, iterations=3, discrete={0: 4},
                   generator=torch.Generator().manual_seed(seed))
    alone = [make(i).optimize(lambda x, g=g: one(x, g)) for i, g in enumerate(goals)]
    calls = []

    def batched(x):                                  # (R, n, H, A) -> (R, n)
        calls.append(x.shape)
        return torch.stack([one(x[r], goals[r]) for r in range(x.shape[0])])
    together = cem_mod.optimize_together([make(i) for i in range(3)], batched)
    for (b1, c1), (b2, c2) in zip(alone, together):
        assert torch.equal(b1, b2) and c1 == c2
    assert len(calls) == 3 and calls[0][:2] == (3, 30) and calls[1][:2] == (3, 26)
    with pytest.raises(ValueError, match="one shape"):
        cem_mod.optimize_together([make(0), CEM(3, 3, candidates=30, elites=4, iterations=3)], batched)


def test_cem_improves_on_fixed_problem():
    env = _start(1, seed=3)
    obj = SimObjective(env.sim, env.get_state().pos[0], env.get_state().target[0])
    cem = CEM(3, 1, candidates=48, elites=8, iterations=4, discrete={0: env.params.n_nodes},
              generator=torch.Generator().manual_seed(0))
    best, cost = cem.optimize(obj)
    h = cem.history
    assert h[-1]["elite_mean"] < h[0]["elite_mean"] and h[-1]["best"] <= h[0]["best"]
    assert obj.sim_evals == 48 + 3 * (48 - 8)                     # elites are kept, not re-simulated
    assert abs(float(obj(best[None])) - cost) < 1e-6              # the returned cost is the plan's cost
    assert cost < float(diffdlo.shape_error(env.get_state().pos, env.get_state().target))
    cem.shift()                                                   # warm start keeps shapes
    assert cem.best.shape == (1, 3) and cem.mean.shape[0] == 1


def test_gradient_matches_finite_differences():
    env = _start(1, seed=4, dtype=torch.float64)
    obj = SimObjective(env.sim, env.get_state().pos[0], env.get_state().target[0])
    s = env.params.action_scale
    node = torch.tensor([[0], [9], [19]])
    u = torch.tensor([[0.3, -0.5], [-0.2, 0.4], [0.8, 0.1]], dtype=torch.float64, requires_grad=True)
    cost = obj.rollout_deltas(node, (s * torch.tanh(u))[:, None])
    (grad,) = torch.autograd.grad(cost.sum(), u)
    assert torch.isfinite(grad).all() and grad.abs().max() > 1e-4
    eps = 1e-6
    fd = torch.zeros_like(u)
    for j in range(2):
        e = torch.zeros_like(u)
        e[:, j] = eps
        with torch.no_grad():
            plus = obj.rollout_deltas(node, (s * torch.tanh(u + e))[:, None])
            minus = obj.rollout_deltas(node, (s * torch.tanh(u - e))[:, None])
        fd[:, j] = (plus - minus) / (2 * eps)
    torch.testing.assert_close(grad, fd, rtol=1e-3, atol=1e-6)


def test_gradient_planner_improves_and_reports_norms():
    env = _start(1, seed=3)
    planner = GradientPlanner(env.sim, iters=4, restarts=1, halvings=1)
    err0 = float(env.info()["shape_error"][0])
    a = planner.plan(env.get_state().pos[0], env.get_state().target[0])
    assert a.shape == (3,) and bool(((a >= 0) & (a <= 1)).all())
    assert planner.last["cost"] < err0 and planner.grad_norms and all(np.isfinite(planner.grad_norms))
    assert planner.sim_evals == 20 * 2 + 10 * 2                    # 20 nodes, halved once after 2 iterations
    _, _, _, _, info = env.step(a.reshape(1, 3).double())
    assert abs(float(info["shape_error"][0]) - planner.last["cost"]) < 1e-5


def test_greedy_reduces_error_on_easy_start():
    env = _start(1, seed=0, target="diagonal")
    planner = GreedyPlanner(env.sim)
    err = [float(env.info()["shape_error"][0])]
    for _ in range(5):
        _, _, _, _, info = env.step(planner.plan(env.get_state().pos[0], env.get_state().target[0]).reshape(1, 3).double())
        err.append(float(info["shape_error"][0]))
    assert err[-1] < 0.5 * err[0] and planner.sim_evals == 0


TINY = {"cem": ["--horizon", "1", "--candidates", "12", "--elites", "3", "--iterations", "2"],
        "gradient": ["--iters", "2", "--restarts", "1", "--halvings", "1"], "greedy": []}
MODULES = {"cem": cem_mod, "gradient": grad_mod, "greedy": greedy_mod}


@pytest.mark.parametrize("name", ["cem", "gradient", "greedy"])
def test_cli_writes_results(name, tmp_path, capsys):
    out = tmp_path / name
    rc = MODULES[name].main(["--target", "planners/targets/arc.npy", "--seed", "1", "--max-steps", "2",
                             "--out", str(out), "--quiet", *TINY[name]])
    assert rc == 0
    r = json.loads((out / "results.json").read_text())
    for key in ("method", "target", "seed", "success_rate", "episodes", "env_steps", "wall_s", "sim_evals"):
        assert key in r
    assert r["method"] == name and r["seed"] == 1 and r["target"] == "planners/targets/arc.npy"
    (ep,) = r["episodes"]
    assert set(ep) >= {"success", "steps", "final_error"} and 1 <= ep["steps"] <= 2 and ep["final_error"] > 0
    assert r["env_steps"] == ep["steps"] and 0 <= r["success_rate"] <= 1
    assert (r["sim_evals"] > 0) == (name != "greedy")
    assert (out / "shapes.png").stat().st_size > 0 and (out / "episode_0.gif").read_bytes()[:3] == b"GIF"
    assert f"{name} arc: success" in capsys.readouterr().out


def _bad_files(tmp_path, params):
    good = diffdlo.target_shape("horizontal", params).numpy()
    np.save(tmp_path / "short.npy", good[:10])
    np.save(tmp_path / "stretched.npy", good * 1.5)
    return [("circle", "unknown target 'circle'"), (str(tmp_path / "short.npy"), "must have shape (20, 2)"),
            (str(tmp_path / "stretched.npy"), "link"), (str(tmp_path / "missing.yaml"), "does not exist")]


def test_bad_target_clear_error(tmp_path, params, capsys):
    for value, reason in _bad_files(tmp_path, params):
        rc = cem_mod.main(["--target", value, "--out", str(tmp_path / "o"), "--quiet"])
        err = capsys.readouterr().err
        assert rc == 2 and f"bad --target {value!r}" in err and reason in err and "Traceback" not in err


def test_bad_target_exit_code_subprocess():
    res = subprocess.run([sys.executable, "-m", "planners.gradient", "--target", "spiral"], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 2 and "bad --target 'spiral'" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.parametrize("family", ["random_curve", "random"])
def test_cli_family_target_draws_each_episodes_target_from_its_reset(family, tmp_path, capsys):
    out = tmp_path / family
    rc = cem_mod.main(["--target", family, "--seed", "3", "--episodes", "2", "--max-steps", "2", "--out", str(out),
                       "--quiet", "--no-gif", *TINY["cem"]])
    assert rc == 0
    r = json.loads((out / "results.json").read_text())
    assert r["target"] == family and len(r["episodes"]) == 2
    recorded = [torch.tensor(ep["target"], dtype=torch.float64) for ep in r["episodes"]]
    env = BatchedShapeControl(1, target=family)
    for i, got in enumerate(recorded):
        assert r["episodes"][i]["seed"] == 3 + i
        env.reset(seed=3 + i)
        assert torch.equal(got, env.get_state().target[0].double())
    if family == "random_curve":
        assert (recorded[0] - recorded[1]).abs().max() > 1e-3
    assert (out / "shapes.png").stat().st_size > 0
    assert f"cem {family}: success" in capsys.readouterr().out


def test_cli_fixed_target_records_no_per_episode_target(tmp_path):
    out = tmp_path / "fixed"
    assert cem_mod.main(["--target", "vertical", "--max-steps", "1", "--out", str(out), "--quiet", "--no-gif",
                         *TINY["cem"]]) == 0
    (ep,) = json.loads((out / "results.json").read_text())["episodes"]
    assert "target" not in ep
