"""Evaluation of a policy (greedy or sampled) over full episodes, on the training task and on held-out target shapes,
and the run's ``results.json`` and picture."""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from agents.common.config import RunOptions, TaskOptions
from agents.common.envs import TrainEnv, make_env
from diffdlo.envs import BatchedShapeControl
from diffdlo.utils.files import shapes_record, write_json_atomic
from diffdlo.planar.params import CableParams
from diffdlo.tasks.task import ROUTE, ROUTE_PREFIX, target_label

# an episode's record in results.json; start_error (the shape error after reset) identifies the start shape, so a
# report can check that two methods' episode i are the same episode (planners record it too); errors and
# worst_errors: the shape error and the worst node's error [m] after the reset and after each move (steps + 1 each,
# as a planner's), from which success at another tolerance is read (benchmarks.compare.stats.success_move)
# a route's episodes also keep sides_kept (every peg on the route's side at the episode's end: the report's
# wrong-side count) and pegs (the board, x, y, radius per peg), as a planner's
EPISODE_KEYS = ("success", "steps", "final_error", "start_error", "target_name", "errors", "worst_errors",
                "sides_kept", "pegs")

# ====================================================================== evaluation
@torch.no_grad()
def evaluate(policy: Callable[[Any, bool], torch.Tensor], env: TrainEnv | BatchedShapeControl, n_episodes: int,
             deterministic: bool = True, seed: int = 10_000,
             check_stop: Callable[[], None] | None = None) -> dict[str, Any]:
    """Run ``n_episodes`` full episodes (in waves of env.num_envs, wave w reset with seed + w * num_envs: episode i
    starts from one rope's ``reset(seed=seed + i)``, as a planner's episode i of ``--seed seed``).

    ``policy(obs, deterministic) -> (B, A) actions``. Returns success_rate, mean_reward, mean_length,
    mean_final_error, episodes [{success, steps, final_error, start_error, return, target_name, errors,
    worst_errors}] (errors, worst_errors: the env's shape_error and worst_node_error after the reset and after each
    move), final ropes and targets.
    ``check_stop()``: called before every move (it raises to stop the evaluation, e.g. on a signal).
    """
    env = env if isinstance(env, TrainEnv) else TrainEnv(env)
    b = env.num_envs
    t0 = time.perf_counter()
    episodes, ropes, targets, starts = [], [], [], []
    wave = 0
    while len(episodes) < n_episodes:
        obs = env.reset(seed=seed + wave * b)
        wave += 1
        first = env.core.info()
        start_err = first["shape_error"].detach().cpu().double()
        errors = [[float(x)] for x in first["shape_error"].cpu()]
        worst_errors = [[float(x)] for x in first["worst_node_error"].cpu()]
        start_pos = env.core.get_state(generators=False).pos.detach().cpu()
        active = torch.ones(b, dtype=torch.bool)
        ret = torch.zeros(b, dtype=torch.float64)
        final_err = torch.zeros(b)
        success = torch.zeros(b, dtype=torch.bool)
        sides = torch.ones(b, dtype=torch.bool)
        steps = torch.zeros(b, dtype=torch.int64)
        final_pos = env.core.get_state(generators=False).pos
        while bool(active.any()):
            if check_stop is not None:
                check_stop()
            actions = policy(obs, deterministic)
            obs, reward, term, trunc, info = env.core.step(actions.to(env.core.device), mask=active)
            obs = env.to_learner(obs)
            ret += reward.double().cpu() * active
            steps += active.long()
            mean_now, worst_now = info["shape_error"].cpu().tolist(), info["worst_node_error"].cpu().tolist()
            for i in active.nonzero().flatten().tolist():
                errors[i].append(mean_now[i])
                worst_errors[i].append(worst_now[i])
            done = (term | trunc).cpu() & active
            final_err[done] = info["shape_error"].cpu().float()[done]
            success[done] = info["is_success"].cpu()[done]
            if "sides_kept" in info:
                sides[done] = info["sides_kept"].cpu()[done]
            if bool(done.any()):
                d = done.to(final_pos.device)
                final_pos[d] = env.core.get_state(generators=False).pos[d]
            active &= ~done
        state = env.core.get_state(generators=False)
        for i in range(min(b, n_episodes - len(episodes))):
            episodes.append({"success": bool(success[i]), "steps": int(steps[i]),
                             "final_error": float(final_err[i]), "start_error": float(start_err[i]),
                             "return": float(ret[i]),
                             "target_name": state.target_names[i], "errors": errors[i],
                             "worst_errors": worst_errors[i]})
            if state.pegs is not None:
                board = state.pegs[i].detach().cpu().double()
                episodes[-1].update(sides_kept=bool(sides[i]), pegs=board[board[:, 2] > 0].tolist())
            ropes.append(final_pos[i].detach().cpu())
            starts.append(start_pos[i])
            targets.append(state.target[i].detach().cpu())
    return {"success_rate": float(np.mean([e["success"] for e in episodes])),
            "mean_reward": float(np.mean([e["return"] for e in episodes])),
            "mean_length": float(np.mean([e["steps"] for e in episodes])),
            "mean_final_error": float(np.mean([e["final_error"] for e in episodes])),
            "episodes": episodes, "ropes": torch.stack(ropes), "targets": torch.stack(targets),
            "starts": torch.stack(starts),
            "s_per_episode": (time.perf_counter() - t0) / len(episodes)}


def episode_records(episodes: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The episodes as results.json keeps them (EPISODE_KEYS; an evaluation saved in a checkpoint before a key was
    recorded keeps the keys it has)."""
    return [{k: e[k] for k in EPISODE_KEYS if k in e} for e in episodes]


def heldout_envs(task: TaskOptions, run: RunOptions, params: CableParams) -> dict[str, tuple[Any, TrainEnv]]:
    """One evaluation env per entry of ``run.eval_targets`` (target shapes the learner does not train on, e.g.
    planners/targets/arc.npy, or fixed routes, e.g. route:hook_wrap), keyed by a label (the file's stem, or the name;
    a fixed route "route_<layout>", the comparison's name of that task): label -> (spec, env). Built before
    training, so a bad target is an error at once, not after the run."""
    envs: dict[str, tuple[Any, TrainEnv]] = {}
    for spec in run.eval_targets or []:
        label = target_label(spec) if target_label(spec) != "custom" else str(spec)
        if isinstance(spec, str) and spec.startswith(ROUTE_PREFIX):
            label = f"{ROUTE}_{label}"
        if label in envs:
            raise ValueError(f"eval_targets: {spec!r} repeats the label {label!r}")
        envs[label] = (spec, make_env(dataclasses.replace(task, target=spec), run, params,
                                      min(run.eval_episodes, 32)))
    return envs


def evaluate_heldout(policy: Callable[[Any, bool], torch.Tensor] | None, envs: dict[str, tuple[Any, TrainEnv]],
                     run: RunOptions, policy_for: Callable[[TrainEnv], Callable] | None = None,
                     check_stop: Callable[[], None] | None = None) -> dict[str, Any]:
    """``evaluate`` on every held-out target (as many episodes, from the same start seeds, as the main evaluation):
    label -> {target, success_rate, mean_final_error, episodes}. ``policy_for(env)``: a policy bound to that env
    (PlaNet's planners keep per-rope state), instead of ``policy``; ``check_stop`` as for ``evaluate``."""
    out = {}
    for label, (spec, env) in envs.items():
        r = evaluate(policy if policy_for is None else policy_for(env), env, run.eval_episodes, seed=run.eval_seed,
                     check_stop=check_stop)
        out[label] = {"target": str(spec), "success_rate": r["success_rate"],
                      "mean_final_error": r["mean_final_error"], "shapes": first_shapes(r),
                      "episodes": episode_records(r["episodes"])}
    return out


def first_shapes(result: dict[str, Any]) -> dict[str, list]:
    """The first episode's start, final shape and target, and on a route its pegs (results.json "shapes": the
    report's galleries)."""
    shapes = shapes_record(result["starts"][0], result["ropes"][0], result["targets"][0])
    first = result["episodes"][0] if result.get("episodes") else {}
    return dict(shapes, pegs=first["pegs"]) if "pegs" in first else shapes


def eval_row(result: dict[str, Any]) -> dict[str, float]:
    return {k: result[k] for k in ("success_rate", "mean_reward", "mean_length", "mean_final_error")}


def write_results(out: Path, method: str, task: TaskOptions, seed: int, result: dict[str, Any], env_steps: int,
                  wall_s: float,
                  max_pictures: int = 8, heldout: dict[str, Any] | None = None,
                  extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """``results.json`` (the fields every method writes: method, target, seed, success_rate, episodes, env_steps,
    wall_s; ``heldout``: per held-out target, its success rate and episodes;
    ``extra``: a learner's own figures, e.g. SAC's ms per update) and ``eval_episodes.png`` (final shapes against
    targets)."""
    out = Path(out)
    eps = result["episodes"]
    results = {"method": method, "target": task.target if isinstance(task.target, str) else "custom",
               "seed": seed, "success_rate": result["success_rate"],
               "episodes": episode_records(eps),
               "env_steps": int(env_steps), "wall_s": float(wall_s),
               "mean_reward": result["mean_reward"], "mean_length": result["mean_length"],
               "eval_s_per_episode": result.get("s_per_episode"),
               "obs": task.obs, "action": task.action, "reward": task.reward}
    if "starts" in result:
        results["shapes"] = first_shapes(result)
    results.update(extra or {})
    if heldout:
        results["heldout"] = heldout
    write_json_atomic(out / "results.json", results)
    try:
        import matplotlib
        matplotlib.use("Agg")
        from diffdlo.utils.render import plot_ropes
        import matplotlib.pyplot as plt
        k = min(max_pictures, len(eps))
        titles = [f"{'success' if e['success'] else 'fail'}: {e['final_error'] * 100:.2f} cm, {e['steps']} steps"
                  for e in eps[:k]]
        fig = plot_ropes(result["ropes"][:k], result["targets"][:k], path=out / "eval_episodes.png", titles=titles)
        plt.close(fig)
    except ImportError:   # matplotlib is the optional [plot] extra
        print("matplotlib not installed: no eval_episodes.png", file=sys.stderr)
    return results
