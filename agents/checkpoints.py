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


def warn_if_large_buffer(rows: int, num_envs: int, obs: Any, limit: float = 4e9) -> None:
    """Warn (stderr) when a replay buffer of rows x num_envs observations like ``obs`` would exceed ``limit`` bytes."""
    obs_bytes = sum(v[0].numel() * v.element_size() for v in (obs.values() if isinstance(obs, dict) else [obs]))
    if rows * num_envs * obs_bytes > limit:
        print(f"warning: the replay buffer will hold {rows * num_envs * obs_bytes / 1e9:.1f} GB of observations; "
              f"lower it with --set buffer_size=N (images: 64x64 pairs are 24.6 kB each)", file=sys.stderr)


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
        raise FileNotFoundError(f"--resume: no checkpoint at {path}")
    return torch.load(path, map_location="cpu", weights_only=False)
