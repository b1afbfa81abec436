"""What does PlaNet's planning budget buy? Evaluate a trained PlaNet (ensemble) checkpoint with several CEM budgets.

For each target (default: the run's own; e.g. held-out shapes in planners/targets/) and each (horizon, candidates,
iterations, propagation) in the grid: the deterministic planner on the run's own evaluation episodes
(``eval_episodes`` from ``eval_seed``), success at the run's tolerance, mean moves to success, mean final error and
planning time per env step (all evaluation ropes planned together, as in training).

    python -m benchmarks.studies.planet_budget --run runs/planet_ens_s0 --candidates 300 150 75 --iterations 5 3 \
        --out runs/planet_budget_s0
    python -m benchmarks.studies.planet_budget --run runs/planet_ens_s0 --targets planners/targets/arc.npy \
        planners/targets/s_curve.yaml --out runs/planet_heldout_s0

Budgets not given are the run's own. Writes ``results.json`` under --out (refuses to replace one without
--overwrite), each row with its episodes (success, moves, final error: the rows share their episodes, to pair).
Elites are 10 % of the candidates. Among pegs, ``--project-pegs 0 1`` also plans with each predicted rope moved out of
the pegs (``diffdlo.tasks.routing.clear_of_pegs``: the model's rope never inside a peg), a grid dimension like the
budgets:

    python -m benchmarks.studies.planet_budget --run runs/compare_route_wm/pets/route/route/seed0 --project-pegs 0 1 \
        --out runs/planet_project_s0

``--pool`` reads such results (of the runs of several seeds: results.json files, folders holding one, or a record
{"runs": {"seed<N>": results}} as docs/results/ keeps) and prints each row pooled over them, paired episode by
episode with the committed cells (docs/results/cells.jsonl) of the grid rows ``--pair`` names, of the same seed and
task (Δ success and Δ moves over the episodes both solved, 95 % t-intervals):

    python -m benchmarks.studies.planet_budget --pool docs/results/pets_route_budget.json --pair cem/route
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from agents import planet
from agents.common import config
from agents.common.checkpoints import CHECKPOINT, load_checkpoint
from agents.common.envs import make_env
from agents.common.evaluation import evaluate
from benchmarks.compare.grid import load_grid
from benchmarks.compare.records import RESULTS_FILE, read_records, record_key
from benchmarks.compare.summary import paired_differences, paired_texts, pairs
from diffdlo.tasks import routing
from diffdlo.planar.shapes import TargetError

ROW_KEYS = {"target": None, "horizon": None, "candidates": None, "iterations": None, "propagation": None,
            "project_pegs": False, "risk": 0.0}              # a row's settings (the defaults: rows of older results)


def projected(predict, rope_radius: float):
    """A model's forward whose ropes are moved out of the pegs they are predicted in (none given: unchanged)."""
    def forward(rope, node, drag, pegs=None, pin=None):
        out = predict(rope, node, drag, pegs, pin)
        if pegs is None:
            return out
        board = pegs.expand(*out.shape[:-2], *pegs.shape[-2:]) if pegs.dim() < out.dim() else pegs
        flat = routing.clear_of_pegs(out.reshape(-1, *out.shape[-2:]), board.reshape(-1, *board.shape[-2:]).to(out),
                                     rope_radius, iterations=5)
        return flat.reshape(out.shape)
    return forward


def load_pooled(paths: list[str]) -> list[tuple[int, dict]]:
    """[(seed, a run's study results)] from results.json files, folders holding one, or records {"runs":
    {"seed<N>": results}}; a file that is none of these is an error naming it."""
    out: list[tuple[int, dict]] = []
    for path in map(Path, paths):
        file = path / "results.json" if path.is_dir() else path
        try:
            data = json.loads(file.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"--pool {path}: not a readable results file ({exc})") from None
        try:
            found = ({int(k.removeprefix("seed")): v for k, v in data["runs"].items()} if "runs" in data
                     else {int(data["seed"]): data} if "seed" in data and "rows" in data else None)
        except (AttributeError, TypeError, ValueError):
            found = None
        if found is None:
            raise ValueError(f"--pool {path}: neither this study's results.json (with its seed) nor a record of them "
                             f"({{'runs': {{'seed<N>': ...}}}})")
        out.extend(found.items())
    return out


def pooled_pairs(pooled: list[tuple[int, dict]], against: list[str], records: list[dict], grid: dict) -> list[dict]:
    """Each study row (target, budget, propagation, projection, risk) pooled over the seeds of ``pooled`` (a row of
    one seed given twice is an error): its success and moves, and per grid row of ``against`` ("method/variant") the
    paired differences against that row's committed cell of the same seed and task (episodes matched by index,
    verified by their start error where both have one)."""
    task_of = {v: k for k, v in (grid.get("routes") or {}).items()}           # the env's target -> the grid's task
    by = {record_key(r): r for r in records}
    groups: dict[tuple, dict[tuple, dict]] = {}
    plan_ms: dict[tuple, float] = {}                                        # summed over the seeds
    for seed, res in sorted(pooled, key=lambda sr: sr[0]):
        for row in res["rows"]:
            key = tuple(row.get(k, default) for k, default in ROW_KEYS.items())
            group = groups.setdefault(key, {})
            if any(s == seed for s, _ in group):
                raise ValueError(f"seed {seed}'s row {dict(zip(ROW_KEYS, key))} is given twice")
            group.update({(seed, i): e for i, e in enumerate(row["episodes"])})
            plan_ms[key] = plan_ms.get(key, 0.0) + row["plan_ms_per_env_step"]
    out = []
    targets = list(dict.fromkeys(k[0] for k in groups))                     # each target's rows together
    for key, eps in sorted(groups.items(), key=lambda kv: (targets.index(kv[0][0]), kv[0][1:])):
        target = task_of.get(key[0], key[0])
        solved = [e["steps"] for e in eps.values() if e["success"]]
        row = {**dict(zip(ROW_KEYS, key)), "task": target, "seeds": len({s for s, _ in eps}), "episodes": len(eps),
               "success_rate": sum(e["success"] for e in eps.values()) / len(eps),
               "moves_to_success": sum(solved) / len(solved) if solved else None,
               "plan_ms_per_env_step": plan_ms[key] / max(len({s for s, _ in eps}), 1), "paired": {}}
        for name in against:
            method, _, variant = name.partition("/")
            other = {}
            for seed in {s for s, _ in eps}:
                rec = by.get((method, variant, target, seed))
                if rec is None:
                    raise ValueError(f"--pair {name}: no committed cell of {name} on {target} seed {seed} in "
                                     f"{RESULTS_FILE}")
                other.update({(seed, i): e for i, e in enumerate(rec["episodes"])})
            pr, unverified, mismatched = pairs(eps, other)
            ds, dm = paired_differences(pr)
            row["paired"][name] = {"ds": ds, "dm": dm, "pairs": len(pr), "unverified": unverified,
                                   "mismatched": mismatched}
        out.append(row)
    return out


def print_pooled(rows: list[dict]) -> None:
    for r in rows:
        moves = "-" if r["moves_to_success"] is None else f"{r['moves_to_success']:.1f}"
        risk = f" risk {r['risk']:g}" if r["risk"] else ""
        print(f"{r['task']}: H={r['horizon']} candidates={r['candidates']} iterations={r['iterations']} "
              f"{r['propagation']}{' projected' if r['project_pegs'] else ''}{risk}, {r['seeds']} seeds x "
              f"{r['episodes'] // max(r['seeds'], 1)}: success {100 * r['success_rate']:.0f} %, moves {moves}, plan "
              f"{r['plan_ms_per_env_step']:.0f} ms per env step (seeds' mean)")
        for name, p in r["paired"].items():
            d_success, d_moves, n = paired_texts(p["ds"], p["dm"], p["pairs"], p["unverified"], p["mismatched"])
            print(f"    vs {name}: success {d_success} pp, moves {d_moves}, pairs {n}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.planet_budget", description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", help="a PlaNet run folder holding checkpoint.pt (model: ensemble)")
    ap.add_argument("--out", help="where results.json goes (with --run)")
    ap.add_argument("--pool", nargs="+", default=None, metavar="RESULTS",
                    help="instead of --run: this study's results of several seeds (results.json, its folder, or a "
                         "record {'runs': {'seed<N>': ...}}), pooled and printed")
    ap.add_argument("--pair", nargs="+", default=[], metavar="METHOD/VARIANT",
                    help="with --pool: grid rows whose committed cells each row is paired with (same seed and task)")
    ap.add_argument("--targets", nargs="+", default=None,
                    help="targets to evaluate on (names, families, .npy/.yaml paths; default: the run's target)")
    ap.add_argument("--horizons", type=int, nargs="+", default=None, help="default: the run's horizon")
    ap.add_argument("--candidates", type=int, nargs="+", default=None, help="default: the run's candidates")
    ap.add_argument("--iterations", type=int, nargs="+", default=None, help="default: the run's iterations")
    ap.add_argument("--propagations", nargs="+", default=None, choices=["members", "mean"],
                    help="default: the run's propagation")
    ap.add_argument("--risks", type=float, nargs="+", default=None,
                    help="the planning cost's risk (+ risk x the members' std of the cost; default: the run's)")
    ap.add_argument("--project-pegs", type=int, nargs="+", default=[0], choices=[0, 1],
                    help="1: each predicted rope moved out of the pegs (a run among pegs); default 0")
    ap.add_argument("--episodes", type=int, default=None, help="evaluation episodes (default: the run's)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--overwrite", action="store_true", help="replace an existing results.json under --out")
    args = ap.parse_args(argv)
    if args.pool is not None:
        if args.run or args.out:
            ap.error("--pool reads finished results: give it without --run and --out")
        grid = load_grid()
        bad = [p for p in args.pair if p.partition("/")[0] not in grid["methods"]
               or p.partition("/")[2] not in grid["methods"][p.partition("/")[0]]["variants"]]
        if bad:
            ap.error(f"--pair: no grid row {bad} in benchmarks/compare.yaml (method/variant)")
        try:
            print_pooled(pooled_pairs(load_pooled(args.pool), args.pair, read_records(), grid))
        except ValueError as exc:
            ap.error(str(exc))
        return 0
    if not args.run or not args.out:
        ap.error("give --run and --out (or --pool)")
    if args.pair:
        ap.error("--pair goes with --pool")
    for name in ("horizons", "candidates", "iterations"):
        bad = [v for v in getattr(args, name) or [] if v < 1]
        if bad:
            ap.error(f"--{name} must be >= 1, got {bad}")
    bad = [r for r in args.risks or [] if not r >= 0]
    if bad:
        ap.error(f"--risks must be >= 0, got {bad}")
    if args.episodes is not None and args.episodes < 1:
        ap.error(f"--episodes must be >= 1, got {args.episodes}")
    out = Path(args.out)
    if (out / "results.json").exists() and not args.overwrite:
        ap.error(f"{out / 'results.json'} exists: pass --overwrite to replace it")
    try:
        ck = load_checkpoint(Path(args.run) / CHECKPOINT)
    except (FileNotFoundError, ValueError) as exc:
        ap.error(str(exc))
    cfg = config.from_flat(planet.PlaNetConfig, ck["config"])
    if cfg.model != "ensemble":
        ap.error(f"{args.run} holds a PlaNet with model {cfg.model!r}; this benchmark plans through the ensemble")
    args.horizons = args.horizons or [cfg.horizon]
    args.candidates = args.candidates or [cfg.candidates]
    args.iterations = args.iterations or [cfg.iterations]
    args.propagations = args.propagations or [cfg.propagation]
    args.risks = [cfg.risk] if args.risks is None else args.risks
    torch.set_num_threads(args.threads)
    n = args.episodes or cfg.run.eval_episodes
    cfg = config.replace(cfg, device="cpu", env_device="cpu")
    params = cfg.task.cable_params()
    targets = args.targets or [cfg.task.target]
    try:
        envs = {str(t): make_env(dataclasses.replace(cfg.task, target=t), cfg.run, params, min(n, 32))
                for t in targets}
    except (ValueError, TargetError) as exc:
        ap.error(f"bad --targets: {exc}")
    env = next(iter(envs.values()))
    model = planet.build_model(cfg, env.reset(seed=0), env.core.action_dim, params)
    model.load_state_dict(ck["model"])
    model.eval()
    if 1 in args.project_pegs and not getattr(model, "max_pegs", 0):
        ap.error(f"--project-pegs 1: {args.run} holds a model without pegs")
    predict = model.forward
    rows = []
    grid = list(itertools.product(targets, args.horizons, args.candidates, args.iterations, args.propagations,
                                  args.project_pegs, args.risks))
    for target, h, c, it, prop, project, risk in tqdm(grid, desc="budgets", file=sys.stderr):
        env = envs[str(target)]
        model.forward = projected(predict, params.rope_radius) if project else predict
        try:
            run_cfg = config.replace(cfg, horizon=h, candidates=c, elites=max(1, c // 10), iterations=it,
                                     propagation=prop, risk=risk)
        except ValueError as exc:
            ap.error(str(exc))
        planner = planet.make_planner(model, run_cfg, env.core, cfg.run.eval_seed)
        t0 = time.perf_counter()
        r = evaluate(planner, env, n, seed=cfg.run.eval_seed)
        succ = [e for e in r["episodes"] if e["success"]]
        rows.append({"target": str(target), "horizon": h, "candidates": c, "iterations": it, "propagation": prop,
                     "project_pegs": bool(project), "risk": risk,
                     "success_rate": r["success_rate"],
                     "moves_to_success": sum(e["steps"] for e in succ) / len(succ) if succ else None,
                     "mean_final_error": r["mean_final_error"],
                     "plan_ms_per_env_step": 1000 * planner.plan_s / max(planner.planned, 1),
                     "model_evals_per_move": h * c * it * (model.E if prop == "members" else 1),
                     "wall_s": time.perf_counter() - t0,
                     "episodes": [{k: e[k] for k in ("success", "steps", "final_error", "start_error", "target_name")
                                   if k in e} for e in r["episodes"]]})
        row = rows[-1]
        moves = "-" if row["moves_to_success"] is None else f"{row['moves_to_success']:.1f}"
        print(f"{target}: H={h} candidates={c} iterations={it} {prop}{' projected' if project else ''}"
              f"{f' risk {risk:g}' if risk else ''}: success {row['success_rate']:.2f}, "
              f"moves {moves}, "
              f"final error {100 * row['mean_final_error']:.2f} cm, plan {row['plan_ms_per_env_step']:.0f} ms per "
              f"env step ({env.num_envs} ropes together)", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps({"run": str(args.run), "seed": cfg.run.seed, "episodes": n,
                                                  "eval_seed": cfg.run.eval_seed, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
