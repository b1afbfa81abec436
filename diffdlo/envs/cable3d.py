"""``DiffDLO/Cable3D-v0``: a real cable's 3-D chain held at both ends by two grippers, brought to a target shape.

The task's rules are diffdlo/tasks/cable3d.py's (docs/CABLE3D.md); this file holds the state and the plumbing, as
core.py does for the planar task: ``BatchedCable3D`` (B cables, tensors in and out, one batched chain rollout per
step), ``Cable3DEnv`` (gymnasium.Env, B = 1) and ``Cable3DVectorEnv`` (gymnasium's VectorEnv, B = num_envs,
autoreset on the next step). Sub-env i reset with seed s behaves exactly as the single env reset with seed s.
"""
from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ..chain3d import grippers as gr
from ..chain3d.cables import Cable, load_cable
from ..tasks import cable3d as rules
from .vector import vector_info

INFO_KEYS = ("marker_error", "worst_marker_error", "at_rest", "is_success", "frames")


class BatchedCable3D:
    """B episodes of the 3-D two-gripper task on one cable (``cable``: a name of params/cables3d.yaml, a
    ``chain3d.cables.Cable``, or None for the file's default; ``residual``: a diffdlo.chain3d.residual network
    trained on that cable, added to its physics: the stand-in for the real cable). ``move_time``, ``settle_time``
    [s], ``rest_speed`` [m/s]: a move's gripper motion, its settle's cap and rest threshold; ``success_tol``, ``success_worst_tol`` [m]:
    the mean and worst marker error of a success; ``max_steps`` moves an episode. dtype float64 or float32.
    ``target`` "reachable", or "recorded" with ``data`` DEFORM's data_set folder (tasks/cable3d.py's rules).
    ``engine``: "auto" runs the moves on the fused C++ kernel unless a residual is given (grippers.move), "eager"
    on the torch path (the reference; the two agree to rounding)."""

    def __init__(self, num_envs: int = 1, cable: str | Cable | None = None, target: str = "reachable",
                 max_steps: int = 20, move_time: float = 1.0, settle_time: float = 5.0, rest_speed: float = 0.01,
                 success_tol: float = 0.01, success_worst_tol: float = 0.02, success_bonus: float = 20.0,
                 residual: Any = None, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64,
                 engine: str = "auto", data: Any = None):
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if target not in rules.TARGETS:
            raise ValueError(f"target must be one of {list(rules.TARGETS)}, got {target!r}")
        if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
        for name, value in (("rest_speed", rest_speed), ("success_tol", success_tol),
                            ("success_worst_tol", success_worst_tol), ("success_bonus", success_bonus)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        if engine not in gr.ENGINES:
            raise ValueError(f"engine must be one of {gr.ENGINES}, got {engine!r}")
        self.engine = engine
        self.cable = cable if isinstance(cable, Cable) else load_cable(cable)
        if (target == "recorded") != (data is not None):
            raise ValueError(f"data (DEFORM's data_set folder) goes with target='recorded' and only with it, got "
                             f"target={target!r} and data={data!r}")
        self.recorded = rules.recorded_targets(data, self.cable) if data is not None else None
        if residual is not None:            # the stand-in for the real cable: the fitted physics + its residual
            config = getattr(residual, "config", None)
            if config is None or config.n != self.cable.n_nodes or tuple(config.held) != self.cable.held:
                raise ValueError(f"residual: a diffdlo.chain3d.residual network for {self.cable.n_nodes} markers held "
                                 f"at {self.cable.held} (cable {self.cable.name}), got "
                                 f"{'none' if config is None else (config.n, tuple(config.held))}")
        self.residual = residual
        self.num_envs, self.target_kind, self.max_steps = num_envs, target, max_steps
        self.move_frames = rules.frames_of(move_time, "move_time")
        self.settle_frames = rules.frames_of(settle_time, "settle_time")
        self.rest_speed, self.success_tol, self.success_worst_tol = rest_speed, success_tol, success_worst_tol
        self.success_bonus = float(success_bonus)
        self.device, self.dtype = torch.device(device), dtype
        n = self.cable.n_nodes
        self.single_observation_space = rules.observation_space(n)
        self.single_action_space = rules.action_space()
        self.action_dim = rules.ACTION_DIM
        self.generators = [torch.Generator().manual_seed(i) for i in range(num_envs)]
        zeros = torch.zeros(num_envs, n, 3, dtype=dtype, device=self.device)
        self.x, self.target = zeros.clone(), zeros.clone()
        self.steps = torch.zeros(num_envs, dtype=torch.int64, device=self.device)
        self.info_state = {k: torch.zeros(num_envs, device=self.device) for k in INFO_KEYS}

    # ---------------------------------------------------------------- physics with the env's settings
    def move(self, x: torch.Tensor, goal: gr.Grippers, settle_frames: int | None = None) -> gr.MoveResult:
        return gr.move(x, None, goal, self.cable, move_frames=self.move_frames, rest_speed=self.rest_speed,
                       check_frames=10, settle_frames=settle_frames or self.settle_frames, accel=self.residual,
                       engine=self.engine)

    def settle(self, x: torch.Tensor) -> gr.MoveResult:
        return gr.settle(x, None, gr.poses_of(x), self.cable, rest_speed=self.rest_speed, check_frames=10,
                         settle_frames=self.settle_frames, accel=self.residual, engine=self.engine)

    # ---------------------------------------------------------------- episodes
    def seed(self, seeds: list[Any]) -> None:
        """Re-seed each env's generator: ints, or numpy Generators (gymnasium's np_random) to draw a seed from."""
        for i, s in enumerate(seeds):
            if s is None:
                continue
            value = int(s.integers(0, 2 ** 62)) if isinstance(s, np.random.Generator) else int(s)
            self.generators[i] = torch.Generator().manual_seed(value)

    def reset(self, mask: np.ndarray | None = None) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """New episodes for the masked envs (all by default): a start hung and settled between random gripper
        poses, and its target."""
        ids = [i for i in range(self.num_envs) if mask is None or bool(mask[i])]
        if ids:
            with torch.no_grad():
                if self.recorded is not None:           # a frame of a recording as the start's grippers, another
                    drawn = [self.recorded.draw(self.generators[i]) for i in ids]
                    poses = [gr.poses_of(start[None].to(self.dtype)) for start, _ in drawn]
                else:
                    poses = [rules.random_grippers(1, self.cable, self.generators[i], self.dtype) for i in ids]
                start = gr.Grippers(torch.cat([p.pos for p in poses]).to(self.device),
                                    torch.cat([p.dirs for p in poses]).to(self.device))
                settled = self.settle(rules.hang(start, self.cable))
                x, target = settled.x, settled.x
                if self.recorded is not None:
                    target = torch.stack([t for _, t in drawn]).to(x)
                for _ in range(rules.REACH_MOVES if self.recorded is None else 0):
                    a = torch.cat([torch.rand(1, rules.ACTION_DIM, generator=self.generators[i],
                                              dtype=torch.float64) * 2 - 1 for i in ids]).to(x)
                    target = self.move(target, rules.decode_action(a, gr.poses_of(target), self.cable)).x
            index = torch.tensor(ids, device=self.device)
            self.x[index], self.target[index] = x, target
            self.steps[index] = 0
            metrics = self._metrics(x, settled.settled, target=target)
            for k in INFO_KEYS:
                self.info_state[k][index] = metrics[k].to(self.info_state[k])
        return self.observe(), self.info()

    def step(self, actions: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor,
                                                   dict[str, torch.Tensor]]:
        a = rules.check_action(torch.as_tensor(actions, dtype=self.dtype, device=self.device), self.num_envs)
        prev = self.x
        goal = rules.decode_action(a, gr.poses_of(prev), self.cable)
        with torch.no_grad():
            out = self.move(prev, goal)
        self.x = out.x
        self.steps = self.steps + 1
        metrics = self._metrics(out.x, out.settled, out.frames)
        self.info_state = metrics
        success = metrics["is_success"].bool()
        reward = torch.where(success, torch.full((self.num_envs,), self.success_bonus, device=self.device),
                             rules.reward(prev, out.x, self.target).to(torch.float32))
        truncated = ~success & (self.steps >= self.max_steps)
        return self.observe(), reward, success, truncated, self.info()

    def _metrics(self, x: torch.Tensor, at_rest: torch.Tensor, frames: torch.Tensor | None = None,
                 target: torch.Tensor | None = None):
        target = self.target if target is None else target
        errors = rules.marker_errors(x, target)
        ok = rules.success(x, target, at_rest, self.success_tol, self.success_worst_tol)
        return {"marker_error": errors.mean(-1).float(), "worst_marker_error": errors.amax(-1).float(),
                "at_rest": at_rest.float(), "is_success": ok.float(),
                "frames": (torch.zeros_like(at_rest, dtype=torch.float32) if frames is None else frames.float())}

    def observe(self) -> dict[str, torch.Tensor]:
        return {k: v.to(torch.float32) for k, v in rules.observe(self.x, self.target).items()}

    def info(self) -> dict[str, torch.Tensor]:
        out = {k: v.clone() for k, v in self.info_state.items()}
        out["at_rest"], out["is_success"] = out["at_rest"].bool(), out["is_success"].bool()
        out["frames"] = out["frames"].to(torch.int64)
        return out


def _numpy(obs: dict[str, torch.Tensor], index: int | None = None) -> dict[str, np.ndarray]:
    return {k: (v[index] if index is not None else v).cpu().numpy() for k, v in obs.items()}


class Cable3DEnv(gym.Env):
    """``DiffDLO/Cable3D-v0`` with one cable; keyword arguments as ``BatchedCable3D``'s. ``info``: marker_error,
    worst_marker_error [m], at_rest, is_success, frames (simulated in the move)."""

    metadata = {"render_modes": []}

    def __init__(self, **kwargs: Any):
        self.core = BatchedCable3D(num_envs=1, **kwargs)
        self.observation_space = self.core.single_observation_space
        self.action_space = self.core.single_action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        self.core.seed([self.np_random])
        obs, info = self.core.reset()
        return _numpy(obs, 0), self._info(info)

    def step(self, action: Any) -> tuple[dict, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.core.step(torch.as_tensor(np.asarray(action)).reshape(1, -1))
        return _numpy(obs, 0), float(reward[0]), bool(terminated[0]), bool(truncated[0]), self._info(info)

    @staticmethod
    def _info(info: dict[str, torch.Tensor]) -> dict[str, Any]:
        return {k: v[0].item() for k, v in info.items()}


class Cable3DVectorEnv(VectorEnv):
    """num_envs episodes on one ``BatchedCable3D``: ONE batched chain rollout per step. After a sub-env ends, its
    next step ignores its action, resets it and returns its first observation with reward 0 (NEXT_STEP)."""

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, **kwargs: Any):
        kwargs.pop("max_episode_steps", None)
        self.core = BatchedCable3D(num_envs=num_envs, **kwargs)
        self.num_envs = num_envs
        self.single_observation_space = self.core.single_observation_space
        self.single_action_space = self.core.single_action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._ended = np.zeros(num_envs, dtype=bool)

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        super().reset(seed=seed if isinstance(seed, (int, np.integer)) else None)
        if seed is not None:            # sub-env i seeded s draws as the single env reset(seed=s) does
            seeds = [seed + i for i in range(self.num_envs)] if isinstance(seed, (int, np.integer)) else list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed must be an int, None or a list of {self.num_envs} seeds, got {seed!r}")
            self.core.seed([None if s is None else seeding.np_random(int(s))[0] for s in seeds])
        self._ended[:] = False
        obs, info = self.core.reset()
        return _numpy(obs), self._info(info)

    def step(self, actions: Any):
        a = torch.as_tensor(np.asarray(actions))
        ended = self._ended.copy()
        obs, reward, terminated, truncated, info = self.core.step(a)
        if ended.any():                                      # last step ended them: this one resets them instead
            obs, info = self.core.reset(mask=ended)
            reward = torch.where(torch.as_tensor(ended), torch.zeros_like(reward), reward)
            terminated = terminated & ~torch.as_tensor(ended)
            truncated = truncated & ~torch.as_tensor(ended)
        terminated, truncated = terminated.cpu().numpy(), truncated.cpu().numpy()
        self._ended = terminated | truncated
        return _numpy(obs), reward.cpu().numpy().astype(np.float64), terminated, truncated, self._info(info)

    def _info(self, info: dict[str, torch.Tensor]) -> dict[str, Any]:
        return vector_info(info, self.num_envs)
