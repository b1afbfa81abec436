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
import torch

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
    total = RUNS[algo][RUNS[algo].index("--total-steps") + 1]
    saved = torch.load(killed / "checkpoint.pt", weights_only=False)["step"]
    assert 0 < saved < int(total) and not (killed / "results.json").exists()   # killed mid-run, not at its end
    assert (killed / ".lock").exists()                  # a killed run leaves its lock: the resume takes it over
    run(command(algo, killed, "--resume", "--total-steps", total, "--no-progress"))
    same_results(whole, killed)


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (children in other process groups included), from /proc."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


TIMINGS = ("wall", "plan_s", "eval_s", "ms_per", "plan_ms", "plan_env_steps", "config", "train_s")


def without_timings(x):
    """A results record without its wall-clock figures (at any depth) and the run's own command line."""
    if isinstance(x, dict):
        return {k: without_timings(v) for k, v in x.items() if not k.startswith(TIMINGS)}
    if isinstance(x, list):
        return [without_timings(v) for v in x]
    return x


def cell_results(root: Path) -> dict[str, dict]:
    found = {}
    for path in sorted(root.rglob("results.json")):
        rel = str(path.relative_to(root))
        if "/ep" not in rel and "superseded" not in rel:
            found[rel] = without_timings(json.loads(path.read_text()))
    return found


@pytest.mark.parametrize("after_cells", [2, 7])
def test_compare_killed_with_its_cells_and_rerun_equals_uninterrupted(after_cells, tmp_path):
    """SIGKILL of compare and of every cell process it started (a machine that dies), after some cells finished;
    the rerun on the same --out finishes the grid with the same cell results as an uninterrupted run."""
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    cmd = [sys.executable, "-m", "benchmarks.compare", "--quick", "--jobs", "1", "--no-progress", "--no-report"]
    run([*cmd, "--out", str(whole)])
    proc = subprocess.Popen([*cmd, "--out", str(killed)], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env={**os.environ, "OMP_NUM_THREADS": "1"})
    deadline = time.time() + 300
    while proc.poll() is None and time.time() < deadline and len(cell_results(killed)) < after_cells:
        time.sleep(0.01)
    for pid in [proc.pid, *descendants(proc.pid)]:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait()
    assert len(cell_results(killed)) < len(cell_results(whole))          # killed before the grid was done
    run([*cmd, "--out", str(killed)])
    assert cell_results(killed) == cell_results(whole)
