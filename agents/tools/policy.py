"""A trained policy from a run's folder: ``load_policy(RUN_DIR)`` rebuilds the learner's networks from
``RUN_DIR/checkpoint.pt`` exactly as its ``train`` built them, loads their weights, and acts as the learner's own
evaluation does.

    policy = load_policy("runs/sac")
    env = gym.make("DiffDLO/ShapeControl-v0", **policy.env_kwargs())    # the run's task, one rope
    obs, _ = env.reset(seed=0)
    policy.reset()                                                        # a new episode (PlaNet's planner)
    obs, reward, terminated, truncated, info = env.step(policy(obs))     # one observation -> one action

    env = policy.make_env()                                               # the run's evaluation env (batched)
    result = evaluate(policy.batched(env), env, 20, seed=policy.config.run.eval_seed)

SAC, PPO and APG act from the observation alone: their actions are the network's deterministic ones (SAC: the argmax
node and the mean drag, or the squashed Gaussian's mean; PPO: the distribution's mode; APG: its node rule's node and
the mean drag). PlaNet acts by planning through its learned model with CEM, and its planner keeps per-rope state
(warm starts, the RSSM's belief) read from the env it is bound to: ``batched(env)`` binds a fresh planner to that
env, and the one-observation form binds one to a private one-rope env that only counts the moves since ``reset()``
(and takes the target from the observation). Its CEM generators start from the run's
``eval_seed``, as the run's evaluation planner did.
"""
from __future__ import annotations

import dataclasses
import importlib
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from agents.common import config as config_lib
from agents.common.checkpoints import CHECKPOINT, load_checkpoint, load_weights
from agents.common.envs import TrainEnv, make_env
from diffdlo.envs import BatchedShapeControl, EnvOptions

# algo -> (its module, its config class, the checkpoint part holding the acting network's weights)
LEARNERS = {"sac": ("agents.sac", "SACConfig", "actor"),
            "ppo": ("agents.ppo", "PPOConfig", "agent"),
            "planet": ("agents.planet", "PlaNetConfig", "model"),
            "apg": ("agents.apg", "APGConfig", "actor"),
            "distill": ("agents.distill", "DistillConfig", "agent")}

BatchedPolicy = Callable[[Any, bool], torch.Tensor]


# ====================================================================== the checkpoint, checked
def checkpoint_path(run_dir: Path | str) -> Path:
    """A run folder's checkpoint file (or the file itself when given one)."""
    path = Path(run_dir)
    return path / CHECKPOINT if path.is_dir() or not path.suffix else path


def read_checkpoint(path: Path) -> dict[str, Any]:
    """The checkpoint's dict, with its algo and parts checked: FileNotFoundError or ValueError naming the file."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no checkpoint there (a run writes one into its --out folder at its first "
                                f"checkpoint_every steps and at its end)")
    try:
        ck = load_checkpoint(path)
    except (ValueError, FileNotFoundError):
        raise                           # already names the file and what is wrong
    except Exception as exc:            # torch.load raises whatever the broken pickle or zip gives it
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ValueError(f"{path}: not a readable checkpoint, the file is corrupt or truncated "
                         f"({type(exc).__name__}{': ' + reason if reason else ''})") from None
    if not isinstance(ck, dict):
        raise ValueError(f"{path}: not a learner's checkpoint (it holds a {type(ck).__name__}, not a dict)")
    algo = ck.get("algo")
    if algo not in LEARNERS:
        raise ValueError(f"{path}: unknown algo {algo!r} in the checkpoint: expected one of {list(LEARNERS)}")
    missing = [k for k in ("config", "step", LEARNERS[algo][2]) if k not in ck]
    if missing:
        raise ValueError(f"{path}: a {algo} checkpoint without {missing}")
    return ck


def checkpoint_config(ck: dict[str, Any], path: Path, device: str):
    """The learner's config from the checkpoint's nested dict, with the networks (and the simulator, unless the
    run kept it on the CPU) moved to ``device``."""
    module, cls_name, _ = LEARNERS[ck["algo"]]
    cls = getattr(importlib.import_module(module), cls_name)
    try:
        cfg = config_lib.from_flat(cls, ck["config"])
        cfg.check()
    except (ValueError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: its config does not fit this version's {cls_name}: {exc}") from None
    env_device = "cpu" if cfg.run.env_device == "cpu" else ""
    moved = config_lib.replace(cfg, device=str(device), env_device=env_device)
    moved.run.check()                  # an unknown or unavailable device: its own message
    return moved


# ====================================================================== the acting networks, rebuilt
def _acting(net: torch.nn.Module, ck: dict[str, Any], key: str, path: Path,
            act: Callable[[Any, bool], torch.Tensor]) -> BatchedPolicy:
    """``net`` with the checkpoint's ``key`` weights, in eval mode, and its policy ``act(obs, deterministic)``
    without gradients."""
    load_weights(net, ck[key], path, key)
    net.eval()

    @torch.no_grad()
    def policy(o: Any, deterministic: bool = True) -> torch.Tensor:
        return act(o, deterministic)
    return policy


def sac_actor(cfg, ck: dict[str, Any], obs: Any, action_dim: int, path: Path) -> BatchedPolicy:
    """SAC's actor as ``agents.sac.train`` builds it (HybridActor or Actor by cfg.policy), and its policy."""
    from agents import sac
    p = cfg.task.cable_params()
    actor = (sac.HybridActor(obs, cfg, p.length, p.n_nodes) if cfg.policy == "hybrid"
             else sac.Actor(obs, action_dim, cfg, p.length)).to(cfg.run.device)
    return _acting(actor, ck, "actor", path, actor.env_action)


def ppo_agent(cfg, ck: dict[str, Any], obs: Any, action_dim: int, path: Path) -> BatchedPolicy:
    """PPO's ActorCritic as ``agents.ppo.train`` builds it, and its policy (the env action of the mode)."""
    from agents import ppo
    p = cfg.task.cable_params()
    agent = ppo.ActorCritic(obs, action_dim, cfg, p.length, p.n_nodes).to(cfg.run.device)
    return _acting(agent, ck, "agent", path, agent.act)


def planet_model(cfg, ck: dict[str, Any], obs: Any, action_dim: int, path: Path) -> Callable[[Any], BatchedPolicy]:
    """PlaNet's world model as ``agents.planet.train`` builds it, and a maker of planners bound to an env core."""
    from agents import planet
    model = planet.build_model(cfg, obs, action_dim, cfg.task.cable_params())
    load_weights(model, ck["model"], path, "model")
    model.eval()
    return lambda core: planet.make_planner(model, cfg, core, cfg.run.eval_seed)


def apg_actor(cfg, ck: dict[str, Any], obs: Any, action_dim: int, path: Path) -> BatchedPolicy:
    """APG's actor as ``agents.apg.train`` builds it, and its policy (its node rule, the mean drag)."""
    from agents import apg
    p = cfg.task.cable_params()
    actor = apg.Actor(obs, cfg, p.length, p.n_nodes).to(cfg.run.device)
    return _acting(actor, ck, "actor", path, actor.env_action)


BUILDERS = {"sac": sac_actor, "ppo": ppo_agent, "planet": planet_model, "apg": apg_actor,
            "distill": ppo_agent}     # a distilled student is PPO's network (agents/distill.py)


# ====================================================================== the policy
class Policy:
    """A trained policy: ``policy(obs)`` maps ONE env observation (numpy dict or array, as the gymnasium env
    returns it) to one env action (float32 in [0, 1]^A), deterministically; ``batched(env)`` is the form
    ``agents.common.evaluation.evaluate`` takes. ``algo``, ``config`` (the learner's), ``step`` (env steps trained),
    ``checkpoint`` (the file) describe where it came from."""

    def __init__(self, algo: str, cfg, step: int, checkpoint: Path, ck: dict[str, Any]):
        self.algo, self.config, self.step, self.checkpoint = algo, cfg, int(step), checkpoint
        self.device = torch.device(cfg.run.device)
        try:
            self._one_rope = BatchedShapeControl(1, cfg.task.env_options(), device=cfg.run.env_device or cfg.run.device)
        except (ValueError, OSError) as exc:
            raise ValueError(f"{checkpoint}: the run's task cannot be rebuilt here: {exc}") from None
        self._one_rope.reset(seed=0)                  # a real rope: the planners' state checks need one
        self.action_dim = self._one_rope.action_dim
        example = TrainEnv(self._one_rope, device=self.device).observe()
        built = BUILDERS[algo](cfg, ck, example, self.action_dim, checkpoint)
        self._planner_for = built if algo == "planet" else None           # PlaNet: env core -> a bound planner
        self._single = built(self._one_rope) if algo == "planet" else built   # what acts on one observation
        self._moves = 0                                                   # since reset(): the one-rope env's steps

    # ------------------------------------------------------------------ envs of the run's task
    def task(self, **changes: Any):
        """The run's task (its TaskOptions), with ``changes`` to its fields (e.g. success_tol=0.002, max_steps=40),
        checked: a bad value raises ValueError naming the field."""
        if not changes:
            return self.config.task
        task = dataclasses.replace(self.config.task, **changes)
        task.check()
        return task

    def env_options(self, **changes: Any) -> EnvOptions:
        """The run's task as the env's options (``BatchedShapeControl(B, policy.env_options())``), with ``changes``
        as for ``task``."""
        return self.task(**changes).env_options()

    def env_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``gym.make("DiffDLO/ShapeControl-v0", ...)``: the run's task."""
        return self.env_options().keywords()

    def make_env(self, num_envs: int | None = None, target: Any = None, **changes: Any) -> TrainEnv:
        """The run's evaluation env (``num_envs`` default min(eval_episodes, 32), as the run's own), optionally with
        another ``target`` spec (a name, family, (N, 2) array or .npy/.yaml path) and ``changes`` to the task as
        for ``task`` (another tolerance, episode length)."""
        cfg = self.config
        task = self.task(**changes)
        task = task if target is None else dataclasses.replace(task, target=target)
        n = min(cfg.run.eval_episodes, 32) if num_envs is None else num_envs
        return make_env(task, cfg.run, task.cable_params(), n)

    # ------------------------------------------------------------------ acting
    def batched(self, env: TrainEnv | BatchedShapeControl | None = None) -> BatchedPolicy:
        """``policy(obs_batch, deterministic) -> (B, A) actions`` on the learner's device. PlaNet's planner is bound
        to ``env`` (required for it: it reads which ropes moved, and its targets); SAC and PPO ignore it."""
        if self._planner_for is None:
            return self._single
        if env is None:
            raise ValueError("PlaNet plans for the ropes of one env: pass it, policy.batched(env)")
        return self._planner_for(env.core if isinstance(env, TrainEnv) else env)

    def reset(self) -> None:
        """A new episode starts for the one-observation form (PlaNet's planner restarts its warm start and belief;
        SAC and PPO keep no state)."""
        self._moves = 0

    def __call__(self, obs: Any) -> np.ndarray:
        batch = self._as_batch(obs)
        if self._planner_for is not None:
            self._track_one_rope(obs)
        with torch.no_grad():
            action = self._single(batch, True)
        self._moves += 1
        return np.clip(action[0].detach().cpu().numpy().astype(np.float32), 0.0, 1.0)

    def _as_batch(self, obs: Any) -> Any:
        """One observation checked against the run's observation space, as a batch of one on the device."""
        space = self._one_rope.single_observation_space
        expected = {k: s.shape for k, s in space.spaces.items()} if hasattr(space, "spaces") else space.shape
        given = ({k: np.shape(v) for k, v in obs.items()} if isinstance(obs, dict) else np.shape(obs))
        if given != expected:
            raise ValueError(f"the observation does not fit the run's task (obs {self.config.task.obs!r}): expected "
                             f"{expected}, got {given}")

        def one(x: Any) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x)).unsqueeze(0).to(self.device)
        return {k: one(v) for k, v in obs.items()} if isinstance(obs, dict) else one(obs)

    def _track_one_rope(self, obs: Any) -> None:
        """The private one-rope env PlaNet's planner reads: the moves since ``reset()``, the rope and the target (where
        the observation shows them)."""
        has_target = isinstance(obs, dict) and "target_poses" in obs
        cfg = self.config
        if not has_target and cfg.model == "rssm" and cfg.plan_objective == "shape":
            raise ValueError(f"this PlaNet plans to the target and obs {cfg.task.obs!r} does not show it: use "
                             "policy.batched(env) with the env the observations come from")
        def shown(key: str) -> torch.Tensor | None:
            return torch.as_tensor(np.asarray(obs[key]))[None] if isinstance(obs, dict) and key in obs else None
        self._one_rope.set_state(steps=self._moves, pos=shown("node_poses"), target=shown("target_poses"))


def load_policy(run_dir: Path | str, device: str | torch.device = "cpu") -> Policy:
    """The trained policy of a run folder (or a checkpoint file). A missing file raises FileNotFoundError; a corrupt,
    truncated or incompatible one ValueError, each naming the file and what is wrong."""
    path = checkpoint_path(run_dir)
    ck = read_checkpoint(path)
    cfg = checkpoint_config(ck, path, str(device))
    return Policy(ck["algo"], cfg, ck["step"], path, ck)
