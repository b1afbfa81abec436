"""The report's routing section (docs/ROUTING.md's task: the rope laid along a route among pegs): per routing task of
the grid (its ``routes``), each row that runs there with its success (the error on the board under 1 cm AND every
peg on the route's side), the episodes that ended on the route but round a peg the wrong way, and the second
gripper's effect: each ``pin`` row paired, episode by episode, against the same method's row that differs from it
by the pin alone (its args without ``pin``); the stall escape's (planners/escape.py) likewise, each ``escape`` row
against the row without it.

The rows also appear in the per-task tables (one per routing task, as every task); this section is where the pin's
and the escape's pairings and the side test are read."""
from __future__ import annotations

from typing import Any

import numpy as np

from planners.escape import stalled

from .grid import learner_source, route_targets, variant_targets
from .stats import fmt_ci, t_interval, wilson
from .summary import _episodes, pairs, paired_differences, paired_texts

HEAD = ["method", "variant", "task", "seeds × episodes", "success @1 cm, every peg on its side", "moves (solved)",
        "under 1 cm, a peg on the wrong side", "misses: wrong side / stalled / improving", "final error [cm]", "sim moves / episode (a learner: its training)", "s / move",
        "pin: Δ success [pp]", "pin: Δ moves (both solved)", "pairs"]


def routing_rows(grid: dict[str, Any]) -> list[tuple[str, str]]:
    """The (method, variant) rows that run some routing task, in the grid's order."""
    routes = set(route_targets(grid))
    return [(m, v) for m, spec in grid["methods"].items() for v, entry in spec["variants"].items()
            if routes & set(variant_targets(grid, entry or {}))]


def _settings(entry: dict[str, Any] | None, flag: str) -> tuple[bool, dict[str, Any]]:
    """Whether a variant has ``flag`` on (a planner's ``--pin 1`` / ``--escape K``; a learner's pin: its
    ``action: node_pin``; ``perception``: a planner's ``--perception PATH``, a learner's with its obs "perceived"),
    and its args and set without it."""
    entry = entry or {}
    args, sets = dict(entry.get("args") or {}), dict(entry.get("set") or {})
    on = bool(args.pop(flag, 0))
    if flag == "perception" and args.get("obs") == "perceived":
        args.pop("obs")
    if flag == "pin" and sets.get("action") == "node_pin":
        on = True
        sets.pop("action")
    return on, {"args": args, "set": sets}


def partner(grid: dict[str, Any], method: str, variant: str, flag: str = "pin") -> str | None:
    """The variant of ``method`` that a row with a true ``flag`` (``pin``, ``escape``: ``_settings``) is paired
    against: the one whose settings are its settings without that flag (None for a row without it, or where there
    is no such variant)."""
    variants = grid["methods"][method]["variants"]
    on, mine = _settings(variants[variant], flag)
    if not on:
        return None
    for other, entry in variants.items():
        their_on, theirs = _settings(entry, flag)
        if other != variant and not their_on and theirs == mine:
            return other
    return None


def wrong_side(e: dict[str, Any]) -> bool:
    """An episode that ended within 1 cm on the board but with a peg on the wrong side (the side test failed)."""
    return e.get("sides_kept") is False and e["final_error"] < 0.01


REFERENCE = "cem"          # the method the other routing rows are paired against (its row of the same variant)
STALL_MOVES = 10          # a miss that gained under STALL_GAIN over its last STALL_MOVES moves had stalled
STALL_GAIN = 0.001        # m


def miss_reason(e: dict[str, Any]) -> str | None:
    """Why an episode missed (None where it succeeded): "wrong side" (it ended with a peg on the wrong side),
    "stalled" (every peg on its side, but its last STALL_MOVES moves brought its best error on the board down by less
    than STALL_GAIN: a local minimum) or "improving" (still getting nearer when its moves ran out)."""
    if e["success"]:
        return None
    if e.get("sides_kept") is False:
        return "wrong side"
    if stalled(e.get("errors") or [], STALL_MOVES, STALL_GAIN):
        return "stalled"
    return "improving"


def reference_variant(grid: dict[str, Any], method: str, variant: str) -> str | None:
    """The CEM row a routing row is paired against: CEM's variant of the same name, else (a learner's own variant,
    e.g. ppo/route_rollouts) CEM's plain routing row with the same grippers (route, or route_pin with the pin)."""
    cem = grid["methods"].get(REFERENCE, {}).get("variants", {})
    if variant in cem:
        return variant
    with_pin = _settings(grid["methods"][method]["variants"][variant], "pin")[0]
    fallback = "route_pin" if with_pin else "route"
    return fallback if fallback in cem else None


def paired_with(grid: dict[str, Any], method: str, variant: str) -> tuple[str, str] | None:
    """The row a routing row names as its ``paired_with`` in compare.yaml (a world model: its own planner, CEM at
    its budget, through the simulator, which splits the moves its planner's budget costs from those its model's
    error costs), or None."""
    twin = (grid["methods"][method]["variants"][variant] or {}).get("paired_with")
    return tuple(twin.split("/", 1)) if twin else None


def routing_data(grid: dict[str, Any], done: dict[tuple, dict]) -> list[dict[str, Any]]:
    """Per routing task and row with finished cells: its statistics and, for a pin (escape) row, the paired
    differences against its partner without the pin (escape)."""
    out = []
    for task in route_targets(grid):
        for method, variant in routing_rows(grid):
            if task not in variant_targets(grid, grid["methods"][method]["variants"][variant] or {}):
                continue
            agent = grid["methods"][method]["kind"] == "agent"
            source = (learner_source(grid, task) if agent else None) or task   # a learner on a held-out route:
            eps = _episodes(grid, done, method, variant, task, source)           # its cells on `route`
            if not eps:
                continue
            runs = [done[(method, variant, source, s)] for s in grid["seeds"] if (method, variant, source, s) in done]
            per_seed = [[e for (s, _), e in sorted(eps.items()) if s == seed] for seed in sorted({s for s, _ in eps})]
            flat = [e for seed in per_seed for e in seed]
            row = {"method": method, "variant": variant, "task": task, "seeds": len(per_seed),
                   "episodes": len(flat),
                   "success": t_interval([np.mean([e["success"] for e in s]) for s in per_seed], (0.0, 1.0)),
                   "success_wilson": wilson(sum(e["success"] for e in flat), len(flat)),
                   "solved": sum(e["success"] for e in flat),
                   "moves": float(np.mean([e["steps"] for e in flat if e["success"]])) if any(
                       e["success"] for e in flat) else float("nan"),
                   "wrong_side": sum(wrong_side(e) for e in flat),
                   "misses": {why: sum(miss_reason(e) == why for e in flat)
                              for why in ("wrong side", "stalled", "improving")},
                   "final_error": t_interval([np.mean([e["final_error"] for e in s]) for s in per_seed],
                                             (0.0, float("inf"))),
                   "sim_evals": (float(np.mean([r["sim_evals"] / len(r["episodes"]) for r in runs]))
                                 if runs and all("sim_evals" in r for r in runs) else float("nan")),
                   "s_per_move": (float(np.mean([r["plan_s_per_step"] for r in runs]))
                                  if runs and all("plan_s_per_step" in r for r in runs) else float("nan")),
                   "env_steps": (float(np.mean([r["env_steps"] for r in runs])) if agent and runs
                                 and all("env_steps" in r for r in runs) else float("nan")),
                   "partner": partner(grid, method, variant, "pin"),
                   "escape_partner": partner(grid, method, variant, "escape"),
                   "picture_partner": partner(grid, method, variant, "perception"),
                   "escapes": sum(e.get("escape_moves", 0) > 0 for e in flat)}
            against = {"pin": (method, row["partner"]) if row["partner"] else None,
                       "escape": (method, row["escape_partner"]) if row["escape_partner"] else None,
                       "pictures": (method, row["picture_partner"]) if row["picture_partner"] else None,
                       "paired_with": paired_with(grid, method, variant),
                       "vs_cem": (REFERENCE, reference_variant(grid, method, variant))
                       if method != REFERENCE and reference_variant(grid, method, variant) else None}
            for name, other in against.items():
                if other is None:
                    continue
                other_source = (learner_source(grid, task) if grid["methods"][other[0]]["kind"] == "agent"
                                else None) or task
                pr, unverified, mismatched = pairs(eps, _episodes(grid, done, *other, task, other_source))
                if pr:
                    ds, dm = paired_differences(pr)
                    row[name] = {"ds": ds, "dm": dm, "pairs": len(pr), "unverified": unverified,
                                 "mismatched": mismatched}
            out.append(row)
    return out


def _cost(r: dict[str, Any]) -> str:
    """A row's cost column: a planner's simulated moves per episode; a learner's training env steps (its acting
    simulates nothing but the episode itself)."""
    if not np.isnan(r["sim_evals"]):
        return f"{r['sim_evals']:.0f}"
    return f"trained {r['env_steps'] / 1000:.0f}k env steps" if not np.isnan(r.get("env_steps", float("nan"))) else "—"


def _paired(p: dict[str, Any]) -> list[str]:
    return paired_texts(p["ds"], p["dm"], p["pairs"], p["unverified"], p["mismatched"])


def routing_section(grid: dict[str, Any], done: dict[tuple, dict], galleries: list[str] | None = None
                    ) -> list[str]:
    """The markdown section (none where no routing cell finished); ``galleries``: the routing galleries' links."""
    data = routing_data(grid, done)
    if not data:
        return []
    lines = ["## Routing: the rope laid along a route among pegs", "",
             "The planners and the learners on the routing task of docs/ROUTING.md: random boards (`route`: 2-4 pegs "
             "and a route drawn per episode) and the two held-out layouts, each episode starting beside the board; at "
             "most the row's max-steps moves. A learner trains on random boards only: its rows on the held-out layouts "
             "are its trained policy (or model) evaluated there, on the planners' episodes. **Success**: the mean node error on the board (no centroid alignment: the pegs fix "
             "where the route lies) under 1 cm AND every peg passed on the route's side (the winding test); "
             "t-interval over seeds, then Wilson over the pooled episodes. **Under 1 cm, a peg on the wrong side**: "
             "episodes that ended on the route but round a peg the wrong way (the distance alone would have called "
             "them solved). **Misses**: the failed episodes by why: ended with a peg on the wrong side; every peg "
             f"on its side but stalled (its last {STALL_MOVES} moves brought its best error down by under "
             f"{STALL_GAIN * 1e3:.0f} mm: a local minimum); still improving when its moves ran out. **pin**: the row "
             "with the second gripper minus the same row without it, on the same "
             "episodes (paired as the other sections: same seed and episode index, checked from the start error and "
             "target); Δ moves over the episodes both solved, 95 % paired t-interval.", "",
             "| " + " | ".join(HEAD) + " |", "|" + "---|" * len(HEAD)]
    for r in data:
        moves = "—" if np.isnan(r["moves"]) else f"{r['moves']:.1f}; {r['solved']}"
        pin = _paired(r["pin"]) if "pin" in r else ["", "", ""]
        lines.append("| " + " | ".join([
            r["method"], r["variant"], r["task"],
            f"{r['seeds']} × {r['episodes'] // max(r['seeds'], 1)}",
            f"{fmt_ci(*r['success'])}; {fmt_ci(*r['success_wilson'])}", moves,
            f"{r['wrong_side']} of {r['episodes']}", " / ".join(str(n) for n in r["misses"].values()),
            fmt_ci(*r["final_error"], scale=100.0),
            _cost(r), "—" if np.isnan(r["s_per_move"]) else f"{r['s_per_move']:.2f}", *pin]) + " |")
    lines.append("")
    versus = [r for r in data if "vs_cem" in r]
    if versus:
        lines += [f"Each row against {REFERENCE.upper()} with the same gripper(s) (the `{REFERENCE}` row of the same "
                  "variant; a learner's own variant against `cem/route`, or `cem/route_pin` with the pin), on the same "
                  "episodes: Δ success in percentage points, Δ moves over the episodes both "
                  "solved (positive: more moves than CEM), 95 % paired t-intervals.", "",
                  "| method | variant | task | Δ success [pp] | Δ moves (both solved) | pairs |", "|---|---|---|---|---|---|"]
        lines += ["| " + " | ".join([r["method"], r["variant"], r["task"], *_paired(r["vs_cem"])]) + " |"
                  for r in versus]
        lines.append("")
    lines += _pairing_table(
        data, "escape", "escaped", lambda r: f"{r['escapes']} of {r['episodes']}",
        "**The stall escape** (planners/escape.py): each row run with `--escape K` (after K moves that brought the "
        "rope's best error down by under 1 mm, greedy moves until it is 1 mm below its best, then the planner again) "
        "minus the same row without it, on the same episodes; **escaped**: the episodes in which it took over at "
        "least once.")
    lines += _pairing_table(
        data, "paired_with", "minus", lambda r: "/".join(paired_with(grid, r["method"], r["variant"])),
        "**Paired as compare.yaml names** (`paired_with`), on the same episodes: a world model's row minus its own "
        "planner (CEM at its budget and cost) through the simulator, a perfect model: the moves its model's error "
        "costs; that planner's row minus CEM at its own budget: the moves the smaller budget costs.")
    lines += _pairing_table(
        data, "pictures", "from the state", lambda r: r["picture_partner"],
        "**From pictures**: each row acting on what a perception reads from the env's 64 px pictures (the rope and "
        "the route, the pegs known) minus the same row given the simulator's state, on the same episodes.")
    lines += [f"![{name.rsplit('.', 1)[0].rsplit('/', 1)[-1]}]({name})" for name in galleries or []]
    return lines + ([""] if galleries else [])


def _pairing_table(data: list[dict[str, Any]], key: str, column: str, cell, intro: str) -> list[str]:
    """The rows paired under ``key`` (their Δ success, Δ moves and pairs), with one more column ``column`` whose
    text ``cell(row)`` gives; none where no row has that pairing."""
    rows = [r for r in data if key in r]
    if not rows:
        return []
    return [intro, "", f"| method | variant | task | {column} | Δ success [pp] | Δ moves (both solved) | pairs |",
            "|---|---|---|---|---|---|---|",
            *["| " + " | ".join([r["method"], r["variant"], r["task"], cell(r), *_paired(r[key])]) + " |"
              for r in rows], ""]
