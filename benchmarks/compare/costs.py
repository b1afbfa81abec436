"""Planning against learning in one currency: simulator moves and wall seconds to train and per episode, and the
episodes after which a learner has paid back its training against CEM (the report's cost section)."""
from __future__ import annotations

import math
from typing import Any

import numpy as np


def acting_sim_evals(runs: list[dict[str, Any]]) -> float:
    """Rope-moves a learner simulates per move it makes: 0 for a policy acting alone, the rollouts' for one acting by
    policy rollouts through the simulator (agents/common/rollout.py)."""
    return float(np.mean([r.get("sim_evals_per_move", 0.0) for r in runs]))


def row_cost(method: str, runs: list[dict[str, Any]], st: dict[str, Any]) -> dict[str, Any]:
    """Simulator moves and wall time of one row: to train (learners: training transitions, each one simulated
    move; planners: none) and per episode (learners: the moves they execute; planners: their simulated
    candidate moves plus the moves executed)."""
    moves = float(np.mean([e["steps"] for r in runs for e in r["episodes"]]))
    if st["sim_evals"] is not None:                                         # a planner
        per_s = float(np.mean([r["wall_s"] / len(r["episodes"]) for r in runs]))
        return {"train_moves": 0.0, "train_s": 0.0, "episode_moves": st["sim_evals"] + moves, "episode_s": per_s,
                "moves": moves, "success": st["s1"][0]}
    per = [r.get("eval_s_per_episode") for r in runs]
    per_s = float(np.mean(per)) if all(x is not None for x in per) else float("nan")
    teacher = float(np.mean([r.get("teacher_sim_evals", 0.0) for r in runs]))      # a distilled policy's teacher
    return {"train_moves": st["env_steps"] + teacher, "train_s": st["wall"],
            "episode_moves": moves * (1 + acting_sim_evals(runs)), "episode_s": per_s,
            "moves": moves, "success": st["s1"][0]}


PAYBACK_SLACK = 0.05   # a learner's payback is reported only if its success is at most this far below CEM's


def payback(learner: dict[str, Any], planner: dict[str, Any], key: str) -> float:
    """Episodes after which a learner (training + its episodes) has cost less than the planner (its episodes), in
    simulator moves (key "moves") or wall seconds ("s"); inf if never, nan if unknown."""
    train, per, per_p = learner[f"train_{key}"], learner[f"episode_{key}"], planner[f"episode_{key}"]
    if any(math.isnan(x) for x in (train, per, per_p)):
        return float("nan")
    return train / (per_p - per) if per_p > per else float("inf")


def cost_section(costs: dict[str, list[dict[str, Any]]], grid: dict[str, Any]) -> list[str]:
    """The markdown lines of the cost section from {task: [row_cost(...) + method, variant, trained_on]}."""
    lines = ["## Planning against learning: what each costs", "",
             "Simulator moves are one currency for both: a learner's training transitions and the moves of its "
             "episodes, a planner's simulated candidate moves (sim evals) plus the moves it executes. **Pays back "
             "after**: the number of episodes after which the learner, training included, has cost fewer simulator "
             "moves (or seconds) than CEM on the same task (∞: never, its episodes cost more than CEM's); only "
             f"for a learner whose success is within {PAYBACK_SLACK:.0%} of CEM's. A "
             "learner's seconds per episode are measured with its evaluation episodes run 20 at once (batched); a "
             "planner's one episode at a time. Success counts at 1 cm; moves are over all episodes.", ""]
    head = ["task", "method", "variant", "success @1 cm", "moves / episode", "sim moves to train",
            "sim moves / episode", "wall s to train", "wall s / episode", "pays back after (sim moves; wall s)"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for target, rows in costs.items():
        cem = next((r for r in rows if r["method"] == "cem"), None)
        for r in rows:
            variant = r["variant"] + ("" if r["trained_on"] == target else f", trained on {r['trained_on']}")
            pb = "—"
            if cem is not None and r["train_moves"] > 0 and r["success"] < cem["success"] - PAYBACK_SLACK:
                pb = "— (less success than CEM)"
            elif cem is not None and r["train_moves"] > 0:
                pb = "; ".join("∞" if math.isinf(x) else ("—" if math.isnan(x) else f"{x:.0f}")
                               for x in (payback(r, cem, "moves"), payback(r, cem, "s")))
            es = "—" if math.isnan(r["episode_s"]) else f"{r['episode_s']:.3g}"
            lines.append("| " + " | ".join([target, r["method"], variant, f"{r['success']:.2f}", f"{r['moves']:.1f}",
                                             f"{r['train_moves']:.0f}", f"{r['episode_moves']:.0f}",
                                             f"{r['train_s']:.0f}", es, pb]) + " |")
    return lines + [""]

