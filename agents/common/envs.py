"""The learners' env: ``BatchedShapeControl`` with same-step autoreset, episode returns, devices and checkpoints."""
from __future__ import annotations

from typing import Any

import torch

from agents.common.config import RunOptions, TaskOptions
from diffdlo.envs import BatchedShapeControl, EnvState
from diffdlo.planar.params import CableParams


class TrainEnv:
    """``BatchedShapeControl`` (tensors end to end) stepped with the core's same-step autoreset, plus episode
    bookkeeping and device placement.

    ``step(actions)`` steps every rope with ONE batched call; the ropes whose episode ended are reset in the same
    call. It returns (obs, reward, terminated, truncated, info, final_obs): ``obs`` is what the policy acts on next
    (the first observation of a new episode where one ended) and ``final_obs`` the observation the step produced
    (the true last observation of an ended episode, used by bootstraps). No step is wasted, unlike gymnasium's
    NEXT_STEP autoreset. ``info`` adds ep_return and ep_length (B,) of the episodes so far (of the ended ones where
    one ended). ``device``: where the learner wants observations, rewards and flags (default: the simulator's
    device); actions are moved to the simulator's device, so the rope can be simulated on the CPU (fused kernel)
    while the networks learn on a GPU, as SB3 does.
    """

    def __init__(self, core: BatchedShapeControl, device: str | torch.device | None = None):
        self.core, self.num_envs = core, core.num_envs
        self.device = core.device if device is None else torch.device(device)
        self.ep_return = torch.zeros(self.num_envs, dtype=torch.float64)
        self.ep_length = torch.zeros(self.num_envs, dtype=torch.int64)

    def reset(self, seed: int | None = None, mask: torch.Tensor | None = None) -> Any:
        m = torch.ones(self.num_envs, dtype=torch.bool) if mask is None else mask.cpu()
        self.core.reset(seed=seed, mask=m)
        self.ep_return[m], self.ep_length[m] = 0.0, 0
        return self.observe()

    def to_learner(self, x: Any) -> Any:
        """A tensor or a dict of tensors on the learner's device."""
        if isinstance(x, dict):
            return {k: v.to(self.device) for k, v in x.items()}
        return x.to(self.device)

    def observe(self) -> Any:
        return self.to_learner(self.core.observe())

    def step(self, actions: torch.Tensor, mask: torch.Tensor | None = None):
        obs, reward, term, trunc, info = self.core.step(actions.to(self.core.device), mask=mask,
                                                        autoreset="same_step")
        final_obs = info.pop("final_obs")
        active = torch.ones(self.num_envs, dtype=torch.bool) if mask is None else mask.cpu()
        self.ep_return += reward.double().cpu() * active      # bookkeeping from the simulator's tensors
        self.ep_length += active.long()
        done = (term | trunc).cpu()
        info = dict(info, ep_return=self.ep_return.clone(), ep_length=self.ep_length.clone())
        self.ep_return[done], self.ep_length[done] = 0.0, 0
        return tuple(self.to_learner(x) for x in (obs, reward, term, trunc)) + (info, self.to_learner(final_obs))

    def state_dict(self) -> dict[str, Any]:
        return {**self.core.get_state().to_dict(), "ep_return": self.ep_return.clone(),
                "ep_length": self.ep_length.clone()}

    def load_state_dict(self, s: dict[str, Any]) -> None:
        self.core.set_state(EnvState.from_dict(s))
        self.ep_return, self.ep_length = s["ep_return"].clone(), s["ep_length"].clone()


def make_env(task: TaskOptions, run: RunOptions, params: CableParams, num_envs: int) -> TrainEnv:
    """The training/evaluation env of a run: the task's options on the run's devices, with its resolved params."""
    core = BatchedShapeControl(num_envs, task.env_options(params), device=run.env_device or run.device)
    return TrainEnv(core, device=run.device)


class EpisodeTracker:
    """Which ropes of an env started a new episode, or moved, since the last call: read from the env's step
    counters (0 after a reset). A planner resets a new rope's warm start and plans only for ropes that moved (in an
    evaluation wave a finished rope stays where it ended and keeps its last action). Used by the world models' planners
    (``agents.models.ensemble.ModelPlanner``, ``agents.models.rssm.LatentPlanner``)."""

    def __init__(self, core):
        self.core = core
        self.last_steps = torch.full((core.num_envs,), -1, dtype=torch.int64)

    def update(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(new (B,) bool, moved (B,) bool); a new rope counts as moved."""
        steps = self.core.get_state(generators=False).steps.cpu().long()
        new = steps == 0
        moved = (steps != self.last_steps) | new
        self.last_steps = steps.clone()
        return new, moved
