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
    frac = ((k * dt) * speed / safe).clamp(max=1.0)
    frac_prev = (((k - 1) * dt) * speed / safe).clamp(max=1.0)
    position = start + frac.unsqueeze(-1) * delta
    velocity = ((frac - frac_prev) / dt).unsqueeze(-1) * delta
    return position, velocity


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
    k_d = p.k_d if k_d is None else per_rope(k_d, 2)          # per-rope damping (diffdlo.physics) if given
    return p.k_p * error + p.k_i * integral + (ramp * p.k_ff * k_d) * ref_velocity
