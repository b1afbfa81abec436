"""Planning under model mismatch: the planners plan on a model's cable parameters while the env moves a "real" rope.

    python -m benchmarks.studies.mismatch --target random --seeds 0 1 2 3 4 --episodes 20 --out runs/mismatch
    python -m benchmarks.studies.mismatch --seeds 0 --episodes 2 --model-scale k_d=1.2 --out runs/mismatch-try
    python -m benchmarks.studies.mismatch --calibrate --target random --seeds 0 1 2 3 4 --episodes 20 --out runs/mismatch

Conditions, for each method (CEM and the gradient planner, their own code in-process: planners.common.build_run
and run_episode):

- matched: model = real rope = the nominal params (--params);
- oracle: the real ropes below, each planned on its own parameters (the matched case for those ropes: the
  other conditions on them are compared against it, episode for episode);
- mismatched: the model is nominal; the real rope has k_s, k_b, k_d and mass each scaled by a factor drawn per seed,
  log-uniform in [1 - spread, 1 + spread] ([0.7, 1.3] by default), from a generator seeded with the seed (printed
  and recorded);
- calibrated (with --calibrate): the same real ropes as mismatched, planned on the nominal params with k_s and k_b
  fitted by diffdlo.calibration.calibrate (Levenberg-Marquardt, start shapes fitted) to --calibration-moves random moves of
  that seed's real rope, recorded with --calibration-noise position noise;
- given (only with --model-params or --model-scale): the same real ropes, planned on the given model
  (--model-params, default the nominal, times --model-scale).

Episode i of seed s starts from env.reset(seed=1000 s + i) (same starts and targets in every condition, up to the
real rope's settling of the start shape). Writes <out>/results.json and <out>/mismatch.md (method, condition,
success at the params' success_tol, mean moves of the successful episodes).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from diffdlo.tasks import task
from diffdlo.utils.files import OutBusyError, check_fresh_out, out_lock, write_json_atomic, write_text_atomic
from diffdlo.planar.params import ParamsError, load_params
from diffdlo.planar.shapes import TargetError
from planners.cem import CEMPlanner
from planners.common import (DEFAULT_MAX_STEPS, PHYSICAL, build_run, check_planner_options, check_same_moves,
                             parse_scales, physical_values, refuse, run_episode, scaled_params)
from planners.gradient import GradientPlanner

METHODS = {"cem": CEMPlanner, "gradient": GradientPlanner}
# smaller than the planners' own defaults so that a short check is quick (the CEM budget the README shows matching
# the gradient planner: 5/5 on diagonal in 6.2 moves)
BUDGETS = {"cem": {"horizon": 1, "candidates": 70, "elites": 10, "iterations": 4},
           "gradient": {"iters": 6, "restarts": 1}}
EPISODE_SEED_STRIDE = 1000


def real_factors(seed: int, spread: float) -> dict[str, float]:
    """Per-seed factors for PHYSICAL, log-uniform in [1 - spread, 1 + spread]."""
    lo, hi = math.log(1 - spread), math.log(1 + spread)
    u = torch.rand(len(PHYSICAL), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return {k: math.exp(lo + float(x) * (hi - lo)) for k, x in zip(PHYSICAL, u)}


def calibrated_model(nominal, factors: dict[str, float], seed: int, moves: int, noise: float) -> dict:
    """The nominal params with k_s and k_b fitted to ``moves`` recorded moves of the rope nominal x factors
    (diffdlo.calibration.calibrate's default fit: k_d and mass held, start shapes fitted). What planning needs are the
    trajectories, which depend on the ratios to k_d, so the fitted model matches the real rope's ratios."""
    import dataclasses

    from diffdlo import Simulator
    from diffdlo.calibration.calibrate import fit_gauss_newton, moves_from_recording
    from diffdlo.calibration.record import make_recording

    rec = make_recording(nominal, moves, seed, noise=noise, scale=factors)
    sim = Simulator(nominal, dtype=torch.float64)
    t0 = time.perf_counter()
    result = fit_gauss_newton(sim, moves_from_recording(rec, nominal.dt))
    fit_s = time.perf_counter() - t0
    params = dataclasses.replace(nominal, **result.values)
    real = scaled_params(nominal, factors)
    ratio = lambda p, a, b: getattr(p, a) / getattr(p, b)
    ratios = {"k_s/k_d": ("k_s", "k_d"), "k_b/k_d": ("k_b", "k_d")}
    return {"params": params, "fitted": result.values, "fit_s": fit_s, "rms_m": result.rms,
            "left_out": sorted(result.left_out), "ratios": {k: ratio(params, *v) for k, v in ratios.items()},
            "rel_error": {k: ratio(params, *v) / ratio(real, *v) - 1 for k, v in ratios.items()}}


def make_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.mismatch", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--target", default="random", help="a target name, family or file, as the planners take it "
                                                      "(default random)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    ap.add_argument("--episodes", type=int, default=20, help="episodes per seed (default 20)")
    ap.add_argument("--max-steps", type=int, default=DEFAULT_MAX_STEPS)
    ap.add_argument("--methods", nargs="+", choices=list(METHODS), default=list(METHODS))
    ap.add_argument("--params", default="cable", help="the nominal params: name or YAML path (default cable)")
    ap.add_argument("--spread", type=float, default=0.3, help="the real rope's factors lie in [1 - spread, "
                                                              "1 + spread] (default 0.3)")
    ap.add_argument("--calibrate", action="store_true",
                    help="add the calibrated condition: each seed's model fitted to recorded moves of its real rope")
    ap.add_argument("--calibration-moves", type=int, default=20, help="recorded moves per seed (default 20)")
    ap.add_argument("--calibration-noise", type=float, default=0.001,
                    help="position noise of those recordings [m] (default 0.001)")
    ap.add_argument("--model-params", default=None, help="the given condition's model (name or YAML path)")
    ap.add_argument("--model-scale", action="append", default=None, metavar="KEY=FACTOR",
                    help=f"multiply the given model's {', '.join(PHYSICAL)} by FACTOR (repeatable)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default="runs/mismatch")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier benchmark in --out")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    for method, cls in METHODS.items():
        group = ap.add_argument_group(f"{method} budget")
        for key, (kind, default, allowed, text) in cls.OPTIONS.items():
            value = BUDGETS[method].get(key, default)
            group.add_argument(f"--{method}-{key.replace('_', '-')}", dest=f"{method}_{key}", type=kind,
                               default=value, help=f"{text}: in {allowed} (default {value})")
    return ap


def summarize(episodes: list[dict]) -> dict:
    wins = [e for e in episodes if e["success"]]
    return {"successes": len(wins), "episodes": len(episodes), "success_rate": len(wins) / len(episodes),
            "moves_mean": sum(e["steps"] for e in wins) / len(wins) if wins else None}


def markdown(rows: list[dict], success_tol: float) -> str:
    lines = [f"| method | condition | success (< {success_tol * 100:g} cm) | moves to success (mean) |",
             "|---|---|---|---|"]
    for r in rows:
        moves = "-" if r["moves_mean"] is None else f"{r['moves_mean']:.1f}"
        lines.append(f"| {r['method']} | {r['condition']} | {r['successes']}/{r['episodes']} "
                     f"({r['success_rate'] * 100:.0f}%) | {moves} |")
    return "\n".join(lines) + "\n"


def plot_rows(rows: list[dict], path: Path) -> None:
    """Success per method (groups) and condition (bars), with the mean moves of the successes on each bar."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    methods = list(dict.fromkeys(r["method"] for r in rows))
    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    fig, ax = plt.subplots(figsize=(2.4 + 1.6 * len(methods) * len(conditions) / 2, 3.6))
    width = 0.8 / len(conditions)
    for j, condition in enumerate(conditions):
        for i, method in enumerate(methods):
            row = next(r for r in rows if r["method"] == method and r["condition"] == condition)
            bar = ax.bar(i + j * width, 100 * row["success_rate"], width, color=f"C{j}",
                         label=condition if i == 0 else None)
            moves = row["moves_mean"]
            if moves is not None:
                ax.bar_label(bar, labels=[f"{moves:.1f} mv"], fontsize=7)
    ax.set_xticks([i + width * (len(conditions) - 1) / 2 for i in range(len(methods))], methods)
    ax.set_ylabel("success at 1 cm [%]")
    ax.set_ylim(0, 110)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = make_parser()
    args = ap.parse_args(argv)
    try:
        if not 1 <= args.episodes <= EPISODE_SEED_STRIDE:
            raise ValueError(f"--episodes must be in [1, {EPISODE_SEED_STRIDE}], got {args.episodes}")
        if args.max_steps < 1:
            raise ValueError(f"--max-steps must be at least 1, got {args.max_steps}")
        if not 0 < args.spread < 1:
            raise ValueError(f"--spread must be in (0, 1), got {args.spread}")
        if args.calibration_moves < 1:
            raise ValueError(f"--calibration-moves must be at least 1, got {args.calibration_moves}")
        if not (math.isfinite(args.calibration_noise) and args.calibration_noise >= 0):
            raise ValueError(f"--calibration-noise must be >= 0, got {args.calibration_noise}")
        budgets = {m: {k: getattr(args, f"{m}_{k}") for k in METHODS[m].OPTIONS} for m in args.methods}
        for m in args.methods:
            check_planner_options(METHODS[m], budgets[m], prefix=f"--{m}-")
        model_factors = parse_scales(args.model_scale, "--model-scale")
    except ValueError as exc:
        return refuse(str(exc))
    try:
        nominal = load_params(args.params)
        calibrated = None
        if args.model_params is not None or model_factors:
            calibrated = scaled_params(load_params(args.model_params or args.params), model_factors, "--model-scale")
            check_same_moves(nominal, calibrated)
        reals = {s: scaled_params(nominal, real_factors(s, args.spread)) for s in args.seeds}
    except (ParamsError, OSError, ValueError) as exc:
        return refuse(f"bad params: {exc}")
    try:
        task.resolve_target(args.target, nominal)
    except TargetError as exc:
        return refuse(f"bad --target {args.target!r}: {exc}")
    out = Path(args.out)
    try:
        check_fresh_out(out, args.overwrite, "an earlier benchmark")
    except FileExistsError as exc:
        return refuse(str(exc))

    for s in args.seeds:
        print(f"seed {s}: real rope = nominal x " + ", ".join(f"{k} {f:.3f}" for k, f in
                                                              real_factors(s, args.spread).items()), flush=True)
    conditions = {"matched": lambda s: (nominal, nominal), "oracle": lambda s: (reals[s], reals[s]),
                  "mismatched": lambda s: (nominal, reals[s])}
    fits = {}
    if args.calibrate:
        for s in args.seeds:
            fits[s] = calibrated_model(nominal, real_factors(s, args.spread), s, args.calibration_moves,
                                       args.calibration_noise)
            print(f"seed {s}: calibrated in {fits[s]['fit_s']:.1f} s from {args.calibration_moves} moves: " + ", ".join(
                f"{k} {100 * e:+.2f} %" for k, e in fits[s]["rel_error"].items()), flush=True)
        conditions["calibrated"] = lambda s: (fits[s]["params"], reals[s])
    if calibrated is not None:
        conditions["given"] = lambda s: (calibrated, reals[s])

    rows, t0 = [], time.perf_counter()
    total = len(args.methods) * len(conditions) * len(args.seeds) * args.episodes
    bar = tqdm(total=total, desc="mismatch", disable=args.quiet, dynamic_ncols=True, file=sys.stderr)
    try:
        with out_lock(out):
            for method in args.methods:
                for condition, pair in conditions.items():
                    per_seed = []
                    for s in args.seeds:
                        model, real = pair(s)
                        env, planner, _ = build_run(METHODS[method], model, real, args.target,
                                                    max_steps=args.max_steps, success_tol=None, device=args.device,
                                                    seed=s, options=budgets[method])
                        episodes = []
                        for i in range(args.episodes):
                            bar.set_postfix_str(f"{method} {condition} seed {s}")
                            e = run_episode(env, planner, EPISODE_SEED_STRIDE * s + i, progress=False)
                            episodes.append({k: e[k] for k in ("seed", "target_name", "success", "steps",
                                                               "start_error", "final_error", "sim_evals")})
                            bar.update(1)
                        per_seed.append({"seed": s, "model_params": physical_values(model),
                                         "real_params": physical_values(real), **summarize(episodes),
                                         "episodes": episodes})
                    everything = [e for r in per_seed for e in r["episodes"]]
                    rows.append({"method": method, "condition": condition, **summarize(everything),
                                 "per_seed": per_seed})
            bar.close()
            table = markdown(rows, nominal.success_tol)
            write_json_atomic(out / "results.json", {
                "target": args.target, "seeds": args.seeds, "episodes_per_seed": args.episodes,
                "max_steps": args.max_steps, "success_tol": nominal.success_tol, "spread": args.spread,
                "nominal_params": physical_values(nominal),
                "real_factors": {str(s): real_factors(s, args.spread) for s in args.seeds},
                "given_params": None if calibrated is None else physical_values(calibrated),
                "calibration": {str(s): {k: v for k, v in f.items() if k != "params"} for s, f in fits.items()}
                or None,
                "calibration_moves": args.calibration_moves if args.calibrate else None,
                "calibration_noise": args.calibration_noise if args.calibrate else None,
                "budgets": budgets, "wall_s": time.perf_counter() - t0, "rows": rows})
            write_text_atomic(out / "mismatch.md", table)
            plot_rows(rows, out / "mismatch.png")
    except OutBusyError as exc:
        return refuse(str(exc))
    print(table + f"-> {out}/results.json, {out}/mismatch.md, {out}/mismatch.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
