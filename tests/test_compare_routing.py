"""The comparison's routing rows (issues 59, 60): compare.yaml's `route` tasks (a task key -> the env's route target),
which only the `route*` variants run, their planner commands, the learners trained on random boards and read on the
held-out layouts, and the report's routing section: the side test's failures counted apart, the pin row paired
against the same row without the pin, and galleries drawn on the board with the pegs."""
import copy

import numpy as np
import pytest

from benchmarks import compare
from benchmarks.compare.figures import _gallery, _gallery_panels, final_errors
from benchmarks.compare.grid import env_target, learner_source, load_grid, route_targets, variant_targets
from benchmarks.compare.summary import task_source
from benchmarks.compare.routing import partner, routing_data, routing_rows, routing_section
from diffdlo.tasks import routing

ROUTE_ROWS = ([("greedy", v) for v in ("route", "route_pin")]
              + [(m, v) for m in ("cem", "gradient")
                 for v in ("route", "route_pin", "route_escape", "route_pin_escape")]
              + [("cem", "route_image"), ("cem", "route_wm_budget")])
LEARNER_ROUTE_ROWS = [("ppo", "route"), ("ppo", "route_pin"), ("ppo", "route_rollouts"), ("pets", "route"),
                      ("pets", "route_pin"), ("latent", "route"), ("latent", "route_pin"), ("sac", "route"), ("apg", "route"),
                      ("pets", "route_image"), ("latent", "route_image")]


def test_only_the_route_rows_run_the_routing_tasks_each_on_its_env_target():
    grid = load_grid()
    routes = route_targets(grid)
    assert routes == ["route", "route_hook_wrap", "route_zigzag_four"]
    assert {env_target(grid, t).split(":")[-1] for t in routes[1:]} == set(routing.HELD_OUT_LAYOUTS)
    assert sorted(routing_rows(grid)) == sorted(ROUTE_ROWS + LEARNER_ROUTE_ROWS)
    cells = compare.build_cells(grid, "/tmp/out")
    on_routes = [c for c in cells if c["target"] in routes]
    assert {(c["method"], c["variant"]) for c in on_routes} == set(ROUTE_ROWS + LEARNER_ROUTE_ROWS)
    planners = [c for c in on_routes if c["kind"] == "planner"]
    assert len(planners) == len(ROUTE_ROWS) * len(routes) * len(grid["seeds"])
    for c in planners:
        argv = c["argv"]
        assert argv[argv.index("--target") + 1] == env_target(grid, c["target"])
        assert argv[argv.index("--max-steps") + 1] == "40"
        assert ("--pin" in argv) == ("_pin" in c["variant"])
        assert ("--escape" in argv) == c["variant"].endswith("_escape")
    # a learner trains on random boards only and is read on the held-out layouts after training, labelled as the
    # grid's tasks
    learners = [c for c in on_routes if c["kind"] == "agent"]
    assert {c["target"] for c in learners} == {"route"}
    assert len(learners) == len(LEARNER_ROUTE_ROWS) * len(grid["seeds"])
    for c in learners:
        argv = c["argv"]
        assert argv[argv.index("--target") + 1] == "route" and argv[argv.index("--max-steps") + 1] == "40"
        assert "eval_targets=[route:hook_wrap, route:zigzag_four]" in argv
        assert ("action=node_pin" in argv) == ("_pin" in c["variant"])
    for task in routes[1:]:
        assert learner_source(grid, task) == "route"
        assert task_source(grid, "pets", "route", task) == "route"
    # every other row runs the free rope only, as before the routes came
    for method, spec in grid["methods"].items():
        for variant, entry in spec["variants"].items():
            if (method, variant) not in ROUTE_ROWS + LEARNER_ROUTE_ROWS:
                assert not set(variant_targets(grid, entry or {})) & set(routes), (method, variant)


def test_a_pin_or_escape_row_is_paired_with_the_row_that_differs_from_it_by_that_alone():
    grid = load_grid()
    for method in ("greedy", "cem", "gradient"):
        assert partner(grid, method, "route_pin") == "route"
        assert partner(grid, method, "route") is None
    for method in ("cem", "gradient"):
        assert partner(grid, method, "route_escape", "escape") == "route"
        assert partner(grid, method, "route_pin_escape", "escape") == "route_pin"
        assert partner(grid, method, "route_pin_escape", "pin") == "route_escape"
        assert partner(grid, method, "route_pin", "escape") is None
    for method in ("ppo", "pets", "latent"):      # a learner's pin: its action node_pin
        assert partner(grid, method, "route_pin") == "route"
    assert partner(grid, "ppo", "route_rollouts") is None
    for method in ("cem", "pets", "latent"):      # from pictures: a planner's --perception, a learner's obs perceived
        assert partner(grid, method, "route_image", "perception") == "route"
        assert partner(grid, method, "route", "perception") is None
    grid = copy.deepcopy(grid)
    grid["methods"]["cem"]["variants"]["route"]["args"]["candidates"] = 100      # no longer the pin alone
    assert partner(grid, "cem", "route_pin") is None


def test_a_route_task_that_is_no_target_of_the_grid_is_refused(tmp_path):
    import yaml
    grids = yaml.safe_load(compare.GRID_FILE.read_text())
    grids["full"]["routes"]["route_nowhere"] = "route:nowhere"
    path = tmp_path / "grid.yaml"
    path.write_text(yaml.safe_dump(grids))
    with pytest.raises(ValueError, match="route_nowhere"):
        load_grid(path=path)


def _episode(i, success, steps, final_error, sides_kept, start_error):
    return {"success": success, "steps": steps, "final_error": final_error, "start_error": start_error,
            "sides_kept": sides_kept}


def _done(grid):
    """Two seeds of cem/route and cem/route_pin on `route`: the pin row solves one more episode and saves moves."""
    done = {}
    for seed in (0, 1):
        base = [_episode(i, i != 3, 10 + i, 0.008 if i != 3 else 0.009, i != 3, 0.3 + 0.01 * i) for i in range(4)]
        # episode 3 of the row without the pin ended under 1 cm but round a peg the wrong way
        pin = [_episode(i, True, 9 + i, 0.007, True, 0.3 + 0.01 * i) for i in range(4)]
        for variant, eps in (("route", base), ("route_pin", pin)):
            done[("cem", variant, "route", seed)] = {"episodes": eps, "sim_evals": 1000 * len(eps),
                                                     "plan_s_per_step": 0.25, "wall_s": 10.0}
    return done


def test_the_routing_section_counts_wrong_sides_and_pairs_the_pin_episode_by_episode():
    grid = load_grid()
    done = _done(grid)
    rows = {r["variant"]: r for r in routing_data(grid, done)}
    assert rows["route"]["solved"] == 6 and rows["route"]["wrong_side"] == 2      # 1 per seed
    assert rows["route_pin"]["solved"] == 8 and rows["route_pin"]["wrong_side"] == 0
    pin = rows["route_pin"]["pin"]
    assert pin["pairs"] == 8
    assert sorted(pin["ds"]) == [0.0] * 6 + [1.0] * 2                 # success: pin minus none
    assert pin["dm"] == [-1.0] * 6                                    # moves over the 6 pairs both solved
    assert "pin" not in rows["route"]
    text = "\n".join(routing_section(grid, done, ["figures/gallery_route.png"]))
    assert "## Routing" in text and "2 of 8" in text and "-1.0" in text
    assert "![gallery_route](figures/gallery_route.png)" in text
    # a mismatched start (another episode) is left out of the pairing, named
    done[("cem", "route_pin", "route", 1)]["episodes"][0]["start_error"] = 0.5
    assert routing_data(grid, done)[1]["pin"]["mismatched"] == 1
    assert routing_section(grid, {}) == []


def test_a_route_gallery_draws_the_pegs_and_measures_the_error_on_the_board():
    pytest.importorskip("matplotlib")
    from benchmarks.compare.figures import _pyplot
    grid = load_grid()
    grid = dict(grid, seeds=[0])
    route = np.stack([np.linspace(0, 0.5, 6), np.zeros(6)], 1)
    final = route + [0.0, 0.004]                     # 4 mm off everywhere: on the board, not after alignment
    shapes = {"start": (route + 0.2).tolist(), "final": final.tolist(), "target": route.tolist(),
              "pegs": [[0.1, 0.03, 0.01], [0.3, -0.03, 0.02]]}
    done = [({"method": "cem", "variant": "route", "target": "route", "seed": 0, "kind": "planner"},
             {"shapes": shapes, "episodes": []})]
    assert final_errors(final, route) == "0.0 / 0.0 mm"
    assert final_errors(final, route, on_board=True) == "4.0 / 4.0 mm"
    assert [label for label, _ in _gallery_panels(grid, done, "route")] == ["cem/route"]   # no main row needed
    plt = _pyplot()
    fig = _gallery(plt, grid, done, "route", "")
    ax = fig.axes[0]
    assert sorted(round(p.radius, 3) for p in ax.patches) == [0.01, 0.02]
    assert any(t.get_text() == "4.0 / 4.0 mm" for t in ax.texts)
    plt.close(fig)


def test_a_miss_is_told_apart_by_why():
    from benchmarks.compare.routing import STALL_MOVES, miss_reason
    assert miss_reason({"success": True}) is None
    assert miss_reason({"success": False, "sides_kept": False, "errors": [0.3, 0.2]}) == "wrong side"
    flat = [0.3, 0.05] + [0.0495] * STALL_MOVES              # under 1 mm gained over the last moves
    assert miss_reason({"success": False, "sides_kept": True, "errors": flat}) == "stalled"
    falling = [0.3 - 0.01 * k for k in range(STALL_MOVES + 2)]
    assert miss_reason({"success": False, "sides_kept": True, "errors": falling}) == "improving"


def test_the_other_planners_are_paired_against_cem_with_the_same_grippers():
    grid = load_grid()
    done = _done(grid)
    for variant in ("route", "route_pin"):        # greedy: two moves more than CEM on every episode
        for seed in (0, 1):
            eps = [dict(e, steps=e["steps"] + 2) for e in done[("cem", variant, "route", seed)]["episodes"]]
            done[("greedy", variant, "route", seed)] = dict(done[("cem", variant, "route", seed)], episodes=eps)
    rows = {(r["method"], r["variant"]): r for r in routing_data(grid, done)}
    assert "vs_cem" not in rows[("cem", "route")]
    assert rows[("greedy", "route")]["vs_cem"]["dm"] == [2.0] * 6
    assert rows[("greedy", "route_pin")]["vs_cem"]["dm"] == [2.0] * 8
    assert "| greedy | route_pin | route | +0 [+0, +0] | +2.0" in "\n".join(routing_section(grid, done))


def test_main_grid_runs_every_routing_row():
    from pathlib import Path
    script = (Path(__file__).parents[1] / "benchmarks/main_grid.sh").read_text().replace("\\\n", " ")
    lines = [x for x in script.splitlines() if "/route" in x and not x.lstrip().startswith("#")]
    rows = [row for line in lines for row in line.split("--rows", 1)[1].split()]
    assert sorted(rows) == sorted(f"{m}/{v}" for m, v in ROUTE_ROWS + LEARNER_ROUTE_ROWS)


def test_an_escape_row_is_paired_against_the_same_row_without_it():
    grid = load_grid()
    done = _done(grid)
    for seed in (0, 1):       # cem/route_escape: the wrong-side episode 3 solved after the escape took over
        eps = [dict(e) for e in done[("cem", "route", "route", seed)]["episodes"]]
        eps[3] = dict(eps[3], success=True, sides_kept=True, steps=20, escape_moves=3)
        done[("cem", "route_escape", "route", seed)] = dict(done[("cem", "route", "route", seed)], episodes=eps)
    rows = {(r["method"], r["variant"]): r for r in routing_data(grid, done)}
    escape = rows[("cem", "route_escape")]
    assert escape["escapes"] == 2 and escape["escape"]["pairs"] == 8
    assert sorted(escape["escape"]["ds"]) == [0.0] * 6 + [1.0] * 2 and escape["escape"]["dm"] == [0.0] * 6
    assert "escape" not in rows[("cem", "route")]
    from benchmarks.compare.records import _episode
    assert _episode(dict(eps[3], errors=[0.3, 0.005]))["escape_moves"] == 3      # the records keep it
    assert "| cem | route_escape | route | 2 of 8 | +25 " in "\n".join(routing_section(grid, done))


def test_a_learner_row_is_paired_against_cem_with_the_same_grippers():
    from benchmarks.compare.routing import reference_variant
    grid = load_grid()
    assert reference_variant(grid, "pets", "route") == "route"
    assert reference_variant(grid, "pets", "route_pin") == "route_pin"
    assert reference_variant(grid, "ppo", "route_rollouts") == "route"          # no cem/route_rollouts: the plain row
    assert reference_variant(grid, "cem", "route_escape") == "route_escape"


def test_a_row_from_pictures_is_paired_against_the_same_row_given_the_state():
    grid = load_grid()
    done = _done(grid)
    for seed in (0, 1):       # cem/route_image: episode 0 missed (the reading), the others one move more
        eps = [dict(e, steps=e["steps"] + 1) for e in done[("cem", "route", "route", seed)]["episodes"]]
        eps[0] = dict(eps[0], success=False, final_error=0.02)
        done[("cem", "route_image", "route", seed)] = dict(done[("cem", "route", "route", seed)], episodes=eps)
    rows = {(r["method"], r["variant"]): r for r in routing_data(grid, done)}
    pictures = rows[("cem", "route_image")]["pictures"]
    assert pictures["pairs"] == 8 and sorted(pictures["ds"]) == [-1.0] * 2 + [0.0] * 6
    assert pictures["dm"] == [1.0] * 4                    # episodes 1 and 2 of each seed, solved by both
    assert "pictures" not in rows[("cem", "route")]
    assert "| cem | route_image | route | route | -25 " in "\n".join(routing_section(grid, done))


def test_a_row_is_paired_with_the_row_compare_yaml_names_and_a_bad_name_is_refused(tmp_path):
    import yaml
    grid = load_grid()
    assert grid["methods"]["pets"]["variants"]["route"]["paired_with"] == "cem/route_wm_budget"
    done = _done(grid)
    for seed in (0, 1):       # the world models' planner through the simulator: one move more than CEM's budget
        eps = [dict(e, steps=e["steps"] + 1) for e in done[("cem", "route", "route", seed)]["episodes"]]
        done[("cem", "route_wm_budget", "route", seed)] = dict(done[("cem", "route", "route", seed)], episodes=eps)
    rows = {(r["method"], r["variant"]): r for r in routing_data(grid, done)}
    assert rows[("cem", "route_wm_budget")]["paired_with"]["dm"] == [1.0] * 6
    assert "paired_with" not in rows[("cem", "route")]
    assert "| cem | route_wm_budget | route | cem/route | +0 [+0, +0] | +1.0" in "\n".join(routing_section(grid, done))
    grids = yaml.safe_load(compare.GRID_FILE.read_text())
    grids["full"]["methods"]["pets"]["variants"]["route"]["paired_with"] = "cem/nowhere"
    path = tmp_path / "grid.yaml"
    path.write_text(yaml.safe_dump(grids))
    with pytest.raises(ValueError, match="cem/nowhere"):
        load_grid(path=path)
