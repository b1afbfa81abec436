"""Contact of the rope with fixed pegs on the table (docs/SIMULATOR.md "Pegs and the second gripper").

A peg is a fixed vertical post: a row (x, y, radius) [m] of a (K, 3) or (B, K, 3) tensor. The rope is a chain of
capsules of radius ``rope_radius`` around its links, so a peg thinner than a link cannot slip between two nodes:
every link meets every peg at the link's closest point to the peg's centre (a node, where that is nearest),

    z = radius + rope_radius - |q - c|,    q = a + t (b - a),  t = clamp((c - a).(b - a) / |b - a|^2, 0, 1),

and stores the energy k_c H(z) with H the C2 "smoothed half square" of width w:

    H = 0 (z <= 0),   z^3 / (6 w) (0 < z < w),   z^2 / 2 - w z / 2 + w^2 / 6 (z >= w),

so the force k_c H'(z) sets in smoothly over the first w of overlap and is a linear spring k_c (z - w / 2) past it.
It pushes the link's two nodes along n = (q - c) / |q - c| with the shares (1 - t) and t (the envelope theorem: t
minimises the distance, so its own change does not enter the first derivative). Pure batched functions of tensors;
device and dtype follow the inputs. ``link_weight`` (B, N - 1): 1 where a link touches the table, 0 where it is
lifted (the links at a grasped node, see Simulator.move).
"""
from __future__ import annotations

import torch

# Below this distance [m] between a peg's centre and a link the direction of the push is undefined (the axis
# through the centre): no force there, a set of measure zero that no move reaches from an admissible state.
_TINY = 1e-12


class PegError(ValueError):
    """Pegs of the wrong shape, or with a non-finite or non-positive value; the message names it."""


def check_pegs(pegs: torch.Tensor, batch: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(K, 3) or (B, K, 3) pegs -> (B, K, 3) on ``device`` in ``dtype``; PegError naming the bad value."""
    if not torch.is_tensor(pegs):
        raise PegError(f"pegs must be a tensor of shape (K, 3) or ({batch}, K, 3) of (x, y, radius) in metres, "
                       f"got {type(pegs).__name__}")
    shape = tuple(pegs.shape)
    if pegs.ndim == 2:
        pegs = pegs.unsqueeze(0).expand(batch, *pegs.shape)
    if pegs.ndim != 3 or pegs.shape[0] != batch or pegs.shape[2] != 3:
        raise PegError(f"pegs must have shape (K, 3) or ({batch}, K, 3) of (x, y, radius) in metres, got {shape}")
    if pegs.is_complex() or not pegs.is_floating_point():
        raise PegError(f"pegs must be a floating-point tensor, got {pegs.dtype}")
    if pegs.device.type != torch.device(device).type:
        raise PegError(f"pegs are on {pegs.device} but the simulator is on {device}")
    pegs = pegs.to(dtype)
    finite = torch.isfinite(pegs).all(-1)
    if not bool(finite.all()):
        bad = [[float(f"{v:.4g}") for v in row] for row in pegs[~finite][:3].tolist()]
        raise PegError(f"pegs must be finite (x, y, radius), got {bad}")
    if bool((pegs[..., 2] <= 0).any()):
        bad = [float(f"{v:.4g}") for v in pegs[..., 2][pegs[..., 2] <= 0][:3].tolist()]
        raise PegError(f"a peg's radius must be > 0 m, got {bad}")
    return pegs


def penalty(z: torch.Tensor, width: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """H(z), H'(z), H''(z) of the smoothed half square of ``width`` (see the module's docstring)."""
    zp = z.clamp_min(0.0)
    ramp = zp < width
    h = torch.where(ramp, zp ** 3 / (6.0 * width), 0.5 * zp * zp - 0.5 * width * zp + width * width / 6.0)
    h1 = torch.where(ramp, zp * zp / (2.0 * width), zp - 0.5 * width)
    h2 = torch.where(ramp, zp / width, torch.ones_like(zp))
    return h, h1, h2


def closest_points(pos: torch.Tensor, pegs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each link's closest point to each peg's centre: (t, r, d), t (B, N - 1, K) its share along the link,
    r = q - c (B, N - 1, K, 2) and d = |r| (B, N - 1, K)."""
    a = pos[:, :-1, None, :]
    e = (pos[:, 1:] - pos[:, :-1])[:, :, None, :]
    c = pegs[:, None, :, :2]
    s = ((c - a) * e).sum(-1) / (e * e).sum(-1)
    t = s.clamp(0.0, 1.0)
    r = a + t.unsqueeze(-1) * e - c
    d = (r * r).sum(-1).clamp_min(_TINY * _TINY).sqrt()
    return t, r, d


def overlap(pos: torch.Tensor, pegs: torch.Tensor, rope_radius: float) -> torch.Tensor:
    """(B, N - 1, K) z: how far each link's surface reaches into each peg [m] (negative: clear of it)."""
    _, _, d = closest_points(pos, pegs)
    return pegs[:, None, :, 2] + rope_radius - d


def depth(pos: torch.Tensor, pegs: torch.Tensor, rope_radius: float) -> torch.Tensor:
    """(B,) the deepest overlap of the rope with any peg [m] (negative: the rope clears every peg by that much)."""
    return overlap(pos, pegs, rope_radius).flatten(1).amax(1)


def energy(pos: torch.Tensor, pegs: torch.Tensor, rope_radius: float, stiffness: float, width: float,
           link_weight: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) contact energy [J] of ropes (B, N, 2) with pegs (B, K, 3)."""
    h, _, _ = penalty(overlap(pos, pegs, rope_radius), width)
    if link_weight is not None:
        h = h * link_weight.unsqueeze(-1)
    return stiffness * h.flatten(1).sum(1)


def forces(pos: torch.Tensor, pegs: torch.Tensor, rope_radius: float, stiffness: float, width: float,
           link_weight: torch.Tensor | None = None) -> torch.Tensor:
    """(B, N, 2) contact forces -dE/dpos [N] (checked against autograd of ``energy`` in tests/test_contact.py)."""
    t, r, d = closest_points(pos, pegs)
    _, h1, _ = penalty(pegs[:, None, :, 2] + rope_radius - d, width)
    push = stiffness * h1 / d                                         # (B, L, K): k H'(z) / d, times r = n d
    if link_weight is not None:
        push = push * link_weight.unsqueeze(-1)
    f_end = ((push * t).unsqueeze(-1) * r).sum(2)                    # (B, L, 2) on each link's end node
    f_start = (push.unsqueeze(-1) * r).sum(2) - f_end                 # (1 - t) share on its start node
    pad = f_end.new_zeros(f_end.shape[0], 1, 2)
    return torch.cat([f_start, pad], 1) + torch.cat([pad, f_end], 1)


def lifted_links(node: torch.Tensor, n_nodes: int, dtype: torch.dtype) -> torch.Tensor:
    """(B, N - 1) link weights with the links at ``node`` (B,) lifted (0) and the others on the table (1)."""
    k = torch.arange(n_nodes - 1, device=node.device)
    at_node = (k[None] == node[:, None]) | (k[None] == node[:, None] - 1)
    return (~at_node).to(dtype)
