"""Stopping a long command the way its user meant, however it was started.

A process started from a background job (``cmd &``, nohup, cron, many CI runners) inherits SIGINT as *ignored*, and
Python then installs no KeyboardInterrupt handler: ``kill -INT`` would do nothing, and SIGTERM would end the process
at once, mid-write. These context managers install the command's own handlers while it runs (and put the previous
ones back after), so SIGINT, SIGTERM and SIGHUP always stop it through the same cleanup as Ctrl-C (SIGHUP except
where it was ignored on purpose: ``nohup`` keeps a run alive when its terminal closes):

* ``stop_on_signals()``: the signal raises at once (KeyboardInterrupt; ``Terminated`` for SIGTERM/SIGHUP), for
  commands whose work is lost anyway (a planner's episode, a calibration);
* ``stop_at_boundary()``: the first signal only sets ``StopRequest.signal`` so that a learner can finish its step,
  save a checkpoint and stop (``Interrupted``); a second one raises at once.

Only the main thread can install handlers: elsewhere both are no-ops.
"""
from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator

EXIT_CODES = {"SIGINT": 130, "SIGTERM": 143, "SIGHUP": 129}     # as a shell reports a command ended by them
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Terminated(KeyboardInterrupt):
    """SIGTERM (or SIGHUP), raised in the main thread like Ctrl-C so that the same cleanup runs."""


class Interrupted(KeyboardInterrupt):
    """A run stopped at a step boundary on a signal, its state saved: ``signal`` names it, ``step`` where."""

    def __init__(self, signal_name: str, step: int | None = None, message: str = ""):
        super().__init__(message or f"stopped by {signal_name}")
        self.signal, self.step = signal_name, step


def exit_code(exc: BaseException) -> int:
    """The shell's exit code for a command stopped by ``exc`` (130 for Ctrl-C)."""
    name = getattr(exc, "signal", None) or (str(exc) if isinstance(exc, Terminated) else "SIGINT")
    return EXIT_CODES.get(name, 130)


def _raise(signum, _frame):
    name = signal.Signals(signum).name
    if signum == signal.SIGINT:
        raise KeyboardInterrupt(name)
    raise Terminated(name)


@contextmanager
def _handlers(handler) -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    # SIGHUP ignored on purpose (nohup) stays ignored: a run started with nohup must outlive its terminal. SIGINT
    # ignored is a shell's default for background jobs, not a request, so it is taken back.
    chosen = [s for s in SIGNALS if not (s == signal.SIGHUP and signal.getsignal(s) == signal.SIG_IGN)]
    old = {s: signal.signal(s, handler) for s in chosen}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """While inside, SIGINT raises KeyboardInterrupt and SIGTERM/SIGHUP raise Terminated, whatever the inherited
    dispositions were."""
    with _handlers(_raise):
        yield


class StopRequest:
    """The signal asked for (its name), or None: read by the loop at its step boundaries."""

    def __init__(self) -> None:
        self.signal: str | None = None

    def __bool__(self) -> bool:
        return self.signal is not None


@contextmanager
def stop_at_boundary() -> Iterator[StopRequest]:
    """While inside, the first SIGINT/SIGTERM/SIGHUP sets the yielded request (the loop stops at its next step
    boundary); a second one raises at once, as ``stop_on_signals``."""
    request = StopRequest()

    def handler(signum, frame):
        if request:
            _raise(signum, frame)
        request.signal = signal.Signals(signum).name

    with _handlers(handler):
        yield request
