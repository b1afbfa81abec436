"""The routing task's rules (the wire-harness task): a board of pegs and a route, the rope's shape at full length
passing each peg on a given side. Batched functions of tensors; device and dtype follow the inputs.

- ``winding``: how far a rope turns round each peg, the topological part of the task: a rope that matches the
  route's shape but passes a peg on the other side turns about 2 pi more or less round it;
- ``sides_kept`` and ``route_errors``: the two halves of success (every peg on the route's side, the mean node
  error on the board under the tolerance; absolute positions: the pegs fix the route on the board);
- ``Layout``: pegs and a route, checked (no overlapping pegs, a route of the rope's length clear of every peg);
  ``random_layout`` draws one (2-4 pegs, some wrapped); ``load_layout`` reads the fixed ones (diffdlo/tasks/layouts/);
- ``start_beside``: a start shape off the route and clear of the pegs.
"""
from __future__ import annotations

import dataclasses
import math
from importlib import resources
from pathlib import Path

import numpy as np
import torch
import yaml

from ..planar import contact
from ..planar.params import CableParams
from ..planar.shapes import TargetError, check_target, random_curve, random_shape

LAYOUTS_DIR = Path(str(resources.files(__package__) / "layouts"))
# The fixed layouts no learner trains on (the comparison's held-out boards); the others are for training and tests.
HELD_OUT_LAYOUTS = ("hook_wrap", "zigzag_four")
# A rope passes a peg on the route's side when it turns round the peg within this much of the route's turn [rad]:
# the other side differs by 2 pi (for ends near the route's), so pi splits the two.
SIDE_MARGIN = math.pi
# Gap [m] between a peg and the route's surface where ``random_layout`` places a peg against a bend, and the least
# gap between two pegs' surfaces (room for the rope, two radii, to pass between).
PEG_CLEARANCE = 0.001
# A drawn board fits in this square [m] centred at the origin (the pictures' view window is 1 m).
BOARD = 0.8
# ``random_layout``'s pegs: the route turns at least this much round each [rad] (a peg it passes by its side).
MIN_TURN = 0.5 * math.pi


class LayoutError(ValueError):
    """A layout with overlapping pegs, a route not of the rope's length, through a peg, or without pegs."""


# ====================================================================== the rules
def winding(pos: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """(..., N, 2) ropes, (..., K, 2) peg centres -> (..., K): the signed angle [rad] each rope turns round each
    centre from its node 0 to its last node (positive counter-clockwise). Exact for ropes whose links clear the
    centres (every admissible rope: its axis is outside every peg)."""
    rel = pos.unsqueeze(-3) - centres.unsqueeze(-2)                      # (..., K, N, 2)
    angle = torch.atan2(rel[..., 1], rel[..., 0])
    return torch.remainder(angle.diff(dim=-1) + math.pi, 2 * math.pi).sub(math.pi).sum(-1)


def wrong_sides(pos: torch.Tensor, route: torch.Tensor, pegs: torch.Tensor) -> torch.Tensor:
    """(..., N, 2) ropes, routes (N, 2) or (..., N, 2), pegs (K, 3) or (..., K, 3) -> (...,) int64: the pegs a rope
    passes on the other side than the route (its winding round the peg SIDE_MARGIN or more off the route's). Rows of
    radius 0 are no pegs (the env's padding)."""
    pegs = pegs.expand(*pos.shape[:-2], *pegs.shape[-2:])
    centres = pegs[..., :2]
    off = (winding(pos, centres) - winding(route.expand_as(pos), centres)).abs() >= SIDE_MARGIN
    return (off & (pegs[..., 2] > 0)).sum(-1)


def sides_kept(pos: torch.Tensor, route: torch.Tensor, pegs: torch.Tensor) -> torch.Tensor:
    """(B,) bool: every peg passed on the route's side (``wrong_sides`` is 0)."""
    return wrong_sides(pos, route, pegs) == 0


def route_errors(pos: torch.Tensor, route: torch.Tensor) -> torch.Tensor:
    """(B, N) each node's distance [m] to its place on the route, on the board (no alignment: the pegs fix it)."""
    return (pos - route.expand_as(pos)).norm(dim=-1)


# What a peg passed on the wrong side costs [m]: five times the success tolerance, more than the error any single move
# removes, so no plan trades a side for distance (the planners' cost; the reward "route_side_gain").
SIDE_COST = 0.05


def route_cost(pos: torch.Tensor, route: torch.Tensor, pegs: torch.Tensor) -> torch.Tensor:
    """(..., N, 2) -> (...,): a route's cost, the mean node distance on the board plus SIDE_COST per peg (K, 3)
    passed on the wrong side."""
    return route_errors(pos, route).mean(-1) + SIDE_COST * wrong_sides(pos, route, pegs).to(pos.dtype)


def clear_of_pegs(pos: torch.Tensor, pegs: torch.Tensor, rope_radius: float, iterations: int = 100) -> torch.Tensor:
    """(N, 2) or (B, N, 2) nodes, (K, 3) or (B, K, 3) pegs (rows of radius 0: none) -> the nodes moved out of the
    pegs until every link's surface clears every peg (to 0.1 mm): first each node straight out from a peg's centre
    it lies within ``radius + rope_radius`` of, then each link still reaching into a peg pushed out (both its ends)
    along the line from the peg's centre to the link's closest point, repeated up to ``iterations`` times.

    A rope read from a picture can lie a few millimetres inside a peg (the perception's error), where the simulator
    refuses to start a move; the planners project the reading out before planning from it. A rope already clear is
    returned unchanged."""
    single = pos.dim() == 2
    if single:
        pos, pegs = pos[None], pegs[None]
    real = pegs[..., 2] > 0                                               # (B, K)
    out = pos
    for k in range(pegs.shape[-2]):
        peg = pegs[:, k:k + 1, :]                                         # (B, 1, 3)
        reach = (peg[..., 2] + rope_radius)[..., None]                    # (B, 1, 1)
        away = out - peg[..., :2]
        dist = away.norm(dim=-1, keepdim=True)
        side = torch.where(dist > 0, away / dist.clamp_min(torch.finfo(pos.dtype).tiny),
                           torch.tensor([1.0, 0.0], dtype=pos.dtype, device=pos.device))
        inside = (dist < reach) & real[:, k, None, None]
        out = torch.where(inside, peg[..., :2] + side * reach, out)
    out, _ = contact.push_out(out, pegs, rope_radius, 1e-4, iterations)
    return out[0] if single else out


# ====================================================================== layouts
@dataclasses.dataclass(frozen=True)
class Layout:
    """A board: pegs (K, 3) of (x, y, radius) [m] and the route (N, 2) the rope is to lie along; ``name`` for people.
    ``check`` refuses what no rope can be laid on."""

    pegs: torch.Tensor
    route: torch.Tensor
    name: str = "custom"

    def check(self, p: CableParams) -> Layout:
        """This layout, float64, checked: LayoutError naming the bad value."""
        pegs, route = torch.as_tensor(self.pegs, dtype=torch.float64), torch.as_tensor(self.route, dtype=torch.float64)
        if pegs.ndim != 2 or pegs.shape[-1] != 3 or pegs.shape[0] == 0:
            raise LayoutError(f"layout {self.name!r}: pegs must be a (K, 3) array of (x, y, radius) [m] with K >= 1 "
                              f"(a route needs a peg), got shape {tuple(pegs.shape)}")
        if bool((pegs[:, 2] <= 0).any()):
            raise LayoutError(f"layout {self.name!r}: a peg's radius must be > 0 m (a layout lists its pegs, no empty "
                              f"slots), got {pegs[:, 2][pegs[:, 2] <= 0].tolist()}")
        try:
            pegs = contact.check_pegs(pegs, 1, torch.float64, torch.device("cpu"), p.rope_radius)[0]
        except contact.PegError as exc:
            raise LayoutError(f"layout {self.name!r}: {exc}") from exc
        try:
            check_target(route, p, f"layout {self.name!r}: the route")
        except TargetError as exc:
            raise LayoutError(str(exc)) from exc
        overlap = contact.overlap(route[None], pegs[None], p.rope_radius)[0]          # (L, K)
        if bool((overlap > 0).any()):
            link, k = (int(v) for v in (overlap > 0).nonzero()[0])
            raise LayoutError(f"layout {self.name!r}: the route's link {link}-{link + 1} runs "
                              f"{float(overlap[link, k]) * 1e3:.3g} mm into peg {k} {pegs[k].tolist()} (a route must "
                              f"clear every peg by the rope's radius, {p.rope_radius * 1e3:g} mm)")
        return Layout(pegs, route, self.name)

    def turns(self) -> torch.Tensor:
        """(K,) the route's winding round each peg [rad]: its sign is the side, its size how far it wraps."""
        return winding(torch.as_tensor(self.route), torch.as_tensor(self.pegs)[:, :2])


def layout_names() -> list[str]:
    """The fixed layouts shipped in diffdlo/tasks/layouts/ (``load_layout`` by name)."""
    return sorted(f.stem for f in LAYOUTS_DIR.glob("*.yaml"))


def load_layout(spec: str | Path, p: CableParams) -> Layout:
    """A fixed layout by name (``layout_names()``) or from a YAML path holding ``pegs: [[x, y, radius], ...]`` and
    ``route: [[x, y], ...]`` (N points); checked. LayoutError naming the problem."""
    path = Path(spec)
    if path.suffix not in (".yaml", ".yml"):
        if str(spec) not in layout_names():
            raise LayoutError(f"no layout {str(spec)!r}: use one of {layout_names()} or a .yaml path")
        path = LAYOUTS_DIR / f"{spec}.yaml"
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as exc:
        raise LayoutError(f"cannot read layout {str(spec)!r}: {exc}") from exc
    if not isinstance(data, dict) or "pegs" not in data or "route" not in data:
        raise LayoutError(f"layout {str(spec)!r} must hold 'pegs' and 'route'")
    try:
        pegs, route = (torch.tensor(np.asarray(data[key], dtype=np.float64)) for key in ("pegs", "route"))
    except (TypeError, ValueError) as exc:
        raise LayoutError(f"layout {str(spec)!r}: pegs and route must be arrays of numbers ({exc})") from exc
    return Layout(pegs, route, path.stem).check(p)


def _normals(route: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per interior node of a route (N, 2): the unit normal towards the inside of its turn (the left of a straight
    node), and the turn [rad]."""
    e = route.diff(dim=0)
    a, b = e[:-1], e[1:]
    turn = torch.atan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], (a * b).sum(-1))
    mean = a / a.norm(dim=-1, keepdim=True) + b / b.norm(dim=-1, keepdim=True)
    left = torch.stack([-mean[:, 1], mean[:, 0]], -1) / mean.norm(dim=-1, keepdim=True)
    return torch.where(turn.unsqueeze(-1) >= 0, left, -left), turn         # a straight node: its left


def peg_against(route: torch.Tensor, node: int, radius: float, p: CableParams, outside: bool = False) -> torch.Tensor:
    """(3,) a peg of ``radius`` against the inside of the route's turn at interior ``node`` (the route wraps it; with
    ``outside``, against the outside: the route passes it), PEG_CLEARANCE from the route's surface."""
    inward, turn = _normals(route)
    reach = radius + p.rope_radius + PEG_CLEARANCE
    if not outside:                       # inside a turn the two links at the node lean towards the peg
        reach = reach / math.cos(0.5 * float(turn[node - 1]))
    centre = route[node] + (-1.0 if outside else 1.0) * inward[node - 1] * reach
    return torch.cat([centre, torch.tensor([radius], dtype=route.dtype)])


def random_layout(p: CableParams, generator: torch.Generator, pegs: tuple[int, int] = (2, 4),
                  radius: tuple[float, float] = (0.008, 0.02), max_turn_deg: float = 20.0,
                  tries: int = 200) -> Layout:
    """A random board: a smooth route of the rope's length (``random_curve`` with turns up to ``max_turn_deg`` per
    node) and 2-4 pegs, each against the inside of one of the route's bends (the route wraps it) or, one in three,
    against the outside of a bend or a straight part (the route passes it), PEG_CLEARANCE from the route's surface,
    the route turning at least MIN_TURN round it, with room for the rope between any two pegs and within the BOARD.
    Drawn from ``generator`` (CPU, float64)."""
    for _ in range(tries):
        route = random_curve(1, p, generator, max_turn_deg=max_turn_deg, dtype=torch.float64)[0]
        _, turn = _normals(route)
        k = int(torch.randint(pegs[0], pegs[1] + 1, (1,), generator=generator))
        # candidate nodes, far enough from the ends to be passed, the sharper turns first
        nodes = torch.arange(2, p.n_nodes - 2)
        order = torch.argsort(turn[nodes - 1].abs() + 0.2 * torch.rand(len(nodes), generator=generator,
                                                                       dtype=torch.float64), descending=True)
        chosen: list[torch.Tensor] = []
        for node in nodes[order].tolist():
            if len(chosen) == k:
                break
            r = radius[0] + (radius[1] - radius[0]) * float(torch.rand(1, generator=generator, dtype=torch.float64))
            peg = peg_against(route, node, r, p, outside=float(torch.rand(1, generator=generator)) < 1 / 3)
            centre = peg[:2]
            if contact.overlap(route[None], peg[None, None], p.rope_radius).max() > -0.5 * PEG_CLEARANCE:
                continue                                   # another part of the route runs through it
            if any(float((peg[:2] - q[:2]).norm() - peg[2] - q[2]) < 2 * p.rope_radius + PEG_CLEARANCE
                   for q in chosen):
                continue
            if float((centre.abs() + r).max()) > BOARD / 2:
                continue
            if abs(float(winding(route, centre[None])[0])) < MIN_TURN:
                continue                                   # hardly passed: no side to keep
            chosen.append(peg)
        if len(chosen) == k:
            return Layout(torch.stack(chosen), route, "random").check(p)
    raise LayoutError(f"no layout with {pegs} pegs found in {tries} tries (max_turn_deg={max_turn_deg})")


ROUTE_STARTS = ("beside", "across")


def start_beside(layout: Layout, p: CableParams, generator: torch.Generator, distance: float = 0.2,
                 tries: int = 200) -> torch.Tensor:
    """(N, 2) a start shape beside the board: a random rope (the thesis's sigma) centred ``distance`` [m] from the
    route's centre in a random direction, clear of every peg by PEG_CLEARANCE and off the route (its mean node error
    above 5 cm). Drawn from ``generator``."""
    return _start(layout, p, generator, lambda: distance, tries)


def start_across(layout: Layout, p: CableParams, generator: torch.Generator, spread: float = 0.05,
                 tries: int = 200) -> torch.Tensor:
    """(N, 2) a start shape across the board: as ``start_beside`` but centred at most ``spread`` [m] from the route's
    centre, so the rope lies among the pegs (docs/ROUTING.md)."""
    return _start(layout, p, generator, lambda: spread * float(torch.rand(1, generator=generator,
                                                                          dtype=torch.float64)), tries)


def _start(layout: Layout, p: CableParams, generator: torch.Generator, distance, tries: int) -> torch.Tensor:
    pegs = layout.pegs.to(torch.float64)
    for _ in range(tries):
        shape = random_shape(1, p, generator, dtype=torch.float64)[0]
        angle = 2 * math.pi * float(torch.rand(1, generator=generator, dtype=torch.float64))
        offset = distance() * torch.tensor([math.cos(angle), math.sin(angle)], dtype=torch.float64)
        shape = shape + layout.route.mean(0) + offset
        if float(contact.depth(shape[None], pegs[None], p.rope_radius)) > -PEG_CLEARANCE:
            continue
        if float(route_errors(shape[None], layout.route)[0].mean()) < 0.05:
            continue
        return shape
    raise LayoutError(f"no start clear of the pegs of layout {layout.name!r} found in {tries} tries")


def padded(pegs: torch.Tensor, slots: int) -> torch.Tensor:
    """(K, 3) pegs -> (slots, 3): the pegs, then rows of zeros (no peg: radius 0). LayoutError past ``slots``."""
    if len(pegs) > slots:
        raise LayoutError(f"a layout of {len(pegs)} pegs does not fit the env's max_pegs={slots}")
    return torch.cat([pegs, pegs.new_zeros(slots - len(pegs), 3)])
