"""Native gymnasium VectorEnv for DiffDLO/ShapeControl-v0: B ropes stepped by ONE batched simulator call.

``gymnasium.make_vec("DiffDLO/ShapeControl-v0", num_envs=B, **kwargs)`` builds this class (registered as the
``vector_entry_point``). Autoreset mode: ``AutoresetMode.NEXT_STEP`` (gymnasium's default, same as SyncVectorEnv):
after a sub-env ends, its next ``step`` ignores its action, resets it and returns the first observation of the new
episode with reward 0 and terminated = truncated = False (the core's ``step(..., autoreset="next_step")``). Sub-env i
reset with seed s behaves exactly like a single ``ShapeControlEnv`` reset with seed s + i.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from .core import BatchedShapeControl, _choice_error, check_actions
from .shape_control import to_numpy


class ShapeControlVectorEnv(VectorEnv):
    """num_envs shape-control episodes on one ``BatchedShapeControl`` (same keyword arguments as the single env).

    Actions (num_envs, A) outside [0, 1] are clipped; NaN/inf or a wrong shape raise ValueError. ``info`` holds
    numpy arrays (num_envs,) for shape_error, orientation_error, is_success, node, substeps, each with its
    ``_key`` mask (all True: every sub-env reports every step). ``options={"reset_mask": mask}`` resets only the
    masked sub-envs. ``render()`` (render_mode="rgb_array") returns a tuple of 256 x 256 RGB pictures.
    The torch-native core is ``self.core``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, render_mode: str | None = None, **kwargs: Any):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise _choice_error("render_mode", render_mode, [None, *self.metadata["render_modes"]])
        self.render_mode = render_mode
        self.core = BatchedShapeControl(num_envs=num_envs, **kwargs)
        self.num_envs = self.core.num_envs
        self.single_observation_space = self.core.single_observation_space
        self.single_action_space = self.core.single_action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed if isinstance(seed, (int, np.integer)) else None)
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        mask_np = np.ones(self.num_envs, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        if seed is not None and not isinstance(seed, (int, np.integer)) and len(seed) != self.num_envs:
            raise ValueError(f"seed must be an int, None or a list of {self.num_envs} seeds, got {seed!r}")
        obs, info = self.core.reset(seed=seed, options=options, mask=mask_np)
        return to_numpy(obs), self._info(info)

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        a = check_actions(actions, (self.num_envs, self.core.action_dim))
        obs, reward, terminated, truncated, info = self.core.step(a, autoreset="next_step")
        return (to_numpy(obs), reward.cpu().numpy().astype(np.float64), terminated.cpu().numpy(),
                truncated.cpu().numpy(), self._info(info))

    def _info(self, info: dict[str, torch.Tensor]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in info.items():
            out[key] = value.cpu().numpy()
            out[f"_{key}"] = np.ones(self.num_envs, dtype=bool)
        return out

    def render(self) -> tuple[np.ndarray, ...] | None:
        if self.render_mode != "rgb_array":
            return None
        return tuple(self.core.render().cpu().numpy())
