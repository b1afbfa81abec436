"""Checkpoints and random state: atomic checkpoint files, every generator's state, seeding, CPU threads.

A checkpoint holds data only: tensors and plain containers of numbers and strings (networks, optimizers, buffers,
the env, RNG states, the config), and it is read with ``torch.load(weights_only=True)``, so opening one runs no code
whatever it holds. A file that needs anything more is refused with the objects it would need named. Checkpoints of
earlier versions kept numpy's RNG state as a numpy array: they still load (numpy's array and dtype allow-listed,
nothing else), and ``python -m agents.common.checkpoints --upgrade FILE`` rewrites one in today's format.
"""
from __future__ import annotations

import contextlib
import os
import pickle
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


def numpy_state(state: tuple | None = None) -> dict[str, Any]:
    """numpy's legacy global RNG state (``np.random.get_state()``) as plain data: a tensor and numbers."""
    name, keys, pos, has_gauss, cached = np.random.get_state() if state is None else state
    return {"bit_generator": str(name), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)),
            "pos": int(pos), "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}


def _numpy_tuple(s: dict[str, Any] | tuple) -> tuple:
    if isinstance(s, tuple):                   # a checkpoint of an earlier version: numpy's own tuple
        return s
    return (s["bit_generator"], s["keys"].numpy().astype(np.uint32), s["pos"], s["has_gauss"], s["cached_gaussian"])


def rng_state() -> dict[str, Any]:
    s = {"torch": torch.get_rng_state(), "numpy": numpy_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        s["cuda"] = torch.cuda.get_rng_state_all()
    return s


def set_rng_state(s: dict[str, Any]) -> None:
    torch.set_rng_state(s["torch"].cpu())      # a checkpoint loaded onto a GPU has its RNG states there too
    np.random.set_state(_numpy_tuple(s["numpy"]))
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


# What a checkpoint of an earlier version needs beyond data: numpy's array (its global RNG state), nothing else
OLD_FORMAT_GLOBALS = ("numpy.dtype", "numpy.ndarray", "numpy._core.multiarray._reconstruct",
                      "numpy.core.multiarray._reconstruct", "numpy.dtypes.UInt32DType")


def _old_format_allowed() -> list:
    import numpy.dtypes
    try:
        from numpy._core.multiarray import _reconstruct
    except ImportError:                        # numpy < 2
        from numpy.core.multiarray import _reconstruct
    return [np.dtype, np.ndarray, _reconstruct, numpy.dtypes.UInt32DType]


def read_data_only(path: Path | str) -> Any:
    """``torch.load(path, weights_only=True)`` onto the CPU: no code in the file runs. A file that needs other
    objects is refused (ValueError naming them) unless they are exactly what an earlier version's checkpoint holds
    (numpy's RNG array), which is then read with only those allow-listed."""
    from torch.serialization import get_unsafe_globals_in_checkpoint, safe_globals

    path = Path(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        pass                                   # needs more than data: see what, before anything is read
    try:
        needed = sorted(get_unsafe_globals_in_checkpoint(path))
    except Exception as exc:  # noqa: BLE001 - not a torch zip archive at all
        raise ValueError(f"{path} is not a readable checkpoint (damaged or not written by diffdlo): "
                         f"{type(exc).__name__}") from None
    if needed and set(needed) <= set(OLD_FORMAT_GLOBALS):
        with safe_globals(_old_format_allowed()):
            return torch.load(path, map_location="cpu", weights_only=True)
    raise ValueError(f"{path}: refused: loading it would run code or build objects ({', '.join(needed)}); a "
                     "diffdlo checkpoint holds tensors and plain values only, so this file was not written by "
                     "diffdlo or was altered. Nothing in it was run.")


def load_checkpoint(path: Path | str) -> dict[str, Any]:
    """A checkpoint, loaded onto the CPU with no code run (``read_data_only``): every part (networks, optimizers,
    buffer, env, planners) moves its own tensors to its device when loaded, and RNG states must stay CPU tensors."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        ck = read_data_only(path)
    except ValueError:
        raise
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds on a damaged file; all mean the same here
        raise ValueError(f"{path} is not a readable checkpoint (damaged or not written by diffdlo): "
                         f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}") from None
    missing = [k for k in ("algo", "config", "step", "env", "rng") if not isinstance(ck, dict) or k not in ck]
    if missing:
        raise ValueError(f"{path} is not a diffdlo learner checkpoint: it lacks {missing}")
    return ck


def upgrade(path: Path | str) -> Path:
    """Rewrite a checkpoint of an earlier version in today's format (numpy's RNG state as plain data). The old file
    is kept beside it as ``<name>.old``. Returns that path."""
    path = Path(path)
    ck = load_checkpoint(path)
    if isinstance(ck["rng"].get("numpy"), tuple):
        ck["rng"]["numpy"] = numpy_state(ck["rng"]["numpy"])
    old = path.with_name(path.name + ".old")
    if old.exists():
        raise FileExistsError(f"{old} exists: move it away first (nothing is overwritten)")
    os.replace(path, old)
    save_checkpoint(path, ck)
    torch.load(path, map_location="cpu", weights_only=True)       # today's format: data only, no allow-list
    return old


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m agents.common.checkpoints", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--upgrade", required=True, metavar="FILE", help="rewrite FILE in today's format (old kept as "
                                                                        "FILE.old)")
    args = ap.parse_args(argv)
    try:
        old = upgrade(args.upgrade)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.upgrade}: rewritten in today's format (data only); the old file is {old}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


def load_weights(part: Any, state: Any, path: Path, name: str) -> None:
    """``part.load_state_dict(state)``, or a ValueError naming the checkpoint file and the part when its state does
    not fit what this run's config builds (another model's weights, another network size)."""
    try:
        part.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError, KeyError, ValueError) as exc:
        first = str(exc).strip().splitlines()
        raise ValueError(f"{path}: the {name!r} weights do not fit the network its config builds "
                         f"({first[0] if first else type(exc).__name__})") from None
