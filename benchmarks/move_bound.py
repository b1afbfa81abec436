"""How few moves does the task need? CEM through the simulator at growing budgets, on the comparison's episodes.

Each budget is CEM's horizon x candidates x iterations (elites 10 % of the candidates) and the weight of the
intermediate states' error in its cost (``running_weight``: 0.5 is planners.cem's default, which rewards every move's
error; 0 scores only the state at the horizon). Every budget plays the same episodes: episode i of seed s is
``env.reset(seed=10000 + 1000 s + i)`` on the task (benchmarks/compare.yaml's rule), the planner re-seeded per
episode. For each budget: success at 1 cm, mean moves to success (and moves paired with the default budget on the
episodes both solved), simulator evaluations per move and planning seconds per move. The fewest moves any budget
reaches is the bound the other methods are measured against (issue "fewer moves than the planner").

    python -m benchmarks.move_bound --out runs/move_bound                      # the default budgets, 5 x 20
    python -m benchmarks.move_bound --out runs/move_bound --budgets 2x300x5 4x1000x10 --running-weights 0.5 0

Resumable: each finished (budget, episode) is a line of ``episodes.jsonl`` under --out, skipped when rerun; the
summary (``results.json``, ``moves_vs_evals.png``) is rewritten from all of them at the end (``--summary-only``:
from the episodes finished so far, marked incomplete).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from diffdlo.utils.files import OutBusyError, out_lock, write_json_atomic
from diffdlo.planar.params import load_params
from diffdlo.utils.signals import exit_code, stop_on_signals
from planners.cem import CEMPlanner
from planners.common import build_run, run_episode

DEFAULT_BUDGETS = ["1x300x5", "2x300x5", "3x1000x5", "4x1000x10"]
REFERENCE = ("2x300x5", 0.5)                # planners.cem's defaults: the comparison's CEM row


def parse_budget(text: str) -> tuple[int, int, int]:
    """"HxCxI" -> (horizon, candidates, iterations), each at least 1 (ValueError naming the text otherwise)."""
    try:
        h, c, i = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"budget {text!r} must be HORIZONxCANDIDATESxITERATIONS, e.g. 2x300x5") from None
    if min(h, c, i) < 1:
        raise ValueError(f"budget {text!r}: horizon, candidates and iterations must be at least 1")
    return h, c, i


def budget_key(budget: str, weight: float) -> str:
    return f"{budget}@{weight:g}"


def run_one(budget: str, weight: float, target: str, seed: int, max_steps: int, p) -> dict:
    """One episode at one budget (cable params ``p``): success, moves, final error, sim evals and planning seconds."""
    h, c, i = parse_budget(budget)
    options = {"horizon": h, "candidates": c, "elites": max(1, c // 10), "iterations": i, "running_weight": weight}
    env, planner, _ = build_run(CEMPlanner, p, p, target, max_steps=max_steps, success_tol=None, device="cpu",
                                seed=seed, options=options)
    e = run_episode(env, planner, seed, progress=False)
    return {"budget": budget, "running_weight": weight, "seed": seed, "success": e["success"], "steps": e["steps"],
            "final_error": e["final_error"], "start_error": e["start_error"], "target_name": e["target_name"],
            "sim_evals": e["sim_evals"], "plan_s": e["plan_s"]}


def summarize(rows: list[dict]) -> list[dict]:
    """Per budget: success, mean moves of the successful episodes, moves paired with the reference budget on the
    episodes both solved, sim evals and planning seconds per move."""
    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(budget_key(r["budget"], r["running_weight"]), []).append(r)
    ref = {r["seed"]: r for r in by.get(budget_key(*REFERENCE), [])}
    out = []
    for key, rs in by.items():
        moves = sum(r["steps"] for r in rs)
        solved = [r["steps"] for r in rs if r["success"]]
        paired = [r["steps"] - ref[r["seed"]]["steps"] for r in rs
                  if r["success"] and r["seed"] in ref and ref[r["seed"]]["success"]]
        out.append({"budget": rs[0]["budget"], "running_weight": rs[0]["running_weight"], "episodes": len(rs),
                    "success": len(solved) / len(rs), "moves": float(np.mean(solved)) if solved else float("nan"),
                    "moves_vs_reference": float(np.mean(paired)) if paired else float("nan"),
                    "paired": len(paired), "sim_evals_per_move": sum(r["sim_evals"] for r in rs) / max(moves, 1),
                    "plan_s_per_move": sum(r["plan_s"] for r in rs) / max(moves, 1)})
    return sorted(out, key=lambda s: (s["running_weight"], s["sim_evals_per_move"]))


def plot(summary: list[dict], path: Path) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for w in sorted({s["running_weight"] for s in summary}):
        pts = [s for s in summary if s["running_weight"] == w]
        ax.plot([s["sim_evals_per_move"] for s in pts], [s["moves"] for s in pts], "o-",
                label=f"running_weight {w:g}")
        for s in pts:
            ax.annotate(f"{s['budget']} ({100 * s['success']:.0f} %)", (s["sim_evals_per_move"], s["moves"]),
                        fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("simulator evaluations per move")
    ax.set_ylabel("moves to success (mean)")
    ax.set_title("CEM through the simulator: moves against budget, the same episodes", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.move_bound", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--target", default="random", help="the task (default random, the thesis's)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--episodes", type=int, default=20, help="episodes per seed (default 20)")
    ap.add_argument("--budgets", nargs="+", default=DEFAULT_BUDGETS, metavar="HxCxI")
    ap.add_argument("--running-weights", type=float, nargs="+", default=[0.5], metavar="W")
    ap.add_argument("--max-steps", type=int, default=100)
    ap.add_argument("--eval-seed-base", type=int, default=10000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--summary-only", action="store_true",
                    help="run nothing: write the summary of the episodes finished so far (marked incomplete)")
    args = ap.parse_args(argv)
    try:
        for b in args.budgets:
            parse_budget(b)
    except ValueError as exc:
        ap.error(str(exc))
    if args.episodes < 1 or args.max_steps < 1 or any(w < 0 for w in args.running_weights):
        ap.error("--episodes and --max-steps must be at least 1, --running-weights at least 0")
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "episodes.jsonl"
    todo = [(b, w, args.eval_seed_base + 1000 * s + i) for b in args.budgets for w in args.running_weights
            for s in args.seeds for i in range(args.episodes)]
    try:
        # --summary-only reads the finished episodes and writes the summary only (atomically): no lock, so it can
        # summarize a run still going
        with (contextlib.nullcontext() if args.summary_only else out_lock(out)), stop_on_signals():
            done = [json.loads(x) for x in log.read_text().splitlines()] if log.exists() else []
            have = {(r["budget"], r["running_weight"], r["seed"]) for r in done}
            left = [] if args.summary_only else [t for t in todo if t not in have]
            params = load_params("cable")                      # read once, not per episode
            t0 = time.perf_counter()
            for b, w, seed in tqdm(left, desc="move bound", disable=args.no_progress):
                row = run_one(b, w, args.target, seed, args.max_steps, params)
                with open(log, "a") as fh:                     # one line per finished episode: resumable
                    fh.write(json.dumps(row) + "\n")
                done.append(row)
            wanted = set(todo)
            rows = [r for r in done if (r["budget"], r["running_weight"], r["seed"]) in wanted]
            summary = summarize(rows)
            given = [a for a in (argv if argv is not None else sys.argv[1:]) if a != "--summary-only"]
            write_json_atomic(out / "results.json", {"command": shlex.join(["python", "-m", "benchmarks.move_bound",
                                                                            *given]),   # the run's own, resumable
                                                     "target": args.target, "seeds": args.seeds,
                                                     "complete": wanted <= {(r["budget"], r["running_weight"],
                                                                              r["seed"]) for r in done},
                                                     "episodes_per_seed": args.episodes, "summary": summary,
                                                     "wall_s": time.perf_counter() - t0})
            plot(summary, out / "moves_vs_evals.png")
    except OutBusyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"move_bound: stopped by {exc or 'SIGINT'}: finished episodes are kept in {log}; rerun to continue",
              file=sys.stderr)
        return exit_code(exc)
    print(f"{'budget':>12s} {'w':>4s} {'success':>8s} {'moves':>6s} {'vs 2x300x5':>10s} {'evals/move':>11s} "
          f"{'s/move':>7s}")
    for s in summary:
        print(f"{s['budget']:>12s} {s['running_weight']:>4g} {100 * s['success']:>7.0f}% {s['moves']:>6.2f} "
              f"{s['moves_vs_reference']:>+10.2f} {s['sim_evals_per_move']:>11.0f} {s['plan_s_per_move']:>7.3f}")
    print(f"-> {out / 'results.json'}, {out / 'moves_vs_evals.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
