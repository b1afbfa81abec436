"""Contact of the rope with fixed pegs on the table (docs/SIMULATOR.md "Pegs and the second gripper").

A peg is a fixed vertical post: a row (x, y, radius) [m] of a (K, 3) or (B, K, 3) tensor; a row of radius 0 is an
empty slot, no peg (the one board convention: boards padded to a fixed number of rows go to the simulator as they
are). The rope is a chain of
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

import math

import torch
import torch.nn.functional as F

# Below this distance [m] between a peg's centre and a link the direction of the push is undefined (the axis
# through the centre): no force there, a set of measure zero that no move reaches from an admissible state.
_TINY = 1e-12


class PegError(ValueError):
    """Pegs of the wrong shape, with a non-finite or negative value, or closer together than the rope's
    diameter; the message names it."""


# Where ``check_pegs`` puts a board's empty rows (radius 0): off the board, one distance test per link, never touched.
FAR_PEG = (1.0e3, 1.0e3, 1.0e-3)


def check_pegs(pegs: torch.Tensor, batch: int, dtype: torch.dtype, device: torch.device,
               rope_radius: float | None = None) -> torch.Tensor:
    """(K, 3) or (B, K, 3) pegs -> (B, K, 3) on ``device`` in ``dtype``; PegError naming the bad value.

    The one board convention: a row of radius 0 is no peg (a board padded to a fixed number of slots, as the envs
    keep it), given back as FAR_PEG so that every engine can take it; a negative radius is refused. With
    ``rope_radius``, two pegs whose surfaces are closer than the rope's diameter are refused: a rope pressed into
    a gap narrower than itself is wedged, which the planar contact does not model (its axis can be held inside a
    peg there, and no move could start from that)."""
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
    if bool((pegs[..., 2] < 0).any()):
        bad = [float(f"{v:.4g}") for v in pegs[..., 2][pegs[..., 2] < 0][:3].tolist()]
        raise PegError(f"a peg's radius must be >= 0 m (0: an empty slot, no peg), got {bad}")
    real = pegs[..., 2] > 0                                               # (B, K)
    if rope_radius is not None and pegs.shape[1] > 1:
        centres, radii = pegs[..., :2], pegs[..., 2]
        gap = (centres[:, :, None] - centres[:, None]).norm(dim=-1) - radii[:, :, None] - radii[:, None]
        both = real[:, :, None] & real[:, None] & ~torch.eye(pegs.shape[1], dtype=torch.bool, device=pegs.device)
        narrow = both & (gap < 2.0 * rope_radius)
        if bool(narrow.any()):
            b, i, j = (int(v) for v in narrow.nonzero()[0])
            rows = [[round(v, 4) for v in pegs[b, k].tolist()] for k in (i, j)]
            raise PegError(f"pegs {i} {rows[0]} and {j} {rows[1]} (rope {b}) leave a gap of "
                           f"{float(gap[b, i, j]) * 1e3:.3g} mm between them, less than the rope's diameter "
                           f"({2e3 * rope_radius:.3g} mm): a board's pegs must leave the rope room to pass")
    if not bool(real.all()):
        pegs = torch.where(real[..., None], pegs, torch.tensor(FAR_PEG, dtype=dtype, device=pegs.device))
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
    """(B, N - 1, K) z: how far each link's surface reaches into each peg [m] (negative: clear of it; -inf for an
    empty row, radius 0)."""
    _, _, d = closest_points(pos, pegs)
    z = pegs[:, None, :, 2] + rope_radius - d
    return torch.where(pegs[:, None, :, 2] > 0, z, torch.full_like(z, -math.inf))


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
    h1 = torch.where(pegs[:, None, :, 2] > 0, h1, torch.zeros_like(h1))     # an empty row (radius 0): no peg
    push = stiffness * h1 / d                                         # (B, L, K): k H'(z) / d, times r = n d
    if link_weight is not None:
        push = push * link_weight.unsqueeze(-1)
    f_end = ((push * t).unsqueeze(-1) * r).sum(2)                    # (B, L, 2) on each link's end node
    f_start = (push.unsqueeze(-1) * r).sum(2) - f_end                 # (1 - t) share on its start node
    pad = f_end.new_zeros(f_end.shape[0], 1, 2)
    return torch.cat([f_start, pad], 1) + torch.cat([pad, f_end], 1)


def push_out(pos: torch.Tensor, pegs: torch.Tensor, margin: float, tolerance: float, iterations: int = 100,
             keep_lengths: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Ropes (B, N, 2) moved out of pegs (B, K, 3; rows of radius 0 are no peg) until every link's axis is at least
    ``radius + margin - tolerance`` from every peg's centre. Each link still closer is pushed along the line from
    the peg's centre through its closest point q = a + t (b - a) by what it lacks of ``radius + margin``, repeated
    up to ``iterations`` times:
    - ``keep_lengths`` False: both its ends by all of the push (the link translated);
    - ``keep_lengths`` True: a position-based projection, its ends by the shares (1 - t) and t of the push scaled so
      that q moves by all of it (a link pushed at two points turns, so it can pass between two pegs at a slant),
      each push followed by one relaxation of every link towards its length on entry (the rope is not stretched
      by the push).
    Returns (pos, what each rope still lacks (B,) [m]: <= tolerance where it got out). A rope already out is
    returned bit for bit; ropes do not affect each other. Differentiable (away from the kinks of the closest point
    and of the push's onset)."""
    real = pegs[..., 2] > 0                                               # (B, K)
    pad_end, pad_start = (0, 0, 0, 1), (0, 0, 1, 0)                      # a (B, L, 2) per link onto (B, N, 2)
    entry_lengths = (pos[:, 1:] - pos[:, :-1]).norm(dim=-1, keepdim=True) if keep_lengths else None
    out = pos
    for step in range(iterations + 1):
        t, r, d = closest_points(out, pegs)                               # (B, L, K, 2), (B, L, K)
        push = torch.where(real[:, None, :], pegs[:, None, :, 2] + margin - d, torch.zeros_like(d))
        lack = push.flatten(1).amax(1) if push.numel() else push.new_zeros(pos.shape[0])
        if float(lack.detach().max()) <= tolerance or step == iterations:
            break
        step_push = push.clamp_min(0.0)[..., None] * r / d[..., None]        # (B, L, K, 2)
        if keep_lengths:
            t = t[..., None]
            scale = 1.0 / ((1.0 - t) ** 2 + t * t)
            to_start, to_end = (step_push * (1.0 - t) * scale).sum(2), (step_push * t * scale).sum(2)
        else:
            to_start = to_end = step_push.sum(2)                          # (B, L, 2) per link
        out = out + F.pad(to_start, pad_end) + F.pad(to_end, pad_start)
        if keep_lengths:                  # half of each link's change of length undone, shared by its two ends
            link = out[:, 1:] - out[:, :-1]
            length = link.norm(dim=-1, keepdim=True)
            fix = 0.25 * (length - entry_lengths) / length * link
            out = out + F.pad(fix, pad_end) - F.pad(fix, pad_start)
    return out, lack.detach()


def lifted_links(node: torch.Tensor, n_nodes: int, dtype: torch.dtype) -> torch.Tensor:
    """(B, N - 1) link weights with the links at ``node`` (B,) lifted (0) and the others on the table (1)."""
    k = torch.arange(n_nodes - 1, device=node.device)
    at_node = (k[None] == node[:, None]) | (k[None] == node[:, None] - 1)
    return (~at_node).to(dtype)
