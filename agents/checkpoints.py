"""Checkpoints and random state: atomic checkpoint files, every generator's state, seeding, CPU threads."""
from __future__ import annotations

import contextlib
import os
import random
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

CHECKPOINT = "checkpoint.pt"


def available_memory() -> int | None:
    """Bytes of memory free for a new allocation (Linux's MemAvailable), or None where it cannot be read."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def replay_rows(buffer_size: int, total_steps: int, num_envs: int, obs: Any, least: int = 2,
                free: int | None = None) -> int:
    """Rows of a replay buffer for a run: ``buffer_size`` transitions, but never more rows than the run can fill
    (total_steps / num_envs plus one), at least ``least``. Image observations: the size is printed; a buffer that
    would not fit in free memory is refused with a ValueError saying how big it is and what to lower."""
    rows = max(least, min(buffer_size // num_envs, -(-total_steps // num_envs) + 1))
    obs_bytes = sum(v[0].numel() * v.element_size() for v in (obs.values() if isinstance(obs, dict) else [obs]))
    total = rows * num_envs * obs_bytes
    images = any(not v.is_floating_point() for v in (obs.values() if isinstance(obs, dict) else [obs]))
    if images:
        print(f"replay buffer: {rows} rows x {num_envs} envs x {obs_bytes / 1e3:.1f} kB of observations = "
              f"{total / 1e9:.2f} GB", file=sys.stderr)
    free = available_memory() if free is None else free
    if free is not None and total > free:
        raise ValueError(f"the replay buffer would need {total / 1e9:.1f} GB ({rows} rows x {num_envs} envs x "
                         f"{obs_bytes / 1e3:.1f} kB) but {free / 1e9:.1f} GB are free: lower --set buffer_size "
                         f"(now {buffer_size}) or --total-steps")
    return rows


def rng_state() -> dict[str, Any]:
    s = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        s["cuda"] = torch.cuda.get_rng_state_all()
    return s


def set_rng_state(s: dict[str, Any]) -> None:
    torch.set_rng_state(s["torch"].cpu())      # a checkpoint loaded onto a GPU has its RNG states there too
    np.random.set_state(s["numpy"])
    random.setstate(s["python"])
    if "cuda" in s and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([t.cpu() for t in s["cuda"]])


@contextlib.contextmanager
def torch_threads(n: int):
    """Run with ``n`` torch intra-op CPU threads, then restore. On a small shared CPU, 1 thread is much faster for
    these small networks (measured on this project's 2-core machine under load: 0.3 s vs 15 s for the same run)."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def save_checkpoint(path: Path | str, state: dict[str, Any]) -> None:
    """Everything in one file, written atomically (temp file + rename: a kill never leaves half a checkpoint)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path | str) -> dict[str, Any]:
    """A checkpoint, loaded onto the CPU: every part (networks, optimizers, buffer, env, planners) moves its own
    tensors to its device when loaded, and RNG states must stay CPU tensors."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds on a damaged file; all mean the same here
        raise ValueError(f"{path} is not a readable checkpoint (damaged or not written by diffdlo): "
                         f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}") from None
    missing = [k for k in ("algo", "config", "step", "env", "rng") if not isinstance(ck, dict) or k not in ck]
    if missing:
        raise ValueError(f"{path} is not a diffdlo learner checkpoint: it lacks {missing}")
    return ck
