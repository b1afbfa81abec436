"""The comparison's precision rows (issue 50): compare.yaml's `precise` variants and their declared `tolerance`
(checked by the grid loader) and their commands."""
import copy
from pathlib import Path

import pytest
import yaml

from benchmarks import compare
from benchmarks.compare.grid import row_tolerance
from benchmarks.compare.records import record_changes, record_key
from benchmarks.compare.settings import comparable_argv

ROOT = Path(__file__).parents[1]
PRECISE = ["cem", "gradient", "ppo", "pets", "latent"]
BASE = {"cem": "default", "gradient": "default", "ppo": "fewest_moves", "pets": "tuned", "latent": "tuned"}


# ---------------------------------------------------------------------- the grid's precision rows
def test_each_precise_row_declares_the_task_tolerance_on_the_two_random_tasks():
    grid = compare.load_grid()
    assert [(m, v) for m, spec in grid["methods"].items() for v in spec["variants"]
            if row_tolerance(grid, m, v) is not None] == [(m, "precise") for m in PRECISE]
    for method in PRECISE:
        v = grid["methods"][method]["variants"]["precise"]
        assert row_tolerance(grid, method, "precise") == (0.005, 0.02)
        assert v["targets"] == ["random", "random_curve"] and v["cpu_min"] > 0
    assert all(row_tolerance(grid, m, v) is None for m, spec in grid["methods"].items() for v in spec["variants"]
               if v != "precise")


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
