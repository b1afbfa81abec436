"""Time integration: semi-implicit (symplectic) Euler with implicitly treated viscous damping (Lv eq 28).

    v+ = (v + dt * F(x) / m) / (1 + dt * k_d / m),    x+ = x + dt * v+

The damping term is implicit because k_d * dt / m = 10 > 2 with the thesis's numbers: explicit damping diverges.
Stable for every mode with dt^2 w^2 < 2 (2 + dt k_d / m) (see CableParams.stability_margin).
Pure functions of tensors; device and dtype follow the inputs.
"""
from __future__ import annotations

from typing import Any

import torch

from .physics import per_rope


def semi_implicit_step(pos: torch.Tensor, vel: torch.Tensor, force: torch.Tensor,
                       dt: float, node_mass: Any, k_d: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """One substep for (B, N, 2) positions and velocities under a total non-damping force. node_mass, k_d: floats
    or per-rope (B,) tensors."""
    node_mass, k_d = per_rope(node_mass, 3), per_rope(k_d, 3)
    vel = (vel + (dt / node_mass) * force) / (1.0 + dt * k_d / node_mass)
    return pos + dt * vel, vel


def max_speed(vel: torch.Tensor) -> torch.Tensor:
    """(B, N, 2) -> (B,) speed of the fastest node."""
    return vel.norm(dim=-1).amax(dim=-1)
