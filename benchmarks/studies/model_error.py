"""What a learned world model's error is near the target, in the planning loop (issue 50: what limits precision).

    python -m benchmarks.studies.model_error RUN_DIR [RUN_DIR ...] [--episodes 20] [--seed S] [--out DIR]

RUN_DIR: a PlaNet run of a model of node positions (the PETS-style ensemble or the latent world model; e.g. the
comparison's runs/compare/pets/precise/random/seed0). Its planner acts as in its evaluation (deterministic, the
run's task and tolerance, episodes from the run's eval_seed); before every move the model also predicts the rope
after the chosen move, and the study compares that with the rope the simulator returns. Open-loop figures
(agents/models/openloop.py) use random moves on fresh ropes; these are the planner's own moves, bucketed by the
rope's mean error to its target before the move, so the last moves of an episode are seen on their own.

Per bucket (median over the moves): the one-move prediction error (mean and worst node [mm], centroids not aligned:
the rope's place), the true move's size (mean node displacement), their ratio, and the mean shape error after the
move as the model predicted it and as it happened. With several runs of one model (e.g. its five seeds) a pooled
table follows. Prints the tables; writes <out>/results.json and <out>/model_error.png when --out is given.

Among pegs (a run on a route, issue 60) the model predicts each move with the board's pegs and the held node as its
planner does, the errors are on the board (no centroid alignment), and a second table splits the prediction error by
each node's true distance to the nearest peg's surface (under NEAR_PEG, 2 cm: in or about to be in contact; farther):
a model that cannot represent contact shows it there.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Callable

import torch

from agents.models.ensemble import NEAR_PEG, peg_clearance
from agents.tools.policy import load_policy
from diffdlo.tasks.rewards import node_errors
from diffdlo.tasks.routing import route_errors
from diffdlo.tasks.task import decode_node_action, decode_pin
from diffdlo.utils.files import OutBusyError, check_fresh_out, out_lock, write_json_atomic

MODEL_NAMES = {"ensemble": "PETS-style ensemble", "latent": "latent world model"}
# the mean error before the move [m]: the buckets' lower edges, largest first
BUCKETS = ((0.02, "≥ 2 cm"), (0.01, "1–2 cm"), (0.005, "5–10 mm"), (0.0, "< 5 mm"))


@torch.no_grad()
def closed_loop_moves(run_dir: Path | str, episodes: int = 20, seed: int | None = None,
                      predict: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
                      ) -> dict[str, Any]:
    """Run the run's planner for ``episodes`` episodes (one wave) and return one record per move: the mean error
    before and after it, the predicted rope's shape error after it, the prediction's mean and worst node distance
    to the true rope, and the true move's mean node displacement [m] (among pegs also the prediction's mean error
    over the nodes within NEAR_PEG of a peg and over the others, None where there are none). ``predict(rope
    (B, N, 2), node (B,), drag (B, 2), pegs (B, K, 3) or None, pin (B,) or None) -> (B, N, 2)`` is the prediction
    checked (default: the run's model, as its planner uses it)."""
    policy = load_policy(run_dir)
    if policy.algo != "planet" or policy.config.model not in ("ensemble", "latent"):
        what = policy.algo if policy.algo != "planet" else f"planet with model {policy.config.model!r}"
        raise ValueError(f"{run_dir}: a {what} run; this study needs a PlaNet run of a model of node positions "
                         "(model 'ensemble' or 'latent')")
    env = policy.make_env(num_envs=episodes)
    planner = policy.batched(env)
    p = env.core.params
    if predict is None:
        model = planner.model

        def predict(rope, node, drag, pegs, pin):
            board = {} if pegs is None else {"pegs": pegs}
            if pin is not None:
                board["pin"] = pin[:, None]
            return model.predict(rope, node[:, None], drag[:, None], **board)[:, 0]
    obs = env.reset(seed=policy.config.run.eval_seed if seed is None else seed)
    active = torch.ones(episodes, dtype=torch.bool)
    moves = []
    while bool(active.any()):
        state = env.core.get_state(generators=False)
        rope, target = state.pos.float().cpu(), state.target.float().cpu()
        pegs = None if state.pegs is None else state.pegs.float().cpu()
        action = planner(obs, True).float().cpu()
        node, drag = decode_node_action(action[:, :3], p)
        pin = decode_pin(action[:, 3], node, p.n_nodes) if action.shape[-1] == 4 else None
        predicted = predict(rope, node, drag, pegs, pin).float()
        obs, _, term, trunc, _ = env.core.step(action.to(env.core.device), mask=active)
        obs = env.to_learner(obs)
        after = env.core.get_state(generators=False).pos.float().cpu()
        miss = (predicted - after).norm(dim=-1)
        errors = node_errors if pegs is None else route_errors       # a route: on the board
        before_err, after_err = errors(rope, target).mean(-1), errors(after, target).mean(-1)
        predicted_err = errors(predicted, target).mean(-1)
        size = (after - rope).norm(dim=-1).mean(-1)
        near = None if pegs is None else peg_clearance(after, pegs) < NEAR_PEG
        for i in active.nonzero().flatten().tolist():
            moves.append({"episode": i, "error_before": float(before_err[i]), "error_after": float(after_err[i]),
                          "predicted_error_after": float(predicted_err[i]), "miss_mean": float(miss[i].mean()),
                          "miss_worst": float(miss[i].max()), "move_size": float(size[i])})
            if near is not None:
                moves[-1].update(
                    miss_near=float(miss[i][near[i]].mean()) if bool(near[i].any()) else None,
                    miss_far=float(miss[i][~near[i]].mean()) if bool((~near[i]).any()) else None)
        active &= ~(term | trunc).cpu()
    return {"run": str(run_dir), "model": policy.config.model, "episodes": episodes,
            "success_tol": env.core.success_tol, "success_worst_tol": env.core.success_worst_tol,
            "moves": moves, "buckets": bucket_rows(moves), "near_pegs": peg_split(moves)}


def peg_split(moves: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Among pegs: the prediction error of the nodes within NEAR_PEG of a peg and of the others (medians over the
    moves that have such nodes, and their count); None off routes."""
    if not moves or "miss_near" not in moves[0]:
        return None

    def median(key: str) -> tuple[float, int]:
        xs = [m[key] for m in moves if m.get(key) is not None]
        return (float(torch.tensor(xs, dtype=torch.float64).median()) if xs else float("nan")), len(xs)
    (near, n_near), (far, n_far) = median("miss_near"), median("miss_far")
    return {"near_peg": near, "moves_near": n_near, "far": far, "moves_far": n_far, "near_within_m": NEAR_PEG}


def bucket_rows(moves: list[dict[str, float]]) -> list[dict[str, Any]]:
    """The moves grouped by their error before the move (BUCKETS), with the medians the table prints."""
    rows = []
    upper = float("inf")
    for lower, label in BUCKETS:
        sel = [m for m in moves if lower <= m["error_before"] < upper]
        upper = lower
        if not sel:
            continue

        def median(f) -> float:
            return float(torch.tensor([f(m) for m in sel], dtype=torch.float64).median())
        rows.append({"bucket": label, "moves": len(sel), "miss_mean": median(lambda m: m["miss_mean"]),
                     "miss_worst": median(lambda m: m["miss_worst"]), "move_size": median(lambda m: m["move_size"]),
                     "miss_relative": median(lambda m: m["miss_mean"] / max(m["move_size"], 1e-9)),
                     "predicted_error_after": median(lambda m: m["predicted_error_after"]),
                     "error_after": median(lambda m: m["error_after"])})
    return rows


def pooled(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One result per model that has several runs at one tolerance: their moves together."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for res in results:
        groups.setdefault((res["model"], res["success_tol"], res["success_worst_tol"]), []).append(res)
    out = []
    for (model, tol, worst), group in groups.items():
        if len(group) > 1:
            moves = [m for res in group for m in res["moves"]]
            out.append({"run": f"pooled: {len(group)} runs", "model": model, "success_tol": tol,
                        "success_worst_tol": worst, "episodes": sum(r["episodes"] for r in group), "moves": moves,
                        "buckets": bucket_rows(moves), "near_pegs": peg_split(moves)})
    return out


def table(res: dict[str, Any]) -> str:
    mm = 1e3
    worst = res["success_worst_tol"]
    lines = [f"{res['run']} (model {res['model']!r}, task at {res['success_tol'] * mm:g} mm mean"
             + (f", {worst * mm:g} mm worst node" if worst else "") + f"), {res['episodes']} episodes, "
             f"{len(res['moves'])} moves",
             "| mean error before the move | moves | prediction error, mean node [mm] | worst node [mm] | "
             "true move, mean node [mm] | prediction error / move | error after the move, predicted / true [mm] |",
             "|---|---|---|---|---|---|---|"]
    for r in res["buckets"]:
        lines.append(f"| {r['bucket']} | {r['moves']} | {r['miss_mean'] * mm:.2f} | {r['miss_worst'] * mm:.2f} | "
                     f"{r['move_size'] * mm:.1f} | {r['miss_relative']:.2f} | "
                     f"{r['predicted_error_after'] * mm:.1f} / {r['error_after'] * mm:.1f} |")
    split = res.get("near_pegs")
    if split:
        lines += ["", "| nodes (true position) | moves | prediction error, mean node [mm] (median over moves) |",
                  "|---|---|---|",
                  f"| within {split['near_within_m'] * 100:g} cm of a peg | {split['moves_near']} | "
                  f"{split['near_peg'] * mm:.2f} |",
                  f"| farther | {split['moves_far']} | {split['far'] * mm:.2f} |"]
    return "\n".join(lines)


def plot(results: list[dict[str, Any]], path: Path) -> None:
    """Each move's prediction error (mean node) against its error before the move, one colour per model (its runs
    together)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no picture", file=sys.stderr)
        return
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for model in dict.fromkeys(res["model"] for res in results):
        runs = [res for res in results if res["model"] == model]
        x = [m["error_before"] * 1e3 for res in runs for m in res["moves"]]
        y = [m["miss_mean"] * 1e3 for res in runs for m in res["moves"]]
        ax.scatter(x, y, s=5, alpha=0.4, label=f"{MODEL_NAMES.get(model, model)} ({len(runs)} runs, {len(x)} moves)")
    ax.axvline(results[0]["success_tol"] * 1e3, color="k", lw=0.8, ls="--", label="the task's mean tolerance")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("mean error to the target before the move [mm]")
    ax.set_ylabel("one-move prediction error, mean node [mm]")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.model_error", description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="PlaNet run folders (model 'ensemble' or 'latent')")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=None, help="first episode's seed (default: each run's eval_seed)")
    ap.add_argument("--out", type=Path, help="folder for results.json and model_error.png")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing results.json in --out")
    args = ap.parse_args(argv)
    if args.episodes < 1:
        ap.error(f"--episodes must be at least 1, got {args.episodes}")
    torch.set_num_threads(1)
    try:
        if args.out is not None:
            check_fresh_out(args.out, args.overwrite, what="a model_error run")
        results = [closed_loop_moves(r, args.episodes, args.seed) for r in args.runs]
    except (ValueError, FileNotFoundError, OutBusyError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for res in results:
        print(table(res), end="\n\n")
    for res in pooled(results):
        print(table(res), end="\n\n")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        with out_lock(args.out):
            write_json_atomic(args.out / "results.json", {"runs": results, "pooled": pooled(results)})
            plot(results, args.out / "model_error.png")
        print(f"wrote {args.out / 'results.json'} and {args.out / 'model_error.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
