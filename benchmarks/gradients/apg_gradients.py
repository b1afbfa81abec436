"""APG's pathwise gradient against the horizon H: how large, how noisy and how aligned it is when H moves are chained.

    python -m benchmarks.gradients.apg_gradients --run runs/apg/tuned-s0 --horizons 1 2 4 8 16 32 --ropes 32 --threads 1

For each H, every one of ``--ropes`` start ropes (the run's task, env resets from ``--seed``) is moved H times by the
policy (its node rule, deterministic; its mean drag), keeping the graph, and the gradient of ITS objective
J_i = sum_t gamma^t r_t (the run's reward, e.g. shape_gain; no episode end inside the window: a rope that reaches
the target keeps moving) with respect to the actor's parameters is taken alone (one backward pass per rope, through
the fused kernel's adjoint). The table prints, per H:

- J: the mean objective; |g_i|: the mean per-rope gradient norm (median, max);
- |mean g|: the norm of the batch gradient (what an update of that many ropes follows); rel. std: the spread of the
  per-rope gradients around it, sqrt(mean |g_i - mean g|^2) / |mean g| (its square over the rope count is the
  relative variance of the batch gradient: above ~1 per rope an update of B ropes is mostly noise unless B is large);
- cos to H=1: the cosine between this H's batch gradient and the one-move gradient;
- |dJ/da_0|: the gradient reaching the FIRST move's drag (median, max over ropes): how the chain carries it back;
- non-finite: ropes whose gradient had NaN/inf (none is ever zeroed; they are counted and left out).

``--bound K`` also runs K episodes of the policy APG's greedy-node relaxation could at best become: at every move
the greedy node with the drag the gradient planner optimizes for that node alone (planners.gradient, 20 Adam
iterations, 3 initial drags, no halving): its success and moves bound what a learned drag can reach with that node.

Without ``--run`` the actor is a fresh one of params/apg.yaml (its drags start near zero); ``--set KEY=VALUE``
changes that config (e.g. --set node=score).
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import torch
import yaml

from agents import apg
from agents.common import config as config_lib
from agents.common.checkpoints import torch_threads
from agents.tools.policy import checkpoint_path, read_checkpoint
from diffdlo.envs import BatchedShapeControl


def load_actor(run: str | None, overrides: dict) -> tuple[apg.APGConfig, dict | None, str]:
    """The config and checkpoint of an apg run (or params/apg.yaml with ``overrides`` and no checkpoint)."""
    if run is None:
        cfg = config_lib.load_config(apg.APGConfig, "apg", overrides)
        return cfg, None, "a fresh actor (params/apg.yaml)"
    path = checkpoint_path(run)
    ck = read_checkpoint(path)
    if ck["algo"] != "apg":
        raise ValueError(f"{path} is a checkpoint of {ck['algo']!r}, not of apg")
    cfg = config_lib.from_flat(apg.APGConfig, ck["config"])
    return cfg, ck, f"{path} (step {ck['step']})"


def rope_gradient(actor: apg.Actor, sim, p, cfg, pos: torch.Tensor, target: torch.Tensor, horizon: int):
    """One rope's J over ``horizon`` moves and its gradient (flattened over the actor's parameters), and the
    gradient reaching its first drag."""
    params = [x for x in actor.parameters()]
    total, first = 0.0, None
    for t in range(horizon):
        o = apg.graph_obs(cfg.task.obs, pos, target)
        log_pk, drags = actor.dist(o)
        node = actor.choose(o, log_pk, deterministic=True)
        drag = drags[torch.arange(1), node]
        if t == 0:
            drag.retain_grad()
            first = drag
        _, pos, r = apg.move_graph(sim, p, pos, target, node, drag, cfg.task.reward, cfg.objective)
        total = total + cfg.gamma ** t * r.sum()
    actor.zero_grad()
    total.backward()
    g = torch.cat([(x.grad if x.grad is not None else torch.zeros_like(x)).flatten() for x in params])
    return total.item(), g, float(first.grad.norm())


def greedy_node_bound(cfg: apg.APGConfig, episodes: int, seed: int) -> tuple[float, float]:
    """(success rate, mean moves of the successes) of the greedy node with a per-move optimized drag."""
    from planners.gradient import GradientPlanner
    p = cfg.task.cable_params()
    env = BatchedShapeControl(1, cfg.task.env_options(p))
    planner = GradientPlanner(env.sim, iters=20, restarts=3, halvings=0)
    wins, moves = [], []
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        for t in range(env.max_steps):
            s = env.get_state(generators=False)
            planner.nodes = [int(apg.greedy_node(obs)[0])]
            obs, _, term, trunc, info = env.step(planner.plan(s.pos[0], s.target[0])[None])
            if bool(term[0] | trunc[0]):
                break
        wins.append(bool(info["is_success"][0]))
        moves += [t + 1] if wins[-1] else []
    return sum(wins) / episodes, sum(moves) / max(len(moves), 1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.gradients.apg_gradients", description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", default=None, help="an apg run folder (its checkpoint.pt); default: a fresh actor")
    ap.add_argument("--horizons", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32])
    ap.add_argument("--ropes", type=int, default=32)
    ap.add_argument("--seed", type=int, default=20_000, help="env reset seed of the start ropes")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--bound", type=int, default=0, metavar="K",
                    help="also K episodes (env.reset(seed=eval_seed + i)) of the greedy node with an optimized drag")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config key (no --run only)")
    args = ap.parse_args(argv)
    if args.ropes < 2 or min(args.horizons) < 1 or args.bound < 0:
        ap.error("--ropes must be at least 2, every horizon at least 1 and --bound at least 0")
    if args.run and args.set:
        ap.error("--set changes the fresh actor's config: a --run brings its own")
    if any("=" not in item for item in args.set):
        ap.error(f"--set expects KEY=VALUE, got {args.set}")
    overrides = {k.strip(): yaml.safe_load(v) for k, v in (item.split("=", 1) for item in args.set)}
    try:
        cfg, ck, label = load_actor(args.run, overrides)
    except (ValueError, TypeError, FileNotFoundError) as exc:
        ap.error(str(exc))
    with torch_threads(args.threads):
        p = cfg.task.cable_params()
        env = BatchedShapeControl(args.ropes, cfg.task.env_options(p))
        obs, _ = env.reset(seed=args.seed)
        torch.manual_seed(0)
        actor = apg.Actor(obs, cfg, p.length, p.n_nodes)
        if ck is not None:
            actor.load_state_dict(ck["actor"])
        state = env.get_state(generators=False)
        print(f"APG gradient against the horizon: {label}; node {cfg.node}, reward {cfg.task.reward}, objective "
              f"{cfg.objective}, gamma {cfg.gamma}; {args.ropes} ropes from env.reset(seed={args.seed}), "
              f"start error {100 * float(state.info['shape_error'].mean()):.1f} cm (mean)")
        head = ["H", "J", "|g_i| mean (median; max)", "|mean g|", "rel. std", "cos to H=1", "|dJ/da_0| median; max",
                "non-finite", "s"]
        print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
        g1 = None
        for h in args.horizons:
            t0 = time.perf_counter()
            rows = [rope_gradient(actor, env.sim, p, cfg, state.pos[i:i + 1], state.target[i:i + 1], h)
                    for i in range(args.ropes)]
            ok = [r for r in rows if math.isfinite(r[0]) and bool(torch.isfinite(r[1]).all())]
            G = torch.stack([r[1] for r in ok])
            norms, mean_g = G.norm(dim=1), G.mean(0)
            rel = float((G - mean_g).norm(dim=1).pow(2).mean().sqrt() / mean_g.norm().clamp_min(1e-30))
            g1 = mean_g if g1 is None and h == args.horizons[0] else g1
            cos = float(torch.dot(mean_g, g1) / (mean_g.norm() * g1.norm()).clamp_min(1e-30))
            a0 = torch.tensor([r[2] for r in ok])
            print(f"| {h} | {sum(r[0] for r in ok) / len(ok):.2f} | {float(norms.mean()):.3g} "
                  f"({float(norms.median()):.3g}; {float(norms.max()):.3g}) | {float(mean_g.norm()):.3g} | {rel:.2f} "
                  f"| {cos:.2f} | {float(a0.median()):.3g}; {float(a0.max()):.3g} | {len(rows) - len(ok)} "
                  f"| {time.perf_counter() - t0:.1f} |", flush=True)
        print(f"(cos to H={args.horizons[0]}: the first horizon listed)")
        if args.bound:
            rate, moves = greedy_node_bound(cfg, args.bound, cfg.run.eval_seed)
            print(f"greedy node + the gradient planner's drag for it, {args.bound} episodes from env.reset(seed="
                  f"{cfg.run.eval_seed} + i): success {rate:.2f}, {moves:.1f} moves (successes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
