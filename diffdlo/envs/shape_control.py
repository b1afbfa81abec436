"""Shape-control task (thesis Chapter 2, Algorithms 1-3) as a batched torch core and a gymnasium single env.

``BatchedShapeControl`` holds B ropes and does all the work in torch on the simulator's device: one batched
``Simulator.move`` per step, one batched ``Simulator.settle`` per reset, batched rewards and batched image rendering.
``ShapeControlEnv`` (gymnasium.Env, ``gymnasium.make("DiffDLO/ShapeControl-v0")``) is the core with B = 1 plus a
numpy conversion; ``ShapeControlVectorEnv`` (diffdlo/envs/vector.py, ``gymnasium.make_vec``) is the core with
B = num_envs plus next-step autoreset. Both wrap the same code, so they cannot disagree.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.utils import seeding

from .. import image as rimage
from ..params import CableParams, load_params
from ..rewards import REWARDS, orientation_error, reward as compute_reward, shape_error
from ..shapes import CURVE_MAX_TURN_DEG, TARGET_FAMILIES, TARGET_NAMES, TargetError, random_curve
from ..simulator import Simulator

OBS_TYPES = ("points", "distance", "image", "image_single")
ACTION_TYPES = ("node", "pixel")
ACTION_DIMS = {"node": 3, "pixel": 4}
# Side [m] of the square view window of image observations and pixel actions, centred at the origin: x, y in
# [-0.5, 0.5]. The rope is 0.5 m long and starts centred at the origin, so a start shape always fits with room for
# ~0.25 m of drift; at 64 px one pixel is 15.6 mm. A rope may drift out of the view (it is truncated only at the
# 2 m workspace): pass view_size=2.0 to see the whole workspace at a coarser 31 mm/pixel.
DEFAULT_VIEW_SIZE = 1.0
RENDER_SIZE = 256
INFO_KEYS = ("shape_error", "orientation_error", "is_success", "node", "substeps")
EXIT_RULES = ("truncate", "fail")


def _choice_error(what: str, value: Any, allowed: Sequence[str]) -> ValueError:
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


class BatchedShapeControl:
    """B independent shape-control episodes in torch: tensors in, tensors out, on the simulator's device.

    Arguments (shared by the gymnasium envs):
      num_envs: B.
      target: "random" (one of TARGET_NAMES drawn at every reset, the thesis's default), "random_curve" (a smooth
        random curve drawn at every reset, diffdlo.shapes.random_curve), a name in TARGET_NAMES, an (N, 2)
        array/tensor, or a .npy/.yaml path. Drawn targets come from the env's per-env generator, seeded like the
        start shapes.
      obs_type: "points" (dict node_poses, target_poses (N, 2) float32: the multi-input observation),
        "distance" ((N, 2) float32 rope - target per node: the single-input observation), "image" (dict
        image, target_image: RGB uint8 (S, S, 3) of the rope and of the target) or "image_single" (dict
        image: rope drawn over the target in one picture).
      action_type: "node" (eq 2.6, [0, 1]^3: node = round(a0 (N-1)), dx, dy = a 2 s - s with s =
        params.action_scale) or "pixel" (eq 2.5, [0, 1]^4: (a0, a1) = (column, row) fractions of the image view
        window, row 0 at the top; the node nearest to that point is grasped; dx, dy as for "node").
        Actions outside [0, 1] are clipped to [0, 1]; NaN/inf or a wrong shape raise ValueError.
      reward: one of diffdlo.REWARDS ("position_orientation" eq 2.9-2.11, "abs_diff" eq 2.7, "delta_gain" eq 2.8,
        "shape_gain": ours, the centimetres of shape error a move removed).
      max_steps, success_tol: default params.max_episode_steps and params.success_tol.
      params: CableParams, params name or YAML path. image_size: S (default 64). view_size: side [m] of the square
        view window centred at the origin (default 1.0). device, dtype, backend: of the simulator
        (backend "torch" forces the eager reference path).
      success_bonus: reward of the successful move (default params.success_bonus = 20, Algorithm 2).
      step_penalty: subtracted from the reward of every move that does not succeed (default 0: the thesis's).
      on_exit: what happens when a node leaves the workspace: "truncate" (default, the thesis's Algorithm 2: the
        episode is cut off, a learner bootstraps as after a time limit) or "fail" (ours: the episode TERMINATES
        with reward -exit_penalty, so leaving pays nothing more, ever; success is still only is_success).
      exit_penalty: the reward of a move that leaves the workspace under on_exit="fail" is -exit_penalty
        (default 0).
      curve_max_turn_deg: the largest turning angle per node of target="random_curve" (default 12 deg).
      mark_end: image observations draw a dot on node 0 of the rope (green) and of the target (amber), so a rope
        and its reversal look different (default False: the thesis's pictures, where they do not).
    Episode end (Algorithm 2 with the error metric): terminated, with reward success_bonus, when
    shape_error < success_tol; otherwise truncated at max_steps or when any node leaves the params.workspace
    rectangle centred at the origin (terminated instead, under on_exit="fail"). ``info["is_success"]`` tells a
    success from a failure: ``terminated`` alone does not, under on_exit="fail".
    """

    def __init__(self, num_envs: int = 1, target: Any = "random", obs_type: str = "points", action_type: str = "node",
                 reward: str = "position_orientation", max_steps: int | None = None, success_tol: float | None = None,
                 params: CableParams | str | Path | None = None, image_size: int = 64,
                 view_size: float = DEFAULT_VIEW_SIZE, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32, backend: str = "auto", success_bonus: float | None = None,
                 step_penalty: float = 0.0, on_exit: str = "truncate", exit_penalty: float = 0.0,
                 curve_max_turn_deg: float = CURVE_MAX_TURN_DEG, mark_end: bool = False):
        if not isinstance(num_envs, (int, np.integer)) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if not isinstance(obs_type, str) or obs_type not in OBS_TYPES:
            raise _choice_error("obs_type", obs_type, OBS_TYPES)
        if not isinstance(action_type, str) or action_type not in ACTION_TYPES:
            raise _choice_error("action_type", action_type, ACTION_TYPES)
        if not isinstance(reward, str) or reward not in REWARDS:
            raise _choice_error("reward", reward, REWARDS)
        self.params = p = resolve_params(params)
        if max_steps is None:
            max_steps = p.max_episode_steps
        if not isinstance(max_steps, (int, np.integer)) or isinstance(max_steps, bool) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
        success_tol = p.success_tol if success_tol is None else success_tol
        if not isinstance(success_tol, (int, float)) or not success_tol > 0 or not np.isfinite(success_tol):
            raise ValueError(f"success_tol must be a positive number [m], got {success_tol!r}")
        if not isinstance(image_size, (int, np.integer)) or isinstance(image_size, bool) or image_size < 8:
            raise ValueError(f"image_size must be an integer >= 8, got {image_size!r}")
        if not isinstance(view_size, (int, float)) or not view_size > 0 or not np.isfinite(view_size):
            raise ValueError(f"view_size must be a positive number [m], got {view_size!r}")
        success_bonus = p.success_bonus if success_bonus is None else success_bonus
        for name, v in (("success_bonus", success_bonus), ("step_penalty", step_penalty),
                        ("exit_penalty", exit_penalty)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
        if not isinstance(on_exit, str) or on_exit not in EXIT_RULES:
            raise _choice_error("on_exit", on_exit, EXIT_RULES)
        try:
            random_curve(1, p, torch.Generator().manual_seed(0), max_turn_deg=curve_max_turn_deg)   # checks the value
        except ValueError as exc:
            raise ValueError(f"curve_max_turn_deg: {exc}") from exc
        self.curve_max_turn_deg = float(curve_max_turn_deg)
        if not isinstance(mark_end, (bool, np.bool_)):
            raise ValueError(f"mark_end must be True or False, got {mark_end!r}")
        self.mark_end = bool(mark_end)
        self.success_bonus, self.step_penalty = float(success_bonus), float(step_penalty)
        self.on_exit, self.exit_penalty = on_exit, float(exit_penalty)
        self.num_envs = int(num_envs)
        self.obs_type, self.action_type, self.reward_type = obs_type, action_type, reward
        self.max_steps, self.success_tol = int(max_steps), float(success_tol)
        self.image_size, self.view_size = int(image_size), float(view_size)
        self.sim = Simulator(p, device=device, dtype=dtype, backend=backend)
        self.device, self.dtype = self.sim.device, dtype
        self._named = {name: self.sim.target_shape(name) for name in TARGET_NAMES}
        self.target_spec = self._check_target(target)
        self.action_dim = ACTION_DIMS[action_type]
        self.single_action_space = spaces.Box(0.0, 1.0, (self.action_dim,), np.float32)
        self.single_observation_space = self._make_observation_space()

        n, b = p.n_nodes, self.num_envs
        self.rngs: list[np.random.Generator | None] = [None] * b
        self.pos = torch.zeros(b, n, 2, device=self.device, dtype=dtype)
        self.target = torch.zeros(b, n, 2, device=self.device, dtype=dtype)
        self.steps = torch.zeros(b, dtype=torch.int64, device=self.device)
        self._info = {
            "shape_error": torch.zeros(b, device=self.device, dtype=dtype),
            "orientation_error": torch.zeros(b, device=self.device, dtype=dtype),
            "is_success": torch.zeros(b, dtype=torch.bool, device=self.device),
            "node": torch.full((b,), -1, dtype=torch.int64, device=self.device),
            "substeps": torch.zeros(b, dtype=torch.int64, device=self.device),
        }
        is_image = obs_type in ("image", "image_single")
        self._target_cov = (torch.zeros(b, self.image_size, self.image_size, device=self.device)
                            if is_image else None)   # cached: fixed per episode
        self._target_end = self._target_cov.clone() if is_image and self.mark_end else None
        self.has_reset = False

    # ----------------------------------------------------------------- configuration
    def _check_target(self, spec: Any) -> Any:
        """A family in TARGET_FAMILIES (returned as is) or a fixed target (an (N, 2) tensor). Raises TargetError."""
        if isinstance(spec, str) and spec in TARGET_FAMILIES:
            return spec
        if isinstance(spec, str) and spec in self._named:
            return self._named[spec]
        try:
            return self.sim.target_shape(spec)
        except TargetError as exc:
            raise TargetError(f"bad target {spec if isinstance(spec, (str, Path)) else type(spec).__name__!r}: "
                              f"{exc} (allowed: {list(TARGET_FAMILIES)}, {list(TARGET_NAMES)}, an (N, 2) array or a "
                              f".npy/.yaml path)") from exc

    def _make_observation_space(self) -> spaces.Space:
        # Bounds of a node coordinate [m]: every node is inside the workspace before a step (else the episode has
        # ended) and a step moves the grasped node by at most max_disp, the rest following within the rope length.
        p, n, s = self.params, self.params.n_nodes, self.image_size
        bound = np.float32(max(p.workspace) / 2 + p.length + p.max_disp)
        points = spaces.Box(-bound, bound, (n, 2), np.float32)
        img = spaces.Box(0, 255, (s, s, 3), np.uint8)
        if self.obs_type == "points":
            return spaces.Dict({"node_poses": points, "target_poses": points})
        if self.obs_type == "distance":
            return spaces.Box(-2 * bound, 2 * bound, (n, 2), np.float32)
        if self.obs_type == "image":
            return spaces.Dict({"image": img, "target_image": img})
        return spaces.Dict({"image": img})

    def _mask(self, mask: Any) -> torch.Tensor:
        if mask is None:
            return torch.ones(self.num_envs, dtype=torch.bool)
        m = torch.as_tensor(np.asarray(mask.cpu() if torch.is_tensor(mask) else mask)).to(torch.bool).cpu()
        if m.shape != (self.num_envs,):
            raise ValueError(f"mask must have shape ({self.num_envs},), got {tuple(m.shape)}")
        return m

    # ----------------------------------------------------------------- episode control
    def seed(self, seed: int | Sequence[int | None] | None, mask: Any = None) -> None:
        """Re-seed the per-env generators: an int s gives env i the generator of seed s + i (gymnasium's rule)."""
        idx = self._mask(mask).nonzero().flatten().tolist()
        for i in idx:
            if seed is None:
                self.rngs[i] = seeding.np_random(None)[0]
            elif isinstance(seed, (int, np.integer)):
                self.rngs[i] = seeding.np_random(int(seed) + i)[0]
            else:
                self.rngs[i] = seeding.np_random(None if seed[i] is None else int(seed[i]))[0]

    def reset(self, seed: int | Sequence[int | None] | None = None, options: dict | None = None,
              mask: Any = None) -> tuple[Any, dict[str, torch.Tensor]]:
        """Reset the envs in ``mask`` (default all): new target, random start shape, settle (thesis model.free).

        ``seed``: int s (env i gets s + i), a per-env list, or None (keep each env's generator; a fresh random one
        the first time). ``options={"target": spec}`` changes the target spec (kept for later resets).
        Returns (obs, info) for the whole batch.
        """
        m = self._mask(mask)
        if options and "target" in options:
            self.target_spec = self._check_target(options["target"])
        if seed is not None:
            self.seed(seed, m)
        idx = m.nonzero().flatten().tolist()
        if idx:
            shapes, targets = [], []
            for i in idx:
                if self.rngs[i] is None:
                    self.rngs[i] = seeding.np_random(None)[0]
                rng = self.rngs[i]
                if isinstance(self.target_spec, str) and self.target_spec == "random":
                    targets.append(self._named[TARGET_NAMES[int(rng.integers(len(TARGET_NAMES)))]])
                elif isinstance(self.target_spec, str):                      # "random_curve"
                    curve_gen = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
                    targets.append(random_curve(1, self.params, curve_gen, self.device, self.dtype,
                                                self.curve_max_turn_deg)[0])
                else:
                    targets.append(self.target_spec)
                gen = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
                shapes.append(self.sim.random_shape(1, generator=gen))
            start, settle_info = self.sim.settle(torch.cat(shapes), return_info=True)
            ids = torch.tensor(idx, device=self.device)
            self.pos[ids] = start
            self.target[ids] = torch.stack(targets)
            self.steps[ids] = 0
            self._cache_target(ids)
            self._update_info(ids, start, self.target[ids], torch.full((len(idx),), -1, dtype=torch.int64,
                                                                        device=self.device), settle_info.substeps)
        self.has_reset = True
        return self.observe(), self.info()

    def set_state(self, pos: Any = None, target: Any = None, steps: Any = None) -> None:
        """Overwrite ropes (B, N, 2), targets ((N, 2) or (B, N, 2)) and/or step counters (B,) (tests, planners)."""
        kw = dict(device=self.device, dtype=self.dtype)
        if pos is not None:
            pos = torch.as_tensor(pos, **kw)
            self.sim._check_state("pos", pos)
            if pos.shape[0] != self.num_envs:
                raise ValueError(f"pos must have shape ({self.num_envs}, N, 2), got {tuple(pos.shape)}")
            self.pos = pos.detach().clone()
        if target is not None:
            target = torch.as_tensor(target, **kw)
            self.target = target.detach().expand(self.num_envs, *self.pos.shape[1:]).clone()
        if steps is not None:
            self.steps = torch.as_tensor(steps, dtype=torch.int64, device=self.device).expand(self.num_envs).clone()
        ids = torch.arange(self.num_envs, device=self.device)
        self._cache_target(ids)
        self._update_info(ids, self.pos, self.target, self._info["node"].clone(), self._info["substeps"].clone())
        self.has_reset = True

    def decode(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, A) clipped actions in [0, 1] (sim dtype) -> grasped node (B,) int64 and drag (B, 2) [m]."""
        p, s = self.params, self.params.action_scale
        delta = actions[:, -2:] * (2 * s) - s
        if self.action_type == "node":
            node = torch.round(actions[:, 0] * (p.n_nodes - 1)).to(torch.int64)
        else:
            h = self.view_size / 2
            point = torch.stack([actions[:, 0] * self.view_size - h, h - actions[:, 1] * self.view_size], dim=-1)
            node = (self.pos - point.unsqueeze(1)).norm(dim=-1).argmin(dim=1)
        return node, delta

    def step(self, actions: Any, mask: Any = None) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor,
                                                             dict[str, torch.Tensor]]:
        """Apply (B, A) actions to the envs in ``mask`` (default all) with ONE batched ``Simulator.move``.

        Actions are clipped to [0, 1]; NaN/inf or a wrong shape raise ValueError. Envs outside the mask keep their
        state and get reward 0, terminated = truncated = False. Returns (obs, reward (B,), terminated (B,) bool,
        truncated (B,) bool, info) as tensors on the device; the core never auto-resets.
        """
        if not self.has_reset:
            raise RuntimeError("call reset() before step()")
        a = check_actions(actions, (self.num_envs, self.action_dim))
        a = a.clamp(0.0, 1.0).to(device=self.device, dtype=self.dtype)
        m = self._mask(mask)
        reward = torch.zeros(self.num_envs, device=self.device, dtype=self.dtype)
        terminated = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        truncated = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        idx = m.nonzero().flatten().tolist()
        if idx:
            ids = torch.tensor(idx, device=self.device)
            node, delta = self.decode(a)
            prev, target = self.pos[ids], self.target[ids]
            new, move_info = self.sim.move(prev, node[ids], delta[ids], return_info=True)
            r = compute_reward(self.reward_type, prev, new, target)
            self.pos[ids] = new
            self.steps[ids] += 1
            success = self._update_info(ids, new, target, node[ids], move_info.substeps)
            half = torch.tensor(self.params.workspace, device=self.device, dtype=self.dtype) / 2
            outside = (new.abs() > half).flatten(1).any(1) & ~success
            failed = outside if self.on_exit == "fail" else torch.zeros_like(outside)
            term = success | failed
            trunc = ~term & ((self.steps[ids] >= self.max_steps) | outside)
            r = torch.where(success, torch.full_like(r, self.success_bonus), r - self.step_penalty)
            reward[ids] = torch.where(failed, torch.full_like(r, -self.exit_penalty), r)
            terminated[ids], truncated[ids] = term, trunc
        return self.observe(), reward, terminated, truncated, self.info()

    def _cache_target(self, ids: torch.Tensor) -> None:
        if self._target_cov is not None:
            self._target_cov[ids] = rimage.coverage(self.target[ids].detach(), self.image_size, self.view_size)
        if self._target_end is not None:
            self._target_end[ids] = rimage.end_marker(self.target[ids].detach(), self.image_size, self.view_size)

    def _update_info(self, ids, pos, target, node, substeps) -> torch.Tensor:
        err = shape_error(pos, target)
        success = err < self.success_tol
        self._info["shape_error"][ids] = err.detach()
        self._info["orientation_error"][ids] = orientation_error(pos, target).detach()
        self._info["is_success"][ids] = success
        self._info["node"][ids] = node.to(self.device)
        self._info["substeps"][ids] = substeps.to(self.device)
        return success

    # ----------------------------------------------------------------- observations
    def info(self) -> dict[str, torch.Tensor]:
        """Per-env info tensors (B,): shape_error [m], orientation_error [rad], is_success, node (-1 after a reset),
        substeps (of the last move, or of the settle after a reset)."""
        return {k: v.clone() for k, v in self._info.items()}

    def render_images(self, ropes: torch.Tensor | None, targets: torch.Tensor | None,
                      size: int | None = None) -> torch.Tensor:
        return rimage.render_ropes(None if ropes is None else ropes.detach(),
                                   None if targets is None else targets.detach(),
                                   size=size or self.image_size, view_size=self.view_size)

    def observe(self) -> Any:
        """The current observation of every env: a dict of (B, ...) tensors, or a (B, N, 2) tensor for
        obs_type="distance"."""
        pos, target = self.pos.detach(), self.target.detach()
        if self.obs_type == "points":
            return {"node_poses": pos.to(torch.float32, copy=True), "target_poses": target.to(torch.float32, copy=True)}
        if self.obs_type == "distance":
            return (pos - target).to(torch.float32)
        rope = [(rimage.coverage(pos, self.image_size, self.view_size), rimage.ROPE_COLOR)]
        tgt = [(self._target_cov, rimage.TARGET_COLOR)]
        if self.mark_end:
            rope.append((rimage.end_marker(pos, self.image_size, self.view_size), rimage.ROPE_END_COLOR))
            tgt.append((self._target_end, rimage.TARGET_END_COLOR))
        if self.obs_type == "image":
            return {"image": rimage.compose(rope), "target_image": rimage.compose(tgt)}
        return {"image": rimage.compose(tgt + rope)}

    def render(self, size: int = RENDER_SIZE) -> torch.Tensor:
        """(B, size, size, 3) uint8 pictures of the ropes (red) over their targets (blue), for people."""
        return self.render_images(self.pos, self.target, size)


def to_numpy(x: Any, index: int | None = None) -> Any:
    """Tensor (or dict of tensors) -> numpy, optionally taking batch member ``index``."""
    if isinstance(x, dict):
        return {k: to_numpy(v, index) for k, v in x.items()}
    arr = x.detach().cpu().numpy()
    return arr if index is None else arr[index]


class ShapeControlEnv(gym.Env):
    """``DiffDLO/ShapeControl-v0``: straighten and orient a planar cable by pick-drag-release actions.

    A gymnasium wrapper of ``BatchedShapeControl`` with one rope; see that class for every keyword argument
    (target, obs_type, action_type, reward, max_steps, success_tol, params, image_size, view_size, device, dtype).
    ``render_mode``: None or "rgb_array" (a 256 x 256 RGB picture, rope red over target blue).

    Actions outside [0, 1] are clipped to [0, 1]; NaN/inf actions or a wrong shape raise ValueError.
    ``info``: shape_error [m], orientation_error [rad], is_success, node (grasped node, -1 after reset), substeps.
    ``reset(seed=s, options={"target": spec})``: seeded random start shape + settle; the target spec is kept.
    A diverged simulation raises diffdlo.SimulationError (never a NaN observation).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, render_mode: str | None = None, **kwargs: Any):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise _choice_error("render_mode", render_mode, [None, *self.metadata["render_modes"]])
        self.render_mode = render_mode
        self.core = BatchedShapeControl(num_envs=1, **kwargs)
        self.observation_space = self.core.single_observation_space
        self.action_space = self.core.single_action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict]:
        super().reset(seed=seed)
        self.core.rngs[0] = self.np_random
        obs, info = self.core.reset(options=options)
        return to_numpy(obs, 0), self._info(info)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        a = check_actions(action, (self.core.action_dim,))
        obs, reward, terminated, truncated, info = self.core.step(a.unsqueeze(0))
        return (to_numpy(obs, 0), float(reward[0]), bool(terminated[0]), bool(truncated[0]), self._info(info))

    @staticmethod
    def _info(info: dict[str, torch.Tensor]) -> dict[str, Any]:
        return {"shape_error": float(info["shape_error"][0]),
                "orientation_error": float(info["orientation_error"][0]),
                "is_success": bool(info["is_success"][0]), "node": int(info["node"][0]),
                "substeps": int(info["substeps"][0])}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        return self.core.render()[0].cpu().numpy()
