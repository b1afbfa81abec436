"""The comparison harness (the package benchmarks/compare/): confidence intervals, a CI-sized quick run, its report,
resume, the per-episode targets of a planner's random cell, and the optional Ray path."""
import json
import math
import re
from pathlib import Path

import pytest

from benchmarks import compare

# quick grid, further restricted: two planners and one learner (64 env steps, tiny networks, 6-node rope), one seed,
# the diagonal task plus greedy on the random task (one planner run per episode, merged)
ARGS = ["--quick", "--methods", "greedy", "cem", "sac", "--seeds", "0", "--jobs", "1", "--no-progress"]


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    root = tmp_path_factory.mktemp("compare")
    argv = [*ARGS, "--out", str(root / "cells"), "--report", str(root / "RESULTS.md")]   # figures: root/figures
    assert compare.main(argv) == 0
    return root, argv


def parse_tables(md: str) -> dict[str, list[dict[str, str]]]:
    """The per-task tables of a report and their (shared) header."""
    tables, target, header, first = {}, None, None, None
    for line in md.splitlines():
        m = re.match(r"## Task: (\S+)", line)
        if m or line.startswith("## "):
            target, header = (m.group(1) if m else None), None
            continue
        if target and line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
            if header is None:
                header, first = cells, first or cells
            elif not set(line.replace("|", "").strip()) <= {"-"}:
                assert len(cells) == len(header), line
                tables.setdefault(target, []).append(dict(zip(header, cells)))
    return tables, first


def test_t_quantile_and_intervals_match_hand_computed():
    # Student t 97.5 % quantiles (tables): df 1, 4, 9, 30
    for df, t in ((1, 12.7062), (4, 2.7764), (9, 2.2622), (30, 2.0423)):
        assert compare.t_quantile(0.975, df) == pytest.approx(t, abs=1e-4)
    # per-seed success rates 0.6 0.8 1.0 0.8 0.8: mean 0.8, sd = sqrt(0.08 / 4) = 0.141421,
    # half width = 2.776445 * 0.141421 / sqrt(5) = 0.175598
    m, lo, hi = compare.t_interval([0.6, 0.8, 1.0, 0.8, 0.8], clip=(0.0, 1.0))
    assert (m, lo, hi) == pytest.approx((0.8, 0.624402, 0.975598), abs=1e-6)
    assert compare.t_interval([0.9, 1.0, 1.0], clip=(0.0, 1.0))[2] == 1.0            # clipped
    assert math.isnan(compare.t_interval([0.5])[1])                                  # one seed: no interval
    # Wilson, 8 of 10, z = 1.96: centre (0.8 + 0.192)/1.384 = 0.716763, half 0.226355
    p, lo, hi = compare.wilson(8, 10)
    assert (p, lo, hi) == pytest.approx((0.8, 0.490162, 0.943318), abs=1e-5)
    assert compare.wilson(0, 10)[1] == 0.0 and compare.wilson(0, 10)[2] == pytest.approx(0.277533, abs=1e-5)


def test_grid_is_data_and_filters_work(tmp_path):
    full = compare.load_grid(quick=False)
    cells = compare.build_cells(full, tmp_path)
    assert len(full["seeds"]) >= 5
    assert {c["method"] for c in cells} == {"greedy", "cem", "gradient", "sac", "ppo", "pets", "latent", "planet", "apg", "distill"}
    heldout = set(full["heldout"])
    # honest names: the ensemble world model is PETS-style, PlaNet is the RSSM; both run agents.planet
    pets, rssm = (compare.build_cells(full, tmp_path, methods=[m], targets=["random"], seeds=[0])[0]
                  for m in ("pets", "planet"))
    assert pets["argv"][1] == rssm["argv"][1] == "agents.planet"
    assert "--preset" not in pets["argv"] and rssm["argv"][rssm["argv"].index("--preset") + 1] == "rssm"
    assert "PETS" in compare.method_label(full, "pets") and "RSSM" in compare.method_label(full, "planet")
    # the main grid: every main row on every main task it can run (learners train on random and random_curve and
    # are evaluated on the held-out shapes), five seeds
    main = {(m, v) for m, v in compare.main_rows(full)}
    assert {m for m, _ in main} == {"greedy", "cem", "gradient", "sac", "ppo", "pets", "latent", "planet", "apg"}
    for m, v in main:
        tasks = {c["target"] for c in cells if (c["method"], c["variant"]) == (m, v)}
        kind = full["methods"][m]["kind"]
        assert tasks >= ({"random", "random_curve"} | (heldout if kind == "planner" else set())), (m, v)
        if kind == "agent":
            assert "eval_targets" in full["methods"][m]["variants"][v].get("set", {}), (m, v)
    heldout = set(full["heldout"])
    routes = set(full["routes"])                        # the routing tasks (tests/test_compare_routing.py)
    assert {"horizontal", "vertical", "diagonal", "antidiagonal", "random", "random_curve"} | heldout | routes \
        == {c["target"] for c in cells}
    assert not any(c["target"] in heldout for c in cells if c["kind"] == "agent")     # no learner trains on them
    arc = compare.build_cells(full, tmp_path, methods=["cem"], targets=["arc"], seeds=[0])[0]
    assert arc["argv"][arc["argv"].index("--target") + 1] == "planners/targets/arc.npy"
    assert {c["variant"] for c in cells if c["method"] == "sac"} == {"tuned", "tuned_image", "points", "points_utd1",
                                                                          "image", "abs_diff", "delta_gain", "route"}
    assert not any(c["target"] in full["heldout_routes"] for c in cells if c["kind"] == "agent")   # nor on these
    # a planner's random cell is one command, episode i on env.reset(seed=eval_seed + i) as the learners'
    rnd, = compare.build_cells(full, tmp_path, methods=["cem"], variants=["default"], targets=["random"], seeds=[1])
    assert "&&" not in compare.command_line(rnd) and rnd["argv"][rnd["argv"].index("--target") + 1] == "random"
    sel = compare.build_cells(full, tmp_path, methods=["sac"], targets=["random"], seeds=[3])
    assert len(sel) == 7 and all(c["seed"] == 3 for c in sel)
    for c in sel:                                                 # the baselines keep SB3's settings explicitly
        preset = c["argv"][c["argv"].index("--preset") + 1] if "--preset" in c["argv"] else "tuned"
        assert preset == ("tuned" if c["variant"] in ("tuned", "tuned_image") else "sb3-default")
    img, = compare.build_cells(full, tmp_path, methods=["ppo"], variants=["image_e2e"], targets=["random"], seeds=[0])
    assert img["argv"][img["argv"].index("--preset") + 1] == "image"        # pictures: params/ppo-image.yaml
    for method in ("ppo", "sac", "pets", "cem"):                            # the perception rows read the pictures
        cell, = compare.build_cells(full, tmp_path, methods=[method], variants=["tuned_image"], targets=["random"],
                                    seeds=[0])
        assert cell["argv"][cell["argv"].index("--perception") + 1] == "models/perception64.pt"
        assert (Path(__file__).parents[1] / "models/perception64.pt").is_file()
    # each seed seeds the learner, its evaluation starts, and the planners' starts and generators
    c = sel[0]
    assert c["argv"][c["argv"].index("--seed") + 1] == "3" and "eval_seed=13000" in c["argv"]
    p = compare.build_cells(full, tmp_path, methods=["cem"], targets=["diagonal"], seeds=[2])[0]
    assert p["argv"][p["argv"].index("--seed") + 1] == "12000"
    # --learner-device: learners' networks there, the rope in the CPU kernel; planners untouched
    dev = compare.build_cells(full, tmp_path, methods=["sac", "cem"], targets=["random"], seeds=[0],
                              learner_device="cuda")
    learner, planner = (next(c for c in dev if c["kind"] == k) for k in ("agent", "planner"))
    assert learner["argv"][-6:-2] == ["--set", "device=cuda", "--set", "env_device=cpu"]
    assert learner["learner_device"] == "cuda"
    assert not any("device" in a for a in planner["argv"]) and "learner_device" not in planner
    assert compare.machine_label({"_machine": {"cpus": 16, "gpu": "H100"}}) == "16-core CPU + H100"
    assert compare.machine_label({}) == "machine not recorded"


def test_quick_run_writes_a_well_formed_table(quick):
    root, _ = quick
    md = (root / "RESULTS.md").read_text()
    assert "QUICK RUN" in md and "NOT results" in md
    assert "**Budgets.** tiny, a format example only: planners 3 moves" in md
    tables, header = parse_tables(md)
    assert header == compare.COLUMNS
    assert [r["method"] for r in tables["diagonal"]] == ["greedy", "cem", "sac"]
    assert [r["method"] for r in tables["random"]] == ["greedy"]
    for rows in tables.values():
        for r in rows:
            assert r["command"].startswith("`python -m benchmarks.compare --quick --methods ")
            assert r["seeds × episodes"] == "1 × 2"
            for col in (compare.COLUMNS[3], compare.COLUMNS[4]):
                t_part, w_part = r[col].split("; ")
                assert t_part.endswith("(n=1)")                       # one seed: no t-interval
                p, lo, hi = map(float, re.findall(r"[\d.]+", w_part))
                assert 0.0 <= lo <= p <= hi <= 1.0
    sac = tables["diagonal"][2]
    assert sac["env steps / cell"] == "64" and sac["sim evals / episode"] == "—"
    assert float(tables["diagonal"][1]["sim evals / episode"]) > 0          # CEM simulates
    rnd = json.loads((root / "cells/greedy/default/random/seed0/results.json").read_text())
    assert len(rnd["episodes"]) == 2 and {e["target_name"] for e in rnd["episodes"]} <= set(compare.NAMED)
    figs = sorted(p.name for p in (root / "figures").glob("*.png"))
    assert "quick_gallery_diagonal.png" in figs and "quick_gallery_random.png" in figs
    assert "quick_planner_error_vs_evals_diagonal.png" in figs and "quick_success_vs_steps_diagonal.png" in figs
    for name in figs:                                       # each figure drawn is linked from the report
        assert f"(figures/{name})" in md


def test_cost_section_puts_planners_and_learners_in_one_currency(quick):
    root, _ = quick
    md = (root / "RESULTS.md").read_text()
    section = md.split("## Planning against learning: what each costs")[1].split("\n## ")[0]
    rows = [[c.strip() for c in line.strip().strip("|").split(" | ")] for line in section.splitlines()
            if line.startswith("| diagonal")]
    by = {r[1]: r for r in rows}
    assert set(by) == {"greedy", "cem", "sac"}
    cells = root / "cells"
    cem = json.loads((cells / "cem/default/diagonal/seed0/results.json").read_text())
    sac = json.loads((cells / "sac/points/diagonal/seed0/results.json").read_text())
    cem_moves = sum(e["steps"] for e in cem["episodes"]) / len(cem["episodes"])
    cem_per_ep = cem["sim_evals"] / len(cem["episodes"]) + cem_moves           # simulated + executed moves
    assert float(by["cem"][6]) == pytest.approx(cem_per_ep, abs=0.5) and by["cem"][5] == "0"
    sac_per_ep = sum(e["steps"] for e in sac["episodes"]) / len(sac["episodes"])
    assert by["sac"][5] == "64" and float(by["sac"][6]) == pytest.approx(sac_per_ep, abs=0.05)
    expected = 64 / (cem_per_ep - sac_per_ep)                                  # episodes until SAC is cheaper
    assert float(by["sac"][9].split(";")[0]) == pytest.approx(expected, abs=0.5)
    assert compare.payback({"train_moves": 100.0, "episode_moves": 5.0}, {"episode_moves": 3.0}, "moves") == math.inf
    assert "quick_cost_diagonal.png" in {p.name for p in (root / "figures").glob("*.png")}


def test_heldout_rows_come_from_the_learners_trained_elsewhere():
    cell = {"target": "random_curve", "method": "ppo", "variant": "tuned"}
    res = {"episodes": [{"success": True, "steps": 4, "final_error": 0.005}],
           "heldout": {"arc": {"episodes": [{"success": False, "steps": 100, "final_error": 0.05}],
                               "success_rate": 0.0}}}
    planner = ({"target": "arc", "method": "cem", "variant": "default"}, {"episodes": []})
    groups = compare.task_groups([(cell, res), planner], "arc")
    assert set(groups) == {("cem", "default", "arc"), ("ppo", "tuned", "random_curve")}
    (_, sub), = groups[("ppo", "tuned", "random_curve")]
    assert sub["episodes"] == res["heldout"]["arc"]["episodes"]
    assert set(compare.task_groups([(cell, res), planner], "random_curve")) == {("ppo", "tuned", "random_curve")}


def test_resume_skips_finished_cells(quick, capsys):
    root, argv = quick
    files = sorted((root / "cells").glob("*/*/*/seed*/results.json"))
    assert len(files) == 4
    before = {f: f.stat().st_mtime_ns for f in files}
    logs = {f: f.read_text() for f in (root / "cells").glob("*/*/*/seed*/log.txt")}
    capsys.readouterr()
    assert compare.main(argv) == 0
    assert "cells: 0 run, 4 already finished (skipped), 0 failed" in capsys.readouterr().out
    assert {f: f.stat().st_mtime_ns for f in files} == before
    assert {f: f.read_text() for f in logs} == logs                     # no entry point was started again
    # an unfinished cell (results.json removed) is the only one that runs again
    files[0].unlink()
    cells = compare.build_cells(compare.load_grid(quick=True), root / "cells", ["greedy", "cem", "sac"], seeds=[0])
    results = compare.run_cells(cells, jobs=1, progress=False)
    assert sorted(r["status"] for r in results) == ["done", "skipped", "skipped", "skipped"]


@pytest.mark.ecosystem    # run by .ci/run after installing the optional extras
def test_ray_smoke(tmp_path):
    ray = pytest.importorskip("ray")
    grid = compare.load_grid(quick=True)
    cells = compare.build_cells(grid, tmp_path, methods=["greedy"], targets=["diagonal"], seeds=[0])
    try:
        results = compare.run_cells(cells, ray_address="local", progress=False)
    finally:
        ray.shutdown()
    assert [r["status"] for r in results] == ["done"]
    assert (Path(cells[0]["dir"]) / "results.json").exists()


def test_partial_report_names_the_cells_not_run(quick, tmp_path):
    import shutil
    root, _ = quick               # the quick planners' cells are also cells of the full grid (sac/points/diagonal not)
    cells_dir = tmp_path / "cells"
    shutil.copytree(root / "cells", cells_dir)
    for meta in cells_dir.rglob("cell.json"):       # their stored (quick) settings would keep them out of the report
        meta.unlink()
    full = compare.load_grid(quick=False)
    compare.write_report(full, cells_dir, tmp_path / "R.md", None)
    md = (tmp_path / "R.md").read_text()
    n = len(compare.build_cells(full, cells_dir))
    assert f"3 of {n} cells finished" in md
    assert f"**Partial comparison: {n - 3} of {n} cells not run yet**" in md
    assert "ppo/points/random: 0 1 2 3 4" in md and "greedy/default/diagonal: 1 2 3 4;" in md
    # the cells outside the main grid are counted and priced (the quick run finished two of them: the diagonal's)
    main = full["main"]
    rows = set(main["rows"]) | set(main.get("image_rows", []))
    outside = [c for c in compare.build_cells(full, cells_dir)
               if f"{c['method']}/{c['variant']}" not in rows or c["target"] not in main["targets"]]
    assert re.search(rf"Of them, {len(outside) - 2} are outside the main grid \(the secondary rows, the precision "
                     r"rows and the named lines\): ≈ \d+\.\d CPU-hours", md)
    budgets = " ".join(full["budgets"].split())                # the grid's own budget statement, reflowed
    assert "measure early learning" in budgets and f"**Budgets.** {budgets}" in md


def test_grid_budgets_must_be_text(tmp_path):
    bad = tmp_path / "grid.yaml"
    bad.write_text("full: {seeds: [0], targets: [diagonal], episodes: 1, eval_seed_base: 0, budgets: [1, 2], methods: {}}")
    with pytest.raises(ValueError, match=r"'budgets' must be text.*\[1, 2\]"):
        compare.load_grid(path=bad)


def test_report_shows_where_a_cell_ran_and_how_it_was_resumed(quick, tmp_path):
    import shutil
    root, _ = quick
    cells_dir = tmp_path / "cells"
    shutil.copytree(root / "cells", cells_dir)
    grid = compare.load_grid(quick=True)
    sac_cell = compare.build_cells(grid, cells_dir, methods=["sac"], targets=["diagonal"], seeds=[0])[0]
    meta_path = Path(sac_cell["dir"]) / "cell.json"
    meta = json.loads(meta_path.read_text())
    assert meta["machine"]["cpus"] >= 1                      # recorded by the harness when the cell ran
    meta.update(learner_device="cuda", resume_command="python -m agents.sac --out X --resume --device cpu",
                machine=dict(meta["machine"], gpu="Some GPU", note="resumed on a CPU"))
    meta_path.write_text(json.dumps(meta))
    from benchmarks.compare.report import KEPT
    (tmp_path / "R.md").write_text(f"# an old report\n\n{KEPT}\n\n## Calibration\n\nhand table\n")
    compare.write_report(grid, cells_dir, tmp_path / "R.md", None)
    md = (tmp_path / "R.md").read_text()
    assert "an old report" not in md and md.endswith(f"{KEPT}\n\n## Calibration\n\nhand table\n")   # kept
    assert "(1 of 1 seeds with --learner-device: machines in the per-seed list)" in md
    assert "--learner-device cuda" in md
    assert "` then `python -m agents.sac --out X --resume --device cpu` (" in md
    assert "+ Some GPU; resumed on a CPU)" in md


def test_payback_only_for_learners_about_as_successful_as_cem():
    def row(method, success, train, per):
        return {"method": method, "variant": "v", "trained_on": "random", "success": success, "moves": per,
                "train_moves": train, "train_s": train / 1000, "episode_moves": per, "episode_s": per / 100}
    cem = row("cem", 1.0, 0.0, 1010.0)
    lines = compare.cost_section({"random": [cem, row("ppo", 0.97, 1000.0, 10.0), row("sac", 0.5, 1000.0, 10.0)]},
                                 {"name": "full"})
    ppo_line, = [x for x in lines if "| ppo |" in x]
    sac_line, = [x for x in lines if "| sac |" in x]
    assert ppo_line.endswith("| 1; 0 |")                     # 1000 / (1010 - 10) = 1 episode; 1 s / 10 s per ep
    assert sac_line.endswith("| — (less success than CEM) |")


# ---------------------------------------------------------------- the results as committed data


def test_skip_recorded_continues_a_grid_whose_run_folders_are_gone(quick, tmp_path, capsys):
    """A new machine has the committed records but no run folders: --skip-recorded runs only the cells without a
    record made with the grid's settings now; without the flag every cell runs again (a reproduction)."""
    from benchmarks.compare.cli import _finished
    root, _ = quick
    cells = compare.build_cells(compare.load_grid(quick=True), root / "cells", ["greedy", "cem", "sac"], seeds=[0])
    results = tmp_path / "cells.jsonl"
    assert compare.collect([(c, *_finished(c)) for c in cells], results) == (4, 4)
    fresh = tmp_path / "new_machine"
    argv = [*ARGS, "--out", str(fresh), "--results", str(results), "--no-report"]
    assert compare.main([*argv, "--list"]) == 0
    assert capsys.readouterr().out.count("todo    ") == 4                  # without the flag: all four again
    assert compare.main([*argv, "--skip-recorded"]) == 0
    out, err = capsys.readouterr()
    assert "4 cell(s) recorded in" in err and "cells: 0 run, 0 already finished (skipped), 0 failed" in out
    assert not list(fresh.rglob("results.json"))
    # a record made with other settings than the grid's is no result for the cell now: that cell runs
    recs = compare.read_records(results)
    greedy = next(r for r in recs if r["method"] == "greedy" and r["target"] == "diagonal")
    greedy["argv"] = [*greedy["argv"], "--max-steps", "99"]
    compare.write_records(recs, results)
    assert compare.main([*argv, "--skip-recorded"]) == 0
    assert "cells: 1 run, 0 already finished" in capsys.readouterr().out
    assert [p.parent.parent.name for p in fresh.rglob("results.json")] == ["diagonal"]
    with pytest.raises(SystemExit) as exit_:                                 # flags that do not go together
        compare.main([*argv, "--skip-recorded", "--report-only"])
    assert exit_.value.code == 2


def test_records_rebuild_the_report_the_run_folders_give(quick, tmp_path):
    """--collect turns the finished cells into records; the report from the records equals the report from the
    folders (but for the command that rebuilds it), and collecting again writes the same bytes."""
    root, _ = quick
    results = tmp_path / "cells.jsonl"
    argv = [*ARGS, "--out", str(root / "cells"), "--results", str(results)]
    assert compare.main([*argv, "--collect", "--report", str(tmp_path / "A.md"), "--no-figures"]) == 0
    first = results.read_bytes()
    assert len(first.splitlines()) == 4
    assert compare.main([*argv, "--collect", "--report", str(tmp_path / "A.md"), "--no-figures"]) == 0
    assert results.read_bytes() == first                                              # stable
    compare.write_report(compare.load_grid(quick=True), root / "cells", tmp_path / "F.md", None)  # the folders now
    from_folders = (tmp_path / "F.md").read_text()
    from_records = (tmp_path / "A.md").read_text()

    def body(md):
        return [line for line in md.splitlines() if not line.startswith("Grid `quick`")]
    assert body(from_records) == body(from_folders)
    assert f"--report-only --results {results}" in from_records
    # a record whose settings differ from the grid's is left out and named, as a changed folder would be
    recs = compare.read_records(results)
    recs[0]["argv"] = [*recs[0]["argv"], "--horizon", "9"]
    compare.write_records(recs, results)
    grid = compare.load_grid(quick=True)
    compare.write_report(grid, root / "cells", tmp_path / "C.md", None, records=compare.read_records(results))
    assert "1 finished cell(s) ran with other settings than the grid's now" in (tmp_path / "C.md").read_text()
    results.write_text(first.decode() + "not json\n")
    with pytest.raises(ValueError, match="cells.jsonl:5: not a cell record"):
        compare.read_records(results)


def test_the_committed_report_is_rebuilt_from_the_committed_records(tmp_path):
    """docs/RESULTS.md is exactly what `python -m benchmarks.compare --report-only` writes from
    docs/results/cells.jsonl (no run folder needed)."""
    root = Path(__file__).parents[1]
    records = compare.read_records(root / "docs/results/cells.jsonl")
    assert records, "no committed records"
    grid = compare.load_grid()
    compare.write_report(grid, "runs/compare", tmp_path / "RESULTS.md", None, records=records,
                         source="python -m benchmarks.compare --report-only")
    assert (tmp_path / "RESULTS.md").read_text() == (root / "docs/RESULTS.md").read_text(), \
        "docs/RESULTS.md is stale: rebuild it with python -m benchmarks.compare --report-only"
    for name in re.findall(r"\]\(figures/([^)]+)\)", (root / "docs/RESULTS.md").read_text()):
        assert (root / "docs/figures" / name).is_file(), name
    # the README's summary block is the same records' short table
    from benchmarks.compare.report import readme_summary
    block = readme_summary(grid, records, compare.build_cells(grid, "runs/compare"))
    assert block in (root / "README.md").read_text(), "README.md's summary block is stale: --report-only rewrites it"


def test_episodes_pair_only_where_start_and_target_agree():
    from benchmarks.compare.summary import pairs
    a = {(0, 0): {"start_error": 0.1, "target_name": "diagonal", "success": True, "steps": 5},
         (0, 1): {"start_error": 0.2, "target_name": "vertical", "success": True, "steps": 5},
         (0, 2): {"success": True, "steps": 5},
         (1, 0): {"start_error": 0.3, "target_name": "vertical", "success": True, "steps": 5}}
    b = {(0, 0): {"start_error": 0.1 + 1e-8, "target_name": "diagonal", "success": True, "steps": 7},
         (0, 1): {"start_error": 0.25, "target_name": "vertical", "success": True, "steps": 7},   # another start
         (0, 2): {"start_error": 0.2, "target_name": "vertical", "success": True, "steps": 7}}    # unverifiable
    pr, unverified, mismatched = pairs(a, b)
    assert [x["start_error"] if "start_error" in x else None for x, _ in pr] == [0.1, None]
    assert (unverified, mismatched) == (1, 1)


def test_summary_names_missing_cells_with_their_cost():
    from benchmarks.compare.summary import missing_section, summary_table
    grid = compare.load_grid()
    ep = {"success": True, "steps": 10, "final_error": 0.005, "start_error": 0.1, "target_name": "diagonal"}
    done = {("cem", "default", "random", s): {"episodes": [ep] * 20, "sim_evals": 60000, "env_steps": 200,
                                              "wall_s": 60.0} for s in (0, 1, 2)}
    table = "\n".join(summary_table(grid, done))
    cem_row = next(line for line in table.splitlines() if line.startswith("| CEM"))
    assert "| 100 % · 10.0 (3/5 seeds) | not run |" in cem_row and "| 3,010 | 3.0 s / episode |" in cem_row
    planet_image = next(line for line in table.splitlines() if "| image |" in line and "RSSM" in line)
    assert "| not run: too costly here |" in planet_image          # compare.yaml marks it too_costly_here
    missing = "\n".join(missing_section(grid, done))
    # 2 + 5 x 5 cells left, priced at the row's measured minute per cell
    assert "| cem/default | 27 | random (3 4); random_curve (0 1 2 3 4);" in missing
    assert " | 1 (measured) | 0.5 |" in missing.split("| cem/default |")[1].splitlines()[0]
    gradient = grid["methods"]["gradient"]["variants"]["default"]["cpu_min"]            # none finished: the estimate
    row = missing.split("| gradient/default |")[1].splitlines()[0]
    assert f" | {gradient:.0f} (estimate) | {30 * gradient / 60:.1f} | queued: " in row
    # a row the grid marks too costly for this machine says why, from compare.yaml
    grid["methods"]["gradient"]["variants"]["default"]["too_costly_here"] = "needs 9 h per cell"
    row = "\n".join(missing_section(grid, done)).split("| gradient/default |")[1].splitlines()[0]
    assert row.endswith(" | needs 9 h per cell |")


def test_a_cell_that_reads_another_cells_run_names_its_own_seed_and_target():
    from benchmarks.compare.grid import build_cells, load_grid
    cells = build_cells(load_grid(), "runs/x", methods=["distill"], seeds=[1, 3])
    assert [c["seed"] for c in cells] == [1, 3]
    for c in cells:
        i = c["argv"].index(f"teacher=runs/x/ppo/fewest_moves/{c['target']}/seed{c['seed']}")
        assert c["argv"][i - 1] == "--set"
    assert "{seed}" in cells[0]["grid_entry"]["set"]["teacher"]      # compare.yaml's entry, as written


def test_a_learner_is_charged_the_simulation_it_acts_and_trains_with():
    from benchmarks.compare.costs import row_cost
    from benchmarks.compare.stats import row_stats
    episode = {"success": True, "steps": 10, "final_error": 0.005, "start_error": 0.1, "target_name": "diagonal"}
    alone = {"episodes": [episode] * 2, "env_steps": 1000, "wall_s": 60.0, "eval_s_per_episode": 0.01}
    rollouts = {**alone, "sim_evals_per_move": 150.0}                      # agents/common/rollout.py
    distilled = {**alone, "teacher_sim_evals": 5000}                        # agents/distill.py
    cost = {name: row_cost("ppo", [r], row_stats([r])) for name, r in
            [("alone", alone), ("rollouts", rollouts), ("distilled", distilled)]}
    assert cost["alone"]["episode_moves"] == 10 and cost["alone"]["train_moves"] == 1000
    assert cost["rollouts"]["episode_moves"] == 10 * (1 + 150)
    assert cost["distilled"]["train_moves"] == 1000 + 5000 and cost["distilled"]["episode_moves"] == 10
    # the summary figure charges the same, and names a method's second main row by its variant
    from benchmarks.compare.figures import _summary_points
    points = {p["label"]: p["spent"] for p in _summary_points(compare.load_grid(), {
        ("ppo", "tuned", "random", 0): alone, ("ppo", "fewest_moves", "random", 0): rollouts})}
    assert points == {"PPO": 1000 + 2 * 10, "PPO + policy rollouts": 1000 + 2 * 10 * (1 + 150)}


def test_paired_interval_is_clipped_to_what_a_success_difference_can_be():
    from benchmarks.compare.summary import _ci
    assert _ci([-1.0] * 19 + [0.0], 100, 0, bounds=(-1.0, 1.0)) == "-95 [-100, -85]"   # unclipped: -105
    assert _ci([-1.0] * 19 + [0.0], 100, 0) == "-95 [-105, -85]"
    assert _ci([7.0]) == "+7.0 (no interval)"


def test_gallery_shows_the_main_rows_and_says_which_cells_ran_without_shapes():
    from benchmarks.compare.figures import NO_SHAPES, _gallery_panels
    grid = compare.load_grid()
    sh = {"start": [[0, 0], [1, 0]], "final": [[0, 0], [0, 1]], "target": [[0, 0], [0, 1]]}
    ep = [{"success": True, "steps": 3, "final_error": 0.005}]

    def cell(method, variant, target, seed, **rec):
        return {"method": method, "variant": variant, "target": target, "seed": seed}, {"episodes": ep, **rec}
    done = [cell("cem", "default", "random", 0, shapes=sh), cell("cem", "default", "random", 1),   # ran, no shapes
            cell("sac", "points", "random", 0, shapes=sh),                                       # secondary row
            cell("pets", "tuned_image", "random", 0),                                            # no shapes at all
            cell("ppo", "tuned", "random", 0, heldout={"arc": {"shapes": sh}}),                  # not heldout's source
            cell("ppo", "tuned", "random_curve", 2, heldout={"arc": {"shapes": sh}})]
    rows = dict(_gallery_panels(grid, done, "random"))
    assert set(rows) == {"cem/default"}
    assert rows["cem/default"] == [sh, NO_SHAPES, None, None, None]
    held = dict(_gallery_panels(grid, done, "arc"))
    assert held == {"ppo/tuned\n(trained on random_curve)": [None, None, sh, None, None]}
