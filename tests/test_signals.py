"""Signals as the user meant them: a learner and a planner started with SIGINT *ignored* (as from a shell's background
job, nohup or a CI runner) still stop on SIGINT (and SIGTERM), with the shell's exit code and one line saying so. A
learner stops at its next step with a regular checkpoint that --resume continues (saved where checkpoint_every
saves: tests/test_kill.py checks that such a checkpoint resumes exactly). The calibration stops as the planners do."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TINY = ["--set", "param_overrides={n_nodes: 6, length: 0.15, max_speed: 1.0, settle_max_substeps: 30}",
        "--num-envs", "4", "--eval-episodes", "4", "--target", "horizontal", "--no-progress", "--threads", "1",
        "--set", "n_steps=16", "--set", "batch_size=32", "--set", "hidden=[16,16]", "--eval-every", "100000"]


def start_ignoring_sigint(cmd: list[str]) -> subprocess.Popen:
    """``cmd`` with SIGINT ignored from the start, as a background job inherits it."""
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "OMP_NUM_THREADS": "1"},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))


def wait_for(path: Path, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.time() + timeout
    while not path.exists():
        assert proc.poll() is None, f"ended before {path.name} appeared: {proc.communicate()}"
        assert time.time() < deadline, f"no {path} after {timeout} s"
        time.sleep(0.05)


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130)])     # SIGTERM: the same path (and the planner's)
def test_a_learner_stops_at_a_step_with_a_checkpoint_and_resumes_exactly(sig, code, tmp_path):
    out = tmp_path / "stopped"
    proc = start_ignoring_sigint([sys.executable, "-m", "agents.ppo", "--out", str(out), "--total-steps", "10000000",
                                  "--checkpoint-every", "10000000", *TINY])
    wait_for(out / "train.csv", proc)                       # training has begun (the first update logged)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    assert f"stopped by {signal.Signals(sig).name} at env step" in err and "--resume" in err
    assert "Traceback" not in err
    assert (out / "checkpoint.pt").exists() and not (out / "results.json").exists()
    import torch
    step = torch.load(out / "checkpoint.pt", weights_only=True)["step"]
    assert 0 < step < 10_000_000
    # the checkpoint is a regular one (saved where checkpoint_every saves; exact resume: tests/test_kill.py)
    done = subprocess.run([sys.executable, "-m", "agents.ppo", "--no-progress", "--out", str(out), "--resume",
                           "--total-steps", str(step + 64)], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert json.loads((out / "results.json").read_text())["env_steps"] == step + 64


def test_the_world_model_learner_stops_between_two_updates_of_a_phase(tmp_path):
    """A SIGTERM inside a training phase (here 100,000 updates) stops PlaNet's RSSM after the update in progress, its
    checkpoint keeping the updates left (the in-process test in tests/test_planet.py checks the exact resume)."""
    out = tmp_path / "rssm"
    proc = start_ignoring_sigint([sys.executable, "-m", "agents.planet", "--preset", "rssm", "--out", str(out),
                                  "--total-steps", "10000", "--max-steps", "8", *TINY[:9], "--threads", "1",
                                  "--set", "seed_episodes=2", "--set", "train_every=16",
                                  "--set", "updates_per_train=100000", "--set", "log_every=1", "--set", "batch_size=4",
                                  "--set", "chunk_length=4", "--set", "deter=8", "--set", "stoch=2",
                                  "--set", "hidden=8", "--set", "embed=8"])
    wait_for(out / "train.csv", proc)                       # the phase has begun (its first update logged)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 143 and "stopped by SIGTERM at env step" in err and "Traceback" not in err, err
    import torch
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    assert 0 < ck["pending_updates"] < 100_000 and ck["n_updates"] + ck["pending_updates"] == 100_000


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_planner_stops_on_a_signal_though_started_with_sigint_ignored(sig, code, tmp_path):
    out = tmp_path / "cem"
    proc = start_ignoring_sigint([sys.executable, "-m", "planners.cem", "--target", "random", "--episodes", "1000",
                                  "--quiet", "--no-gif", "--out", str(out)])
    wait_for(out / ".lock", proc)
    time.sleep(0.5)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code and f"cem: stopped by {signal.Signals(sig).name}" in err, err
    assert "Traceback" not in err
    assert not (out / ".lock").exists()                     # the lock is released: the folder is free again


def test_the_calibration_stops_on_sigterm_though_started_with_sigint_ignored(tmp_path):
    out = tmp_path / "cal"
    proc = start_ignoring_sigint([sys.executable, "-m", "diffdlo.calibration.calibrate", "--synthetic", "--moves", "8",
                                  "--iterations", "100000", "--method", "adam", "--no-progress", "--out", str(out)])
    wait_for(out / ".lock", proc)
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and "calibrate: stopped by SIGTERM" in err, err
    assert "Traceback" not in err and not (out / "results.json").exists() and not (out / ".lock").exists()


def test_nohup_is_respected_a_hangup_does_not_stop_a_run(tmp_path):
    """SIGHUP ignored on purpose (nohup) stays ignored: the run outlives its terminal; SIGTERM still stops it."""
    out = tmp_path / "cem"
    proc = subprocess.Popen([sys.executable, "-m", "planners.cem", "--target", "random", "--episodes", "1000",
                             "--quiet", "--no-gif", "--out", str(out)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    wait_for(out / ".lock", proc)
    proc.send_signal(signal.SIGHUP)
    time.sleep(1.0)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and "stopped by SIGTERM" in err
