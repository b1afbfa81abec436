"""The batched shape-control env core (thesis Chapter 2, Algorithms 1-3): ``BatchedShapeControl``.

It holds B ropes in ONE state object (``EnvState``) and does all the work in torch on the
simulator's device: one batched ``Simulator.move`` per step, one batched ``Simulator.settle`` per reset. The task's
rules (targets, action decoding, rewards, episode end, observations) are diffdlo/tasks/task.py's; this file holds the
state and the plumbing. ``ShapeControlEnv`` (gymnasium.Env, ``gymnasium.make("DiffDLO/ShapeControl-v0")``) is the
core with B = 1 plus a numpy conversion; ``ShapeControlVectorEnv`` (diffdlo/envs/vector.py, ``gymnasium.make_vec``)
is the core with B = num_envs. Both wrap the same code, so they cannot disagree.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.utils import seeding

from ..tasks import image as rimage
from ..tasks import routing, task
from ..planar.shapes import TARGET_NAMES, check_finite_nodes, check_link_lengths, check_shape, target_shape
from ..planar.simulator import Simulator
from ..tasks.task import ACTION_DIMS
from .options import EnvOptions, _choice_error, check_actions, env_options
from .state import EnvState

RENDER_SIZE = 256
INFO_KEYS = ("shape_error", "worst_node_error", "orientation_error", "sides_kept", "is_success", "node", "substeps")
AUTORESET_MODES = (None, "next_step", "same_step")


class BatchedShapeControl:
    """B independent shape-control episodes in torch: tensors in, tensors out, on the simulator's device.

    ``BatchedShapeControl(num_envs, options)`` or ``BatchedShapeControl(num_envs, **keywords)``: the task's options
    are one ``EnvOptions`` (diffdlo/envs/options.py; each field's help says what it does), given as such or as its
    field names (target, obs_type, action_type, reward, max_steps, success_tol, success_worst_tol, params,
    image_size, view_size, success_bonus, step_penalty, on_exit, exit_penalty, curve_max_turn_deg, mark_end, start,
    max_episode_steps, action_scale, perception, perception_refine), not both; the shared gymnasium envs take the
    same. ``options`` holds them resolved (the params, the episode length). num_envs: B. device, dtype, backend: of
    the simulator (backend "torch" forces the eager reference path).
    Episode end: diffdlo.tasks.task.step_outcome (Algorithm 2 with the error metric). ``info["is_success"]`` tells a
    success from a failure: ``terminated`` alone does not, under on_exit="fail".
    """

    def __init__(self, num_envs: int = 1, options: EnvOptions | None = None, *, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32, backend: str = "auto", **keywords: Any):
        if not isinstance(num_envs, (int, np.integer)) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.options = o = env_options(options, keywords).resolve()
        self.params = p = o.params
        # the perception reads a rope's order from the end marker: "perceived" pictures always carry it
        self.curve_max_turn_deg, self.mark_end = o.curve_max_turn_deg, o.mark_end or o.obs_type == "perceived"
        self.num_envs = int(num_envs)
        self.obs_type, self.action_type = o.obs_type, o.action_type
        self.image_size, self.view_size = o.image_size, o.view_size
        self.sim = Simulator(p, device=device, dtype=dtype, backend=backend)
        self.device, self.dtype = self.sim.device, dtype
        self.perception = self._load_perception(o.perception, o.perception_refine)
        self._seen_target: torch.Tensor | None = None          # the perceived targets, read once per episode
        self._named = {name: target_shape(name, p, self.device, dtype) for name in TARGET_NAMES}
        self.start = None if o.start is None else self._check_start(o.start)
        self.action_dim = ACTION_DIMS[o.action_type]
        self.single_action_space = spaces.Box(0.0, 1.0, (self.action_dim,), np.float32)
        # a route (target "route" or "route:NAME"): pegs on the board, in the state, the moves and the observations
        self.route = task.is_route(o.target)
        self.max_pegs = o.max_pegs if self.route else 0
        self.single_observation_space = task.observation_space(o.obs_type, p, self.image_size, self.max_pegs)

        n, b, kw = p.n_nodes, self.num_envs, dict(device=self.device, dtype=dtype)
        self._state = EnvState(
            pos=torch.zeros(b, n, 2, **kw), target=torch.zeros(b, n, 2, **kw),
            steps=torch.zeros(b, dtype=torch.int64, device=self.device),
            info={"shape_error": torch.zeros(b, **kw), "worst_node_error": torch.zeros(b, **kw),
                  "orientation_error": torch.zeros(b, **kw),
                  "sides_kept": torch.ones(b, dtype=torch.bool, device=self.device),
                  "is_success": torch.zeros(b, dtype=torch.bool, device=self.device),
                  "node": torch.full((b,), -1, dtype=torch.int64, device=self.device),
                  "substeps": torch.zeros(b, dtype=torch.int64, device=self.device)},
            target_names=[task.CUSTOM] * b, target_spec=task.resolve_target(o.target, p, self.device, dtype),
            rngs=[None] * b, needs_reset=torch.zeros(b, dtype=torch.bool),
            pegs=torch.zeros(b, self.max_pegs, 3, **kw) if self.route else None)
        self._pictures: task.TargetPictures | None = None     # the targets' image layers, drawn once per episode
        self.has_reset = False

    def _load_perception(self, perception: Any, refine: int | None):
        """The perception of obs_type "perceived" (EnvOptions checked that it is given) on the env's device."""
        if self.obs_type != "perceived":
            return None
        from ..perception import Perception, PerceptionError
        if not isinstance(perception, Perception):
            return Perception.load(perception, self.device, refine_iters=refine, image_size=self.image_size,
                                   n_nodes=self.params.n_nodes, view_size=self.view_size)
        if refine is not None:
            perception = Perception(perception.net, perception.rest_length, refine, perception.meta)
        for name, have in (("image_size", self.image_size), ("n_nodes", self.params.n_nodes),
                           ("view_size", self.view_size)):
            if getattr(perception, name) != have:
                raise PerceptionError(f"the perception reads {name}={getattr(perception, name)}, the env has "
                                      f"{name}={have}")
        return perception.to(self.device)

    # ----------------------------------------------------------------- configuration and state
    @property
    def max_steps(self) -> int:
        return self.options.max_steps

    @property
    def success_tol(self) -> float:
        return self.options.success_tol

    @property
    def success_worst_tol(self) -> float | None:
        return self.options.success_worst_tol

    @property
    def reward_type(self) -> str:
        return self.options.reward

    def _check_start(self, start: Any) -> torch.Tensor:
        s = torch.as_tensor(np.load(start) if isinstance(start, (str, Path)) else np.asarray(start, dtype=np.float64))
        check_shape(s.to(torch.float64), self.params, "start shape")
        return s.to(device=self.device, dtype=self.dtype)

    def set_target(self, spec: Any) -> None:
        """Draw the targets of later resets from ``spec`` (any ``target`` argument; a route env takes routes only,
        and another env no route: the observations differ). Raises TargetError."""
        if task.is_route(spec) != self.route:
            raise ValueError(f"target {spec!r}: a {'route' if self.route else 'shape'} env's targets stay "
                             f"{'routes' if self.route else 'shapes'} (its observation space has "
                             f"{'' if self.route else 'no '}pegs); make another env")
        self._state.target_spec = task.resolve_target(spec, self.params, self.device, self.dtype)

    def get_state(self, generators: bool = True) -> EnvState:
        """A copy of the env's state (changing it changes nothing until ``set_state``). ``generators=False``: without
        the per-rope generators (copying them is most of the cost: 3 ms of 16 ropes, 39 ms of 512), for readers of
        ropes, targets and counters; such a copy cannot be written back."""
        return self._state.clone(generators)

    def set_state(self, state: EnvState | None = None, *, pos: Any = None, target: Any = None,
                  steps: Any = None, pegs: Any = None) -> None:
        """Write a state (from ``get_state``), or overwrite only ropes (B, N, 2), targets ((N, 2) or (B, N, 2)),
        step counters (B,) and/or a route's pegs ((K, 3) or (B, K, 3), K = max_pegs, rows of zeros: no peg) of the
        current one; the per-rope figures (info) are recomputed from the ropes, targets and pegs. The env's only way
        in: planners and tests place ropes with it."""
        kw = dict(device=self.device, dtype=self.dtype)
        if state is not None and state.rngs is None:
            raise ValueError("this state was read with get_state(generators=False): it has no generators to write "
                             "back; save one with get_state()")
        s = self._state.clone() if state is None else state.clone()
        b, n = self.num_envs, self.params.n_nodes
        if pos is not None:
            s.pos = torch.as_tensor(pos, **kw).detach().clone()
        if target is not None:
            s.target = torch.as_tensor(target, **kw).detach().expand(b, n, 2).clone()
            s.target_names = [task.CUSTOM] * b
        if steps is not None:
            s.steps = torch.as_tensor(steps, dtype=torch.int64, device=self.device).expand(b).clone()
        if pegs is not None:
            if not self.route:
                raise ValueError("pegs: this env's target is not a route (it has no pegs to overwrite)")
            pegs = torch.as_tensor(pegs, **kw).detach()
            if pegs.shape[-2:] != (self.max_pegs, 3) or not torch.isfinite(pegs).all() or bool((pegs[..., 2] < 0).any()):
                raise ValueError(f"pegs must be finite ({self.max_pegs}, 3) or ({b}, {self.max_pegs}, 3) rows of (x, y, "
                                 f"radius >= 0), got shape {tuple(pegs.shape)}")
            s.pegs = pegs.expand(b, self.max_pegs, 3).clone()
        s.pos, s.target = s.pos.to(**kw), s.target.to(**kw)
        self.sim._check_state("pos", s.pos)
        if target is not None:
            check_finite_nodes(s.target, "target")
            check_link_lengths(s.target, self.params.rest_length, "target")
        if s.pos.shape != (b, n, 2) or s.target.shape != (b, n, 2):
            raise ValueError(f"pos and target must have shape ({b}, {n}, 2), got {tuple(s.pos.shape)} and "
                             f"{tuple(s.target.shape)}")
        s.steps, s.needs_reset = s.steps.to(self.device), s.needs_reset.cpu()
        s.info = {k: v.to(self.device) for k, v in s.info.items()}
        missing = [k for k in INFO_KEYS if k not in s.info]   # a state saved before a figure was reported (an older
        if state is None or missing:                          # checkpoint): that figure now, from its ropes
            metrics = task.task_metrics(s.pos, s.target, self.success_tol, self.success_worst_tol, s.pegs)
            s.info.update(metrics if state is None else {k: v for k, v in metrics.items() if k in missing})
        self._state = s
        self._pictures, self._seen_target = None, None
        self.has_reset = True

    def _mask(self, mask: Any) -> torch.Tensor:
        if mask is None:
            return torch.ones(self.num_envs, dtype=torch.bool)
        m = torch.as_tensor(np.asarray(mask.cpu() if torch.is_tensor(mask) else mask)).to(torch.bool).cpu()
        if m.shape != (self.num_envs,):
            raise ValueError(f"mask must have shape ({self.num_envs},), got {tuple(m.shape)}")
        return m

    # ----------------------------------------------------------------- episode control
    def seed(self, seed: int | Sequence[int | np.random.Generator | None] | None, mask: Any = None) -> None:
        """Re-seed the per-env generators: an int s gives env i the generator of seed s + i (gymnasium's rule); a
        per-env list holds seeds, None (fresh entropy) or generators to draw from (the single env's np_random)."""
        rngs = self._state.rngs
        for i in self._mask(mask).nonzero().flatten().tolist():
            if seed is None:
                rngs[i] = seeding.np_random(None)[0]
            elif isinstance(seed, (int, np.integer)):
                rngs[i] = seeding.np_random(int(seed) + i)[0]
            elif isinstance(seed[i], np.random.Generator):
                rngs[i] = seed[i]
            else:
                rngs[i] = seeding.np_random(None if seed[i] is None else int(seed[i]))[0]

    def reset(self, seed: int | Sequence[int | None] | None = None, options: dict | None = None,
              mask: Any = None) -> tuple[Any, dict[str, torch.Tensor]]:
        """Reset the envs in ``mask`` (default all): new target, random start shape, settle (thesis model.free).

        ``seed``: int s (env i gets s + i), a per-env list, or None (keep each env's generator; a fresh random one
        the first time). ``options={"target": spec}`` changes the target spec (kept for later resets).
        Returns (obs, info) for the whole batch.
        """
        m = self._mask(mask)
        if options and "target" in options:
            self.set_target(options["target"])
        if seed is not None:
            self.seed(seed, m)
        idx = m.nonzero().flatten().tolist()
        if idx:
            self._reset_ropes(idx)
        self.has_reset = True
        return self.observe(), self.info()

    def _reset_ropes(self, idx: list[int]) -> None:
        s = self._state
        shapes, targets, boards = [], [], []
        for i in idx:
            if s.rngs[i] is None:
                s.rngs[i] = seeding.np_random(None)[0]
            rng = s.rngs[i]
            if self.route:
                layout = task.draw_route(s.target_spec, rng, self.params)
                tgt, s.target_names[i] = layout.route.to(self.device, self.dtype), task.target_label(s.target_spec)
                boards.append(routing.padded(layout.pegs, self.max_pegs).to(self.device, self.dtype))
            else:
                tgt, s.target_names[i] = task.draw_target(s.target_spec, rng, self.params, self._named, self.device,
                                                          self.dtype, self.curve_max_turn_deg)
            targets.append(tgt)
            gen = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))   # drawn even for a fixed start
            if self.start is None:
                start = routing.start_across if self.options.route_start == "across" else routing.start_beside
                shapes.append(start(layout, self.params, gen)[None].to(self.device, self.dtype)
                              if self.route else self.sim.random_shape(1, generator=gen))
        ids = torch.tensor(idx, device=self.device)
        pegs = None
        if self.route:
            s.pegs[ids] = torch.stack(boards)
            pegs = s.pegs[ids]
        if self.start is None:
            start, settle_info = self.sim.settle(torch.cat(shapes), return_info=True, pegs=pegs)
            substeps = settle_info.substeps
        else:
            start = self.start.expand(len(idx), *self.start.shape)
            if pegs is not None:
                self.sim._check_pegs(start, pegs)           # a fixed start inside a peg is refused by name
            substeps = torch.zeros(len(idx), dtype=torch.int64)
        s.pos[ids] = start
        s.target[ids] = torch.stack(targets)
        s.steps[ids] = 0
        s.needs_reset[ids.cpu()] = False
        self._update_info(ids, start, s.target[ids], torch.full((len(idx),), -1, dtype=torch.int64), substeps)
        if self._pictures is not None:
            fresh = task.target_pictures(s.target[ids], self.image_size, self.view_size, self.mark_end,
                                         None if s.pegs is None else s.pegs[ids])
            self._pictures.coverage[ids] = fresh.coverage
            if fresh.end is not None:
                self._pictures.end[ids] = fresh.end
            if fresh.pegs is not None:
                self._pictures.pegs[ids] = fresh.pegs
            if self._seen_target is not None:
                pictures = task.observe("image", start, s.target[ids], self.image_size, self.view_size, fresh)
                self._seen_target[ids] = self.perception.read(pictures["target_image"], rope=False,
                                                              pegs=None if s.pegs is None else s.pegs[ids])

    def decode(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, A) clipped actions in [0, 1] (sim dtype) -> grasped node (B,) int64 and drag (B, 2) [m]."""
        return task.decode_action(self.action_type, actions, self._state.pos, self.params, self.view_size)

    def step(self, actions: Any, mask: Any = None, autoreset: str | None = None
             ) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Apply (B, A) actions to the envs in ``mask`` (default all) with ONE batched ``Simulator.move``.

        Actions are clipped to [0, 1]; NaN/inf or a wrong shape raise ValueError. Envs outside the mask keep their
        state and get reward 0, terminated = truncated = False. Returns (obs, reward (B,), terminated (B,) bool,
        truncated (B,) bool, info) as tensors on the device.
        ``autoreset``: None (never reset), "next_step" (gymnasium's default: a rope whose episode ended is reset by
        its NEXT step, which ignores its action and returns the new episode's first observation with reward 0 and
        terminated = truncated = False) or "same_step" (ropes whose episode ends are reset at once: ``obs`` is
        the new episodes' first observation; ``info`` is the step's, with ``info["final_obs"]`` the observation the
        step produced).
        """
        if not self.has_reset:
            raise RuntimeError("call reset() before step()")
        if autoreset not in AUTORESET_MODES:
            raise _choice_error("autoreset", autoreset, AUTORESET_MODES)
        a = check_actions(actions, (self.num_envs, self.action_dim))
        a = a.clamp(0.0, 1.0).to(device=self.device, dtype=self.dtype)
        m = self._mask(mask)
        pending = self._state.needs_reset.clone() if autoreset == "next_step" else torch.zeros_like(m)
        reward = torch.zeros(self.num_envs, device=self.device, dtype=self.dtype)
        terminated = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        truncated = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        idx = (m & ~pending).nonzero().flatten().tolist()
        if idx:
            s, ids = self._state, torch.tensor(idx, device=self.device)
            node, delta = self.decode(a)
            pin = task.decode_action_pin(self.action_type, a, node, self._state.pos, self.params, self.view_size)
            pin = None if pin is None else pin[ids]
            prev, target = s.pos[ids], s.target[ids]
            pegs = None if s.pegs is None else s.pegs[ids]
            new, move_info = self.sim.move(prev, node[ids], delta[ids], None if pegs is None else
                                           pegs, pin, return_info=True)
            s.pos[ids] = new
            s.steps[ids] += 1
            self._update_info(ids, new, target, node[ids], move_info.substeps)
            r, term, trunc, _ = task.step_outcome(self.options, prev, new, target, s.steps[ids], pegs)
            reward[ids], terminated[ids], truncated[ids] = r, term, trunc
        ended = (terminated | truncated).cpu()
        if autoreset == "next_step":
            if bool(pending.any()):
                self._reset_ropes(pending.nonzero().flatten().tolist())
            self._state.needs_reset = ended | (pending & ~m)
            return self.observe(), reward, terminated, truncated, self.info()
        obs, info = self.observe(), self.info()
        if autoreset == "same_step":
            info["final_obs"] = obs                    # the step's observation and info, before any reset
            if bool(ended.any()):
                self._reset_ropes(ended.nonzero().flatten().tolist())
                obs = self.observe()
        return obs, reward, terminated, truncated, info

    def _update_info(self, ids, pos, target, node, substeps) -> None:
        info, pegs = self._state.info, self._state.pegs
        for k, v in task.task_metrics(pos, target, self.success_tol, self.success_worst_tol,
                                      None if pegs is None else pegs[ids]).items():
            info[k][ids] = v
        info["node"][ids] = node.to(self.device)
        info["substeps"][ids] = substeps.to(self.device)

    # ----------------------------------------------------------------- observations
    def info(self) -> dict[str, torch.Tensor]:
        """Per-env info tensors (B,): shape_error [m] (a route's on the board), worst_node_error [m],
        orientation_error [rad], sides_kept (routes only: every peg on the route's side), is_success, node (-1 after
        a reset), substeps (of the last move, or of the settle after a reset)."""
        return {k: v.clone() for k, v in self._state.info.items() if self.route or k != "sides_kept"}

    def render_images(self, ropes: torch.Tensor | None, targets: torch.Tensor | None,
                      size: int | None = None) -> torch.Tensor:
        return rimage.render_ropes(None if ropes is None else ropes.detach(),
                                   None if targets is None else targets.detach(),
                                   size=size or self.image_size, view_size=self.view_size)

    def observe(self) -> Any:
        """The current observation of every env (diffdlo.tasks.task.observe): a dict of (B, ...) tensors, or a (B, N, 2)
        tensor for obs_type="distance"."""
        s = self._state
        if self.obs_type in task.DRAWN_OBS and self._pictures is None:
            self._pictures = task.target_pictures(s.target, self.image_size, self.view_size, self.mark_end, s.pegs)
        if self.obs_type != "perceived":
            return task.observe(self.obs_type, s.pos, s.target, self.image_size, self.view_size, self._pictures,
                                s.pegs)
        # a route's pegs are drawn in both pictures and known (the board's fixtures): the perception reads the rope
        # and the route with them, and the observation carries them exactly, as "points" does
        pictures = task.observe("image", s.pos, s.target, self.image_size, self.view_size, self._pictures)
        if self._seen_target is None:
            self._seen_target = self.perception.read(pictures["target_image"], rope=False, pegs=s.pegs)
        return self.perception.perceive(pictures, target=self._seen_target, pegs=s.pegs)

    def render(self, size: int = RENDER_SIZE) -> torch.Tensor:
        """(B, size, size, 3) uint8 pictures of the ropes (red) over their targets (blue), for people."""
        return self.render_images(self._state.pos, self._state.target, size)
