"""Native gymnasium VectorEnv for DiffDLO/ShapeControl-v0: B ropes stepped by ONE batched simulator call.

``gymnasium.make_vec("DiffDLO/ShapeControl-v0", num_envs=B, autoreset_mode=..., max_episode_steps=..., **kwargs)``
builds this class (registered as the ``vector_entry_point``). Sub-env i reset with seed s behaves exactly like a
single ``ShapeControlEnv`` reset with seed s + i.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from .core import BatchedShapeControl
from .options import EnvOptions, _choice_error, check_actions
from .shape_control import to_numpy

SUPPORTED_AUTORESET_MODES = (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP)
# The core's autoreset argument for each gymnasium mode.
CORE_AUTORESET = {AutoresetMode.NEXT_STEP: "next_step", AutoresetMode.SAME_STEP: "same_step"}


def resolve_autoreset_mode(mode: Any) -> AutoresetMode:
    """An AutoresetMode or its value ("NextStep", "SameStep"); DISABLED and anything else raise ValueError."""
    try:
        resolved = mode if isinstance(mode, AutoresetMode) else AutoresetMode(mode)
    except (ValueError, TypeError):
        resolved = None
    if resolved not in SUPPORTED_AUTORESET_MODES:
        allowed = [f"AutoresetMode.{m.name} ({m.value!r})" for m in SUPPORTED_AUTORESET_MODES]
        raise ValueError(f"unsupported autoreset_mode {mode!r}: use one of {allowed}")
    return resolved


def with_time_limit(options: EnvOptions | None, keywords: dict[str, Any]) -> EnvOptions | None:
    """``make_vec`` passes gymnasium's ``max_episode_steps`` (the spec's 100 unless given) beside any ``options``: an
    episode then ends at the nearer of the two limits, as under ``gymnasium.make``'s TimeLimit."""
    if options is None or "max_episode_steps" not in keywords:
        return options
    limit, own = keywords.pop("max_episode_steps"), options.max_episode_steps
    nearer = limit if own is None or not isinstance(limit, int) or limit < 1 else min(own, limit)
    return dataclasses.replace(options, max_episode_steps=nearer)


def vector_info(info: dict[str, torch.Tensor], num_envs: int) -> dict[str, Any]:
    """A core's (num_envs,) tensors as a vector env's info: numpy arrays, each with its ``_key`` mask (all True:
    every sub-env reports every step)."""
    out: dict[str, Any] = {}
    for key, value in info.items():
        out[key] = value.cpu().numpy()
        out[f"_{key}"] = np.ones(num_envs, dtype=bool)
    return out


class ShapeControlVectorEnv(VectorEnv):
    """num_envs shape-control episodes on one ``BatchedShapeControl`` (the same ``options`` or keyword arguments as
    the single env).

    Actions (num_envs, A) outside [0, 1] are clipped; NaN/inf or a wrong shape raise ValueError. ``info`` holds
    numpy arrays (num_envs,) for shape_error, worst_node_error, orientation_error, is_success, node, substeps, each
    with its ``_key`` mask (all True: every sub-env reports every step). ``options={"reset_mask": mask}`` resets
    only the masked sub-envs. ``render()`` (render_mode="rgb_array") returns a tuple of 256 x 256 RGB pictures.
    The torch-native core is ``self.core``.

    ``autoreset_mode`` (declared in ``self.metadata["autoreset_mode"]``), laid out as gymnasium's SyncVectorEnv:
      ``AutoresetMode.NEXT_STEP`` (default): after a sub-env ends, its next ``step`` ignores its action, resets it
        and returns the first observation of the new episode with reward 0 and terminated = truncated = False.
      ``AutoresetMode.SAME_STEP``: a sub-env that ends is reset in the same ``step``: the returned observation and
        ``info`` are the new episode's first (its reset's), and ``info["final_obs"]`` (an object array (num_envs,)
        holding each ended sub-env's own observation, None elsewhere) and ``info["final_info"]`` (a dict of
        (num_envs,) arrays of the ending step's info, each with its ``_key`` mask) are the ending step's;
        ``info["_final_obs"]`` and ``info["_final_info"]`` mark the ended sub-envs. Both keys are absent when none
        ended.
      ``AutoresetMode.DISABLED`` is not supported.
    ``max_episode_steps`` (``make_vec`` passes the registered spec's, 100, unless given): episodes are truncated
    after min(max_steps, max_episode_steps) moves, as ``gymnasium.make``'s TimeLimit over the single env does.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, render_mode: str | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, options: EnvOptions | None = None,
                 **kwargs: Any):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise _choice_error("render_mode", render_mode, [None, *self.metadata["render_modes"]])
        self.autoreset_mode = resolve_autoreset_mode(autoreset_mode)
        self.metadata = {**type(self).metadata, "autoreset_mode": self.autoreset_mode}
        self.render_mode = render_mode
        options = with_time_limit(options, kwargs)             # takes max_episode_steps out of kwargs
        self.core = BatchedShapeControl(num_envs, options, **kwargs)
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
        obs, reward, terminated, truncated, info = self.core.step(a, autoreset=CORE_AUTORESET[self.autoreset_mode])
        terminated, truncated = terminated.cpu().numpy(), truncated.cpu().numpy()
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            final_obs = info.pop("final_obs")
            vector_info = self._info(self.core.info())           # the new episodes' first info where reset
            ended = terminated | truncated
            if ended.any():
                vector_info.update(self._final_entries(final_obs, info, ended))
        else:
            vector_info = self._info(info)
        return to_numpy(obs), reward.cpu().numpy().astype(np.float64), terminated, truncated, vector_info

    def _info(self, info: dict[str, torch.Tensor]) -> dict[str, Any]:
        return vector_info(info, self.num_envs)

    def _final_entries(self, final_obs: Any, step_info: dict[str, torch.Tensor], ended: np.ndarray) -> dict[str, Any]:
        """SyncVectorEnv's SAME_STEP entries: final_obs, final_info and their masks, for the ended sub-envs only."""
        obs = to_numpy(final_obs)
        per_env_obs = np.full(self.num_envs, None, dtype=object)
        final_info: dict[str, Any] = {}
        for i in np.flatnonzero(ended):
            per_env_obs[i] = {k: v[i] for k, v in obs.items()} if isinstance(obs, dict) else obs[i]
        for key, value in step_info.items():
            values = value.cpu().numpy()
            final_info[key] = np.where(ended, values, np.zeros_like(values))
            final_info[f"_{key}"] = ended.copy()
        return {"final_obs": per_env_obs, "_final_obs": ended.copy(),
                "final_info": final_info, "_final_info": ended.copy()}

    def render(self) -> tuple[np.ndarray, ...] | None:
        if self.render_mode != "rgb_array":
            return None
        return tuple(self.core.render().cpu().numpy())
