"""Two grippers holding the 3-D chain by its ends, as DEFORM's robots hold its cables: a move of both, then rest.

Each gripper holds its end's two markers (nodes 0 and 1, N-1 and N-2), so its pose is the end marker's position p
and the unit direction d from it to the next marker: ``Grippers(pos (B, 2, 3), dirs (B, 2, 3))``. The held markers
sit at p and p + l d (l the held link's rest length), rigidly, whatever the cable does.

``move`` takes the grippers from their poses to goal poses over ``move_frames`` frames of 10 ms along a smooth path
(minimum jerk: s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5, zero velocity and acceleration at both ends; the position
moves straight, the direction turns about one fixed axis), then holds them while the cable comes to rest: every
``check_frames`` frames the free markers' fastest speed is compared with ``rest_speed``; a cable below it is at rest
and frozen (batch members never influence each other), the others go on up to ``settle_frames`` frames (the cap).
The chain is diffdlo/chain3d/chain.py's ``rollout`` (gravity, stretching, bending, drag, internal damping), so the
whole move is differentiable with respect to the start state, the goal poses and the cable's parameters. On the CPU,
without ``accel`` and with no gradient wanted w.r.t. the cable's parameters, ``engine="auto"`` runs the same move on
the fused C++ kernel and its adjoint (diffdlo/chain3d/kernel.py), about 40-200x faster
(benchmarks/speed/cable3d_speed.py); ``engine="eager"`` forces the torch path.
Pure batched functions of tensors; device and dtype follow the state.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import torch

from . import kernel
from .cables import FRAME_DT, Cable
from .chain import rollout

_TINY = 1e-12


class Grippers(NamedTuple):
    """Both grippers' poses: the end markers' positions (B, 2, 3) [m] and unit directions (B, 2, 3) inwards."""
    pos: torch.Tensor
    dirs: torch.Tensor


class MoveResult(NamedTuple):
    x: torch.Tensor                   # (B, N, 3) the markers at the end [m]
    v: torch.Tensor                   # (B, N, 3) their velocities [m/s]
    settled: torch.Tensor             # (B,) bool: at rest (False: stopped by the cap)
    frames: torch.Tensor              # (B,) int64: frames simulated (the move's and the settle's)


def unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(_TINY)


def poses_of(x: torch.Tensor) -> Grippers:
    """The grippers' poses of chains (B, N, 3): the end markers and the directions to their neighbours."""
    pos = torch.stack([x[:, 0], x[:, -1]], 1)
    return Grippers(pos, unit(torch.stack([x[:, 1], x[:, -2]], 1) - pos))


def held_markers(grippers: Grippers, cable: Cable) -> torch.Tensor:
    """(B, 4, 3) the held markers' positions (nodes 0, 1, N-2, N-1) of gripper poses."""
    rest = cable.params.rest_lengths.to(grippers.pos)
    near = grippers.pos + torch.stack([rest[0], rest[-1]]).view(1, 2, 1) * grippers.dirs
    return torch.stack([grippers.pos[:, 0], near[:, 0], near[:, 1], grippers.pos[:, 1]], 1)


def rotate(d: torch.Tensor, turn: torch.Tensor) -> torch.Tensor:
    """Directions (..., 3) turned by rotation vectors (..., 3) [rad] (Rodrigues); differentiable, also at 0."""
    turn, d = torch.broadcast_tensors(turn, d)
    angle = turn.norm(dim=-1, keepdim=True)
    axis = turn / angle.clamp_min(_TINY)
    cos, sin = torch.cos(angle), torch.sin(angle)
    return d * cos + torch.cross(axis, d, dim=-1) * sin + axis * (axis * d).sum(-1, keepdim=True) * (1 - cos)


def turn_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The rotation vector (..., 3) of the shortest turn taking unit directions a to b."""
    axis = torch.cross(a, b, dim=-1)
    sin = axis.norm(dim=-1, keepdim=True)
    angle = torch.atan2(sin, (a * b).sum(-1, keepdim=True))
    return axis / sin.clamp_min(_TINY) * angle


def min_jerk(tau: torch.Tensor) -> torch.Tensor:
    return tau ** 3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)


def gripper_path(start: Grippers, goal: Grippers, cable: Cable, move_frames: int) -> torch.Tensor:
    """(move_frames + 1, B, 4, 3) the held markers at every frame of the move, frame 0 the start."""
    tau = torch.arange(move_frames + 1, dtype=start.pos.dtype, device=start.pos.device) / max(move_frames, 1)
    s = min_jerk(tau).view(-1, 1, 1, 1)
    turn = turn_between(start.dirs, goal.dirs)
    pos = start.pos + s * (goal.pos - start.pos)                                  # (T, B, 2, 3)
    dirs = rotate(start.dirs.expand_as(pos), s * turn)
    flat = Grippers(pos.flatten(0, 1), dirs.flatten(0, 1))
    return held_markers(flat, cable).view(move_frames + 1, -1, 4, 3)


def _held_mask(cable: Cable, device: torch.device) -> torch.Tensor:
    mask = torch.zeros(cable.n_nodes, dtype=torch.bool, device=device)
    mask[list(cable.held)] = True
    return mask


ENGINES = ("auto", "eager", "kernel")


def _on_kernel(engine: str, x: torch.Tensor, cable: Cable, accel: Callable | None) -> bool:
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if engine == "eager":
        return False
    ok = kernel.usable(x, cable.params, accel)
    if engine == "kernel" and not ok:
        raise ValueError("engine='kernel' needs the kernel built, a CPU float32/float64 state, no accel and no "
                         f"gradient wanted w.r.t. the cable's parameters (kernel: "
                         f"{kernel.unavailable_reason() or 'built'}, state {x.dtype} on {x.device}, accel "
                         f"{'given' if accel is not None else 'None'}, parameters requiring grad: "
                         f"{torch.is_grad_enabled() and kernel.params_need_grad(cable.params)})")
    return ok


def settle(x: torch.Tensor, v: torch.Tensor | None, grippers: Grippers, cable: Cable, *, rest_speed: float,
           check_frames: int, settle_frames: int, accel: Callable | None = None, engine: str = "auto"
           ) -> MoveResult:
    """The cable held still by ``grippers`` until its free markers are slower than ``rest_speed`` [m/s] (checked
    every ``check_frames`` frames, at most ``settle_frames``); each cable frozen once at rest. ``accel``: an extra
    acceleration (x, v) -> (B, N, 3), e.g. a learned residual (diffdlo/chain3d/residual.py): chain.rollout's."""
    batch = x.shape[0]
    held = held_markers(grippers, cable)
    if _on_kernel(engine, x, cable, accel):
        return MoveResult(*kernel.move(x, v, cable.held, held.unsqueeze(0), held, cable.params, cable.substeps,
                                       frame_dt=FRAME_DT, rest_speed=rest_speed, check_frames=check_frames,
                                       settle_frames=settle_frames))
    mask = _held_mask(cable, x.device)
    v = torch.zeros_like(x) if v is None else v
    settled = torch.zeros(batch, dtype=torch.bool, device=x.device)
    frames = torch.zeros(batch, dtype=torch.int64, device=x.device)
    done = 0
    while done < settle_frames and not bool(settled.all()):
        chunk = min(check_frames, settle_frames - done)
        path = held.unsqueeze(0).expand(chunk + 1, *held.shape)
        xs, vs = rollout(x, v, mask, path, cable.params, cable.substeps, frame_dt=FRAME_DT, return_velocities=True,
                         accel=accel)
        keep = settled.view(batch, 1, 1)
        x, v = torch.where(keep, x, xs[-1]), torch.where(keep, v, vs[-1])
        frames = frames + (~settled).to(torch.int64) * chunk
        done += chunk
        speed = v.detach()[:, ~mask].norm(dim=-1).amax(-1)
        settled = settled | (speed < rest_speed)
    return MoveResult(x, v, settled, frames)


def move(x: torch.Tensor, v: torch.Tensor | None, goal: Grippers, cable: Cable, *, move_frames: int,
         rest_speed: float, check_frames: int, settle_frames: int, accel: Callable | None = None,
         engine: str = "auto") -> MoveResult:
    """Both grippers from their poses in ``x`` (B, N, 3) to ``goal`` along the minimum-jerk path over
    ``move_frames`` frames, then held there while the cable comes to rest (``settle``; ``accel`` as there)."""
    path = gripper_path(poses_of(x), goal, cable, move_frames)
    if _on_kernel(engine, x, cable, accel):
        return MoveResult(*kernel.move(x, v, cable.held, path, held_markers(goal, cable), cable.params,
                                       cable.substeps, frame_dt=FRAME_DT, rest_speed=rest_speed,
                                       check_frames=check_frames, settle_frames=settle_frames))
    xs, vs = rollout(x, v, _held_mask(cable, x.device), path, cable.params, cable.substeps, frame_dt=FRAME_DT, return_velocities=True,
                     accel=accel)
    out = settle(xs[-1], vs[-1], goal, cable, rest_speed=rest_speed, check_frames=check_frames,
                 settle_frames=settle_frames, accel=accel, engine="eager")
    return out._replace(frames=out.frames + move_frames)
