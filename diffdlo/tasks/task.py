"""The shape-control task's rules (thesis Chapter 2), each written once, as batched functions of tensors.

Everything that says what the task IS lives here; the env (diffdlo/envs), the planners, PlaNet and the learners
call these functions rather than restating them:

- targets: ``resolve_target`` (a name, an (N, 2) array, a .npy/.yaml file, a family drawn anew per episode, or a
  route among pegs: "route" drawn anew, "route:NAME" a fixed layout) and ``draw_target`` / ``draw_route`` (one
  episode's target, or layout, from that episode's generator); the routing rules themselves are
  diffdlo/tasks/routing.py's;
- actions: ``decode_node`` / ``decode_drag`` / ``encode_node_action`` (the node action, eq 2.6),
  ``decode_pixel_node`` (the pixel action, eq 2.5), ``decode_action`` (either);
- the greedy move (the node farthest from its place, dragged towards it): ``greedy_drags``;
- rewards, success and episode end: ``step_outcome`` (its success test ``task_success``), by the env's options
  (``diffdlo.envs.EnvOptions``; the rewards and the errors themselves are in diffdlo/tasks/rewards.py, eq 2.7-2.11);
- observations: ``observation_space`` and ``observe``.

A new target family, reward, action head or observation is an addition here.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium import spaces

from . import image as rimage
from . import routing
from ..planar.params import CableParams
from .rewards import is_success, node_errors, orientation_error, reward as move_reward, within_tolerance
from ..planar.shapes import CURVE_MAX_TURN_DEG, TARGET_FAMILIES, TARGET_NAMES, TargetError, random_curve, target_shape


OBS_TYPES = ("points", "distance", "image", "image_single", "perceived")
# The observation kinds, named once. POINT_OBS: {node_poses, target_poses}, the rope's and target's node positions
# ("perceived": read from the env's pictures). COORDINATE_OBS: node coordinates of either form (positions, or
# "distance": rope - target per node). PICTURE_OBS: the observation is pictures. DRAWN_OBS: the env draws pictures.
POINT_OBS = ("points", "perceived")
COORDINATE_OBS = ("points", "distance", "perceived")
PICTURE_OBS = ("image", "image_single")
DRAWN_OBS = PICTURE_OBS + ("perceived",)
ACTION_TYPES = ("node", "pixel", "node_pin", "pixel_pin")
ACTION_DIMS = {"node": 3, "pixel": 4, "node_pin": 4, "pixel_pin": 6}
ROUTE = "route"                # the routing family: a random layout of pegs and a route per episode
ROUTE_PREFIX = "route:"        # a fixed layout: "route:NAME" (diffdlo/tasks/layouts) or "route:PATH.yaml"
ROUTE_OBS = ("points", "image", "image_single", "perceived")      # the observations that carry the pegs
EXIT_RULES = ("truncate", "fail")
CUSTOM = "custom"       # the label of a target given as an array or a file


# ====================================================================== targets
def resolve_target(spec: Any, p: CableParams, device: torch.device | str = "cpu",
                   dtype: torch.dtype = torch.float32) -> str | torch.Tensor:
    """A family in TARGET_FAMILIES (returned as is: drawn per episode by ``draw_target``) or a fixed target as an
    (N, 2) tensor (a name in TARGET_NAMES, an (N, 2) array/tensor, or a .npy/.yaml path). Raises TargetError."""
    if isinstance(spec, str) and spec in TARGET_FAMILIES + (ROUTE,):
        return spec
    if isinstance(spec, routing.Layout):
        return spec.check(p)
    if isinstance(spec, str) and spec.startswith(ROUTE_PREFIX):
        try:
            return routing.load_layout(spec[len(ROUTE_PREFIX):], p)
        except routing.LayoutError as exc:
            raise TargetError(f"bad target {spec!r}: {exc}") from exc
    try:
        return target_shape(spec, p, device, dtype)
    except TargetError as exc:
        raise TargetError(f"bad target {spec if isinstance(spec, (str, Path)) else type(spec).__name__!r}: "
                          f"{exc} (allowed: {list(TARGET_FAMILIES)}, {list(TARGET_NAMES)}, an (N, 2) array, a "
                          f".npy/.yaml path, {ROUTE!r} or '{ROUTE_PREFIX}NAME' with NAME in "
                          f"{routing.layout_names()} or a layout .yaml)") from exc


def is_route(spec: Any) -> bool:
    """Whether a target spec (as given or resolved) is a route among pegs."""
    return isinstance(spec, routing.Layout) or (isinstance(spec, str) and (spec == ROUTE or
                                                                           spec.startswith(ROUTE_PREFIX)))


def target_label(spec: Any) -> str:
    """The name of a target spec as a person reads it: a name or family as is, a file by its stem, a fixed route
    by its layout's name, else "custom"."""
    if isinstance(spec, str) and (spec in TARGET_NAMES or spec in TARGET_FAMILIES or spec == ROUTE):
        return spec
    if isinstance(spec, routing.Layout):
        return spec.name
    if isinstance(spec, str) and spec.startswith(ROUTE_PREFIX):
        return Path(spec[len(ROUTE_PREFIX):]).stem
    if isinstance(spec, (str, Path)) and str(spec).endswith((".npy", ".yaml", ".yml")):
        return Path(spec).stem
    return CUSTOM


def draw_target(spec: str | torch.Tensor, rng: np.random.Generator, p: CableParams,
                named: dict[str, torch.Tensor], device: torch.device | str = "cpu",
                dtype: torch.dtype = torch.float32,
                curve_max_turn_deg: float = CURVE_MAX_TURN_DEG) -> tuple[torch.Tensor, str]:
    """One episode's target (N, 2) and its name, for a resolved spec. ``"random"``: one of the named straight
    targets (``named``: name -> (N, 2)), uniformly (the thesis's task); ``"random_curve"``: a smooth random curve
    (diffdlo.planar.shapes.random_curve); a fixed (N, 2) target: itself, named "custom" (or its name when it is one of
    ``named``). Draws from ``rng`` (the episode's generator) only for a family."""
    if isinstance(spec, str) and spec == "random":
        name = TARGET_NAMES[int(rng.integers(len(TARGET_NAMES)))]
        return named[name], name
    if isinstance(spec, str):                                                     # "random_curve"
        curve_gen = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
        return random_curve(1, p, curve_gen, device, dtype, curve_max_turn_deg)[0], spec
    name = next((n for n, t in named.items() if t.shape == spec.shape and bool(torch.equal(t, spec))), CUSTOM)
    return spec, name


def draw_route(spec: str | routing.Layout, rng: np.random.Generator, p: CableParams) -> routing.Layout:
    """One episode's layout for a resolved route spec: ``"route"`` a random one (routing.random_layout, from a
    generator seeded by ``rng``), a Layout itself."""
    if isinstance(spec, routing.Layout):
        return spec
    return routing.random_layout(p, torch.Generator().manual_seed(int(rng.integers(0, 2**62))))


# ====================================================================== actions (eq 2.5, 2.6)
def decode_node(a0: torch.Tensor, n_nodes: int) -> torch.Tensor:
    """Eq 2.6's node: round(a0 (N - 1)) with a0 clipped to [0, 1] -> int64 node ids (no gradient)."""
    return torch.round(a0.detach().clamp(0.0, 1.0) * (n_nodes - 1)).to(torch.int64)


def decode_drag(a: torch.Tensor, scale: float) -> torch.Tensor:
    """Eq 2.6's drag: a 2 s - s for a in [0, 1] (already clipped), i.e. [-s, s] per axis. Differentiable.
    ``scale`` 1 gives the drag in units of action_scale (the learners' hybrid head)."""
    return a * (2 * scale) - scale


def encode_node_action(node: torch.Tensor, drag: torch.Tensor, n_nodes: int, scale: float) -> torch.Tensor:
    """The inverse of eq 2.6: node ids (...,) and drags (..., 2) in [-scale, scale] (clipped) -> (..., 3) node
    actions in [0, 1] that decode to that node and drag."""
    a0 = node.to(drag.dtype) / (n_nodes - 1)
    return torch.cat([a0.unsqueeze(-1), ((drag + scale) / (2 * scale)).clamp(0.0, 1.0)], dim=-1)


def decode_node_action(actions: torch.Tensor, p: CableParams) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 3) node actions (clipped to [0, 1]) -> node (...,) int64 and drag (..., 2) [m]; differentiable with
    respect to the drag part."""
    a = actions.clamp(0.0, 1.0)
    return decode_node(a[..., 0], p.n_nodes), decode_drag(a[..., 1:], p.action_scale)


def decode_pixel_node(point: torch.Tensor, pos: torch.Tensor, view_size: float) -> torch.Tensor:
    """Eq 2.5's node: (B, 2) (column, row) fractions of the square view window (side ``view_size`` m, centred at
    the origin, row 0 at the top) -> the node of ``pos`` (B, N, 2) nearest to that point (B,)."""
    h = view_size / 2
    xy = torch.stack([point[:, 0] * view_size - h, h - point[:, 1] * view_size], dim=-1)
    return (pos - xy.unsqueeze(1)).norm(dim=-1).argmin(dim=1)


def decode_action(action_type: str, actions: torch.Tensor, pos: torch.Tensor, p: CableParams,
                  view_size: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, A) actions clipped to [0, 1] -> grasped node (B,) int64 and drag (B, 2) [m], for any action type (the
    pin of the pin actions: ``decode_action_pin``)."""
    if action_type in ("node", "node_pin"):
        return decode_node(actions[:, 0], p.n_nodes), decode_drag(actions[:, 1:3], p.action_scale)
    return decode_pixel_node(actions[:, :2], pos, view_size), decode_drag(actions[:, 2:4], p.action_scale)


def decode_action_pin(action_type: str, actions: torch.Tensor, node: torch.Tensor, pos: torch.Tensor,
                      p: CableParams, view_size: float) -> torch.Tensor | None:
    """The second gripper's node (B,) int64 (-1: none) of (B, A) clipped actions, None for an action type without
    one: "node_pin" ``decode_pin`` of entry 3; "pixel_pin" the node nearest the point (entries 4, 5: column, row
    fractions of the view, as eq 2.5's grasp), none where that is the grasped node."""
    if action_type == "node_pin":
        return decode_pin(actions[:, 3], node, p.n_nodes)
    if action_type == "pixel_pin":
        pin = decode_pixel_node(actions[:, 4:6], pos, view_size)
        return torch.where(pin == node, torch.full_like(pin, -1), pin)
    return None


def decode_pin(a: torch.Tensor, node: torch.Tensor, n_nodes: int) -> torch.Tensor:
    """The "node_pin" action's last entry a in [0, 1] (clipped) -> the node the second gripper holds (B,) int64:
    round(a N) - 1, so a < 1 / (2 N) is no pin (-1); a pin on the grasped node is no pin either."""
    pin = torch.round(a.detach().clamp(0.0, 1.0) * n_nodes).to(torch.int64) - 1
    return torch.where(pin == node, torch.full_like(pin, -1), pin)


def encode_pin(pin: torch.Tensor, n_nodes: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The inverse of ``decode_pin``: pins (...,) in [-1, N - 1] -> the action entries that decode to them."""
    return (pin.to(dtype) + 1) / n_nodes


def greedy_drags(pos: torch.Tensor, target: torch.Tensor, max_disp: float,
                 align: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """The greedy move's ingredients for rope(s) (..., N, 2): every node's gap to its place in the target moved onto
    the rope's centroid (``align``; a route's place on the board without), capped at ``max_disp`` in length
    (..., N, 2), and the uncapped gap lengths (..., N). The greedy move drags the node with the largest gap by its
    capped gap."""
    aligned = target - target.mean(-2, keepdim=True) + pos.mean(-2, keepdim=True) if align else target
    gap = aligned - pos
    dist = gap.norm(dim=-1)
    return gap * (max_disp / dist.clamp_min(1e-12)).clamp(max=1.0).unsqueeze(-1), dist


def greedy_action(pos: torch.Tensor, target: torch.Tensor, p: CableParams, pin: bool = False,
                  align: bool = True) -> torch.Tensor:
    """The greedy move of one rope (N, 2) as an env action: the node farthest from its place (``greedy_drags``)
    dragged towards it, (3,) node action; with ``pin`` (4,) node_pin, a second gripper holding the node, two or more
    links from the grasped one, that is nearest its place. The greedy planner's move and the planners' stall escape."""
    drags, dist = greedy_drags(pos, target, p.max_disp, align=align)
    node = dist.argmax()
    action = encode_node_action(node, drags[node], p.n_nodes, p.action_scale)
    if not pin:
        return action
    far = (torch.arange(p.n_nodes, device=pos.device) - node).abs() >= 2
    held = torch.where(far, dist, torch.full_like(dist, float("inf"))).argmin()
    return torch.cat([action, encode_pin(held, p.n_nodes, action.dtype).to(action.device)[None]])


# ====================================================================== rewards, success, episode end
def step_outcome(rules: Any, prev: torch.Tensor, new: torch.Tensor, target: torch.Tensor,
                 steps: torch.Tensor, pegs: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Score the moves prev -> new (B, N, 2) towards ``target`` after ``steps`` (B,) moves (this one included), by
    the rules of resolved env options (``EnvOptions.resolve()``, an env's ``options``): reward, success_tol,
    success_worst_tol, max_steps, success_bonus, step_penalty, on_exit, exit_penalty and workspace (thesis
    Algorithm 2 with the error metric; the options after max_steps are ours, off by default).

    Returns (reward, terminated, truncated, success), each (B,). Success (``task_success``): shape_error <
    success_tol and, when success_worst_tol is set, worst_node_error < success_worst_tol; it terminates with reward
    success_bonus. The test is ``task_success`` (a route, ``pegs`` (B, K, 3) given: ``route_success``, on the board).
    A node outside the workspace rectangle (centred at the origin) truncates the episode (on_exit "truncate", Algorithm
    2) or terminates it with reward -exit_penalty (on_exit "fail"); reaching max_steps truncates. Every other move gets
    the named reward minus step_penalty.
    """
    r = move_reward(rules.reward, prev, new, target, pegs)
    success = task_success(new, target, rules.success_tol, rules.success_worst_tol, pegs)
    half = torch.tensor(rules.workspace, device=new.device, dtype=new.dtype) / 2
    outside = (new.abs() > half).flatten(1).any(1) & ~success
    failed = outside if rules.on_exit == "fail" else torch.zeros_like(outside)
    terminated = success | failed
    truncated = ~terminated & ((steps >= rules.max_steps) | outside)
    r = torch.where(success, torch.full_like(r, rules.success_bonus), r - rules.step_penalty)
    return torch.where(failed, torch.full_like(r, -rules.exit_penalty), r), terminated, truncated, success


def task_success(pos: torch.Tensor, target: torch.Tensor, tol: float, worst_tol: float | None = None,
                 pegs: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) bool: THE success test, the one that ends an episode, pays its bonus and is reported as
    ``info["is_success"]`` (``step_outcome`` and ``task_metrics`` both call it): a shape ``is_success``, a route
    (``pegs`` given) ``route_success``."""
    if pegs is None:
        return is_success(pos, target, tol, worst_tol)
    return route_success(pos, target, pegs, tol, worst_tol)


def route_success(pos: torch.Tensor, route: torch.Tensor, pegs: torch.Tensor, tol: float,
                  worst_tol: float | None = None) -> torch.Tensor:
    """(B,) bool: the rope lies along the route ON THE BOARD (mean node distance < tol, the worst < worst_tol where
    given; no centroid alignment) AND passes every peg on the route's side (routing.sides_kept)."""
    errors = routing.route_errors(pos, route)
    return within_tolerance(errors.mean(-1), errors.amax(-1), tol, worst_tol) & routing.sides_kept(pos, route, pegs)


def task_metrics(pos: torch.Tensor, target: torch.Tensor, success_tol: float,
                 success_worst_tol: float | None = None, pegs: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """The per-rope figures an env reports after every reset and move: shape_error [m] (the mean node distance),
    worst_node_error [m] (the largest), orientation_error [rad], sides_kept (every peg on the route's side; True
    without pegs), is_success (``task_success``, the test that ends the episode). For a route (``pegs`` given) the
    distances are on the board."""
    errors = node_errors(pos, target) if pegs is None else routing.route_errors(pos, target)
    sides = (torch.ones(pos.shape[0], dtype=torch.bool, device=pos.device) if pegs is None
             else routing.sides_kept(pos, target, pegs))
    return {"shape_error": errors.mean(-1).detach(), "worst_node_error": errors.amax(-1).detach(),
            "orientation_error": orientation_error(pos, target).detach(), "sides_kept": sides,
            "is_success": task_success(pos, target, success_tol, success_worst_tol, pegs)}


# ====================================================================== observations
def observation_space(obs_type: str, p: CableParams, image_size: int, max_pegs: int = 0) -> spaces.Space:
    """The gymnasium space of one rope's observation of type ``obs_type`` (see ``observe``); with ``max_pegs`` > 0
    (a route) "points" carries the pegs too."""
    # Bounds of a node coordinate [m]: every node is inside the workspace before a step (else the episode has
    # ended) and a step moves the grasped node by at most max_disp, the rest following within the rope length.
    n, s = p.n_nodes, image_size
    bound = np.float32(max(p.workspace) / 2 + p.length + p.max_disp)
    points = spaces.Box(-bound, bound, (n, 2), np.float32)
    img = spaces.Box(0, 255, (s, s, 3), np.uint8)
    if obs_type in POINT_OBS:
        if max_pegs > 0:
            pegs = spaces.Box(-bound, bound, (max_pegs, 3), np.float32)
            return spaces.Dict({"node_poses": points, "target_poses": points, "pegs": pegs})
        return spaces.Dict({"node_poses": points, "target_poses": points})
    if obs_type == "distance":
        return spaces.Box(-2 * bound, 2 * bound, (n, 2), np.float32)
    if obs_type == "image":
        return spaces.Dict({"image": img, "target_image": img})
    return spaces.Dict({"image": img})


@dataclasses.dataclass
class TargetPictures:
    """The target's layers of an image observation, drawn once per episode: coverage (B, S, S) and, with mark_end,
    the dot on its node 0."""
    coverage: torch.Tensor
    end: torch.Tensor | None = None
    pegs: torch.Tensor | None = None        # (B, S, S) the pegs' discs, for a route


def target_pictures(target: torch.Tensor, image_size: int, view_size: float, mark_end: bool,
                    pegs: torch.Tensor | None = None) -> TargetPictures:
    t = target.detach()
    return TargetPictures(rimage.coverage(t, image_size, view_size),
                          rimage.end_marker(t, image_size, view_size) if mark_end else None,
                          None if pegs is None else rimage.discs(pegs.detach(), image_size, view_size))


def observe(obs_type: str, pos: torch.Tensor, target: torch.Tensor, image_size: int = 64, view_size: float = 1.0,
            pictures: TargetPictures | None = None, pegs: torch.Tensor | None = None) -> Any:
    """The observation of ropes ``pos`` (B, N, 2) with targets (B, N, 2):

    "points": {node_poses, target_poses} (B, N, 2) float32 (the multi-input observation); "distance": rope - target
    (B, N, 2) float32 (the single-input one); "image": {image, target_image} (B, S, S, 3) uint8 pictures of the rope
    and of the target; "image_single": {image}, the rope drawn over the target ("perceived" is the env's: the
    "image" pictures read by its perception network). ``pictures``: the target's layers
    (``target_pictures``, cached per episode by the env; drawn here when None); their ``end`` layer also marks the
    rope's node 0. ``pegs`` (B, K, 3) (a route): "points" carries them as "pegs" (rows of zeros: no peg), and the
    pictures draw them (grey discs under the target and the rope).
    """
    pos, target = pos.detach(), target.detach()
    if obs_type == "points":
        obs = {"node_poses": pos.to(torch.float32, copy=True), "target_poses": target.to(torch.float32, copy=True)}
        if pegs is not None:
            obs["pegs"] = pegs.detach().to(torch.float32, copy=True)
        return obs
    if obs_type == "distance":
        return (pos - target).to(torch.float32)
    if obs_type not in PICTURE_OBS:
        raise ValueError(f"observe draws obs_type 'points', 'distance', 'image' or 'image_single', got {obs_type!r} "
                         "(an env reads 'perceived' with its perception)")
    if pictures is None:
        pictures = target_pictures(target, image_size, view_size, mark_end=False, pegs=pegs)
    rope = [(rimage.coverage(pos, image_size, view_size), rimage.ROPE_COLOR)]
    tgt = [(pictures.coverage, rimage.TARGET_COLOR)]
    if pictures.pegs is not None:
        board = (pictures.pegs, rimage.PEG_COLOR)
        rope.insert(0, board)
        tgt.insert(0, board)
    if pictures.end is not None:
        rope.append((rimage.end_marker(pos, image_size, view_size), rimage.ROPE_END_COLOR))
        tgt.append((pictures.end, rimage.TARGET_END_COLOR))
    if obs_type == "image":
        return {"image": rimage.compose(rope), "target_image": rimage.compose(tgt)}
    return {"image": rimage.compose(tgt + rope[1:] if pictures.pegs is not None else tgt + rope)}
