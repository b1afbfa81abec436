"""The planners on routes among pegs (issue 59): the objective rolls out with the pegs and the pin and scores on the
board with the side cost, matching the env; each planner plans with and without the pin; the CLI records the board."""
import json

import pytest
import torch

from diffdlo.tasks import routing, task
from diffdlo.envs import BatchedShapeControl
from planners import SimObjective
from planners import greedy as greedy_mod
from planners.cem import CEMPlanner
from planners.common import build_run, run_episode
from planners.gradient import GradientPlanner
from planners.greedy import GreedyPlanner
from planners.objective import SIDE_COST, route_cost


def route_env(b=3, action_type="node_pin"):
    env = BatchedShapeControl(b, target="route:u_two_pegs", reward="route_gain", action_type=action_type)
    env.reset(seed=0)
    return env


def test_the_objective_matches_the_env_on_a_route_with_pins():
    env = route_env()
    state = env.get_state()
    start, route, pegs = state.pos[0].clone(), state.target[0].clone(), state.pegs[0].clone()
    actions = torch.rand(3, 2, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    actions[1, :, 3] = 0.0                                           # rope 1: no pin
    obj = SimObjective(env.sim, start, route, pegs=pegs[None][0])
    node, delta = task.decode_node_action(actions[..., :3].float(), env.params)
    pin = task.decode_pin(actions[..., 3].float(), node, env.params.n_nodes)
    cost, states = obj.rollout_deltas(node, delta, return_states=True, pin=pin)
    torch.testing.assert_close(obj(actions), cost, rtol=0, atol=0)
    env.set_state(pos=start.expand(3, -1, -1), steps=0)
    for t in range(2):
        env.step(actions[:, t])
    torch.testing.assert_close(states[:, -1], env.get_state().pos, rtol=0, atol=1e-6)
    info = env.info()
    real = pegs[pegs[:, 2] > 0]
    extra = (route_cost(env.get_state().pos.double(), route.double(), real.double())
             - info["shape_error"].double()) / SIDE_COST                     # the pegs passed on the wrong side
    torch.testing.assert_close(extra, extra.round(), rtol=0, atol=1e-4)
    assert ((extra.round() == 0) == info["sides_kept"]).all()


def test_the_side_cost_charges_each_peg_on_the_wrong_side():
    env = route_env(1)
    layout = routing.load_layout("u_two_pegs", env.params)
    route = layout.route
    shifted = route + torch.tensor([0.0, 0.3], dtype=route.dtype)            # both pegs now below the rope...
    on = float(route_cost(route[None], route, layout.pegs)[0])
    off = float(route_cost(shifted[None], route, layout.pegs)[0])
    assert on < 1e-12
    assert abs(off - (0.3 + SIDE_COST * 2)) < 1e-9                           # ...both on the wrong side


def test_every_planner_plans_routes_with_and_without_the_pin():
    env = route_env(1)
    state = env.get_state()
    pos, route, pegs = state.pos[0], state.target[0], state.pegs[0][state.pegs[0][:, 2] > 0]
    n = env.params.n_nodes
    for pin in (0, 1):
        planners = [GreedyPlanner(env.sim, pin=pin),
                    CEMPlanner(env.sim, horizon=1, candidates=20, elites=4, iterations=2, pin=pin),
                    GradientPlanner(env.sim, iters=2, restarts=1, halvings=1, pin=pin)]
        for planner in planners:
            action = planner.plan(pos, route, pegs[None][0])
            assert action.shape == (4 if pin else 3,), (planner.name, action.shape)
            assert bool(((action >= 0) & (action <= 1)).all())
            if pin and planner.name == "greedy":
                node, _ = task.decode_node_action(action[:3], env.params)
                held = task.decode_pin(action[3:], node[None], n)
                assert int(held) >= 0 and abs(int(held) - int(node)) >= 2
    grad = GradientPlanner(env.sim, pin=1)
    options = grad.pin_candidates(pos, pegs).tolist()
    nearest = (pos[None] - pegs[:, None, :2]).norm(dim=-1).argmin(-1).tolist()
    assert options[0] == -1 and {0, n - 1} <= set(options) and set(nearest) <= set(options)


def test_greedy_drags_a_route_towards_its_place_on_the_board():
    env = route_env(1, "node")
    state = env.get_state()
    pos, route = state.pos[0], state.target[0]
    action = GreedyPlanner(env.sim).plan(pos, route, state.pegs[0][:2])
    node, drag = task.decode_node_action(action, env.params)
    gap = route[node] - pos[node]                                      # on the board, not centroid-aligned
    cos = float(drag @ gap / (drag.norm() * gap.norm()))
    assert cos > 0.99


def test_a_route_episode_records_its_board_and_sides(tmp_path, capsys):
    p = route_env(1).params
    env, planner, target = build_run(GreedyPlanner, p, p, "route:u_two_pegs", max_steps=2, success_tol=None,
                                     device="cpu", seed=0, options={"pin": 1})
    assert env.action_type == "node_pin" and env.route and target.shape == (p.n_nodes, 2)
    ep = run_episode(env, planner, seed=0, progress=False)
    assert len(ep["pegs"]) == 2 and isinstance(ep["sides_kept"], bool) and ep["steps"] == 2
    out = tmp_path / "greedy"
    assert greedy_mod.main(["--target", "route:u_two_pegs", "--pin", "1", "--max-steps", "2", "--out", str(out),
                            "--quiet", "--no-gif"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["episodes"][0]["pegs"] == ep["pegs"] and (out / "shapes.png").is_file()


def test_the_planners_take_a_board_of_any_size(tmp_path):
    """A layout of 5 pegs (the learners' envs keep 4 slots): every planner's run plans and records all five."""
    import yaml
    p = route_env(1).params
    layout = routing.random_layout(p, torch.Generator().manual_seed(0), pegs=(5, 5), radius=(0.006, 0.01),
                                   max_turn_deg=25.0)
    path = tmp_path / "five.yaml"
    path.write_text(yaml.safe_dump({"pegs": layout.pegs.tolist(), "route": layout.route.tolist()}))
    for planner_cls, options in ((GreedyPlanner, {"pin": 1}), (CEMPlanner, {"candidates": 8, "elites": 2,
                                                                          "iterations": 1, "horizon": 1})):
        env, planner, target = build_run(planner_cls, p, p, f"route:{path}", max_steps=1, success_tol=None,
                                         device="cpu", seed=0, options=options)
        ep = run_episode(env, planner, seed=0, progress=False)
        assert len(ep["pegs"]) == 5 and ep["steps"] == 1
    out = tmp_path / "greedy"
    assert greedy_mod.main(["--target", f"route:{path}", "--max-steps", "1", "--out", str(out), "--quiet",
                            "--no-gif"]) == 0
    assert len(json.loads((out / "results.json").read_text())["episodes"][0]["pegs"]) == 5


def test_the_routing_study_runs_missing_cells_reads_done_ones_and_records(tmp_path, capsys):
    from benchmarks.studies import routing_planners as study
    record = tmp_path / "routing.json"
    argv = ["--out", str(tmp_path / "runs"), "--planners", "greedy", "--targets", "route:u_two_pegs",
            "--episodes", "2", "--max-steps", "1"]
    assert study.main(argv + ["--record", str(record)]) == 0
    table = json.loads(record.read_text())["cells"]
    assert set(table) == {"greedy route:u_two_pegs pin0", "greedy route:u_two_pegs pin1"}
    assert table["greedy route:u_two_pegs pin1"]["pin_effect"]["pairs"] == 0      # one move solves nothing
    assert "| greedy | route:u_two_pegs | 1 | 0/2 |" in capsys.readouterr().out
    stamp = (tmp_path / "runs" / "greedy-u_two_pegs-pin0" / "results.json").stat().st_mtime_ns
    assert study.main(argv) == 0                                                  # done cells are read, not re-run
    assert (tmp_path / "runs" / "greedy-u_two_pegs-pin0" / "results.json").stat().st_mtime_ns == stamp
    assert study.main(argv + ["--record", str(record)]) == 2                      # never replaced without asking
    paired = study.paired_pin({"steps": [3, 5, 4], "solved": [True, True, False], "success": 2},
                              {"steps": [2, 6, 1], "solved": [True, True, True], "success": 3})
    assert paired == {"pairs": 2, "moves_delta": 0.0, "moves_delta_se": 1.0, "success_delta": 1}


def test_the_routing_study_refuses_a_target_that_is_no_route(capsys):
    import pytest
    from benchmarks.studies import routing_planners as study
    for target in ("diagonal", "route:nope"):
        with pytest.raises(SystemExit):
            study.main(["--out", "unused", "--targets", target])
        assert f"--targets {target!r}" in capsys.readouterr().err


def test_the_models_contact_width_smooths_the_planner_not_the_env(tmp_path, monkeypatch, capsys):
    import pytest

    from planners import common
    built = {}
    real_build = common.build_run

    def spy(planner_cls, model, real, *a, **k):
        built["model"], built["real"] = model, real
        return real_build(planner_cls, model, real, *a, **k)
    monkeypatch.setattr(common, "build_run", spy)
    out = tmp_path / "greedy"
    assert greedy_mod.main(["--target", "route:u_two_pegs", "--max-steps", "1", "--model-contact-width", "0.005",
                            "--out", str(out), "--quiet", "--no-gif"]) == 0
    default = route_env(1).params.contact_width
    assert built["model"].contact_width == 0.005 and built["real"].contact_width == default != 0.005
    assert json.loads((out / "results.json").read_text())["config"]["model_contact_width"] == 0.005
    for bad in ("0", "-0.001", "nan"):
        with pytest.raises(SystemExit):
            greedy_mod.main(["--target", "route:u_two_pegs", "--model-contact-width", bad, "--out",
                             str(tmp_path / "bad"), "--quiet", "--no-gif"])
        assert f"--model-contact-width must be in (0, inf), got {float(bad)!r}" in capsys.readouterr().err


def test_the_stall_escape_takes_greedy_moves_after_a_stall_until_the_rope_beats_its_best():
    from planners.escape import StallEscape
    env = route_env(1)
    state = env.get_state(generators=False)
    target, pegs = state.target[0], state.pegs[0][state.pegs[0][:, 2] > 0]
    escape = StallEscape(env.sim, patience=2, pin=True)
    greedy = GreedyPlanner(env.sim, pin=1)

    def rope(error):            # the target shifted sideways: every node `error` off its place on the board
        return target + torch.tensor([0.0, error], dtype=target.dtype)
    assert escape.plan(rope(0.10), target, pegs) is None                 # gaining: the planner plans
    assert escape.plan(rope(0.05), target, pegs) is None
    assert escape.plan(rope(0.0502), target, pegs) is None               # one move without gain: patience 2
    action = escape.plan(rope(0.0498), target, pegs)                     # two moves that gained 0.2 mm: a stall
    assert action is not None and torch.equal(action, greedy.plan(rope(0.0498), target, pegs))
    assert escape.plan(rope(0.049), target, pegs) is not None            # still escaping: not 1 mm below 4.98 cm
    assert escape.plan(rope(0.0485), target, pegs) is None               # 1 mm below its best: the planner again
    assert (escape.escapes, escape.moves) == (1, 2)
    escape.reset()
    assert (escape.escapes, escape.moves, escape.errors) == (0, 0, [])
    with pytest.raises(ValueError, match="--escape must be >= 1 to escape"):
        StallEscape(env.sim, patience=0)


def test_a_stuck_planner_is_taken_out_of_its_stall_by_the_escape_in_an_episode():
    from planners.escape import StallEscape
    p = route_env(1).params
    env, planner, _ = build_run(GreedyPlanner, p, p, "route:u_two_pegs", max_steps=8, success_tol=None,
                                device="cpu", seed=0, options={"pin": 0})

    class Stuck:           # drags node 0 by nothing: the rope never moves, a stall from the first move on
        name, sim_evals = "stuck", 0

        def reset(self, seed=None):
            pass

        def plan(self, pos, target, pegs=None):
            return task.encode_node_action(torch.tensor(0), torch.zeros(2, dtype=pos.dtype), p.n_nodes,
                                           p.action_scale)
    stuck = run_episode(env, Stuck(), seed=0, progress=False)
    assert max(stuck["errors"]) - min(stuck["errors"]) < 1e-3 and "escapes" not in stuck     # under 1 mm: stalled
    freed = run_episode(env, Stuck(), seed=0, progress=False, escape=StallEscape(env.sim, patience=3))
    assert freed["escapes"] >= 1 and freed["escape_moves"] >= 1
    assert freed["errors"][:4] == stuck["errors"][:4]                    # the planner's own moves until the stall
    assert min(freed["errors"]) < stuck["errors"][0] - 0.01              # then greedy's: the rope gets nearer


def test_the_escape_flag_is_recorded_and_a_bad_value_refused(tmp_path, capsys):
    out = tmp_path / "greedy"
    assert greedy_mod.main(["--target", "route:u_two_pegs", "--max-steps", "2", "--escape", "1", "--out", str(out),
                            "--quiet", "--no-gif"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["config"]["escape"] == 1 and {"escapes", "escape_moves"} <= set(results["episodes"][0])
    assert greedy_mod.main(["--target", "route:u_two_pegs", "--max-steps", "1", "--out", str(tmp_path / "none"),
                            "--quiet", "--no-gif"]) == 0
    assert "escapes" not in json.loads((tmp_path / "none" / "results.json").read_text())["episodes"][0]
    with pytest.raises(SystemExit):
        greedy_mod.main(["--target", "route:u_two_pegs", "--escape", "-1", "--out", str(tmp_path / "bad"), "--quiet"])
    assert "--escape must be in [0, inf), got -1" in capsys.readouterr().err
