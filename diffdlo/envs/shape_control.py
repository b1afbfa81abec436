"""The gymnasium single env ``DiffDLO/ShapeControl-v0``: the batched core (diffdlo/envs/core.py) with one rope."""
from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from .core import BatchedShapeControl
from .options import _choice_error, check_actions


def to_numpy(x: Any, index: int | None = None) -> Any:
    """Tensor (or dict of tensors) -> numpy, optionally taking batch member ``index``."""
    if isinstance(x, dict):
        return {k: to_numpy(v, index) for k, v in x.items()}
    arr = x.detach().cpu().numpy()
    return arr if index is None else arr[index]


class ShapeControlEnv(gym.Env):
    """``DiffDLO/ShapeControl-v0``: straighten and orient a planar cable by pick-drag-release actions.

    A gymnasium wrapper of ``BatchedShapeControl`` with one rope: the task's options as ``options=EnvOptions(...)``
    or as its keyword arguments (target, obs_type, action_type, reward, max_steps, ...: ``diffdlo.envs.EnvOptions``),
    plus the simulator's device, dtype and backend.
    ``render_mode``: None or "rgb_array" (a 256 x 256 RGB picture, rope red over target blue).

    Actions outside [0, 1] are clipped to [0, 1]; NaN/inf actions or a wrong shape raise ValueError.
    ``info``: shape_error [m] (for a route: on the board), worst_node_error [m], orientation_error [rad],
    sides_kept (routes only: every peg on the route's side), is_success, node (grasped node, -1
    after reset), substeps.
    ``reset(seed=s, options={"target": spec})``: seeded random start shape + settle; the target spec is kept.
    A diverged simulation raises diffdlo.SimulationError (never a NaN observation).

    Episode length under ``gymnasium.make``: the registered spec has max_episode_steps = 100 (the params' default
    max_steps), so ``make`` wraps the env in gymnasium's TimeLimit, which truncates at the same step as the env's
    own truncation by default (both after 100 moves) and so never fights it. An episode lasts min(max_steps,
    max_episode_steps) moves: ``make(..., max_steps=50)`` and ``make(..., max_episode_steps=50)`` both end after 50;
    for episodes longer than 100 pass both (``max_steps=200, max_episode_steps=200``) or ``max_episode_steps=-1``
    (no TimeLimit). ``make_vec`` applies the same rule (``ShapeControlVectorEnv``). Built directly, the env
    takes ``max_episode_steps`` as well, with the same meaning.
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
        self.core.seed([self.np_random])          # gymnasium's seeding rule; the core draws from this generator
        obs, info = self.core.reset(options=options)
        return to_numpy(obs, 0), self._info(info)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        a = check_actions(action, (self.core.action_dim,))
        obs, reward, terminated, truncated, info = self.core.step(a.unsqueeze(0))
        return (to_numpy(obs, 0), float(reward[0]), bool(terminated[0]), bool(truncated[0]), self._info(info))

    def _info(self, info: dict[str, torch.Tensor]) -> dict[str, Any]:
        out = {"shape_error": float(info["shape_error"][0]), "worst_node_error": float(info["worst_node_error"][0]),
               "orientation_error": float(info["orientation_error"][0]),
               "is_success": bool(info["is_success"][0]), "node": int(info["node"][0]),
               "substeps": int(info["substeps"][0])}
        if self.core.route:                          # a route: every peg on the route's side (part of success)
            out["sides_kept"] = bool(info["sides_kept"][0])
        return out

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        return self.core.render()[0].cpu().numpy()
