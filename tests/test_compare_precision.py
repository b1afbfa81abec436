"""The comparison's precision rows (issue 50): compare.yaml's `precise` variants and their declared `tolerance`
(checked by the grid loader), their commands, and the report's precision section and figure, read at a tolerance from
the episodes' recorded errors (stats.success_move), with a lower bound marked where an episode ended at its own
success first; without precision cells the report is as before."""
import copy
import re
from pathlib import Path

import pytest
import yaml

from benchmarks import compare
from benchmarks.compare.figures import figure_names
from benchmarks.compare.grid import row_tolerance
from benchmarks.compare.precision import (LADDER, episode_at, ladder_points, precision_section, precise_rows,
                                          ran_until, split_done)
from benchmarks.compare.records import record_changes, record_key
from benchmarks.compare.settings import comparable_argv

ROOT = Path(__file__).parents[1]
PRECISE = ["cem", "gradient", "ppo", "pets", "latent"]
BASE = {"cem": "default", "gradient": "default", "ppo": "fewest_moves", "pets": "tuned", "latent": "tuned"}


# ---------------------------------------------------------------------- the grid's precision rows
def test_each_precise_row_declares_the_task_tolerance_on_the_two_random_tasks():
    grid = compare.load_grid()
    assert [(m, v) for m, v, _ in precise_rows(grid)] == [("cem", "precise"), ("cem", "precise_image")] + [
        (m, "precise") for m in PRECISE[1:]]
    assert row_tolerance(grid, "cem", "precise_image") == (0.005, 0.02)
    assert ran_until(grid, "cem", "precise_image") == (0.002, None)
    assert grid["methods"]["cem"]["variants"]["precise_image"]["args"]["perception"] == "models/perception64.pt"
    for method in PRECISE:
        v = grid["methods"][method]["variants"]["precise"]
        assert row_tolerance(grid, method, "precise") == (0.005, 0.02)
        assert v["targets"] == ["random", "random_curve"] and v["cpu_min"] > 0
    assert ran_until(grid, "cem", "precise") == ran_until(grid, "gradient", "precise") == (0.002, None)
    for method in ("ppo", "pets", "latent"):
        assert ran_until(grid, method, "precise") == (0.005, 0.02)
    assert ran_until(grid, "cem", "default") == (0.01, None)                          # the env's 1 cm
    assert all(row_tolerance(grid, m, v) is None for m, spec in grid["methods"].items() for v in spec["variants"]
               if v not in ("precise", "precise_image"))


def planner_args(cell):
    import importlib

    from planners.common import make_parser
    module = importlib.import_module(cell["argv"][1])
    cls = next(c for c in vars(module).values() if isinstance(c, type) and hasattr(c, "OPTIONS")
               and c.__module__ == module.__name__)
    return vars(make_parser(cell["method"], None, cls).parse_args(cell["argv"][2:]))


def learner_config(cell):
    from agents.common.cli import config_from_args, make_parser
    from agents.planet import PlaNetConfig
    from agents.ppo import PPOConfig
    cls, algo = {"agents.ppo": (PPOConfig, "ppo"), "agents.planet": (PlaNetConfig, "planet")}[cell["argv"][1]]
    ap = make_parser(algo, None)
    return config_from_args(cls, algo, ap.parse_args(cell["argv"][2:]), ap)


@pytest.mark.parametrize("method", PRECISE)
def test_a_precise_cell_runs_its_base_row_with_the_precise_tolerance(method, tmp_path):
    grid = compare.load_grid()
    precise, = compare.build_cells(grid, tmp_path, methods=[method], variants=["precise"], targets=["random"],
                                   seeds=[3])
    base, = compare.build_cells(grid, tmp_path, methods=[method], variants=[BASE[method]], targets=["random"],
                                seeds=[3])
    assert {c["target"] for c in compare.build_cells(grid, tmp_path, methods=[method], variants=["precise"])} \
        == {"random", "random_curve"}
    if precise["kind"] == "planner":
        got, want = planner_args(precise), planner_args(base)
        assert got.pop("success_tol") == 0.002 and want.pop("success_tol") is None
        assert got.pop("success_worst_tol") is None
        assert got.pop("out").endswith(f"{method}/precise/random/seed3") and want.pop("out")
        want.pop("success_worst_tol")
        assert got == want                                      # the same planner, budget, episodes and seeds
        assert compare.command_line(precise).endswith(
            f"--success-tol 0.002 --quiet --no-gif --target random --seed 13000 --episodes 20 --out "
            f"{tmp_path}/{method}/precise/random/seed3")
    else:
        cfg, base_cfg = learner_config(precise), learner_config(base)
        env = cfg.task.env_options().resolve()
        assert (env.success_tol, env.success_worst_tol) == (0.005, 0.02)
        base_env = base_cfg.task.env_options().resolve()
        assert (base_env.success_tol, base_env.success_worst_tol) == (0.01, None)
        sets = [precise["argv"][i + 1] for i, a in enumerate(precise["argv"]) if a == "--set"]
        assert sets[-2:] == ["success_tol=0.005", "success_worst_tol=0.02"]
        assert not any(s.startswith("eval_targets=") for s in sets)          # random and random_curve only
        # the rest is the base row's command: its preset, budget, seeds and (PPO) policy rollouts
        strip = {"success_tol=0.005", "success_worst_tol=0.02"}
        rest = [a for i, a in enumerate(precise["argv"]) if a not in strip
                and not (a == "--set" and precise["argv"][i + 1] in strip)]
        base_argv = [a for i, a in enumerate(base["argv"]) if not a.startswith("eval_targets=")
                     and not (a == "--set" and base["argv"][i + 1].startswith("eval_targets="))]
        assert comparable_argv(rest) == comparable_argv(base_argv)
        assert cfg.run.total_steps == base_cfg.run.total_steps
        if method == "ppo":
            assert "rollout_candidates=32" in sets and "rollout_moves=20" in sets
        if method == "latent":
            assert precise["argv"][precise["argv"].index("--preset") + 1] == "latent"


def test_adding_the_precise_rows_changes_no_cell_of_the_other_rows(tmp_path):
    """Every cell of the other rows has the command it had without the precise rows, and every committed record
    still matches its cell (nothing for --rerun-changed)."""
    grid = compare.load_grid()
    without = copy.deepcopy(grid)
    for method in PRECISE:
        del without["methods"][method]["variants"]["precise"]
    before = {record_key(c): c["argv"] for c in compare.build_cells(without, tmp_path)}
    after = {record_key(c): c["argv"] for c in compare.build_cells(grid, tmp_path) if c["variant"] != "precise"}
    assert after == before
    records = compare.read_records(ROOT / "docs/results/cells.jsonl")
    cells = {record_key(c): c for c in compare.build_cells(grid, "runs/compare")}
    matched = [rec for rec in records if record_key(rec) in cells]
    assert len(matched) == len(records) > 0
    assert [record_key(r) for r in matched if record_changes(r, cells[record_key(r)])] == []


BAD = [("{mean: -0.005, worst: 0.02}", r"'tolerance' mean must be a positive finite number \[m\], got -0\.005"),
       ("{mean: '5mm'}", r"'tolerance' mean must be a positive finite number \[m\], got '5mm'"),
       ("{mean: 0.005, worst: 0}", r"'tolerance' worst must be a positive finite number \[m\] or null, got 0"),
       ("{mean: .nan}", r"'tolerance' mean must be a positive finite number \[m\], got nan"),
       ("{mean: true}", r"'tolerance' mean must be a positive finite number \[m\], got True"),
       ("{worst: 0.02}", r"'tolerance' needs its mean \[m\], got \{'worst': 0\.02\}"),
       ("{mean: 0.005, wrst: 0.02}", r"'tolerance' has the keys mean and worst, got 'wrst'"),
       ("0.005", r"'tolerance' must be a mapping \{mean: M, worst: W\} \[m\] \(worst optional\), got 0\.005"),
       ("'5 mm'", r"'tolerance' must be a mapping .*, got '5 mm'")]


@pytest.mark.parametrize("value,message", BAD, ids=[b[0] for b in BAD])
def test_a_bad_tolerance_is_refused_naming_the_variant_and_the_value(value, message, tmp_path):
    grid = {"full": {"seeds": [0], "targets": ["random"], "episodes": 1, "eval_seed_base": 0, "methods": {
        "cem": {"kind": "planner", "variants": {"default": {"args": {"max-steps": 1}},
                                                "precise": {"args": {"success-tol": 0.002}}}}}}}
    path = tmp_path / "grid.yaml"
    precise = grid["full"]["methods"]["cem"]["variants"]["precise"]
    precise["tolerance"] = yaml.safe_load(value)                  # as compare.yaml would spell it
    path.write_text(yaml.safe_dump(grid))
    with pytest.raises(ValueError, match=rf"grid.yaml: grid 'full': variant cem/precise: {message}"):
        compare.load_grid(path=path)
    precise["tolerance"] = {"mean": 0.004}
    path.write_text(yaml.safe_dump(grid))
    loaded = compare.load_grid(path=path)
    assert row_tolerance(loaded, "cem", "precise") == (0.004, None) and row_tolerance(loaded, "cem", "default") is None


# ---------------------------------------------------------------------- the report's precision section
# Two rows, 2 seeds x 2 episodes on random: (seed, episode) -> (own success, errors, worst_errors) after the reset
# and each move. CEM ran until 2 mm (mean only); PPO until 5 mm mean and 2 cm at the worst node. The same episode
# starts at the same error for both (paired).
EPISODES = {
    ("cem", 0, 0): (True, [0.05, 0.015, 0.008, 0.004, 0.0019], [0.1, 0.04, 0.025, 0.012, 0.006]),
    ("cem", 0, 1): (True, [0.04, 0.0105, 0.0045, 0.003, 0.0015], [0.08, 0.03, 0.021, 0.015, 0.004]),
    ("cem", 1, 0): (False, [0.03, 0.012, 0.006, 0.0042], [0.06, 0.03, 0.02, 0.019]),      # max moves, not 2 mm
    ("cem", 1, 1): (False, [0.02, 0.011, 0.0099], [0.05, 0.03, 0.025]),
    ("ppo", 0, 0): (True, [0.05, 0.008, 0.0045], [0.1, 0.025, 0.015]),                      # ended at 5 mm
    ("ppo", 0, 1): (True, [0.04, 0.012, 0.006, 0.0018], [0.08, 0.03, 0.02, 0.005]),
    ("ppo", 1, 0): (False, [0.03, 0.025, 0.021, 0.015], [0.06, 0.04, 0.035, 0.03]),
    ("ppo", 1, 1): (True, [0.02, 0.004], [0.05, 0.01]),                                     # ended at 5 mm
}
# what the rows are at (5 mm, worst 2 cm), by hand (first move with mean < 5 mm and worst < 2 cm):
#   cem: 3, 3 (not 2: its worst node 2.1 cm), 3, none -> 3 of 4 in 3.0 moves; per seed 1.0 and 0.5
#   ppo: 2, 3, none, 1                                 -> 3 of 4 in 2.0 moves; per seed 1.0 and 0.5
#   paired ppo - cem: success 0, 0, -1, +1; moves -1, 0 (both within)
#   worst node at that move [mm]: cem 12, 15, 19 (median 15, 90th pct 15 + 0.8 * 4 = 18.2); ppo 15, 5, 10 (10, 14)
# and at the mean alone:           2 cm          1 cm          5 mm                 2 mm
#   cem                            1 1 1 1       2 2 2 2       3 2 3 -              4 4 - -   (all exact)
#   ppo                            1 1 3 1       1 2 - 1       2 3 - 1              - 3 - -   (2 ended at 5 mm)


def fake_records(grid, methods=("cem", "ppo"), variant="precise", targets=("random",)):
    """The records of the cells of ``methods``' ``variant`` on ``targets``, seeds 0 and 1, with EPISODES (CEM's for
    a planner, PPO's for a learner)."""
    out = []
    for c in compare.build_cells(grid, "runs/x", methods=list(methods), variants=[variant], targets=list(targets),
                                 seeds=[0, 1]):
        eps = []
        for i in range(2):
            success, errors, worst = EPISODES[("cem" if c["kind"] == "planner" else "ppo", c["seed"], i)]
            eps.append({"success": success, "steps": len(errors) - 1, "start_error": errors[0],
                        "final_error": errors[-1], "target_name": "diagonal", "errors": errors,
                        "worst_errors": worst})
        rec = {**{k: c[k] for k in ("method", "variant", "target", "seed", "kind")}, "command": "python -m x",
               "argv": comparable_argv(c["argv"]), "machine": None, "learner_device": None, "env_steps": 100,
               "wall_s": 60.0, "episodes": eps}
        if c["kind"] == "planner":
            rec.update(sim_evals=3000, plan_s_per_step=0.5)
        out.append(rec)
    return out


def table(md: str, header_start: str) -> list[dict[str, str]]:
    """The rows of the markdown table whose header starts with ``header_start``."""
    lines = md.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(header_start))
    head = [c.strip() for c in lines[i].strip().strip("|").split(" | ")]
    rows = []
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
        assert len(cells) == len(head), line
        rows.append(dict(zip(head, cells)))
    return rows


def report(tmp_path, records, sub=".", figures=None) -> str:
    doc = tmp_path / sub / "R.md"
    doc.parent.mkdir(parents=True, exist_ok=True)
    compare.write_report(compare.load_grid(), "runs/x", doc, figures, records=records, source="rebuild")
    return doc.read_text()


def test_episode_at_reads_a_tolerance_and_says_when_the_answer_is_only_a_lower_bound():
    ok, errs, worst = EPISODES[("ppo", 0, 0)]
    ep = {"success": ok, "errors": errs, "worst_errors": worst}
    assert episode_at(ep, 0.005, 0.02) == (2, True)
    assert episode_at(ep, 0.01) == (1, True)
    assert episode_at(ep, 0.002) == (None, False)         # ended at its own 5 mm success: it might have got there
    ok, errs, worst = EPISODES[("cem", 1, 0)]
    assert episode_at({"success": ok, "errors": errs, "worst_errors": worst}, 0.002) == (None, True)   # ran out
    assert episode_at({"success": True, "errors": errs, "worst_errors": worst}, 0.005, 0.019) == (None, False)
    with pytest.raises(ValueError, match="no recorded errors"):
        episode_at({"success": True, "steps": 3}, 0.005)


def test_the_precision_table_reads_each_row_at_its_tolerance(tmp_path):
    md = report(tmp_path, fake_records(compare.load_grid()))
    assert "## Precision: success at 5 mm, worst node 2 cm" in md
    rows = {r["method"]: r for r in table(md, "| method | variant | task | tolerance |")}
    cem, ppo = rows["CEM through the simulator (MPC)"], rows["PPO"]
    p, lo, hi = compare.wilson(3, 4)
    # 3 of 4 (per seed 1.0, 0.5: t-interval 0.75 +- 12.706 * 0.354 / 1.414, clipped to [0, 1])
    assert cem["success: t-CI; Wilson"] == ppo["success: t-CI; Wilson"] == \
        f"0.75 [0.00, 1.00]; 0.75 [{lo:.2f}, {hi:.2f}]"
    assert (cem["moves (mean; n)"], ppo["moves (mean; n)"]) == ("3.0; 3", "2.0; 3")
    assert (cem["tolerance"], ppo["tolerance"]) == ("5 mm, worst node 2 cm",) * 2
    assert (cem["ran until"], ppo["ran until"]) == ("2 mm", "5 mm, worst node 2 cm")
    assert cem["seeds × episodes"] == "2 × 2" and cem["task"] == "random" and cem["variant"] == "precise"
    # paired against cem/precise: Δ success 0, 0, -1, +1 (sd sqrt(2/3), t 3.182: +-130 pp, clipped); Δ moves -1, 0
    assert cem["Δ success vs cem/precise [pp]"] == "(reference)"
    assert ppo["Δ success vs cem/precise [pp]"] == "+0 [-100, +100]"
    assert ppo["Δ moves vs cem/precise (both within)"] == "-0.5 [-6.9, +5.9] (n=2)"      # -0.5 +- 12.706 * 0.5
    assert ppo["pairs"] == "4"
    assert cem["worst node at success [mm]: median; 90th pct"] == "15.0; 18.2 (n=3)"
    assert ppo["worst node at success [mm]: median; 90th pct"] == "10.0; 14.0 (n=3)"


def test_success_against_the_tolerance_marks_the_lower_bounds(tmp_path):
    md = report(tmp_path, fake_records(compare.load_grid()))
    rows = {r["method"]: r for r in table(md, "| method | variant | task | ran until | mean < 2 cm")}
    cem, ppo = rows["CEM through the simulator (MPC)"], rows["PPO"]
    assert [cem[f"mean < {t}"] for t in ("2 cm", "1 cm", "5 mm", "2 mm")] == \
        ["100 % · 1.0", "100 % · 2.0", "75 % · 2.7", "50 % · 4.0"]                       # exact: ran until 2 mm
    assert [ppo[f"mean < {t}"] for t in ("2 cm", "1 cm", "5 mm", "2 mm")] == \
        ["100 % · 1.5", "75 % · 1.3", "75 % · 2.0", "≥ 25 % · 3.0"]                      # 2 mm: two ended at 5 mm
    assert cem["the row's tolerance"] == "75 % · 3.0 (5 mm, worst node 2 cm)"
    assert ppo["the row's tolerance"] == "75 % · 2.0 (5 mm, worst node 2 cm)"
    # the figure's points: the same rates, the lower bound not exact
    grid = compare.load_grid()
    done = {record_key(r): r for r in fake_records(grid)}
    points = {p["label"]: p for p in ladder_points(grid, done)}
    assert points["PPO + policy rollouts"]["tols"] == list(LADDER) == [0.02, 0.01, 0.005, 0.002]
    assert points["PPO + policy rollouts"]["success"] == [1.0, 0.75, 0.75, 0.25]
    assert points["PPO + policy rollouts"]["exact"] == [True, True, True, False]
    assert points["CEM"]["success"] == [1.0, 1.0, 0.75, 0.5] and all(points["CEM"]["exact"])


def test_a_row_tolerance_is_a_lower_bound_where_the_planner_stopped_before_the_worst_node_was_within(tmp_path):
    grid = compare.load_grid()
    records = fake_records(grid, methods=("cem",))
    records[0]["episodes"][0]["worst_errors"][3:] = [0.03, 0.025]         # at 2 mm its worst node is 2.5 cm
    rows = {r["method"]: r for r in table(report(tmp_path, records), "| method | variant | task | tolerance |")}
    _, lo, hi = compare.wilson(2, 4)                          # 1 of 2 on each seed
    assert rows["CEM through the simulator (MPC)"]["success: t-CI; Wilson"] == \
        f"≥ 0.50 [0.50, 0.50]; 0.50 [{lo:.2f}, {hi:.2f}] (1 ended at their own success first)"


def test_precision_rows_stay_out_of_the_task_tables_and_the_report_without_them_is_as_before(tmp_path):
    grid = compare.load_grid()
    base = fake_records(grid, variant="default", methods=("cem",))
    precise = fake_records(grid, methods=("cem", "ppo"))
    without = report(tmp_path, base, "a")
    with_ = report(tmp_path, base + precise, "b")
    assert "## Precision" not in without and "precision.png" not in without     # (the notes may name it)
    assert "## Precision: success at 5 mm, worst node 2 cm" in with_ and "![precision](figures/precision.png)" in with_
    tail = without.index("## Task: random")
    assert with_[with_.index("## Task: random"):] == without[tail:]        # task tables, costs, figures: the same
    assert "| cem | precise |" not in with_ and "cem/precise seed" not in with_
    # what comes before the task tables: the same but for the precision section and the cells finished
    head = re.sub(r"\d+ of \d+ cells|\*\*Partial comparison.*|\*\*CPU-hours.*", "", with_[:with_.index("## Task:")])
    section = head[head.index("## Precision"):head.index("## Definitions")]
    assert head.replace(section, "") == re.sub(r"\d+ of \d+ cells|\*\*Partial comparison.*|\*\*CPU-hours.*", "",
                                               without[:tail])
    # the figures: the precision figure only with precision cells, and no precision row in the task figures
    cells = {record_key(c): c for c in compare.build_cells(grid, "runs/x")}
    loaded = [(cells[record_key(r)], r) for r in base + precise]
    names = figure_names(grid, loaded, {})
    assert [n for n in names if n != "precision.png"] == figure_names(grid, loaded[:len(base)], {}) == \
        ["summary.png", "planner_error_vs_evals_random.png"] and "precision.png" in names
    regular, prec = split_done(grid, loaded)
    assert [c["variant"] for c, _ in regular] == ["default"] * 2 and len(prec) == 4
    assert precision_section(grid, {record_key(r): r for r in base}) == []


def test_the_precision_figure_is_drawn_and_linked(tmp_path):
    pytest.importorskip("matplotlib")
    grid = compare.load_grid()
    md = report(tmp_path, fake_records(grid, targets=("random", "random_curve")), figures=tmp_path / "figures")
    assert (tmp_path / "figures/precision.png").stat().st_size > 0 and "](figures/precision.png)" in md
    assert md.count("](figures/precision.png)") == 1                          # in its section, not again below


def test_main_grid_runs_the_precise_rows():
    script = (ROOT / "benchmarks/main_grid.sh").read_text()
    line, = [x for x in script.splitlines() if "precise" in x and not x.lstrip().startswith("#")]
    rows = line.split("--rows", 1)[1].split()
    assert sorted(rows) == sorted([f"{m}/precise" for m in PRECISE] + ["cem/precise_image"])
    assert line.split()[:3] == ["nice", "-n", "10"] and line.split()[3] == "$C"       # as the script's other runs


def test_a_gallery_panel_shows_the_final_mean_and_worst_node_error():
    import numpy as np
    from benchmarks.compare.figures import final_errors
    target = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0], [0.3, 0.0]])
    final = target + np.array([[0.0, 0.002], [0.0, 0.0], [0.0, 0.0], [0.0, -0.002]]) + 5.0   # moved: ignored
    # centroid unchanged by the +-2 mm pair: node errors 2, 0, 0, 2 mm
    assert final_errors(final, target) == "1.0 / 2.0 mm"
