"""The cells' subprocesses: each one the leader of its own process group, so that stopping compare stops them and
whatever they started (SIGTERM to the group, a short wait, then SIGKILL), and no new one starts once stopping."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

from diffdlo.utils.signals import Terminated, stop_on_signals  # noqa: F401 - Terminated: cli's exit code

# how long a stopped cell's group gets to exit on SIGTERM before SIGKILL: a learner finishes its update (2.4 s for
# PlaNet's RSSM from pictures) and writes its checkpoint, replay buffer included (0.5 GB of pictures in the grid's
# 20k-step planet/image cell)
GRACE_S = 60.0

_lock = threading.Lock()
_running: set[subprocess.Popen] = set()
_stopping = threading.Event()


class Stopped(Exception):
    """Raised instead of starting a subprocess once compare is stopping."""


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)            # the child leads its group (start_new_session): its pgid is its pid
    except (ProcessLookupError, PermissionError):
        pass


def _end_group(procs: list[subprocess.Popen], grace_s: float) -> None:
    """SIGTERM to each group, up to ``grace_s`` for them to exit, SIGKILL to the groups of those that did not."""
    for p in procs:
        _signal_group(p, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for p in procs:
        try:
            p.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
    for p in procs:
        _signal_group(p, signal.SIGKILL)    # also the group's other members, if its leader already exited
        try:
            p.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            pass


def run_in_own_group(argv: list[str], **popen_kw) -> int:
    """subprocess.run(argv).returncode, the child in its own process group and known to stop_children; an
    exception while waiting (KeyboardInterrupt in this thread, a Ray task cancelled) ends its group first."""
    with _lock:
        if _stopping.is_set():
            raise Stopped("compare is stopping: not started")
        proc = subprocess.Popen(argv, start_new_session=True, **popen_kw)
        _running.add(proc)
    try:
        return proc.wait()
    except BaseException:
        _end_group([proc], GRACE_S)
        raise
    finally:
        with _lock:
            _running.discard(proc)


def running_children() -> list[subprocess.Popen]:
    with _lock:
        return list(_running)


def stop_children(reason: str, grace_s: float = GRACE_S) -> int:
    """Start no more subprocesses and end the running ones' groups, saying so on stderr. Returns how many ran."""
    with _lock:
        _stopping.set()
        procs = list(_running)
    if procs:
        print(f"compare: {reason}: stopping {len(procs)} running cell process(es) "
              f"(pids {' '.join(str(p.pid) for p in procs)}): SIGTERM to their process groups, "
              f"SIGKILL after {grace_s:.0f} s", file=sys.stderr, flush=True)
        _end_group(procs, grace_s)
        print(f"compare: stopped {len(procs)} cell process(es); their cells rerun (learners resume from their "
              "checkpoint) next time", file=sys.stderr, flush=True)
    else:
        print(f"compare: {reason}: no cell process running", file=sys.stderr, flush=True)
    return len(procs)


def allow_children() -> None:
    """Undo stop_children (a new run in the same process, e.g. a test)."""
    _stopping.clear()


def signals_stop_compare():
    """While inside: SIGTERM and SIGHUP raise Terminated in the main thread and SIGINT raises KeyboardInterrupt, also
    where the process was started with SIGINT ignored (a shell's background job: ``cmd &``); the previous handlers
    come back on leaving (diffdlo.utils.signals.stop_on_signals)."""
    return stop_on_signals()
