"""benchmarks/studies/precision_limits.py: how far a rope the settle cap stopped still moves."""
import json

import pytest

from benchmarks.studies import precision_limits as pl
from tests.conftest import cli_error


def test_ropes_start_near_their_straight_target():
    import torch
    from diffdlo import Simulator, load_params
    from diffdlo.tasks.rewards import node_errors
    sim = Simulator(load_params("cable"), dtype=torch.float64)
    rope, target = pl.near_target_ropes(sim, 8, 0.05, torch.Generator().manual_seed(0))
    links = (rope[:, 1:] - rope[:, :-1]).norm(dim=-1)
    assert torch.allclose(links, torch.full_like(links, sim.params.rest_length))     # at rest length
    err = node_errors(rope, target).mean(-1)
    assert (err > 1e-4).all() and (err < 0.02).all()                                 # millimetres off, not straight


def test_the_rope_keeps_moving_after_the_cap_and_the_drift_grows(tmp_path, capsys):
    res = pl.measure(ropes=6, seed=1)
    assert 0.0 <= res["stopped_by_cap"] <= 1.0
    drift = [r["drift_mean"]["median"] for r in res["relax"]]
    assert [r["seconds"] for r in res["relax"]] == list(pl.RELAX_SECONDS)
    assert 0 < drift[0] < drift[1] < drift[2] < 0.01                                 # creeping, sub-centimetre
    assert all(r["drift_worst"]["median"] >= r["drift_mean"]["median"] for r in res["relax"])
    assert pl.main(["--ropes", "3", "--out", str(tmp_path)]) == 0
    assert json.loads((tmp_path / "results.json").read_text())["seed"] == 0
    assert "relaxing on for" in capsys.readouterr().out
    (tmp_path / "results.json").write_text(json.dumps({"ropes": 3}))
    assert str(tmp_path) in cli_error(pl.main, ["--ropes", "3", "--out", str(tmp_path)], capsys)   # not overwritten
    assert json.loads((tmp_path / "results.json").read_text())["ropes"] == 3


@pytest.mark.parametrize("argv,shown", [(["--ropes", "0"], "--ropes must be at least 1, got 0"),
                                        (["--sigma", "nan"], "--sigma must be a positive number, got nan"),
                                        (["--sigma", "-0.1"], "--sigma must be a positive number, got -0.1")])
def test_bad_arguments_are_refused_naming_them(argv, shown, capsys):
    assert shown in cli_error(pl.main, argv, capsys)
