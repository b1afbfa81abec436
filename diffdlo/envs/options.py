"""The env's options, one frozen dataclass (``EnvOptions``): each field's rule and help beside it, checked when the
options are built (each error names the bad value and what is allowed) and resolved once (``EnvOptions.resolve``:
the params and their defaults, the episode length). The learners' ``agents.common.config.TaskOptions`` maps onto it."""
from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..tasks import task
from ..utils.checks import check_fields, option
from ..planar.params import CableParams, load_params
from ..tasks.rewards import BOARD_REWARDS, PEG_REWARDS, REWARDS
from ..tasks.routing import ROUTE_STARTS
from ..planar.shapes import CURVE_MAX_TURN_DEG, random_curve
from ..tasks.task import ACTION_TYPES, EXIT_RULES, OBS_TYPES

# Side [m] of the square view window of image observations and pixel actions, centred at the origin: x, y in
# [-0.5, 0.5]. The rope is 0.5 m long and starts centred at the origin, so a start shape always fits with room for
# ~0.25 m of drift; at 64 px one pixel is 15.6 mm. A rope may drift out of the view (it is truncated only at the
# 2 m workspace): pass view_size=2.0 to see the whole workspace at a coarser 31 mm/pixel.
DEFAULT_VIEW_SIZE = 1.0


def _choice_error(what: str, value: Any, allowed: Sequence[Any]) -> ValueError:
    return ValueError(f"unknown {what} {value!r}: use one of {list(allowed)}")


def resolve_params(params: CableParams | str | Path | None) -> CableParams:
    """A CableParams, a params name (``params/<name>.yaml``), a YAML path, or None (``cable``)."""
    if params is None:
        return load_params("cable")
    if isinstance(params, CableParams):
        return params
    if isinstance(params, (str, Path)):
        return load_params(params)
    raise TypeError(f"params must be a CableParams, a params name or a YAML path, got {type(params).__name__}")


def check_actions(actions: Any, shape: tuple[int, ...]) -> torch.Tensor:
    """Validate an action batch: exact shape, finite values. Returns a float64 tensor (not yet clipped)."""
    try:
        a = actions.detach() if torch.is_tensor(actions) else torch.as_tensor(np.asarray(actions, dtype=np.float64))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"action must be an array of numbers of shape {shape}, got {actions!r}") from exc
    if not (a.is_floating_point() or a.dtype in (torch.int64, torch.int32, torch.bool)):
        raise ValueError(f"action must hold real numbers, got dtype {a.dtype}")
    if tuple(a.shape) != tuple(shape):
        raise ValueError(f"action must have shape {tuple(shape)}, got {tuple(a.shape)}: {actions!r}")
    a = a.to(torch.float64)
    if not bool(torch.isfinite(a).all()):
        raise ValueError(f"action contains NaN or inf: {a.cpu().numpy().tolist()}")
    return a


@dataclasses.dataclass(frozen=True)
class EnvOptions:
    """The options of the shape-control task env (``BatchedShapeControl``, ``gymnasium.make`` / ``make_vec`` of
    ``DiffDLO/ShapeControl-v0``, which take them as keywords too); each field's help says what it does.

    Checked when built (a ValueError names the field, what is allowed and the value). ``resolve()`` gives the
    options the env runs with: the params a CableParams (action_scale applied), max_steps, success_tol and
    success_bonus filled in from the params (success_worst_tol as given), max_steps cut to max_episode_steps, the
    target checked; those are also the rules ``diffdlo.tasks.task.step_outcome`` reads (with ``workspace``). Change a
    resolved one by resolving a ``dataclasses.replace`` of the options as given: the filled-in values follow the
    params they came from.
    The simulator's placement (device, dtype, backend) is not an option: the env takes it beside them.
    """
    target: Any = option("random", help=(
        '"random" (one of TARGET_NAMES drawn at every reset, the thesis\'s default), "random_curve" (a smooth random '
        "curve drawn at every reset, diffdlo.planar.shapes.random_curve), a name in TARGET_NAMES, an (N, 2) "
        "array/tensor, or a .npy/.yaml path; or a ROUTE among pegs (the wire-harness task, diffdlo/tasks/routing.py): "
        '"route" (a random board of 2-4 pegs and a route drawn at every reset, the rope starting beside it) or '
        '"route:NAME" (a fixed layout of diffdlo/tasks/layouts, or route:PATH.yaml). Drawn targets come from the '
        "env's per-env generator, seeded like the start shapes"))
    obs_type: str = option("points", choices=OBS_TYPES, help=(
        '"points" (dict node_poses, target_poses (N, 2) float32: the multi-input observation), "distance" ((N, 2) '
        'float32 rope - target per node: the single-input observation), "image" (dict image, target_image: RGB '
        'uint8 (S, S, 3) of the rope and of the target), "image_single" (dict image: rope drawn over the target in '
        'one picture) or "perceived" (dict node_poses, target_poses like "points", but READ from the "image" '
        "pictures, end markers drawn, by the perception network ``perception``: diffdlo/perception/network.py; the "
        'target is read once per episode; a route\'s known pegs are given to the reading and carried exactly as "pegs")'))
    action_type: str = option("node", choices=ACTION_TYPES, help=(
        '"node" (eq 2.6, [0, 1]^3: node = round(a0 (N-1)), dx, dy = a 2 s - s with s = params.action_scale) or '
        '"pixel" (eq 2.5, [0, 1]^4: (a0, a1) = (column, row) fractions of the image view window, row 0 at the top; '
        'the node nearest to that point is grasped; dx, dy as for "node") or "node_pin" (ours, [0, 1]^4: "node"\'s '
        "three, then a second gripper's node held still during the drag, round(a3 N) - 1: -1 (a3 < 1/(2N)) or the "
        'grasped node is no pin; diffdlo.tasks.task.decode_pin) or "pixel_pin" (ours, [0, 1]^6: "pixel"\'s four, then '
        "the second gripper's point (column, row): the node nearest it is held, none where that is the grasped node). "
        "Actions outside [0, 1] are clipped to [0, 1]; NaN/inf or a wrong shape raise ValueError"))
    reward: str = option("position_orientation", choices=REWARDS, help=(
        'one of diffdlo.REWARDS ("position_orientation" eq 2.9-2.11, "abs_diff" eq 2.7, "delta_gain" eq 2.8, '
        '"shape_gain": ours, the centimetres of shape error a move removed)'))
    params: CableParams | str | Path | None = option(
        None, says="a CableParams, a params name or a YAML path",
        help="CableParams, params name (params/<name>.yaml) or YAML path, resolved once (None: cable)")
    action_scale: float | None = option(None, "(0, inf)", says="a positive number [m]", help=(
        "s of the drag, dx, dy in [-s, s] [m] (None: params.action_scale = 0.1): overrides the params' value"))
    max_steps: int | None = option(None, "[1, inf)", says="a positive integer", help=(
        "moves per episode (None: params.max_episode_steps)"))
    max_episode_steps: int | None = option(None, "[1, inf)", says="a positive integer or None", help=(
        "gymnasium's time limit (``make_vec(..., max_episode_steps=)``; the registered spec's is 100): episodes are "
        "truncated after min(max_steps, max_episode_steps) moves, as ``gymnasium.make``'s TimeLimit wrapper over "
        "the env's own truncation does. None: max_steps alone"))
    success_tol: float | None = option(None, "(0, inf)", says="a positive finite number [m]", help=(
        "shape error [m] (the mean node distance, diffdlo.tasks.rewards.shape_error) below which a move succeeds "
        "(None: params.success_tol: 0.01 in params/cable.yaml, Table 2.1)"))
    success_worst_tol: float | None = option(None, "(0, inf)", says="a positive finite number [m] or None", help=(
        "worst node error [m] (the largest node distance, diffdlo.tasks.rewards.worst_node_error) below which a move "
        "succeeds too: success is shape error < success_tol AND worst node error < success_worst_tol (None: no "
        "worst-node condition, the thesis's test)"))
    image_size: int = option(64, "[8, inf)", says="an integer >= 8", help=(
        "side S [px] of image observations (and of the perceived pictures)"))
    view_size: float = option(DEFAULT_VIEW_SIZE, "(0, inf)", says="a positive number [m]", help=(
        "side [m] of the square view window of pictures and pixel actions, centred at the origin"))
    success_bonus: float | None = option(None, "(-inf, inf)", says="a finite number", help=(
        "reward of the successful move (None: params.success_bonus = 20, Algorithm 2)"))
    step_penalty: float = option(0.0, "(-inf, inf)", says="a finite number", help=(
        "subtracted from the reward of every move that does not succeed (0: the thesis's)"))
    on_exit: str = option("truncate", choices=EXIT_RULES, help=(
        'what happens when a node leaves the workspace: "truncate" (the thesis\'s Algorithm 2: the episode is cut '
        'off, a learner bootstraps as after a time limit) or "fail" (ours: the episode TERMINATES with reward '
        "-exit_penalty, so leaving pays nothing more, ever; success is still only is_success)"))
    exit_penalty: float = option(0.0, "(-inf, inf)", says="a finite number", help=(
        'the reward of a move that leaves the workspace under on_exit="fail" is -exit_penalty'))
    route_start: str = option("beside", choices=ROUTE_STARTS, help=(
        'a route\'s start (routes only): "beside" (a random rope 0.2 m from the route\'s centre, clear of the pegs) or '
        '"across" (within 5 cm of it: the rope lies among the pegs)'))
    max_pegs: int = option(4, "[1, inf)", says="a positive integer", help=(
        "a route's peg slots: the points observation's \"pegs\" is (max_pegs, 3) of (x, y, radius) [m], rows of "
        "zeros past the layout's pegs (routes only)"))
    curve_max_turn_deg: float = option(CURVE_MAX_TURN_DEG, "[0, 90]", help=(
        'the largest turning angle per node [deg] of target="random_curve"'))
    mark_end: bool = option(False, says="True or False", help=(
        "image observations draw a dot on node 0 of the rope (green) and of the target (amber), so a rope and its "
        "reversal look different (False: the thesis's pictures, where they do not)"))
    start: Any = option(None, help=(
        "None (a random start shape, settled: thesis model.free) or a fixed (N, 2) start shape (or .npy path) placed "
        "as is after every reset (custom easy tasks): finite, with no two consecutive nodes closer than 10% of the "
        "rest length (ValueError naming the nodes otherwise)"))
    perception: Any = option(None, help=(
        'obs_type="perceived" only: a perception checkpoint path (``python -m diffdlo.perception``) or a '
        "``diffdlo.perception.Perception``, made for these pictures (image_size, view_size, n_nodes)"))
    perception_refine: int | None = option(None, "[0, inf)", says="None or an integer >= 0", help=(
        "analysis-by-synthesis steps after the network per picture (None: the checkpoint's; 0: the network alone, "
        "the cheap reading for hundreds of ropes per step)"))

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):              # numpy scalars (np.int64(64), np.bool_) as Python's
            v = getattr(self, f.name)
            if isinstance(v, np.generic):
                object.__setattr__(self, f.name, v.item())
        check_fields(self, skip=("curve_max_turn_deg",))   # resolve checks it in random_curve's own words
        self._check_perception()

    def _check_route(self) -> None:
        """A route is scored on the board and shows its pegs: refuse what cannot (naming it)."""
        if self.obs_type not in task.ROUTE_OBS:
            raise ValueError(f"obs_type={self.obs_type!r} cannot show a route's pegs: use one of {list(task.ROUTE_OBS)} "
                             f"with target={self.target!r}")
        if self.reward not in BOARD_REWARDS:
            raise ValueError(f"reward={self.reward!r} does not see where the rope lies on the board (it aligns "
                             f"centroids or compares shapes): a route (target={self.target!r}) takes one of "
                             f"{list(BOARD_REWARDS)} (gymnasium.make('DiffDLO/Routing-v0') sets 'route_gain')")

    def _check_perception(self) -> None:
        if self.obs_type != "perceived":
            if self.perception is not None or self.perception_refine is not None:
                raise ValueError(f"perception and perception_refine are read only by obs_type='perceived', got "
                                 f"obs_type={self.obs_type!r}")
            return
        if self.perception is None:
            from ..perception import PerceptionError
            raise PerceptionError("obs_type='perceived' needs perception=PATH, a checkpoint of "
                                  "python -m diffdlo.perception")

    @property
    def workspace(self) -> tuple[float, float]:
        """The workspace rectangle [m] (centred at the origin) of the resolved params."""
        return tuple(self.params.workspace)

    def keywords(self) -> dict[str, Any]:
        """The options as keyword arguments (``gymnasium.make("DiffDLO/ShapeControl-v0", **options.keywords())``)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def resolve(self) -> EnvOptions:
        """The options the env runs with (see the class's docstring); resolving them again changes nothing. Raises
        ValueError, TargetError or ParamsError naming the bad option."""
        p = resolve_params(self.params)
        if self.action_scale is not None:
            p = dataclasses.replace(p, action_scale=float(self.action_scale))
        max_steps = p.max_episode_steps if self.max_steps is None else self.max_steps
        limit = max_steps if self.max_episode_steps is None else min(max_steps, self.max_episode_steps)
        if self.max_steps is not None and limit < max_steps:
            warnings.warn(f"episodes end after max_episode_steps={self.max_episode_steps} moves, not "
                          f"max_steps={max_steps} (gymnasium's time limit; the registered spec's is 100): pass "
                          f"max_episode_steps={max_steps} for longer episodes", stacklevel=3)
        try:
            random_curve(1, p, torch.Generator().manual_seed(0), max_turn_deg=self.curve_max_turn_deg)
        except ValueError as exc:
            raise ValueError(f"curve_max_turn_deg: {exc}") from exc
        task.resolve_target(self.target, p)         # a bad target is named here, before any simulator is built
        if task.is_route(self.target):
            self._check_route()
        elif self.reward in PEG_REWARDS:
            raise ValueError(f"reward={self.reward!r} scores the sides a rope passes pegs on: it needs a route "
                             f"(target 'route' or 'route:NAME'), got target={self.target!r}")
        return dataclasses.replace(
            self, params=p, action_scale=p.action_scale, max_steps=int(limit),
            success_tol=float(p.success_tol if self.success_tol is None else self.success_tol),
            success_worst_tol=None if self.success_worst_tol is None else float(self.success_worst_tol),
            success_bonus=float(p.success_bonus if self.success_bonus is None else self.success_bonus),
            step_penalty=float(self.step_penalty), exit_penalty=float(self.exit_penalty),
            view_size=float(self.view_size), curve_max_turn_deg=float(self.curve_max_turn_deg))


def env_field(name: str) -> Any:
    """A field of another options type that is EnvOptions' field ``name`` under its own name (the learners' ``obs``
    for ``obs_type``): the same default, rule and help, broken rules named by the interval or choices (no ``says``),
    and ``env_name`` to map it back."""
    f = EnvOptions.__dataclass_fields__[name]
    return dataclasses.field(default=f.default, metadata={**f.metadata, "says": None, "env_name": name})


def env_options(options: EnvOptions | None, keywords: dict[str, Any]) -> EnvOptions:
    """The options an env is given, as ``options`` or as keywords (the names of EnvOptions' fields), not both."""
    if options is None:
        unknown = sorted(set(keywords) - set(EnvOptions.__dataclass_fields__))
        if unknown:
            raise TypeError(f"unknown env option(s) {unknown}: use {list(EnvOptions.__dataclass_fields__)}")
        return EnvOptions(**keywords)
    if not isinstance(options, EnvOptions):
        raise TypeError(f"options must be a diffdlo.envs.EnvOptions, got {type(options).__name__}")
    if keywords:
        raise TypeError(f"give the env's options as options=EnvOptions(...) or as keywords, not both: got options and "
                        f"{sorted(keywords)}")
    return options
