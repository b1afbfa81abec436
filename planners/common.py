"""Shared receding-horizon (MPC) episode loop, CLI and results for the planners.

A planner has ``name``, ``sim_evals`` (rope-moves it has simulated), ``reset(seed)`` (new episode; its generator
re-seeded with the episode's seed, so an episode's plan does not depend on the episodes before it) and
``plan(pos (N, 2), target (N, 2)) -> action (3,)`` (an env node action in [0, 1]^3); ``run_episode`` executes
its first action in ``BatchedShapeControl`` and replans until success (shape_error < success_tol and, with
``--success-worst-tol``, worst_node_error < it: the env's test) or max_steps. The episode's record keeps the mean
error ("errors") and the worst node's error ("worst_errors") after the reset and after every move.
Episode i starts from ``env.reset(seed=seed + i)``; with ``--target random`` or ``random_curve`` (a family in
diffdlo.planar.shapes.TARGET_FAMILIES) that reset also draws episode i's target, recorded under the episode in
results.json. That is the learners' evaluation rule too (agents/common/evaluation.py: episode i of a one-rope or batched
evaluation env reset with seed s is ``reset(seed=s + i)`` of one rope), so a planner and a learner evaluated with the
same seed see the same start shapes and targets, episode by episode (tests/test_paired_episodes.py).

Model mismatch: ``--params`` are the model's, the planner plans with a Simulator of those; ``--real-params`` and
``--real-scale`` give the "real" rope that the env moves and scores. The real rope must decode an action into the same
move (n_nodes, length, action_scale, max_disp equal). ``build_run`` builds the pair (used by
benchmarks/studies/mismatch.py).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from diffdlo.envs import BatchedShapeControl, EnvOptions
from diffdlo.planar.params import CableParams, ParamsError, load_params
from diffdlo.planar.physics import PHYSICAL, physical_values, scaled_params   # what a scale may change
from diffdlo.planar.shapes import TARGET_FAMILIES, TARGET_NAMES, TargetError
from diffdlo.planar.simulator import Simulator
from diffdlo.tasks import routing, task
from diffdlo.utils.checks import check_interval
from diffdlo.utils.files import OutBusyError, check_fresh_out, out_lock, shapes_record, write_json_atomic
from diffdlo.utils.signals import exit_code, stop_on_signals

from .escape import StallEscape

DEFAULT_MAX_STEPS = 15
SAME_MOVES = ("n_nodes", "length", "action_scale", "max_disp")   # model and real rope must agree on these


# ---------------------------------------------------------------------- the model's and the real rope's params
def parse_scales(items: list[str] | None, flag: str = "--real-scale") -> dict[str, float]:
    """["k_s=1.3", "k_d=0.7"] -> {"k_s": 1.3, "k_d": 0.7}. Raises ValueError naming the bad item."""
    factors: dict[str, float] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or key not in PHYSICAL:
            raise ValueError(f"bad {flag} {item!r}: give KEY=FACTOR with KEY one of {', '.join(PHYSICAL)}")
        if key in factors:
            raise ValueError(f"bad {flag} {item!r}: {key} is scaled twice")
        try:
            factor = float(text)
        except ValueError:
            factor = math.nan
        if not (math.isfinite(factor) and factor > 0):
            raise ValueError(f"bad {flag} {item!r}: the factor must be a positive finite number, got {text!r}")
        factors[key] = factor
    return factors


def check_same_moves(model: CableParams, real: CableParams) -> None:
    """The same action must mean the same move on the model and the real rope. Raises ParamsError naming the field."""
    for field in SAME_MOVES:
        if getattr(model, field) != getattr(real, field):
            raise ParamsError(f"the real rope's {field} = {getattr(real, field)!r} differs from the model's "
                              f"{getattr(model, field)!r}: the same actions would not mean the same moves")


def build_run(planner_cls, model: CableParams, real: CableParams, target_spec, *, max_steps: int,
              success_tol: float | None, device: str, seed: int, options: dict[str, Any],
              success_worst_tol: float | None = None, route_start: str = "beside"):
    """The env (moving and scoring the ``real`` rope) and the planner (planning on a Simulator of ``model``), with
    the target set. Returns (env, planner, target), target None for a family (drawn per episode). Raises ParamsError
    (ropes that disagree on SAME_MOVES), TargetError, or ValueError/RuntimeError (the env's options, the device)."""
    check_same_moves(model, real)
    route = task.is_route(target_spec)
    # a board of any size: the env's peg slots fit the layout (nothing in planning needs the learners' fixed count)
    layout = task.resolve_target(target_spec, model) if route else None
    slots = {"max_pegs": max(EnvOptions().max_pegs, len(layout.pegs))} if isinstance(layout, routing.Layout) else {}
    task_options = EnvOptions(target="route" if route else "horizontal", max_steps=max_steps, success_tol=success_tol,
                              success_worst_tol=success_worst_tol, params=real,
                              reward="route_gain" if route else "position_orientation",
                              action_type="node_pin" if options.get("pin") else "node", route_start=route_start,
                              **slots)
    env = BatchedShapeControl(1, task_options, device=device)
    target = task.resolve_target(target_spec, model, env.device, env.dtype)
    env.set_target(target)
    sim = env.sim if real == model else Simulator(model, device=env.device, dtype=env.dtype,
                                                  backend=env.sim.backend)
    planner = planner_cls(sim, seed=seed, **options)
    return env, planner, (None if isinstance(target, str) else
                          target.route.to(env.device, env.dtype) if route else target)


def seen(points: torch.Tensor, perception, rope: bool = True, pegs: torch.Tensor | None = None) -> torch.Tensor:
    """(N, 2) positions -> the (N, 2) positions ``perception`` (diffdlo.perception.Perception) reads from the env's
    picture of them (obs_type "image" with end markers, at the perception's image size and view); ``pegs`` (K, 3): a
    route's board, drawn in the picture as the env draws it and known to the reading."""
    from diffdlo.perception import render_uint8
    board = None if pegs is None else pegs[None].float()
    picture = render_uint8(points[None].float(), perception.image_size, perception.view_size, rope, board)
    return perception.read(picture, rope=rope, pegs=board)[0].to(points)


def run_episode(env: BatchedShapeControl, planner, seed: int, desc: str = "", progress: bool = True,
                perception=None, escape=None) -> dict[str, Any]:
    """One episode of receding-horizon control. Returns the episode record plus its frames (T+1, N, 2). The record's
    "errors" and "worst_errors" (T+1 each): the shape error and the worst node's error [m] after the reset and after
    each move, the env's own figures.
    ``perception``: the planner is given the rope and the target as this perception reads them from the env's
    pictures (the target once per episode), not the simulator's state; "seen_error_mm" records how far off they were
    (mean node distance, averaged over the moves; "seen_errors_mm" per move).
    ``escape`` (planners.escape.StallEscape): its greedy moves replace the planner's after a stall; "escapes" and
    "escape_moves" record how often and how many."""
    env.reset(seed=seed)
    planner.reset(seed=seed)
    if escape is not None:
        escape.reset()
    state = env.get_state(generators=False)
    target, target_name = state.target[0], state.target_names[0]
    pegs = None if state.pegs is None else state.pegs[0][state.pegs[0][:, 2] > 0]       # a route's board
    planned_target = target if perception is None else seen(target, perception, rope=False, pegs=pegs)
    seen_errors: list[float] = []
    frames = [state.pos[0]]
    errors = [float(state.info["shape_error"][0])]
    worst_errors = [float(state.info["worst_node_error"][0])]
    grad0 = getattr(planner, "grad_evals", 0)
    if hasattr(planner, "grad_norms"):
        planner.grad_norms = []
    evals0, plan_s, steps, success = planner.sim_evals, 0.0, 0, bool(env.info()["is_success"][0])
    bar = tqdm(total=env.max_steps, desc=desc, disable=not progress, leave=True, dynamic_ncols=True)
    while not success:
        t0 = time.perf_counter()
        rope = frames[-1].clone()
        if perception is not None:
            rope = seen(rope, perception, pegs=pegs)        # a route: read among its pegs, planned among the true ones
            if pegs is not None:                            # a reading a few mm inside a peg: out to its surface
                rope = routing.clear_of_pegs(rope, pegs, env.sim.params.rope_radius)
            seen_errors.append(float((rope - frames[-1]).norm(dim=-1).mean()))
        action = None if escape is None else escape.plan(rope, planned_target, pegs)
        if action is None:
            action = planner.plan(rope, planned_target) if pegs is None else planner.plan(rope, planned_target, pegs)
        plan_s += time.perf_counter() - t0
        _, _, term, trunc, info = env.step(action.detach().reshape(1, -1).to(torch.float64))
        steps += 1
        frames.append(env.get_state(generators=False).pos[0])
        errors.append(float(info["shape_error"][0]))
        worst_errors.append(float(info["worst_node_error"][0]))
        success = bool(info["is_success"][0])
        bar.update(1)
        bar.set_postfix(err_cm=f"{errors[-1] * 100:.2f}", node=int(info["node"][0]))
        if bool(trunc[0]):
            break
    bar.close()
    stats = planner.episode_stats() if hasattr(planner, "episode_stats") else {}
    if "grad_evals" in stats:
        stats["grad_evals"] -= grad0
    if perception is not None:
        stats["seen_error_mm"] = 1000 * sum(seen_errors) / max(len(seen_errors), 1)
        stats["seen_errors_mm"] = [round(1000 * e, 2) for e in seen_errors]      # per move, before each plan
        stats["seen_target_error_mm"] = 1000 * float((planned_target - target).norm(dim=-1).mean())
    if escape is not None:
        stats["escapes"], stats["escape_moves"] = escape.escapes, escape.moves
    return {**stats, "success": success, "steps": steps, "final_error": errors[-1], "start_error": errors[0],
            "errors": errors, "worst_errors": worst_errors, "sim_evals": planner.sim_evals - evals0, "plan_s": plan_s,
            "plan_s_per_step": plan_s / max(steps, 1), "seed": seed, "target_name": target_name,
            **({} if pegs is None else {"pegs": pegs.detach().cpu().to(torch.float64).tolist(),
                                        "sides_kept": bool(info["sides_kept"][0]) if steps else None}),
            "frames": torch.stack(frames),
            "target_points": target}


def make_parser(name: str, doc: str | None, planner_cls) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"python -m planners.{name}", description=doc,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--target", default="diagonal",
                        help=f"one of {list(TARGET_NAMES)}, a family drawn anew per episode {list(TARGET_FAMILIES)} "
                             f"(episode i's target is the one env.reset(seed=SEED + i) draws), a path to an (N, 2) "
                             f".npy/.yaml polyline of the rope's link lengths, or a route among pegs: 'route' (a "
                             f"random board per episode) or 'route:NAME' (NAME in {routing.layout_names()} or a "
                             f"layout .yaml) (default diagonal)")
    parser.add_argument("--route-start", choices=routing.ROUTE_STARTS, default="beside",
                        help="a route's start: beside the board (default) or across it, among the pegs")
    parser.add_argument("--seed", type=int, default=0, help="episode i starts from env.reset(seed=SEED + i) (default 0)")
    parser.add_argument("--episodes", type=int, default=1, help="episodes (default 1)")
    parser.add_argument("--max-steps", type=int, default=DEFAULT_MAX_STEPS,
                        help=f"moves per episode (default {DEFAULT_MAX_STEPS})")
    parser.add_argument("--out", default=None, help=f"output folder (default runs/{name}-<target>)")
    parser.add_argument("--device", default="cpu", help="simulator device (default cpu)")
    parser.add_argument("--params", default="cable",
                        help="the model's params: a name or YAML path (default cable); the planner plans with them")
    parser.add_argument("--model-contact-width", type=float, default=None, metavar="W",
                        help="the model's contact width [m] (its penalty's smoothing among pegs: a wider one smooths "
                             "the planner's cost across the onset of contact); the env's rope keeps --params' (or "
                             "--real-params') own (default: the model's params' contact width)")
    parser.add_argument("--real-params", default=None,
                        help="the real rope's params (name or YAML path) that the env moves and scores (default "
                             "--params); n_nodes, length, action_scale and max_disp must equal the model's")
    parser.add_argument("--real-scale", action="append", default=None, metavar="KEY=FACTOR",
                        help=f"multiply the real rope's {', '.join(PHYSICAL)} (those of --real-params, else of "
                             f"--params) by FACTOR > 0; repeat for several keys, e.g. --real-scale k_d=2")
    parser.add_argument("--success-tol", type=float, default=None,
                        help="success threshold [m] of the shape error, the mean node distance (default params: 0.01)")
    parser.add_argument("--success-worst-tol", type=float, default=None,
                        help="also require the worst node's error [m] below this for success (default: no "
                             "worst-node condition)")
    parser.add_argument("--perception", default=None, metavar="PATH",
                        help="plan from the rope and target as this perception checkpoint reads them from the env's "
                             "pictures (python -m diffdlo.perception), not from the simulator's state")
    parser.add_argument("--perception-refine", type=int, default=None, metavar="STEPS",
                        help="with --perception: its refinement steps per picture (default: the checkpoint's)")
    parser.add_argument("--escape", type=int, default=0, metavar="K",
                        help="after K moves that brought the best error down by under 1 mm, take greedy moves (the "
                             "farthest node towards its place) until the rope is 1 mm below its best, then plan again "
                             "(planners/escape.py; default 0: off)")
    parser.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run in --out")
    parser.add_argument("--no-gif", action="store_true", help="skip the GIFs")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    group = parser.add_argument_group(planner_cls.name)
    for key, (kind, default, allowed, text) in planner_cls.OPTIONS.items():
        group.add_argument(f"--{key.replace('_', '-')}", type=kind, default=default,
                           help=f"{text}: in {allowed} (default {default})")
    return parser


def check_planner_options(planner_cls, options: dict[str, Any], prefix: str = "--") -> None:
    """Raise ValueError naming the first option (as the flag ``prefix`` + its name) outside its allowed range."""
    def flag(key: str) -> str:
        return prefix + key.replace("_", "-")
    for key, (_, _, allowed, _) in planner_cls.OPTIONS.items():
        check_interval(flag(key), options[key], allowed)
    if "elites" in planner_cls.OPTIONS and options["elites"] > options["candidates"]:
        raise ValueError(f"{flag('elites')} must be at most {flag('candidates')} ({options['candidates']}), "
                         f"got {options['elites']}")


def refuse(message: str) -> int:
    """One line on stderr naming the bad value; the command's exit code 2."""
    print(f"error: {' '.join(message.split())}", file=sys.stderr)
    return 2


def run_cli(planner_cls, name: str, doc: str | None, argv: list[str] | None = None) -> int:
    parser = make_parser(name, doc, planner_cls)
    args = parser.parse_args(argv)
    try:
        check_interval("--episodes", args.episodes, "[1, inf)")
        check_interval("--max-steps", args.max_steps, "[1, inf)")
        check_interval("--escape", args.escape, "[0, inf)")
        for flag in ("--success-tol", "--success-worst-tol"):
            value = getattr(args, flag[2:].replace("-", "_"))
            if value is not None:
                check_interval(flag, value, "(0, inf)")
        check_planner_options(planner_cls, {k: getattr(args, k) for k in planner_cls.OPTIONS})
    except ValueError as exc:
        parser.error(str(exc))
    try:
        base = load_params(args.params)
    except (ParamsError, OSError, ValueError) as exc:
        parser.error(f"bad --params {args.params!r}: {exc}")
    p = base
    if args.model_contact_width is not None:
        try:
            check_interval("--model-contact-width", args.model_contact_width, "(0, inf)")
            p = dataclasses.replace(base, contact_width=float(args.model_contact_width))
        except (ParamsError, ValueError) as exc:
            parser.error(str(exc))
    try:
        factors = parse_scales(args.real_scale)
    except ValueError as exc:
        return refuse(str(exc))
    try:
        real = scaled_params(load_params(args.real_params) if args.real_params is not None else base, factors,
                             "--real-scale")
        check_same_moves(p, real)
    except (ParamsError, OSError, ValueError) as exc:
        source = f"--real-params {args.real_params!r}" if args.real_params is not None else "--real-scale"
        return refuse(f"bad {source}: {exc}")
    options = {k: getattr(args, k) for k in planner_cls.OPTIONS}
    try:
        env, planner, target = build_run(planner_cls, p, real, args.target, max_steps=args.max_steps,
                                         success_tol=args.success_tol, device=args.device, seed=args.seed,
                                         options=options, success_worst_tol=args.success_worst_tol,
                                         route_start=args.route_start)
    except TargetError as exc:
        return refuse(f"bad --target {args.target!r}: {exc}")
    except (ValueError, RuntimeError) as exc:
        parser.error(str(exc))
    perception = None
    if args.perception is not None:
        from diffdlo.perception import Perception, PerceptionError
        try:
            if args.perception_refine is not None and args.perception_refine < 0:
                raise PerceptionError(f"--perception-refine must be >= 0, got {args.perception_refine}")
            perception = Perception.load(args.perception, refine_iters=args.perception_refine, n_nodes=real.n_nodes,
                                         view_size=env.view_size)
        except PerceptionError as exc:
            parser.error(f"--perception: {exc}")
    escape = None
    if args.escape:
        escape = StallEscape(planner.sim, args.escape, pin=bool(options.get("pin")))
    label = task.target_label(args.target)
    out = Path(args.out or f"runs/{name}-{label}")
    try:
        check_fresh_out(out, args.overwrite, "an earlier run")
    except FileExistsError as exc:
        parser.error(str(exc))

    try:
        with out_lock(out), stop_on_signals():              # one writer per --out; signals stop it however started
            t0 = time.perf_counter()
            episodes = [run_episode(env, planner, args.seed + i, progress=not args.quiet, perception=perception,
                                    escape=escape, desc=f"{name} {label} ep {i + 1}/{args.episodes}")
                        for i in range(args.episodes)]
            mismatch = {} if real == p else {"model_params": physical_values(p), "real_params": physical_values(real)}
            write_outputs(out, name, args, label, target, episodes, time.perf_counter() - t0, extra=mismatch)
    except OutBusyError as exc:
        parser.error(str(exc))
    except KeyboardInterrupt as exc:
        print(f"{name}: stopped by {exc or 'SIGINT'}: no results written (a planner keeps no partial state)",
              file=sys.stderr)
        return exit_code(exc)
    return 0


def write_outputs(out: Path, name: str, args, label: str, target: torch.Tensor | None, episodes: list[dict],
                  wall: float, extra: dict | None = None):
    """results.json (with ``extra``'s fields), shapes.png and the GIFs. ``target`` None: the target was drawn per
    episode (a family), so each episode's own target (its "target_points") is drawn and recorded under the episode as
    "target" ([[x, y], ...])."""
    from diffdlo.utils import render

    n = len(episodes)
    steps = sum(e["steps"] for e in episodes)
    plan_s = sum(e["plan_s"] for e in episodes)
    records = [{k: v for k, v in e.items() if k not in ("frames", "target_points")} for e in episodes]
    if target is None:
        for rec, e in zip(records, episodes):
            rec["target"] = e["target_points"].detach().cpu().to(torch.float64).tolist()
    targets = [e["target_points"] if target is None else target for e in episodes]
    results = {
        "method": name, "target": args.target, "seed": args.seed,
        "success_rate": sum(e["success"] for e in episodes) / n,
        "episodes": records, "env_steps": steps, "wall_s": wall,
        "sim_evals": sum(e["sim_evals"] for e in episodes),
        "plan_s_per_step": plan_s / max(steps, 1), "max_steps": args.max_steps,
        "shapes": dict(shapes_record(episodes[0]["frames"][0], episodes[0]["frames"][-1], targets[0]),
                       **({"pegs": episodes[0]["pegs"]} if "pegs" in episodes[0] else {})),   # a route's board
        "config": {k: v for k, v in vars(args).items() if k not in ("out", "quiet")},
        **(extra or {}),
    }
    write_json_atomic(out / "results.json", results)
    ropes, rope_targets, titles = [], [], []
    for i, e in enumerate(episodes):
        ropes += [e["frames"][0], e["frames"][-1]]
        rope_targets += [targets[i], targets[i]]
        titles += [f"ep {i} (seed {e['seed']}) start: {e['start_error'] * 100:.1f} cm",
                   f"after {e['steps']} moves: {e['final_error'] * 100:.2f} cm"]
    png = out / "shapes.png"
    route = "pegs" in episodes[0]                          # a route: drawn where it lies, among its pegs
    boards = [torch.tensor(e["pegs"]) for e in episodes for _ in range(2)] if route else None
    render.plot_ropes(torch.stack(ropes), torch.stack(rope_targets), png, titles=titles, cols=2,
                      align_target=not route, pegs=boards)
    if not args.no_gif:
        for i, e in enumerate(episodes):
            render.save_gif(e["frames"], out / f"episode_{i}.gif", targets[i], fps=2, title=f"{name} ep {i}",
                            align_target=not route, pegs=torch.tensor(e["pegs"]) if route else None)
    succ = [e for e in episodes if e["success"]]
    moves = f"{sum(e['steps'] for e in succ) / len(succ):.1f}" if succ else "-"
    print(f"{name} {label}: success {len(succ)}/{n}, moves to success (mean) {moves}, final error mean "
          f"{sum(e['final_error'] for e in episodes) / n * 100:.2f} cm max "
          f"{max(e['final_error'] for e in episodes) * 100:.2f} cm, plan {results['plan_s_per_step']:.2f} s/step, "
          f"sim_evals/episode {results['sim_evals'] / n:.0f}, wall {wall:.1f} s -> {out}/results.json, {png}")
