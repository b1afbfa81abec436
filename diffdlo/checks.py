"""Checks of user-given numbers shared by every command line (planners, learners, benchmarks): the message names
the option, its allowed interval and the bad value."""
from __future__ import annotations

import math
from typing import Any


def check_interval(name: str, v: Any, interval: str) -> None:
    """Raise ValueError unless the number ``v`` lies in ``interval``, written "[lo, hi]", "(lo, hi)" or mixed, with
    inf for no bound (e.g. "[1, inf)", "(0, 1]"). NaN is never inside."""
    lo, hi = (float(x) for x in interval[1:-1].split(","))
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and not math.isnan(v)
    ok = ok and (v >= lo if interval[0] == "[" else v > lo) and (v <= hi if interval[-1] == "]" else v < hi)
    if not ok:
        raise ValueError(f"{name} must be in {interval}, got {v!r}")
