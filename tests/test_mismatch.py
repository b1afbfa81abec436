"""Planning under model mismatch: the planner's model (--params) and the real rope the env moves (--real-params,
--real-scale), and benchmarks/studies/mismatch.py."""
import json

import pytest
import torch

import diffdlo
from benchmarks.studies import mismatch
from planners import SimObjective
from planners import cem as cem_mod
from planners.cem import CEMPlanner
from planners.common import PHYSICAL, build_run, physical_values, scaled_params
from diffdlo.tasks.task import decode_node_action

TINY_CEM = ["--horizon", "1", "--candidates", "8", "--elites", "2", "--iterations", "1"]


def _executed_and_predicted(model, real, start):
    """One env move of the real rope from ``start``, and the planner's model's prediction of that same move."""
    env, planner, target = build_run(CEMPlanner, model, real, "diagonal", max_steps=5, success_tol=None,
                                     device="cpu", seed=0,
                                     options={"horizon": 1, "candidates": 8, "elites": 2, "iterations": 1})
    env.reset(seed=0)
    env.set_state(pos=start[None], target=target, steps=0)
    action = torch.tensor([[0.3, 0.9, 0.2]], dtype=env.dtype)
    node, delta = decode_node_action(action, planner.p)
    _, predicted = SimObjective(planner.sim, start, target).rollout_deltas(node[:, None], delta[:, None],
                                                                          return_states=True)
    env.step(action)
    return env.get_state().pos[0], predicted[0, 0], planner, env


def test_real_scale_changes_what_the_env_does_not_what_the_model_predicts(params):
    start = diffdlo.Simulator(params).random_shape(1, generator=torch.Generator().manual_seed(3))[0]
    executed, predicted, planner, env = _executed_and_predicted(params, params, start)
    assert planner.sim is env.sim                                   # no real params: the one simulator, as before
    assert torch.equal(executed, predicted)

    real = scaled_params(params, {"k_d": 2.0})
    executed_real, predicted_real, planner, env = _executed_and_predicted(params, real, start)
    assert planner.sim.params == params and env.sim.params == real
    assert torch.equal(predicted_real, predicted)                   # the model's prediction is untouched
    gap = (executed_real - predicted_real).norm(dim=-1).max()
    assert gap > 1e-3, gap                                          # the real rope moved otherwise


def test_results_json_records_both_parameter_sets(tmp_path, params):
    out = tmp_path / "run"
    rc = cem_mod.main(["--target", "vertical", "--max-steps", "1", "--real-scale", "k_d=2", "--real-scale",
                       "mass=0.5", "--out", str(out), "--quiet", "--no-gif", *TINY_CEM])
    assert rc == 0
    res = json.loads((out / "results.json").read_text())
    assert res["model_params"] == physical_values(params)
    assert res["real_params"] == {**physical_values(params), "k_d": params.k_d * 2, "mass": params.mass * 0.5}

    same = tmp_path / "same"
    assert cem_mod.main(["--target", "vertical", "--max-steps", "1", "--out", str(same), "--quiet", "--no-gif",
                         *TINY_CEM]) == 0
    res = json.loads((same / "results.json").read_text())
    assert "model_params" not in res and "real_params" not in res


BAD_SCALES = [["k_x=2"], ["k_f=2"], ["k_d"], ["k_d=0"], ["k_d=-1"], ["k_d=inf"], ["k_d=nan"], ["k_d=abc"],
              ["k_d=2", "k_d=3"]]


@pytest.mark.parametrize("items", BAD_SCALES, ids=[" ".join(i) for i in BAD_SCALES])
def test_bad_real_scale_is_refused_and_named(items, tmp_path, capsys):
    argv = [x for item in items for x in ("--real-scale", item)]
    rc = cem_mod.main([*argv, "--out", str(tmp_path / "run"), "--quiet", "--no-gif"])
    err = capsys.readouterr().err
    assert rc == 2 and items[-1] in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("field,value", [("n_nodes", 10), ("length", 0.6), ("action_scale", 0.05)])
def test_real_params_that_would_change_the_moves_are_refused(field, value, tmp_path, capsys):
    text = (diffdlo.planar.params.PARAMS_DIR / "cable.yaml").read_text()
    key = {"n_nodes": "n_nodes: 20", "length": "length: 0.5", "action_scale": "action_scale: 0.1"}[field]
    assert key in text
    path = tmp_path / "other.yaml"
    path.write_text(text.replace(key, f"{field}: {value}"))
    rc = cem_mod.main(["--real-params", str(path), "--out", str(tmp_path / "run"), "--quiet", "--no-gif"])
    err = capsys.readouterr().err
    assert rc == 2 and field in err and str(value) in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "run").exists()


def test_mismatch_benchmark_tiny_run_writes_its_table(tmp_path, capsys):
    out = tmp_path / "bench"
    argv = ["--target", "diagonal", "--seeds", "0", "--episodes", "1", "--max-steps", "2", "--cem-candidates", "8",
            "--cem-elites", "2", "--cem-iterations", "1", "--gradient-iters", "1", "--model-scale", "k_d=1.1",
            "--calibrate", "--calibration-moves", "4", "--out", str(out), "--quiet"]
    assert mismatch.main(argv) == 0
    printed = capsys.readouterr().out
    factors = mismatch.real_factors(0, 0.3)
    assert all(f"{k} {factors[k]:.3f}" in printed for k in PHYSICAL)       # the seed's factors are shown
    assert all(0.7 <= f <= 1.3 for f in factors.values())
    table = (out / "mismatch.md").read_text()
    assert (out / "mismatch.png").stat().st_size > 0                        # the picture beside the table
    for method in ("cem", "gradient"):
        for condition in ("matched", "oracle", "mismatched", "calibrated", "given"):
            assert f"| {method} | {condition} |" in table
    res = json.loads((out / "results.json").read_text())
    rows = {(r["method"], r["condition"]): r for r in res["rows"]}
    nominal = diffdlo.load_params()
    mis = rows["cem", "mismatched"]["per_seed"][0]
    assert mis["model_params"] == physical_values(nominal)
    assert mis["real_params"] == pytest.approx({k: getattr(nominal, k) * factors[k] for k in PHYSICAL})
    assert rows["gradient", "given"]["per_seed"][0]["model_params"]["k_d"] == pytest.approx(nominal.k_d * 1.1)
    assert rows["cem", "oracle"]["per_seed"][0]["model_params"] == mis["real_params"]
    fitted = rows["cem", "calibrated"]["per_seed"][0]["model_params"]      # fitted to 4 moves of the real rope
    real = mis["real_params"]
    for a in ("k_s", "k_b"):
        assert fitted[a] / fitted["k_d"] == pytest.approx(real[a] / real["k_d"], rel=0.03), a
    assert abs(fitted["k_s"] / fitted["k_d"] / (nominal.k_s / nominal.k_d) - factors["k_s"] / factors["k_d"]) < 0.03
    assert set(res["calibration"]["0"]["rel_error"]) == {"k_s/k_d", "k_b/k_d"}

    assert mismatch.main(argv) == 2                                 # never over an earlier benchmark
    assert "--overwrite" in capsys.readouterr().err
    assert (out / "mismatch.md").read_text() == table
