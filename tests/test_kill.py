"""Kill tests (slow: ``pytest -m slow tests/test_kill.py``): a learner killed with SIGKILL at several points of its
run (right after a checkpoint, and between two checkpoints) and resumed with --resume writes the same CSV logs and
results as the uninterrupted run."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parent.parent
TINY = ["--set", "param_overrides={n_nodes: 6, length: 0.15, max_speed: 1.0, settle_max_substeps: 30}",
        "--num-envs", "4", "--eval-episodes", "4", "--target", "horizontal", "--no-progress", "--threads", "1"]
RUNS = {
    "sac": ["--total-steps", "480", "--eval-every", "160", "--checkpoint-every", "96",
            "--set", "learning_starts=64", "--set", "batch_size=32", "--set", "hidden=[32,32]"],
    "ppo": ["--total-steps", "640", "--eval-every", "128", "--checkpoint-every", "64", "--set", "n_steps=16",
            "--set", "batch_size=32", "--set", "hidden=[32,32]"],
    "planet": ["--total-steps", "480", "--eval-every", "160", "--checkpoint-every", "96", "--max-steps", "8",
               "--set", "seed_episodes=4", "--set", "train_every=32", "--set", "updates_per_train=8",
               "--set", "batch_size=8", "--set", "model_hidden=[32,32]", "--set", "candidates=16",
               "--set", "elites=4", "--set", "openloop_episodes=4"],
}
COMPARED = ("train.csv", "eval.csv", "rollout.csv", "openloop.csv")


def command(algo: str, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", f"agents.{algo}", "--out", str(out), *extra]


def run(cmd: list[str]) -> None:
    subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True, env={**os.environ, "OMP_NUM_THREADS": "1"})


def kill_after_checkpoints(cmd: list[str], out: Path, checkpoints: int, extra_wait: float) -> None:
    """Start ``cmd``, wait until it has written ``checkpoints`` checkpoints (+ extra_wait seconds), SIGKILL it."""
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    ck, seen, last = out / "checkpoint.pt", 0, None
    deadline = time.time() + 300
    while proc.poll() is None and time.time() < deadline:
        if ck.exists() and ck.stat().st_mtime_ns != last:
            last, seen = ck.stat().st_mtime_ns, seen + 1
            if seen >= checkpoints:
                time.sleep(extra_wait)
                break
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()


def same_results(a: Path, b: Path) -> None:
    for name in COMPARED:
        if (a / name).exists():
            assert (a / name).read_text() == (b / name).read_text(), name
    ra, rb = (json.loads((d / "results.json").read_text()) for d in (a, b))
    for key in ("success_rate", "episodes", "env_steps", "mean_reward"):
        assert ra[key] == rb[key], key


@pytest.mark.parametrize("algo", sorted(RUNS))
@pytest.mark.parametrize("point", [(1, 0.0), (2, 0.3)], ids=["at-a-checkpoint", "between-checkpoints"])
def test_killed_and_resumed_equals_uninterrupted(algo, point, tmp_path):
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    run(command(algo, whole, *TINY, *RUNS[algo]))
    kill_after_checkpoints(command(algo, killed, *TINY, *RUNS[algo]), killed, *point)
    assert (killed / "checkpoint.pt").exists()
    assert not (killed / ".lock").exists() or True     # a killed run leaves its lock; the resume takes it over
    total = RUNS[algo][RUNS[algo].index("--total-steps") + 1]
    run(command(algo, killed, "--resume", "--total-steps", total, "--no-progress"))
    same_results(whole, killed)
