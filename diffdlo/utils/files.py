"""Writing run outputs without losing anything, for every command line (planners, learners, the comparison):

- atomic writes: a reader (a report, a second session, a crash) sees the old file or the new one, never half of one;
- ``check_fresh_out``: a fresh run refuses a folder that holds an earlier run's files unless told to replace them;
- ``out_lock``: one writer per folder, a lock file created exclusively and holding the writer's pid and host; a lock
  whose pid no longer runs on this host is stale and taken over (with a message), a live one is an ``OutBusyError``
  naming the pid and the lock file. Released when the writer ends, however it ends.
"""
from __future__ import annotations

import contextlib
import json
import os
import socket
import sys
import tempfile
from pathlib import Path
from typing import Any, Iterator

LOCK_NAME = ".lock"


class OutBusyError(RuntimeError):
    """Another live process is writing into the same output folder."""


# ====================================================================== atomic writes
@contextlib.contextmanager
def replacing(path: Path | str, suffix: str = "") -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; on leaving the block it replaces ``path`` (on an error it is
    removed and ``path`` is untouched). ``suffix`` keeps an extension for writers that infer the format from it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{suffix}", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as f:             # what the writer wrote is on disk before the rename
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text_atomic(path: Path | str, text: str) -> None:
    with replacing(path) as tmp:
        tmp.write_text(text)


def write_json_atomic(path: Path | str, data: Any) -> None:
    write_text_atomic(path, json.dumps(data, indent=2))


# ====================================================================== an earlier run's folder
def shapes_record(start: Any, final: Any, target: Any, decimals: int = 4) -> dict[str, list]:
    """An episode's start shape, final shape and target ((N, 2) tensors) as lists rounded to ``decimals`` (0.1 mm at
    4): what results.json keeps of one episode so that a report can draw it without the run (the galleries)."""
    def points(t: Any) -> list:
        return [[round(float(x), decimals), round(float(y), decimals)] for x, y in t.detach().cpu().tolist()]
    return {"start": points(start), "final": points(final), "target": points(target)}


def check_fresh_out(out: Path | str, overwrite: bool, what: str = "a run", flag: str = "--overwrite") -> None:
    """Refuse to start in a folder that already holds files (an earlier run's results), unless ``overwrite``.
    Raises FileExistsError naming the folder, what it holds and what to do."""
    out = Path(out)
    if overwrite or not out.exists():
        return
    if not out.is_dir():
        raise FileExistsError(f"--out {str(out)!r} is a file, not a folder")
    found = sorted(p.name for p in out.iterdir() if not p.name.endswith(LOCK_NAME))
    if found:
        shown = ", ".join(found[:4]) + (", ..." if len(found) > 4 else "")
        raise FileExistsError(f"--out {str(out)!r} already holds {what} ({shown}): choose another --out, continue it "
                              f"with --resume where the command has one, or pass {flag} to replace it")


def check_fresh_file(path: Path | str, overwrite: bool) -> None:
    """Refuse to replace a file a user has (a figure, a record) unless ``overwrite``: FileExistsError naming it."""
    if not overwrite and Path(path).exists():
        raise FileExistsError(f"{path} exists; pass --overwrite to replace it")


# ====================================================================== one writer per folder
def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:                                 # runs, under another user
        return True
    return True


def _owner(path: Path) -> dict:
    """The lock's {"pid", "host"} ({} when unreadable: a writer that died between creating and filling it)."""
    try:
        text = path.read_text().strip()
    except FileNotFoundError:
        return {}
    try:
        owner = json.loads(text)
    except ValueError:
        return {}
    if isinstance(owner, int):                              # a lock holding only a pid
        return {"pid": owner, "host": socket.gethostname()}
    return owner if isinstance(owner, dict) and isinstance(owner.get("pid"), int) else {}


def _create(path: Path) -> bool:
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))
    return True


def acquire_lock(out: Path | str, name: str = LOCK_NAME, who: str = "a process") -> Path:
    """Take the lock ``<out>/<name>`` (``out`` created if missing). Raises OutBusyError when a live writer holds
    it; ``who`` names the kind of writer in the messages."""
    out = Path(out)
    path = out / name
    out.mkdir(parents=True, exist_ok=True)
    for _ in range(3):                                      # a stale lock removed, then one more try
        if _create(path):
            return path
        owner = _owner(path)
        pid, host = owner.get("pid"), owner.get("host")
        if pid is not None and host != socket.gethostname():
            raise OutBusyError(f"{path} is held by pid {pid} on host {host}: {who} writes to {out} "
                               f"(if it no longer runs, remove {path})")
        if pid is not None and pid != os.getpid() and pid_alive(pid):
            raise OutBusyError(f"{str(out)!r} is being written by pid {pid} ({who}; lock file {path}); wait for "
                               f"it to end or stop it (kill {pid}), or use another --out")
        if pid != os.getpid():
            print(f"taking over the stale lock {path} of pid {pid if pid is not None else '(unreadable)'}, which no "
                  "longer runs", file=sys.stderr)
        path.unlink(missing_ok=True)
    raise OutBusyError(f"could not take the lock {path}: other writers keep taking it")


def release_lock(path: Path) -> None:
    """Remove the lock if it is still this process's."""
    if _owner(path).get("pid") == os.getpid():
        path.unlink(missing_ok=True)


@contextlib.contextmanager
def out_lock(out: Path | str, name: str = LOCK_NAME, who: str = "a process") -> Iterator[Path]:
    """Hold ``<out>/<name>`` while writing into ``out`` (see ``acquire_lock``)."""
    path = acquire_lock(out, name, who)
    try:
        yield path
    finally:
        release_lock(path)
