"""Confidence intervals (95 %, scipy.stats), the statistics of one report row, and an episode's success at another
tolerance.

  * t-interval over seeds: mean of the per-seed values +- t_{0.975, n-1} * sd / sqrt(n) (sample sd, ddof 1);
    success rates clipped to [0, 1]; undefined for one seed;
  * Wilson score interval over all episodes of all seeds pooled (ignores between-seed variance);
  * ``success_move``: the first move at which an episode's recorded errors pass a (mean, worst node) tolerance.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from diffdlo.tasks.rewards import within_tolerance


def t_quantile(p: float, df: float) -> float:
    """Student t quantile."""
    from scipy import stats

    return float(stats.t.ppf(p, df))


def t_interval(values, clip: tuple[float, float] | None = None) -> tuple[float, float, float]:
    """(mean, low, high): 95 % t-interval of the mean of per-seed values; low = high = nan for fewer than 2 values."""
    x = np.asarray(values, dtype=float)
    m = float(x.mean()) if len(x) else float("nan")
    if len(x) < 2:
        return m, float("nan"), float("nan")
    half = t_quantile(0.975, len(x) - 1) * float(x.std(ddof=1)) / math.sqrt(len(x))
    lo, hi = m - half, m + half
    if clip is not None:
        lo, hi = max(lo, clip[0]), min(hi, clip[1])
    return m, lo, hi


def wilson(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float, float]:
    """(p, low, high): Wilson score interval of a binomial proportion; nan for no trials."""
    if n == 0:
        return float("nan"), float("nan"), float("nan")
    from scipy import stats

    ci = stats.binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return successes / n, float(ci.low), float(ci.high)


def fmt_ci(m: float, lo: float, hi: float, scale: float = 1.0, nd: int = 2) -> str:
    """"m [lo, hi]", "m (n=1)" without an interval, "—" without a value."""
    if math.isnan(m):
        return "—"
    if math.isnan(lo):
        return f"{m * scale:.{nd}f} (n=1)"
    return f"{m * scale:.{nd}f} [{lo * scale:.{nd}f}, {hi * scale:.{nd}f}]"


def row_stats(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate the finished seeds of one (method, variant, target)."""
    s1 = [np.mean([e["success"] for e in r["episodes"]]) for r in runs]
    s2 = [np.mean([e["final_error"] < 0.02 for e in r["episodes"]]) for r in runs]
    err = [np.mean([e["final_error"] for e in r["episodes"]]) for r in runs]
    eps = [e for r in runs for e in r["episodes"]]
    succ = [e["steps"] for e in eps if e["success"]]
    to2 = [next((k for k, x in enumerate(e["errors"]) if x < 0.02), None) for e in eps if "errors" in e]
    to2 = [k for k in to2 if k is not None]
    planner = "sim_evals" in runs[0]
    return {
        "seeds": len(runs), "episodes": len(eps),
        "s1": t_interval(s1, (0.0, 1.0)), "s1_w": wilson(sum(e["success"] for e in eps), len(eps)),
        "s2": t_interval(s2, (0.0, 1.0)), "s2_w": wilson(sum(e["final_error"] < 0.02 for e in eps), len(eps)),
        "err": t_interval(err, (0.0, float("inf"))),
        "moves": (float(np.mean(succ)), len(succ)) if succ else (float("nan"), 0),
        "moves2": float(np.mean(to2)) if to2 else float("nan"),
        "env_steps": float(np.mean([r["env_steps"] for r in runs])),
        "sim_evals": float(np.mean([r["sim_evals"] / len(r["episodes"]) for r in runs])) if planner else None,
        "wall": float(np.mean([r["wall_s"] for r in runs])),
        # APG: rope-moves backpropagated through the simulator in training (its results' sim_backward)
        "sim_backward": (float(np.mean([r["sim_backward"] for r in runs]))
                         if all("sim_backward" in r for r in runs) else None),
        "s_per_move": float(np.mean([r["plan_s_per_step"] for r in runs])) if planner else None,
    }


def success_move(errors: Sequence[float], worst_errors: Sequence[float] | None, tol: float,
                 worst_tol: float | None = None) -> int | None:
    """The move at which an episode would have succeeded at tolerance (``tol``, ``worst_tol``), from its recorded
    errors after the reset and after each move (an episode record's "errors" and "worst_errors", both steps + 1
    long): the first k with errors[k] < tol and, when ``worst_tol`` is given, worst_errors[k] < worst_tol (the env's
    test, ``diffdlo.tasks.rewards.within_tolerance``); 0 for a start already within it; None where no recorded move is.

    The answer is read from the moves the episode made: it ended at its own success (at the tolerance it ran with)
    or after max_steps, so at a looser pair it is exact, and at a tighter one an episode that succeeded at its own
    tolerance may have got there had it gone on (None here). A record's errors are rounded down to 10 µm
    (``records.floor_error``), which keeps the test exact at tolerances that are multiples of 10 µm; records
    collected before worst errors were kept rounded to the nearest 10 µm, so there an error within 5 µm of a
    tolerance may read on the wrong side (7 of the 3100 planner episodes of the committed records at 1 cm).
    Raises ValueError where ``worst_tol`` is given and the episode has no worst errors (a record made before they
    were kept), or the lists differ in length."""
    if worst_tol is not None:
        if worst_errors is None:
            raise ValueError(f"worst_tol={worst_tol!r} needs the episode's worst node errors; this episode has none "
                             "(recorded before they were kept)")
        if len(worst_errors) != len(errors):
            raise ValueError(f"an episode's errors and worst_errors must have one entry per move each, got "
                             f"{len(errors)} and {len(worst_errors)}")
    for k, mean in enumerate(errors):
        worst = None if worst_tol is None else worst_errors[k]
        if within_tolerance(mean, worst, tol, worst_tol):
            return k
    return None
