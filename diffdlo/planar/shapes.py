"""Rope shapes: random initial shapes (thesis sigma) and target shapes (named, arrays, .npy or .yaml files)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from .params import CableParams

# Named targets: a straight rope of full length through the origin, node 0 first, at this angle [deg].
TARGET_ANGLES = {"horizontal": 0.0, "vertical": 90.0, "diagonal": 45.0, "antidiagonal": 135.0}
TARGET_NAMES = tuple(TARGET_ANGLES)
# Target families drawn anew at every reset from the env's generator: "random" (one of the named straight targets,
# the thesis's task) and "random_curve" (a smooth random curve, random_curve below).
TARGET_FAMILIES = ("random", "random_curve")
# random_curve: the largest turning angle at an interior node [deg]. The S-curve of planners/targets turns up to
# ~15 deg per node; 12 deg keeps every drawn curve gentler than that (a 20-node rope can turn 216 deg in all).
CURVE_MAX_TURN_DEG = 12.0
# A custom target's links may differ from the rope's rest length by at most this fraction.
LINK_TOLERANCE = 0.10
# Consecutive nodes of a target or start shape closer than this fraction of the rest length are (nearly)
# coincident: such a link has no direction, so neither a reward nor the rope's bending force is defined there.
MIN_LINK_FRACTION = 0.10


class TargetError(ValueError):
    """A target shape is unknown, malformed or not reachable by the rope; the message names the problem."""


def polyline_from_angles(angles: torch.Tensor, rest_length: float) -> torch.Tensor:
    """(B, N-1) link directions [rad] -> (B, N, 2) node positions with the centroid at the origin."""
    steps = rest_length * torch.stack([angles.cos(), angles.sin()], dim=-1)
    pos = torch.cat([steps.new_zeros(steps.shape[0], 1, 2), steps.cumsum(dim=1)], dim=1)
    return pos - pos.mean(dim=1, keepdim=True)


def random_shape(batch: int, p: CableParams, generator: torch.Generator | None = None,
                 device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(B, N, 2) random rope shapes at rest length, centred at the origin.

    Reading of the thesis's sigma (cable.yaml env.sigma): the link directions are a random walk,
    theta_0 ~ U(-pi, pi), theta_{k+1} = theta_k + sigma * N(0, 1). Drawn on the CPU in float64 from ``generator``,
    so a seed gives the same shapes on every device.
    """
    if not isinstance(batch, int) or batch < 1:
        raise ValueError(f"batch must be a positive integer, got {batch!r}")
    first = (torch.rand(batch, 1, generator=generator, dtype=torch.float64) * 2 - 1) * math.pi
    turns = p.sigma * torch.randn(batch, p.n_nodes - 2, generator=generator, dtype=torch.float64)
    angles = torch.cat([first, first + turns.cumsum(dim=1)], dim=1)
    return polyline_from_angles(angles, p.rest_length).to(device=device, dtype=dtype)


def random_curve(batch: int, p: CableParams, generator: torch.Generator | None = None,
                 device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                 max_turn_deg: float = CURVE_MAX_TURN_DEG) -> torch.Tensor:
    """(B, N, 2) smooth random target curves at the rope's link length, centred at the origin.

    The turning angle along the rope is a random smooth function of the arc length s in [0, 1],
    turn(s) = c0 + c1 sin(pi s + phi1) + c2 sin(2 pi s + phi2), with c0 ~ U(-1, 1) M / 2, c1 ~ U(-1, 1) M,
    c2 ~ U(-1, 1) M / 2, phi ~ U(0, 2 pi), clipped to +-M = ``max_turn_deg``, and the first link points in a
    uniform random direction. The family holds straight lines, arcs, S-curves, hooks and waves: the named targets,
    planners/targets/arc.npy and s_curve.yaml are members of it (as limits), never drawn exactly. Drawn on the CPU
    in float64 from ``generator``, so a seed gives the same curves on every device.
    """
    if not isinstance(batch, int) or batch < 1:
        raise ValueError(f"batch must be a positive integer, got {batch!r}")
    if isinstance(max_turn_deg, bool) or not isinstance(max_turn_deg, (int, float)) or not 0 <= max_turn_deg <= 90:
        raise ValueError(f"max_turn_deg must be a number of degrees in [0, 90], got {max_turn_deg!r}")
    m = math.radians(max_turn_deg)
    u = torch.rand(batch, 6, generator=generator, dtype=torch.float64)
    c0, c1, c2 = (u[:, 0:1] * 2 - 1) * m / 2, (u[:, 1:2] * 2 - 1) * m, (u[:, 2:3] * 2 - 1) * m / 2
    phi1, phi2 = u[:, 3:4] * 2 * math.pi, u[:, 4:5] * 2 * math.pi
    s = torch.linspace(0.0, 1.0, p.n_nodes - 2, dtype=torch.float64).unsqueeze(0)
    turn = (c0 + c1 * torch.sin(math.pi * s + phi1) + c2 * torch.sin(2 * math.pi * s + phi2)).clamp(-m, m)
    first = (u[:, 5:6] * 2 - 1) * math.pi
    angles = torch.cat([first, first + turn.cumsum(dim=1)], dim=1)
    return polyline_from_angles(angles, p.rest_length).to(device=device, dtype=dtype)


def straight_shape(angle_deg: float, p: CableParams) -> torch.Tensor:
    """(N, 2) straight rope of full length centred at the origin, node 0 first, pointing at angle_deg."""
    angles = torch.full((1, p.n_nodes - 1), math.radians(angle_deg), dtype=torch.float64)
    return polyline_from_angles(angles, p.rest_length)[0]


def _load_file(path: Path) -> Any:
    if not path.is_file():
        raise TargetError(f"target file {str(path)!r} does not exist")
    if path.suffix == ".npy":
        try:
            return np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:          # EOFError: an empty or cut-short file
            raise TargetError(f"target file {str(path)!r} is not a readable .npy array: "
                              f"{exc or type(exc).__name__}") from exc
    if path.suffix in (".yaml", ".yml"):
        with open(path) as fh:
            try:
                data = yaml.safe_load(fh)
            except (yaml.YAMLError, UnicodeDecodeError) as exc:     # UnicodeDecodeError: not text at all
                raise TargetError(f"target file {str(path)!r} is not valid YAML: {exc}") from exc
        if isinstance(data, dict):
            if "points" not in data:
                raise TargetError(f"target file {str(path)!r} must hold a list of [x, y] points or a mapping "
                                  f"with key 'points', got keys {sorted(data)}")
            data = data["points"]
        return data
    raise TargetError(f"target file {str(path)!r} must end in .npy, .yaml or .yml")


def check_finite_nodes(points: torch.Tensor, source: str, error: type[ValueError] = ValueError) -> None:
    """Raise ``error`` naming the first node of points (..., N, 2) that holds NaN or inf, and its value."""
    bad = ~torch.isfinite(points).all(-1)
    if bool(bad.any()):
        *rope, node = bad.nonzero()[0].tolist()
        where = f"rope {rope[0]}, node {node}" if rope else f"node {node}"
        raise error(f"{source} contains NaN or inf: {where} is {points[(*rope, node)].tolist()}")


def check_link_lengths(points: torch.Tensor, rest_length: float, source: str, min_fraction: float = MIN_LINK_FRACTION,
                       error: type[ValueError] = ValueError) -> None:
    """Raise ``error`` naming the first pair of consecutive nodes of points (..., N, 2) closer than ``min_fraction``
    of the rest length, and their distance."""
    lengths = (points[..., 1:, :] - points[..., :-1, :]).detach().norm(dim=-1)
    short = lengths < min_fraction * rest_length
    if bool(short.any()):
        *rope, node = short.nonzero()[0].tolist()
        where = f"rope {rope[0]}: " if rope else ""
        raise error(f"{source}: {where}nodes {node} and {node + 1} are {float(lengths[(*rope, node)]):.3g} m apart, "
                    f"coincident or nearly so (consecutive nodes must be at least {min_fraction:.0%} of the rest "
                    f"length {rest_length:.4f} m apart)")


def check_shape(points: torch.Tensor, p: CableParams, source: str, error: type[ValueError] = ValueError) -> None:
    """Raise ``error`` unless points is a finite (N, 2) polyline with no coincident or nearly coincident consecutive
    nodes (closer than MIN_LINK_FRACTION of the rest length): the checks shared by targets and start shapes."""
    if points.ndim != 2 or points.shape != (p.n_nodes, 2):
        raise error(f"{source} must have shape ({p.n_nodes}, 2) for a {p.n_nodes}-node rope, "
                    f"got {tuple(points.shape)}")
    check_finite_nodes(points, source, error)
    check_link_lengths(points, p.rest_length, source, error=error)


def check_target(points: torch.Tensor, p: CableParams, source: str = "target") -> None:
    """Raise TargetError unless points is a finite (N, 2) polyline (``check_shape``) whose links are close to the
    rope's."""
    check_shape(points, p, source, TargetError)
    lengths = (points[1:] - points[:-1]).norm(dim=-1)
    rel = (lengths / p.rest_length - 1.0).abs()
    worst = int(rel.argmax())
    if rel[worst] > LINK_TOLERANCE:
        raise TargetError(
            f"{source}: link {worst} (nodes {worst}-{worst + 1}) is {float(lengths[worst]):.4f} m long, but the "
            f"rope's links are {p.rest_length:.4f} m (tolerance {LINK_TOLERANCE:.0%}); a target must be a "
            f"polyline of the rope's length ({p.length} m over {p.n_nodes} nodes)")


def target_shape(spec: Any, p: CableParams, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(N, 2) target: a name in TARGET_NAMES, an (N, 2) array/tensor, or a path to a .npy/.yaml polyline.

    Named targets are centred at the origin; custom ones are kept where they are (the shape error is
    translation-free). Raises TargetError with the reason.
    """
    if isinstance(spec, str) and spec in TARGET_ANGLES:
        points = straight_shape(TARGET_ANGLES[spec], p)
        source = f"target {spec!r}"
    else:
        source = "target"
        if isinstance(spec, (str, Path)):
            path = Path(spec)
            if path.suffix not in (".npy", ".yaml", ".yml"):
                raise TargetError(f"unknown target {str(spec)!r}: use one of {list(TARGET_NAMES)}, an (N, 2) "
                                  f"array, or a path to a .npy/.yaml file")
            source = f"target file {str(path)!r}"
            spec = _load_file(path)
        try:
            points = torch.as_tensor(np.asarray(spec, dtype=np.float64) if not torch.is_tensor(spec) else spec)
        except (ValueError, TypeError) as exc:
            raise TargetError(f"{source} is not an (N, 2) array of numbers: {exc}") from exc
        points = points.to(torch.float64)
        check_target(points, p, source)
    return points.to(device=device, dtype=dtype)
