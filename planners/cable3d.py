"""Planners through the 3-D chain: the two-gripper task on a real cable's fitted chain (diffdlo/tasks/cable3d.py,
docs/CABLE3D.md), receding horizon: plan a move, execute it in the env, re-plan from where the cable came to rest.

- ``cem``: the generic ``CEM`` (planners/cem.py) over (H, 12) gripper actions in [-1, 1]^12, each candidate rolled
  through the chain (``ChainObjective``: one batched move per step of the horizon).
- ``gradient``: Adam on u, a = tanh(u), through the chain's autograd (the whole move differentiable), from
  ``starts`` random first guesses at once, the best kept.
The planner's chain is the env's cable unless told otherwise: ``--model-cable`` plans with another cable's fit,
``--stand-in`` makes the env's cable the fitted physics plus its learned residual (the stand-in for the real cable)
while the planner plans with physics alone (``--plan-with stand-in``: with the stand-in itself), ``--open-loop``
plans a whole sequence once and executes it blind. ``--plan-settle`` [s] caps the planner's settle (cheaper, a cable
not quite at rest) where the env's own move settles up to ``--settle-time``. ``--target recorded --data DIR``: the
targets are shapes DEFORM's real cable took (diffdlo/tasks/cable3d.py).

    python -m planners.cable3d --cable DLO3 --episodes 5 --out runs/cable3d-cem
    python -m planners.cable3d --planner gradient --cable DLO3 --episodes 5 --out runs/cable3d-gradient
    python -m planners.cable3d --cable DLO3 --target recorded --data DEFORM/data_set --out runs/cable3d-recorded
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from diffdlo.chain3d import grippers as gr
from diffdlo.chain3d.cables import FRAME_DT, CableError, cable_names
from diffdlo.chain3d.chain import rollout
from diffdlo.envs.cable3d import BatchedCable3D
from diffdlo.tasks import cable3d as rules
from diffdlo.utils.files import OutBusyError, check_fresh_out, out_lock, write_json_atomic
from diffdlo.utils.signals import exit_code, stop_on_signals

from .cem import CEM


class ChainObjective:
    """objective(actions (B, H, 12)) -> (B,) the mean marker error [m] after the H moves (plus ``running_weight`` x
    the errors after the moves before the last), every candidate from the cable ``x`` (N, 3) at rest."""

    def __init__(self, core: BatchedCable3D, x: torch.Tensor, target: torch.Tensor, settle_frames: int,
                 running_weight: float = 0.5):
        self.core, self.x, self.target = core, x, target
        self.settle_frames, self.running_weight = settle_frames, running_weight
        self.moves = 0                                        # moves simulated (the planner's cost axis)

    def rollout(self, actions: torch.Tensor) -> list[torch.Tensor]:
        x = self.x.expand(actions.shape[0], *self.x.shape).to(self.core.dtype)
        states = []
        for t in range(actions.shape[1]):
            goal = rules.decode_action(actions[:, t].clamp(-1, 1).to(x), gr.poses_of(x), self.core.cable)
            x = self.core.move(x, goal, settle_frames=self.settle_frames).x
            states.append(x)
            self.moves += actions.shape[0]
        return states

    def __call__(self, actions: torch.Tensor) -> torch.Tensor:
        states = self.rollout(actions)
        cost = rules.marker_errors(states[-1], self.target).mean(-1)
        for x in states[:-1]:
            cost = cost + self.running_weight * rules.marker_errors(x, self.target).mean(-1)
        return cost


class CEMPlanner:
    name = "cem"

    def __init__(self, core: BatchedCable3D, seed: int = 0, horizon: int = 1, candidates: int = 128,
                 elites: int = 12, iterations: int = 5, plan_settle: float = 1.0):
        self.core, self.horizon, self.plan_settle = core, horizon, rules.frames_of(plan_settle, "--plan-settle")
        self.cem = CEM(rules.ACTION_DIM, horizon, candidates, elites, iterations, low=-1.0, high=1.0,
                       init_std=0.3, generator=torch.Generator().manual_seed(seed))
        self.sim_moves = 0

    def reset(self, seed: int) -> None:
        """A new episode: the search distribution back to its prior (no warm start from another episode's plan),
        the generator seeded with the episode's seed."""
        self.cem.reset()
        self.cem.gen.manual_seed(seed)

    def plan_sequence(self, x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """The best (H, 12) sequence from the cable ``x`` at rest (open loop: all executed blind)."""
        objective = ChainObjective(self.core, x, target, self.plan_settle)
        with torch.no_grad():
            best, _ = self.cem.optimize(objective)
        self.sim_moves += objective.moves
        return best

    def plan(self, x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        best = self.plan_sequence(x, target)
        self.cem.shift()
        return best[0]


class GradientPlanner:
    name = "gradient"

    def __init__(self, core: BatchedCable3D, seed: int = 0, starts: int = 8, steps: int = 12, lr: float = 0.3,
                 plan_settle: float = 1.0):
        self.core, self.starts, self.steps, self.lr = core, starts, steps, lr
        self.plan_settle = rules.frames_of(plan_settle, "--plan-settle")
        self.gen = torch.Generator().manual_seed(seed)
        self.sim_moves = 0

    def reset(self, seed: int) -> None:
        """A new episode: the first guesses' generator seeded with the episode's seed."""
        self.gen.manual_seed(seed)

    def plan(self, x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        objective = ChainObjective(self.core, x, target, self.plan_settle)
        u = (0.5 * torch.randn(self.starts, 1, rules.ACTION_DIM, generator=self.gen, dtype=torch.float64)
             ).to(self.core.dtype).requires_grad_(True)
        u.data[0] = 0.0                                       # one guess: stay where it is
        opt = torch.optim.Adam([u], lr=self.lr)
        best, best_cost = None, float("inf")
        for _ in range(self.steps):
            cost = objective(torch.tanh(u))
            i = int(cost.detach().argmin())
            if float(cost.detach()[i]) < best_cost:
                best, best_cost = torch.tanh(u[i, 0]).detach().clone(), float(cost.detach()[i])
            opt.zero_grad()
            cost.sum().backward()
            opt.step()
        self.sim_moves += objective.moves
        return best


PLANNERS = {"cem": CEMPlanner, "gradient": GradientPlanner}


def run_episode(core: BatchedCable3D, planner, seed: int, progress: bool = True,
                open_loop: bool = False) -> dict[str, Any]:
    """One episode in the env ``core`` (its cable may differ from the planner's model), re-planned after every move
    (closed loop) or, ``open_loop``, one plan of the planner's horizon made at the start and executed blind; the
    record and the start, target and final markers."""
    core.seed([seed])
    planner.reset(seed)                  # each episode on its own: the same seed, the same episode, wherever it runs
    core.reset()
    start, target = core.x[0].clone(), core.target[0].clone()
    errors = [float(core.info()["marker_error"][0])]
    worst = [float(core.info()["worst_marker_error"][0])]
    moves0, plan_s, steps, success = planner.sim_moves, 0.0, 0, False
    bar = tqdm(total=core.max_steps, desc=f"{planner.name} {core.cable.name} seed {seed}", disable=not progress,
               leave=False, dynamic_ncols=True)
    blind, actions, frames = None, [], []
    while not success and steps < core.max_steps:
        t0 = time.perf_counter()
        if open_loop:
            if blind is None:
                blind = list(planner.plan_sequence(core.x[0], target))
            if not blind:
                break
            action = blind.pop(0)
        else:
            action = planner.plan(core.x[0], target)
        plan_s += time.perf_counter() - t0
        _, _, terminated, _, info = core.step(action.reshape(1, -1))
        actions.append(action.reshape(-1).tolist())
        frames.append(int(info["frames"][0]))
        steps += 1
        errors.append(float(info["marker_error"][0]))
        worst.append(float(info["worst_marker_error"][0]))
        success = bool(info["is_success"][0])
        bar.update(1)
        bar.set_postfix(error_cm=f"{100 * errors[-1]:.2f}")
    bar.close()
    return {"seed": seed, "success": success, "steps": steps, "errors": errors, "worst_errors": worst,
            "plan_seconds_per_move": plan_s / max(steps, 1), "sim_moves": planner.sim_moves - moves0,
            "actions": actions, "frames": frames,
            "start": start.tolist(), "target": target.tolist(), "final": core.x[0].tolist()}


def draw(episodes: list[dict[str, Any]], path: Path) -> None:
    """Start (grey), target (black dashed) and final (blue) markers of each episode in 3-D."""
    from diffdlo.utils.render import _pyplot
    plt = _pyplot()
    fig = plt.figure(figsize=(4 * min(len(episodes), 4), 4))
    for i, ep in enumerate(episodes[:4]):
        ax = fig.add_subplot(1, min(len(episodes), 4), i + 1, projection="3d")
        for key, style in (("start", dict(color="0.6", marker="o", ms=3)), ("target", dict(color="k", ls="--")),
                           ("final", dict(color="tab:blue", marker="o", ms=3))):
            x = torch.tensor(ep[key])
            ax.plot(x[:, 0], x[:, 1], x[:, 2], label=key, **style)
        ax.set_title(f"seed {ep['seed']}: {'solved' if ep['success'] else 'not solved'} in {ep['steps']}, "
                     f"{100 * ep['errors'][-1]:.2f} cm", fontsize=9)
        points = torch.cat([torch.tensor(ep[k]) for k in ("start", "target", "final")])
        ax.set_box_aspect(tuple((points.amax(0) - points.amin(0)).clamp_min(0.05).tolist()))   # metres alike
        ax.locator_params(nbins=4)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
    fig.axes[0].legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def replay(core: BatchedCable3D, episode: dict[str, Any], every: int = 5) -> torch.Tensor:
    """(F, N, 3) the cable every ``every`` frames through an episode's moves, replayed on the chain (its physics:
    the grippers' path, then the hold for as many frames as each move's settle took in the env)."""
    cable = core.cable
    mask = torch.zeros(cable.n_nodes, dtype=torch.bool)
    mask[list(cable.held)] = True
    x = torch.tensor(episode["start"], dtype=torch.float64)[None]
    shown = [x[0]]
    for action, used in zip(episode["actions"], episode["frames"]):
        goal = rules.decode_action(torch.tensor([action], dtype=torch.float64), gr.poses_of(x), cable)
        path = gr.gripper_path(gr.poses_of(x), goal, cable, core.move_frames)
        hold = gr.held_markers(goal, cable)[None].expand(max(used - core.move_frames, 0) + 1, -1, -1, -1)
        with torch.no_grad():
            moving, v = rollout(x, None, mask, path, cable.params, cable.substeps, frame_dt=FRAME_DT,
                                return_velocities=True)
            held = rollout(moving[-1], v[-1], mask, hold, cable.params, cable.substeps, frame_dt=FRAME_DT)
        trajectory = torch.cat([moving[1:], held[1:]])[:, 0]
        shown += list(trajectory[every - 1::every]) + [trajectory[-1]]
        x = trajectory[-1:]
    return torch.stack(shown)


def draw_gif(core: BatchedCable3D, episode: dict[str, Any], path: Path, every: int = 5) -> None:
    """A GIF of an episode in 3-D at a fifth of real time (every ``every``-th 10 ms frame, 20 frames/s): the cable
    (blue), its held markers (black), the target (dashed)."""
    from matplotlib.animation import FuncAnimation, PillowWriter

    from diffdlo.utils.render import _pyplot
    plt = _pyplot()
    frames = replay(core, episode, every).numpy()
    target = np.asarray(episode["target"])
    points = np.concatenate([frames.reshape(-1, 3), target])
    low, high = points.min(0) - 0.02, points.max(0) + 0.02
    held = list(core.cable.held)
    fig = plt.figure(figsize=(4.5, 4.5))
    ax = fig.add_subplot(projection="3d")

    def draw(i: int):
        ax.clear()
        ax.plot(*target.T, color="k", ls="--", label="target")
        ax.plot(*frames[i].T, color="tab:blue", marker="o", ms=3, label="cable")
        ax.plot(*frames[i, held].T, color="k", marker="s", ms=4, ls="none", label="held")
        ax.set_xlim(low[0], high[0]), ax.set_ylim(low[1], high[1]), ax.set_zlim(low[2], high[2])
        ax.set_box_aspect(tuple((high - low).tolist()))                        # metres alike on every axis
        ax.locator_params(nbins=4)
        ax.set_title(f"{core.cable.name}, seed {episode['seed']}: t = {i * every * FRAME_DT:.2f} s", fontsize=9)
        ax.legend(loc="upper left", fontsize=7)

    anim = FuncAnimation(fig, draw, frames=len(frames))
    anim.save(path, writer=PillowWriter(fps=20))
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m planners.cable3d", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--planner", choices=sorted(PLANNERS), default="cem")
    ap.add_argument("--cable", default=None, help=f"one of {cable_names()} (default: the file's, DLO3)")
    ap.add_argument("--episodes", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0, help="episode i is the env reset with seed SEED + i")
    ap.add_argument("--max-steps", type=int, default=20)
    ap.add_argument("--move-time", type=float, default=1.0, help="[s] the grippers' motion per move")
    ap.add_argument("--settle-time", type=float, default=5.0, help="[s] the env's settle cap")
    ap.add_argument("--plan-settle", type=float, default=1.0, help="[s] the planner's settle cap")
    ap.add_argument("--horizon", type=int, default=1, help="cem: moves planned ahead")
    ap.add_argument("--candidates", type=int, default=128, help="cem: sequences per iteration")
    ap.add_argument("--elites", type=int, default=12, help="cem: elites refit per iteration")
    ap.add_argument("--iterations", type=int, default=5, help="cem: iterations per move")
    ap.add_argument("--starts", type=int, default=8, help="gradient: first guesses optimised together")
    ap.add_argument("--steps", type=int, default=12, help="gradient: Adam steps per move")
    ap.add_argument("--target", choices=rules.TARGETS, default="reachable",
                    help="reachable: a shape the model reaches by two random moves; recorded (with --data): a shape "
                         "the real cable took in DEFORM's eval recordings")
    ap.add_argument("--data", type=Path, default=None, help="DEFORM's data_set folder (for --target recorded)")
    ap.add_argument("--model-cable", default=None, help="the planner's cable (default: --cable's): a parameter "
                                                         "mismatch, planned with one cable's fit, run on another's")
    ap.add_argument("--stand-in", type=Path, default=None,
                    help="a residual checkpoint of --cable (python -m benchmarks.real_cable_residual's "
                         "DLO<k>_residual.pt): the env's cable is the fitted physics + that residual, the stand-in "
                         "for the real cable; the planner plans with physics alone unless --plan-with stand-in")
    ap.add_argument("--plan-with", choices=("physics", "stand-in"), default="physics")
    ap.add_argument("--open-loop", action="store_true", help="cem: plan --horizon moves once, execute them blind")
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--quiet", action="store_true")
    ap.add_argument("--no-gif", action="store_true", help="skip the first episode's GIF")
    args = ap.parse_args(argv)
    if args.episodes < 1 or args.max_steps < 1:
        ap.error(f"--episodes and --max-steps must be >= 1, got {args.episodes} and {args.max_steps}")
    if args.threads is not None:
        if args.threads < 1:
            ap.error(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    try:
        residual = None
        if args.stand_in is not None:
            from diffdlo.chain3d.residual import ResidualError, load
            try:
                residual = load(args.stand_in).to(getattr(torch, args.dtype))
            except ResidualError as exc:
                raise ValueError(f"--stand-in: {exc}") from None
        elif args.plan_with == "stand-in":
            raise ValueError("--plan-with stand-in needs --stand-in")
        if args.open_loop and args.planner != "cem":
            raise ValueError("--open-loop plans a whole sequence: --planner cem")
        settings = dict(max_steps=args.max_steps, move_time=args.move_time, settle_time=args.settle_time,
                        dtype=getattr(torch, args.dtype))
        if (args.target == "recorded") != (args.data is not None):
            raise ValueError(f"--data goes with --target recorded and only with it, got --target {args.target} and "
                             f"--data {args.data}")
        core = BatchedCable3D(1, cable=args.cable, residual=residual, target=args.target, data=args.data,
                              **settings)
        model_cable = args.model_cable or args.cable
        model = core if model_cable == args.cable and (residual is None or args.plan_with == "stand-in") else \
            BatchedCable3D(1, cable=model_cable, residual=residual if args.plan_with == "stand-in" else None,
                           **settings)
        if model.cable.n_nodes != core.cable.n_nodes:
            raise ValueError(f"--model-cable {model.cable.name} has {model.cable.n_nodes} markers, the env's cable "
                             f"{core.cable.name} {core.cable.n_nodes}: plan with a cable of as many")
        options = ({"horizon": args.horizon, "candidates": args.candidates, "elites": args.elites,
                    "iterations": args.iterations} if args.planner == "cem" else
                   {"starts": args.starts, "steps": args.steps})
        for key, value in options.items():
            if value < 1:
                raise ValueError(f"--{key} must be >= 1, got {value}")
        if args.planner == "cem" and args.elites > args.candidates:
            raise ValueError(f"--elites ({args.elites}) must be at most --candidates ({args.candidates})")
        planner = PLANNERS[args.planner](model, seed=args.seed, plan_settle=args.plan_settle, **options)
    except (CableError, ValueError) as exc:
        ap.error(str(exc))
    out = args.out or Path(f"runs/cable3d-{args.planner}-{core.cable.name}")
    try:
        check_fresh_out(out, args.overwrite, "an earlier run")
    except FileExistsError as exc:
        ap.error(str(exc))
    try:
        with out_lock(out), stop_on_signals():
            t0 = time.perf_counter()
            episodes = [run_episode(core, planner, args.seed + i, progress=not args.quiet, open_loop=args.open_loop)
                        for i in range(args.episodes)]
            solved = [e for e in episodes if e["success"]]
            summary = {"planner": args.planner, "cable": core.cable.name, "model_cable": model.cable.name,
                       "stand_in": None if args.stand_in is None else str(args.stand_in),
                       "plan_with": args.plan_with, "open_loop": args.open_loop, "target": args.target,
                       "episodes": len(episodes),
                       "success_rate": len(solved) / len(episodes),
                       "mean_moves_to_success": (sum(e["steps"] for e in solved) / len(solved)) if solved else None,
                       "plan_seconds_per_move": sum(e["plan_seconds_per_move"] for e in episodes) / len(episodes),
                       "sim_moves_per_episode": sum(e["sim_moves"] for e in episodes) / len(episodes),
                       "options": options, "wall_seconds": time.perf_counter() - t0, "argv": sys.argv[1:] if argv is None else argv}
            write_json_atomic(out / "results.json", {**summary, "episode_records": episodes})
            try:
                draw(episodes, out / "shapes.png")
                if not args.no_gif:
                    draw_gif(core, episodes[0], out / "episode_0.gif")
            except ImportError:
                pass
    except OutBusyError as exc:
        ap.error(str(exc))
    except KeyboardInterrupt as exc:
        print(f"{args.planner}: stopped by {exc or 'SIGINT'}: no results written", file=sys.stderr)
        return exit_code(exc)
    print(f"{args.planner} {core.cable.name}: success {len(solved)}/{len(episodes)}, moves to success "
          f"{summary['mean_moves_to_success'] or '-'}, plan {summary['plan_seconds_per_move']:.2f} s/move -> "
          f"{out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
