"""The batched env's arguments, checked (each error names the bad value and what is allowed) and resolved once."""
from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from .. import task
from ..params import CableParams, load_params
from ..rewards import REWARDS
from ..shapes import random_curve
from ..task import ACTION_TYPES, EXIT_RULES, OBS_TYPES


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


def _is_positive_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1


def episode_length(max_steps: int, max_episode_steps: int | None) -> int:
    """The moves an episode may last: ``max_steps``, cut to gymnasium's ``max_episode_steps`` when given. This is
    what ``gymnasium.make`` does too (the env truncates at max_steps, its TimeLimit at max_episode_steps), so
    ``make`` and ``make_vec`` end episodes at the same step for the same arguments."""
    if max_episode_steps is None:
        return max_steps
    if not _is_positive_int(max_episode_steps):
        raise ValueError(f"max_episode_steps must be a positive integer or None, got {max_episode_steps!r}")
    return min(max_steps, int(max_episode_steps))


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


def with_action_scale(p: CableParams, action_scale: Any) -> CableParams:
    if action_scale is None:
        return p
    if (isinstance(action_scale, bool) or not isinstance(action_scale, (int, float, np.floating, np.integer))
            or not np.isfinite(action_scale) or not action_scale > 0):
        raise ValueError(f"action_scale must be a positive number [m], got {action_scale!r}")
    return dataclasses.replace(p, action_scale=float(action_scale))


def checked_options(num_envs: Any, obs_type: Any, action_type: Any, reward: Any, max_steps: Any,
                    success_tol: Any, params: Any, image_size: Any, view_size: Any, success_bonus: Any,
                    step_penalty: Any, on_exit: Any, exit_penalty: Any, curve_max_turn_deg: Any, mark_end: Any,
                    max_episode_steps: Any, action_scale: Any) -> tuple[CableParams, task.EpisodeRules]:
    """Check every env argument (a ValueError names the bad one) and resolve the params once: returns the params
    (with action_scale applied) and the episode rules."""
    if not isinstance(num_envs, (int, np.integer)) or isinstance(num_envs, bool) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
    if not isinstance(obs_type, str) or obs_type not in OBS_TYPES:
        raise _choice_error("obs_type", obs_type, OBS_TYPES)
    if not isinstance(action_type, str) or action_type not in ACTION_TYPES:
        raise _choice_error("action_type", action_type, ACTION_TYPES)
    if not isinstance(reward, str) or reward not in REWARDS:
        raise _choice_error("reward", reward, REWARDS)
    p = with_action_scale(resolve_params(params), action_scale)
    max_steps_given = max_steps is not None
    if max_steps is None:
        max_steps = p.max_episode_steps
    if not _is_positive_int(max_steps):
        raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
    limit = episode_length(int(max_steps), max_episode_steps)
    if max_steps_given and limit < max_steps:
        warnings.warn(f"episodes end after max_episode_steps={max_episode_steps} moves, not max_steps={max_steps} "
                      f"(gymnasium's time limit; the registered spec's is 100): pass "
                      f"max_episode_steps={max_steps} for longer episodes", stacklevel=2)
    max_steps = limit
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
    if not isinstance(mark_end, (bool, np.bool_)):
        raise ValueError(f"mark_end must be True or False, got {mark_end!r}")
    rules = task.EpisodeRules(reward, float(success_tol), int(max_steps), float(success_bonus),
                              float(step_penalty), on_exit, float(exit_penalty), tuple(p.workspace))
    return p, rules
