"""Internal energy and forces of the planar mass-spring cable (thesis eq 2.2-2.4; docs/SIMULATOR.md "The model").

Pure batched functions of ``pos`` (B, N, 2); device and dtype follow the input.

E = sum_links k_s (l_e - l0)^2 / 2 + sum_interior k_b beta_i^2 / 2, with beta_i = atan2(cross, dot) the signed
turning angle between the links meeting at node i. The forces are -dE/dpos written out by hand (checked against
autograd in tests/test_forces.py). Unlike the printed eq 2.3 (atan of |cross| / dot, 1 / sin beta) this form is
right past 90 degrees and regular for a straight rope: d beta / d e = perp(e) / |e|^2 per link.
"""
from __future__ import annotations

from typing import Any

import torch

from .physics import per_rope


def links(pos: torch.Tensor) -> torch.Tensor:
    """(B, N, 2) -> (B, N-1, 2) link vectors e_k = p_{k+1} - p_k."""
    return pos[:, 1:] - pos[:, :-1]


def cross2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def turning_angles(pos: torch.Tensor) -> torch.Tensor:
    """(B, N, 2) -> (B, N-2) signed turning angle at each interior node, in (-pi, pi]."""
    e = links(pos)
    a, b = e[:, :-1], e[:, 1:]
    return torch.atan2(cross2(a, b), (a * b).sum(-1))


def energy(pos: torch.Tensor, rest_length: float, k_s: Any, k_b: Any) -> torch.Tensor:
    """(B, N, 2) -> (B,) axial + bending potential energy [J]. k_s, k_b: floats or per-rope (B,) tensors."""
    length = links(pos).norm(dim=-1)
    axial = 0.5 * k_s * ((length - rest_length) ** 2).sum(-1)
    bending = 0.5 * k_b * (turning_angles(pos) ** 2).sum(-1)
    return axial + bending


def internal_forces(pos: torch.Tensor, rest_length: float, k_s: Any, k_b: Any) -> torch.Tensor:
    """(B, N, 2) -> (B, N, 2) axial + bending forces -dE/dpos (no damping, no grasp). k_s, k_b: floats or per-rope
    (B,) tensors."""
    k_s, k_b = per_rope(k_s, 2), per_rope(k_b, 2)
    e = links(pos)                                        # (B, N-1, 2)
    length2 = (e * e).sum(-1)                             # (B, N-1)
    length = length2.sqrt()
    a, b = e[:, :-1], e[:, 1:]
    beta = torch.atan2(cross2(a, b), (a * b).sum(-1))     # (B, N-2)
    # dE/de_k: axial k_s (l - l0) e / l, bending k_b (beta_{k-1} - beta_k) perp(e_k) / |e_k|^2, where
    # beta_{k-1} is the angle at the link's start node (e_k is its 'outgoing' link, d beta/d e = +perp/|e|^2)
    # and beta_k the angle at its end node (e_k is its 'incoming' link, d beta/d e = -perp/|e|^2).
    zero = beta.new_zeros(beta.shape[0], 1)
    beta_start = torch.cat([zero, beta], dim=1)           # angle at node k (0 at the free end)
    beta_end = torch.cat([beta, zero], dim=1)             # angle at node k+1 (0 at the free end)
    perp = torch.stack([-e[..., 1], e[..., 0]], dim=-1)
    grad_link = (k_s * (1.0 - rest_length / length)).unsqueeze(-1) * e \
        + (k_b * (beta_start - beta_end) / length2).unsqueeze(-1) * perp
    # e_k = p_{k+1} - p_k, so dE/dp_j = dE/de_{j-1} - dE/de_j and the force is its negative.
    pad = grad_link.new_zeros(grad_link.shape[0], 1, 2)
    return torch.cat([grad_link, pad], dim=1) - torch.cat([pad, grad_link], dim=1)
