"""A checkpoint cannot run code: every entry point that reads one (load_policy, python -m agents.tools.evaluate, a learner's
--resume, benchmarks/studies/planet_budget.py, benchmarks/gradients/apg_gradients.py) reads it with torch.load(weights_only=True) and
refuses a file that needs more than data, naming what it would need, before anything in it runs. Checkpoints of an
earlier version (numpy's RNG state as an array) still load and can be rewritten with --upgrade."""
from __future__ import annotations

import pytest
import torch

import agents
from agents.common import checkpoints
from agents import ppo
from agents.tools import evaluate as evaluate_cli
from agents.common.checkpoints import CHECKPOINT, load_checkpoint
from agents.common.config import load_config

pytestmark = pytest.mark.usefixtures("one_thread")

PO = dict(n_nodes=6, length=0.15, max_speed=1.0, settle_max_substeps=30, settle_check_every=10)
TINY = dict(param_overrides=PO, max_steps=4, num_envs=4, eval_episodes=4, checkpoint_every=10**9, eval_every=10**9,
            total_steps=32, hidden=[8, 8], n_steps=8, batch_size=16, n_epochs=1)


class Payload:
    """Unpickling this creates the file ``marker`` (a stand-in for any command a crafted file could run)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ppo")
    ppo.train(load_config(ppo.PPOConfig, "ppo", TINY), folder, progress=False)
    return folder


def planted(tmp_path, run, where: str):
    """A copy of a real checkpoint with the payload planted under ``where``; returns (folder, marker)."""
    marker = tmp_path / f"ran-{where}"
    ck = torch.load(run / CHECKPOINT, weights_only=True)
    ck[where] = Payload(marker)
    folder = tmp_path / where
    folder.mkdir()
    torch.save(ck, folder / CHECKPOINT)
    return folder, marker


def test_a_fresh_checkpoint_is_data_only(run):
    ck = torch.load(run / CHECKPOINT, map_location="cpu", weights_only=True)     # no allow-list needed
    assert ck["algo"] == "ppo" and isinstance(ck["rng"]["numpy"], dict)


@pytest.mark.parametrize("entry", ["load_checkpoint", "load_policy", "evaluate", "resume", "planet_budget",
                                   "apg_gradients"])
def test_a_planted_payload_is_refused_and_never_runs(entry, run, tmp_path, capsys):
    folder, marker = planted(tmp_path, run, "config")
    if entry == "load_checkpoint":
        with pytest.raises(ValueError, match="refused: loading it would run code or build objects"):
            load_checkpoint(folder / CHECKPOINT)
    elif entry == "load_policy":
        with pytest.raises(ValueError, match="refused") as exc:
            agents.load_policy(folder)
        assert "io.open" in str(exc.value) and str(folder / CHECKPOINT) in str(exc.value)
    elif entry == "evaluate":
        assert evaluate_cli.main([str(folder)]) == 2
    elif entry == "resume":
        with pytest.raises(SystemExit) as exc:
            ppo.main(["--out", str(folder), "--resume", "--no-progress"])
        assert exc.value.code == 2
    elif entry == "planet_budget":
        from benchmarks.studies import planet_budget
        with pytest.raises(SystemExit) as exc:
            planet_budget.main(["--run", str(folder), "--out", str(tmp_path / "budget")])
        assert exc.value.code == 2
    else:
        from benchmarks.gradients import apg_gradients
        with pytest.raises(SystemExit) as exc:
            apg_gradients.main(["--run", str(folder)])
        assert exc.value.code == 2
    if entry not in ("load_checkpoint", "load_policy"):
        assert "refused" in capsys.readouterr().err
    assert not marker.exists(), "the payload ran"


def test_an_earlier_versions_checkpoint_loads_and_upgrades(run, tmp_path, capsys):
    import numpy as np

    ck = torch.load(run / CHECKPOINT, weights_only=True)
    ck["rng"]["numpy"] = np.random.get_state()                   # as checkpoints were written before
    old = tmp_path / "old"
    old.mkdir()
    torch.save(ck, old / CHECKPOINT)
    with pytest.raises(Exception):                               # needs numpy's array: not data only
        torch.load(old / CHECKPOINT, weights_only=True)
    assert isinstance(load_checkpoint(old / CHECKPOINT)["rng"]["numpy"], tuple)      # still loads (allow-list)
    agents.load_policy(old)
    assert checkpoints.main(["--upgrade", str(old / CHECKPOINT)]) == 0
    assert (old / (CHECKPOINT + ".old")).exists()                # nothing lost
    new = torch.load(old / CHECKPOINT, weights_only=True)
    checkpoints.set_rng_state(new["rng"])
    assert np.array_equal(np.random.get_state()[1], ck["rng"]["numpy"][1])   # the same RNG state, as data
    assert checkpoints.main(["--upgrade", str(old / CHECKPOINT)]) == 2       # the .old would be overwritten
    assert "exists" in capsys.readouterr().err
