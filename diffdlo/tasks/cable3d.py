"""The 3-D two-gripper task's rules, written once (docs/CABLE3D.md): a real cable's chain (diffdlo/chain3d/cables.py)
held at both ends by two grippers, brought to a target shape by moves of both grippers.

- **Action** (12,) in [-1, 1] (clipped; NaN/inf refused): per gripper (the one at marker 0, then the one at the last
  marker) a translation of its end marker, ``a * MAX_SHIFT`` per axis [m], and a turn of its held end's direction,
  the rotation vector ``a * MAX_TURN`` per axis [rad]. The goal's end markers are kept in ``WORKSPACE`` (clipped per
  axis) and at most ``MAX_SPAN`` of the cable's marker-to-marker length apart (both pulled towards their midpoint).
- **A move** (diffdlo/chain3d/grippers.py): both grippers along a minimum-jerk path over ``move_time`` [s], then held
  while the cable comes to rest: the free markers slower than ``rest_speed`` [m/s], checked every 0.1 s, at most
  ``settle_time`` [s].
- **Start**: the grippers at a random pose in the workspace's middle, SPAN_RANGE of the cable's length apart along a
  random horizontal heading, their ends pointing down (tilted up to START_TILT), as DEFORM's robots hold the cables;
  the cable hung between them in a vertical parabola of its own length, then left to come to rest.
- **Target** "reachable": the markers where the model itself takes the start by ``REACH_MOVES`` random actions: a shape
  every cable can reach, always solvable. (Recorded shapes of the real cables: not yet.)
- **Success**: at rest, the markers' mean distance to the target's under ``success_tol`` (1 cm) and the worst under
  ``success_worst_tol`` (2 cm). **Reward**: 100 x (mean marker error before - after) [cm], ``success_bonus`` on
  success (the planar task's shape_gain and bonus).
- **Observation**: the markers (N, 3), the grippers' poses (2, 6: end marker, direction), the target's markers (N, 3).
Pure batched functions of tensors; device and dtype follow the inputs.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from gymnasium import spaces

from ..chain3d.cables import FRAME_DT, Cable
from ..chain3d.grippers import Grippers, held_markers, poses_of, rotate, unit

ACTION_DIM = 12
MAX_SHIFT = 0.05          # [m] per axis of a gripper's translation per move (ours: 5 cm, a tenth of a span)
MAX_TURN = 0.3            # [rad] per axis of a gripper's turn per move (ours: 17 degrees)
# [m] the end markers' box, (low, high) per axis: the range of DEFORM's recordings (the five cables' train splits:
# x 0.0-1.1, y -0.7-0.2, z 0.21-0.87 for the end markers), in their frame, z up.
WORKSPACE = ((0.0, -0.7, 0.25), (1.1, 0.2, 0.9))
MAX_SPAN = 0.9            # the end markers at most this share of the cable's marker-to-marker length apart
SPAN_RANGE = (0.3, 0.6)   # a start's end markers this share of that length apart
START_TILT = 0.3          # [rad] at most between a start's end directions and straight down
REACH_MOVES = 2           # random actions from the start to a "reachable" target
TARGETS = ("reachable",)
OBS_KEYS = ("markers", "grippers", "target_markers")


def check_action(a: torch.Tensor, batch: int) -> torch.Tensor:
    """(B, 12) actions clipped to [-1, 1]; ValueError naming a wrong shape or a non-finite entry."""
    if not torch.is_tensor(a) or tuple(a.shape) != (batch, ACTION_DIM):
        shape = tuple(a.shape) if torch.is_tensor(a) else type(a).__name__
        raise ValueError(f"actions must have shape ({batch}, {ACTION_DIM}) in [-1, 1], got {shape}")
    if not bool(torch.isfinite(a).all()):
        bad = (~torch.isfinite(a)).any(-1).nonzero().flatten().tolist()
        raise ValueError(f"actions must be finite, got NaN/inf in rows {bad}: {a[bad].tolist()}")
    return a.clamp(-1.0, 1.0)


def span_limit(cable: Cable) -> float:
    """[m] the farthest apart the grippers' end markers may be."""
    return MAX_SPAN * float(cable.params.rest_lengths.sum())


def keep_reachable(pos: torch.Tensor, cable: Cable) -> torch.Tensor:
    """End marker positions (B, 2, 3) kept in WORKSPACE (clipped per axis) and within ``span_limit`` (pulled
    towards their midpoint), so no move stretches the cable between the grippers."""
    low, high = (pos.new_tensor(w) for w in WORKSPACE)
    pos = torch.maximum(torch.minimum(pos, high), low)
    middle = pos.mean(1, keepdim=True)
    half = pos - middle
    span = 2.0 * half[:, :1].norm(dim=-1, keepdim=True)
    scale = (span_limit(cable) / span.clamp_min(1e-12)).clamp(max=1.0)
    return middle + half * scale


def decode_action(a: torch.Tensor, grippers: Grippers, cable: Cable) -> Grippers:
    """Clipped actions (B, 12) -> the grippers' goal poses."""
    a = a.view(-1, 2, 6)
    pos = keep_reachable(grippers.pos + MAX_SHIFT * a[..., :3], cable)
    return Grippers(pos, rotate(grippers.dirs, MAX_TURN * a[..., 3:]))


def random_grippers(batch: int, cable: Cable, generator: torch.Generator, dtype: torch.dtype) -> Grippers:
    """Start poses: the middle of the workspace's x-y box at 0.6-0.8 m high, SPAN_RANGE of the cable's length apart
    along a heading within 45 degrees of x, each end pointing down, tilted by up to START_TILT."""
    u = lambda *shape: torch.rand(*shape, generator=generator, dtype=torch.float64)
    (x0, y0, _), (x1, y1, _) = WORKSPACE
    centre = torch.stack([x0 + (x1 - x0) * (0.3 + 0.4 * u(batch)), y0 + (y1 - y0) * (0.3 + 0.4 * u(batch)),
                          0.6 + 0.2 * u(batch)], -1)
    heading = (u(batch) - 0.5) * (math.pi / 2)
    along = torch.stack([heading.cos(), heading.sin(), torch.zeros(batch, dtype=torch.float64)], -1)
    length = float(cable.params.rest_lengths.sum())
    span = (SPAN_RANGE[0] + (SPAN_RANGE[1] - SPAN_RANGE[0]) * u(batch)) * length
    pos = torch.stack([centre - 0.5 * span[:, None] * along, centre + 0.5 * span[:, None] * along], 1)
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(batch, 2, 3)
    tilt = torch.cat([(u(batch, 2, 2) * 2 - 1) * (START_TILT / math.sqrt(2)), torch.zeros(batch, 2, 1,
                                                                                           dtype=torch.float64)], -1)
    return Grippers(pos.to(dtype), unit(rotate(down, tilt)).to(dtype))


def hang(grippers: Grippers, cable: Cable) -> torch.Tensor:
    """(B, N, 3) the cable between the grippers' held markers along a vertical parabola of the free links' length,
    the free markers at their rest spacing along it (a start to settle from)."""
    held = held_markers(grippers, cable)                                        # (B, 4, 3)
    a, b = held[:, 1], held[:, 2]
    rest = cable.params.rest_lengths.to(a)
    free = rest[1:-1]                                                           # the links from marker 1 to N-2
    total = float(free.sum())
    t = torch.linspace(0.0, 1.0, 401, dtype=a.dtype, device=a.device).view(1, -1, 1)
    lo = torch.zeros(a.shape[0], 1, 1, dtype=a.dtype, device=a.device)
    hi = torch.full_like(lo, total)
    down = a.new_tensor([0.0, 0.0, -1.0])
    for _ in range(50):                          # the sag whose curve is as long as the free links
        depth = 0.5 * (lo + hi)
        curve = a[:, None] + t * (b - a)[:, None] + depth * 4 * t * (1 - t) * down
        longer = (curve[:, 1:] - curve[:, :-1]).norm(dim=-1).sum(1, keepdim=True).unsqueeze(-1) > total
        hi, lo = torch.where(longer, depth, hi), torch.where(longer, lo, depth)
    curve = a[:, None] + t * (b - a)[:, None] + (0.5 * (lo + hi)) * 4 * t * (1 - t) * down
    arc = torch.cat([torch.zeros_like(curve[:, :1, 0]), (curve[:, 1:] - curve[:, :-1]).norm(dim=-1).cumsum(1)], 1)
    wanted = torch.cumsum(free, 0)[:-1] / total * arc[:, -1:]                  # (B, N - 4) arc lengths
    index = torch.searchsorted(arc.contiguous(), wanted.contiguous()).clamp(1, arc.shape[1] - 1)
    left, right = arc.gather(1, index - 1), arc.gather(1, index)
    share = ((wanted - left) / (right - left).clamp_min(1e-12)).unsqueeze(-1)
    pick = lambda i: curve.gather(1, i.unsqueeze(-1).expand(-1, -1, 3))
    inner = pick(index - 1) + share * (pick(index) - pick(index - 1))
    return torch.cat([held[:, :2], inner, held[:, 2:]], 1)


def marker_errors(x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B, N) each marker's distance to its place in the target [m] (where they lie: no alignment, the grippers
    fix where the cable is)."""
    return (x - target).norm(dim=-1)


def success(x: torch.Tensor, target: torch.Tensor, at_rest: torch.Tensor, tol: float,
            worst_tol: float) -> torch.Tensor:
    """(B,) bool: at rest, the mean marker error < tol and the worst < worst_tol."""
    errors = marker_errors(x, target)
    return at_rest & (errors.mean(-1) < tol) & (errors.amax(-1) < worst_tol)


def reward(prev: torch.Tensor, new: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) 100 x (mean marker error before - after) [cm]."""
    return 100.0 * (marker_errors(prev, target).mean(-1) - marker_errors(new, target).mean(-1))


def observe(x: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
    poses = poses_of(x)
    return {"markers": x, "grippers": torch.cat([poses.pos, poses.dirs], -1), "target_markers": target}


def observation_space(n_markers: int) -> spaces.Dict:
    bound = np.float32(5.0)
    return spaces.Dict({"markers": spaces.Box(-bound, bound, (n_markers, 3), np.float32),
                        "grippers": spaces.Box(-bound, bound, (2, 6), np.float32),
                        "target_markers": spaces.Box(-bound, bound, (n_markers, 3), np.float32)})


def action_space() -> spaces.Box:
    return spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)


def frames_of(seconds: float, name: str) -> int:
    """Seconds -> whole 10 ms frames (>= 1); ValueError naming the option."""
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 0 < seconds < math.inf:
        raise ValueError(f"{name} must be a positive number of seconds, got {seconds!r}")
    return max(1, int(round(seconds / FRAME_DT)))
