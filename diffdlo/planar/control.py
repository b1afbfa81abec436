"""How a grasped node is driven during a drag (Algorithm 2, model.move_idx).

Both controllers track the same reference: a straight path from the grasp point to its goal at the constant speed
``max_speed`` (faster only if the drag would otherwise need more than ``max_drag_steps`` substeps).
- kinematic: the grasped node sits exactly on the reference at every substep.
- pid: the thesis's force controller pushes the node towards the reference; it holds the goal for ``ff_len`` after
  the path ends so the integral term can remove the lag, then releases.
Pure functions of tensors; device and dtype follow the inputs.
"""
from __future__ import annotations

import math

from typing import Any

import torch

from .params import CableParams
from .physics import per_rope


def clip_drag(delta: torch.Tensor, max_disp: float) -> torch.Tensor:
    """Shorten (B, 2) drags longer than max_disp along their own direction (differentiable)."""
    length = delta.norm(dim=-1, keepdim=True)
    scale = torch.where(length > max_disp, max_disp / length.clamp_min(max_disp), torch.ones_like(length))
    return delta * scale


def drag_speed(distance: torch.Tensor, p: CableParams) -> torch.Tensor:
    """(B,) reference speed: max_speed, or faster if the drag would exceed max_drag_steps substeps."""
    return torch.clamp_min(distance / (p.max_drag_steps * p.dt), p.max_speed)


def path_substeps(distance: torch.Tensor, p: CableParams) -> torch.Tensor:
    """(B,) number of substeps (int64) the reference path takes; 0 for a zero drag."""
    steps = torch.ceil(distance.detach() / (drag_speed(distance.detach(), p) * p.dt) - 1e-9)
    return steps.clamp(0, p.max_drag_steps).to(torch.int64)


def reference(start: torch.Tensor, delta: torch.Tensor, speed: torch.Tensor, k: int,
              dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference position and velocity (B, 2) of the grasped node at substep k >= 1 of the drag.

    The velocity is the path's displacement over the substep divided by dt, so it is continuous in delta: on the
    last substep it is the remaining distance / dt (a release velocity that jumped between 0 and max_speed as the
    path length crossed a whole number of substeps would make the outcome discontinuous in the action).
    """
    safe = delta.norm(dim=-1).clamp_min(1e-12)
    # min(raw, 1) with no gradient at raw == 1 (a path of exactly a whole number of substeps ends ON the goal, which
    # moves with the drag: clamp's gradient there would hold the end still, dropping d(move)/d(drag) along it)
    raw, raw_prev = (k * dt) * speed / safe, ((k - 1) * dt) * speed / safe
    frac = torch.where(raw < 1.0, raw, torch.ones_like(raw))
    frac_prev = torch.where(raw_prev < 1.0, raw_prev, torch.ones_like(raw_prev))
    position = start + frac.unsqueeze(-1) * delta
    velocity = ((frac - frac_prev) / dt).unsqueeze(-1) * delta
    return position, velocity


def last_substep_fraction(distance: torch.Tensor, speed: torch.Tensor, path_steps: torch.Tensor,
                          p: CableParams) -> torch.Tensor:
    """(B,) share phi in (0, 1] of the drag's last substep that the path still fills (1 for a zero drag, for the
    PID and for a drag of a whole number of substeps); differentiable in ``distance``.

    The kinematic drag uses it twice so that a move is continuous in the drag also where the path's length crosses
    a whole number of substeps (where path_substeps steps up by one): on the last drag substep the grasped node goes
    only the share phi of the way from where the free dynamics would take it to the reference (a release within the
    substep, to first order), and a rope stopped by the settle cap returns its state the share phi of the way from
    its last-but-one substep to its last (the cap then counts from the release's true time, path length / speed).
    """
    if p.controller != "kinematic":
        return torch.ones_like(distance)
    raw = distance / (speed * p.dt) - (path_steps - 1).to(distance.dtype)
    return torch.where(path_steps > 0, raw.clamp(0.0, 1.0), torch.ones_like(distance))


def hold_substeps(p: CableParams) -> int:
    """Substeps the PID holds the goal after the path ends (0 for the kinematic drag)."""
    return int(math.ceil(p.ff_len / p.dt - 1e-9)) if p.controller == "pid" else 0


def pid_force(error: torch.Tensor, integral: torch.Tensor, ref_velocity: torch.Tensor, t: float,
              p: CableParams, k_d: Any = None) -> torch.Tensor:
    """(B, 2) force on the grasped node: K_p e + K_i int(e) + ramp(t) K_ff k_d v_ref.

    The feedforward pushes the share k_ff of the node's own viscous drag along the reference velocity; it ramps
    up linearly over ff_len (the thesis's force profile) to avoid an impulsive start.
    """
    ramp = min(1.0, t / p.ff_len) if p.ff_len > 0 else 1.0
    k_d = p.k_d if k_d is None else per_rope(k_d, 2)          # per-rope damping (diffdlo.planar.physics) if given
    return p.k_p * error + p.k_i * integral + (ramp * p.k_ff * k_d) * ref_velocity
