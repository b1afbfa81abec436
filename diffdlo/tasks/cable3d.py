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
  every cable can reach, always solvable. "recorded" (with DEFORM's recordings, ``recorded_targets``): a shape the
  real cable took, one of the ``RECORDED_PER_RECORDING`` slowest frames of each eval recording (the real cables are
  never at rest there: these frames' fastest free marker moves at about 0.1-1 m/s), its grippers within reach; the start
  hung at the grippers' poses of another frame of the same recording, at least ``START_GAP`` frames away.
- **Success**: at rest, the markers' mean distance to the target's under ``success_tol`` (1 cm) and the worst under
  ``success_worst_tol`` (2 cm). **Reward**: 100 x (mean marker error before - after) [cm], ``success_bonus`` on
  success (the planar task's shape_gain and bonus).
- **Observation**: the markers (N, 3), the grippers' poses (2, 6: end marker, direction), the target's markers (N, 3).
Pure batched functions of tensors; device and dtype follow the inputs.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from gymnasium import spaces

from ..chain3d import deform
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
TARGETS = ("reachable", "recorded")
RECORDED_PER_RECORDING = 5  # "recorded" targets: the slowest frames of each eval recording ...
RECORDED_GAP = 50           # ... at least this many frames (0.5 s) apart
START_GAP = 100             # a recorded target's start: a frame of its recording at least 1 s away
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


@dataclasses.dataclass(frozen=True)
class RecordedTargets:
    """DEFORM's eval recordings of one cable as targets."""
    recordings: list[torch.Tensor]         # [(T, N, 3)] the markers of each recording [m]
    targets: list[tuple[int, int]]         # (recording, frame) of each target
    speeds: list[float]                    # [m/s] each target frame's fastest free marker (central differences)
    reachable: list[list[bool]]            # per recording and frame: its grippers within reach

    def draw(self, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """(start frame's markers, target markers) (N, 3) of one drawn target: the start a frame of the same
        recording at least START_GAP frames from the target's, its grippers within reach."""
        r, k = self.targets[int(torch.randint(len(self.targets), (1,), generator=generator))]
        frames = self.recordings[r]
        far = [j for j in range(frames.shape[0]) if abs(j - k) >= START_GAP and self.reachable[r][j]]
        return frames[far[int(torch.randint(len(far), (1,), generator=generator))]], frames[k]


def recorded_targets(data_dir, cable: Cable) -> RecordedTargets:
    """The "recorded" targets of ``cable`` (one of DEFORM's, DLO1-5) from DEFORM's data_set folder ``data_dir``:
    each eval recording's RECORDED_PER_RECORDING slowest frames RECORDED_GAP apart whose grippers are within reach
    (in WORKSPACE and at most MAX_SPAN apart, to 1 mm) and that have a start frame in reach. ValueError naming the
    cable or the folder where there are none; deform.RecordingError for bad recordings."""
    number = {c.name: k for k, c in deform.CABLES.items()}.get(cable.name)
    if number is None:
        raise ValueError(f"recorded targets need one of DEFORM's cables {[c.name for c in deform.CABLES.values()]}, "
                         f"got cable {cable.name!r}")
    recordings = [x for _, x in sorted(deform.load_split(data_dir, number, "eval").items())]
    free = [j for j in range(cable.n_nodes) if j not in cable.held]
    targets, speeds, reach = [], [], []
    for r, x in enumerate(recordings):
        ends = x[:, [0, -1]]
        reach.append(((keep_reachable(ends, cable) - ends).norm(dim=-1).amax(-1) < 1e-3).tolist())
        speed = torch.full((x.shape[0],), math.inf, dtype=x.dtype)
        speed[1:-1] = deform.marker_speeds(x)[:, free].amax(-1)
        chosen: list[int] = []
        for k in speed.argsort().tolist():
            if len(chosen) == RECORDED_PER_RECORDING or not math.isfinite(float(speed[k])):
                break
            if (reach[r][k] and all(abs(k - j) >= RECORDED_GAP for j in chosen)
                    and any(reach[r][j] for j in range(x.shape[0]) if abs(j - k) >= START_GAP)):
                chosen.append(k)
        targets += [(r, k) for k in chosen]
        speeds += [float(speed[k]) for k in chosen]
    if not targets:
        raise ValueError(f"{data_dir}: no eval frame of {cable.name} has its grippers within reach")
    return RecordedTargets(recordings, targets, speeds, reach)


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
