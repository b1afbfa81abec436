"""Runs lose nothing and run what they say: a resume after the last checkpoint changes nothing, a second writer is
refused, a resume refuses changed settings, PPO makes exactly --total-steps, a damaged checkpoint is named."""
import json
import os

import pytest

from agents import planet, ppo
from planners import greedy
from diffdlo.utils.files import OutBusyError, out_lock

TINY = "param_overrides={n_nodes: 6, length: 0.15, max_speed: 1.0, settle_max_substeps: 30, settle_check_every: 10}"
PLANET = ["--num-envs", "4", "--set", TINY, "--max-steps", "8", "--eval-every", "64", "--eval-episodes", "4",
          "--checkpoint-every", "64", "--no-progress", "--set", "seed_episodes=4", "--set", "train_every=32",
          "--set", "updates_per_train=4", "--set", "batch_size=8", "--set", "model_hidden=[16,16]",
          "--set", "candidates=12", "--set", "elites=3", "--set", "openloop_episodes=4"]


def files(out):
    return {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.suffix in (".csv", ".json")}


def test_planet_resumed_after_its_last_checkpoint_changes_nothing(tmp_path):
    out = tmp_path / "run"
    assert planet.main(["--out", str(out), "--total-steps", "96", *PLANET]) == 0
    before = files(out)
    assert planet.main(["--out", str(out), "--resume", "--total-steps", "96", "--no-progress"]) == 0
    after = files(out)
    assert after.keys() == before.keys()
    for name in before:
        if name.endswith(".csv"):
            assert after[name] == before[name], name                  # no duplicate eval or open-loop row
    a, b = json.loads(before["results.json"]), json.loads(after["results.json"])
    assert {k: v for k, v in a.items() if "wall" not in k and "plan_" not in k} == \
        {k: v for k, v in b.items() if "wall" not in k and "plan_" not in k}


def test_resume_refuses_settings_that_differ_from_the_checkpoint(tmp_path, capsys):
    out = tmp_path / "run"
    assert planet.main(["--out", str(out), "--total-steps", "64", *PLANET]) == 0
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        planet.main(["--out", str(out), "--resume", "--total-steps", "128", "--seed", "3", "--target", "diagonal",
                     "--set", "lr=0.01", "--no-progress"])
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert "seed (the run's 0, asked 3)" in err and "target (the run's 'random', asked 'diagonal')" in err
    assert "lr (the run's 0.001, asked 0.01)" in err and "total_steps" not in err


def test_a_second_writer_is_refused_and_a_dead_writers_lock_taken_over(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / ".lock").write_text(str(os.getppid()))                  # a live process (the test's parent) holds it
    with pytest.raises(OutBusyError, match=f"being written by pid {os.getppid()}"):
        with out_lock(out):
            pass
    with pytest.raises(SystemExit) as exc:                          # the planners' command line says so in one line
        greedy.main(["--out", str(out), "--quiet", "--no-gif"])
    assert exc.value.code == 2 and f"pid {os.getppid()}" in capsys.readouterr().err
    (out / ".lock").write_text("999999999")                        # a pid that does not exist: stale
    with out_lock(out) as lock:
        assert json.loads(lock.read_text())["pid"] == os.getpid()
    assert not (out / ".lock").exists()


def test_a_damaged_checkpoint_is_named_in_one_line(tmp_path, capsys):
    out = tmp_path / "run"
    assert planet.main(["--out", str(out), "--total-steps", "64", *PLANET]) == 0
    (out / "checkpoint.pt").write_bytes(b"not a checkpoint")
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        planet.main(["--out", str(out), "--resume", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert exc.value.code == 2 and "checkpoint.pt is not a readable checkpoint" in err


def test_ppo_makes_exactly_total_steps_with_a_short_last_rollout(tmp_path):
    out = tmp_path / "run"
    argv = ["--out", str(out), "--total-steps", "100", "--num-envs", "4", "--set", TINY, "--max-steps", "8",
            "--eval-every", "1000", "--eval-episodes", "4", "--no-progress", "--set", "n_steps=16",
            "--set", "batch_size=16", "--set", "hidden=[16,16]"]
    assert ppo.main(argv) == 0
    assert json.loads((out / "results.json").read_text())["env_steps"] == 100   # 64 + a rollout of 9 x 4
