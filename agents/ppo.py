"""Proximal Policy Optimization (Schulman et al. 2017; thesis Algorithm 4), CleanRL-style in one file:
config -> networks -> loop.

    python -m agents.ppo --target random --obs points --action node --total-steps 1000000 --num-envs 16 --out runs/ppo

Env: ``BatchedShapeControl`` directly (tensors end to end) through ``agents.common.TrainEnv`` (one batched step, one
masked reset of the ended ropes). Each rollout fills the shared ``ReplayBuffer`` from row 0 (n_steps rows x num_envs)
with log-probs and values; GAE(lambda) bootstraps a truncated step from V(true final observation) and never a
terminated one.

Actions: a diagonal Gaussian with a state-independent log-std (SB3/CleanRL). The raw sample u is stored and its
log-probability used in the ratio; the env receives clip(u, 0, 1) (SB3's clipping of Box actions; the env itself
clips as well). The mean head starts at 0.5 (the middle of the box) and the std at 0.5, half of SB3's 1.0 because
our box [0, 1] is half as wide as SB3's usual [-1, 1]. Deterministic actions: clip(mean, 0, 1).
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
from tqdm import tqdm

from agents.buffer import ReplayBuffer
from agents.common import (CHECKPOINT, EpisodeStats, Logger, ObsEncoder, eval_row, evaluate, fmt_postfix,
                           load_checkpoint, make_env, make_params, mlp, rng_state, run_cli, save_checkpoint,
                           seed_everything, set_rng_state, torch_threads, write_results)


# ====================================================================== config (defaults: params/ppo.yaml)
@dataclasses.dataclass
class PPOConfig:
    # task
    target: Any = "random"
    obs: str = "points"
    action: str = "node"
    reward: str = "position_orientation"
    max_steps: int | None = None
    params: str = "cable"
    param_overrides: dict | None = None
    start: Any = None
    success_tol: float | None = None      # None: params' 0.01 m
    image_size: int = 64
    # run
    total_steps: int = 1_000_000
    num_envs: int = 16
    seed: int = 0
    device: str = "cpu"                   # networks and buffer
    env_device: str = ""                  # the simulator ("": same as device; "cpu" with device "cuda": fused CPU kernel)
    threads: int = 1
    eval_every: int = 20_000
    eval_episodes: int = 20
    eval_seed: int = 10_000
    checkpoint_every: int = 50_000       # checked after each rollout + update
    log_every: int = 1                   # rollouts between train-loss rows
    # algorithm
    lr: float = 3e-4
    n_steps: int = 2048                  # rows per rollout (per env)
    batch_size: int = 64
    n_epochs: int = 10
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    normalize_advantage: bool = True
    log_std_init: float = -0.6931471805599453   # log 0.5
    hidden: list = dataclasses.field(default_factory=lambda: [64, 64])
    cnn_channels: list = dataclasses.field(default_factory=lambda: [32, 64, 64])
    features_dim: int = 256


# ====================================================================== networks
def ortho(layer: nn.Module, gain: float) -> nn.Module:
    for m in layer.modules():
        if isinstance(m, (nn.Linear, nn.Conv2d)):
            nn.init.orthogonal_(m.weight, gain)
            nn.init.zeros_(m.bias)
    return layer


class ActorCritic(nn.Module):
    """Shared observation encoder (SB3 PPO shares its features extractor), separate tanh MLPs for pi and V
    (SB3 net_arch pi=[64, 64], vf=[64, 64]), orthogonal init (gains sqrt 2, 0.01 for pi, 1 for V)."""

    def __init__(self, obs_example: Any, action_dim: int, cfg: PPOConfig, scale: float):
        super().__init__()
        self.enc = ObsEncoder(obs_example, scale, cfg.cnn_channels, cfg.features_dim)
        last = cfg.hidden[-1] if cfg.hidden else self.enc.out_dim
        self.pi = ortho(mlp(self.enc.out_dim, cfg.hidden, None, nn.Tanh), math.sqrt(2))
        self.vf = ortho(mlp(self.enc.out_dim, cfg.hidden, None, nn.Tanh), math.sqrt(2))
        self.mean = ortho(nn.Linear(last, action_dim), 0.01)
        self.value_head = ortho(nn.Linear(last, 1), 1.0)
        self.log_std = nn.Parameter(torch.full((action_dim,), float(cfg.log_std_init)))

    def value(self, obs: Any) -> torch.Tensor:
        return self.value_head(self.vf(self.enc(obs))).squeeze(-1)

    def dist(self, obs: Any) -> tuple[torch.distributions.Normal, torch.Tensor]:
        h = self.enc(obs)
        mean = 0.5 + self.mean(self.pi(h))
        return torch.distributions.Normal(mean, self.log_std.exp().expand_as(mean)), self.value_head(self.vf(h)).squeeze(-1)

    def act(self, obs: Any, deterministic: bool = False) -> torch.Tensor:
        d, _ = self.dist(obs)
        return (d.mean if deterministic else d.sample()).clamp(0.0, 1.0)


# ====================================================================== training loop
def train(cfg: PPOConfig, out: Path | str, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    with torch_threads(cfg.threads):
        return _train(cfg, out, resume, progress)


def _train(cfg: PPOConfig, out: Path | str, resume: bool, progress: bool) -> dict[str, Any]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(cfg.device)
    seed_everything(cfg.seed)
    env = make_env(cfg, cfg.num_envs)
    eval_env = make_env(cfg, min(cfg.eval_episodes, 32))
    obs = env.reset(seed=cfg.seed)
    action_dim = env.core.action_dim
    agent = ActorCritic(obs, action_dim, cfg, 1.0 / make_params(cfg).length).to(device)
    opt = torch.optim.Adam(agent.parameters(), lr=cfg.lr, eps=1e-5)   # SB3 PPO uses Adam eps 1e-5
    rb = ReplayBuffer(cfg.n_steps, cfg.num_envs, obs, action_dim, device, store_log_prob=True, store_value=True)
    stats = EpisodeStats()
    step, n_updates, last_eval, last_ckpt, wall_before, rollouts = 0, 0, 0, 0, 0.0, 0
    last_success: float | None = None
    if resume:
        ck = load_checkpoint(out / CHECKPOINT)
        agent.load_state_dict(ck["agent"])
        opt.load_state_dict(ck["opt"])
        rb.load_state_dict(ck["buffer"])
        env.load_state_dict(ck["env"])
        obs = env.observe()
        stats.buf.extend(ck["episode_stats"])
        step, n_updates, last_eval, last_ckpt = ck["step"], ck["n_updates"], ck["last_eval"], ck["last_ckpt"]
        rollouts, last_success, wall_before = ck["rollouts"], ck["last_success"], ck["wall_s"]
        set_rng_state(ck["rng"])
    logger = Logger(out, resume_step=step if resume else None)

    def policy(o: Any, deterministic: bool) -> torch.Tensor:
        return agent.act(o, deterministic)

    t0 = time.perf_counter()
    res = None
    per_rollout = cfg.n_steps * cfg.num_envs
    bar = tqdm(total=cfg.total_steps, initial=min(step, cfg.total_steps), desc="ppo", disable=not progress,
               dynamic_ncols=True, file=sys.stderr)
    while step < cfg.total_steps:
        # ---- collect one rollout into rows [0, n_steps)
        rb.reset()
        for _ in range(cfg.n_steps):
            with torch.no_grad():
                d, value = agent.dist(obs)
                u = d.sample()
                log_prob = d.log_prob(u).sum(-1)
            next_obs, reward, term, trunc, info, final_obs = env.step(u.clamp(0.0, 1.0))
            rb.add(obs, u, reward, term, trunc, final_obs=final_obs, log_prob=log_prob, value=value)
            done = (term | trunc).cpu()
            if bool(done.any()):
                stats.add(info, done, term)
            obs = next_obs
            step += cfg.num_envs
        bar.update(min(per_rollout, cfg.total_steps - bar.n))
        rollouts += 1
        with torch.no_grad():
            last_value = agent.value(obs)
        rb.compute_gae(last_value, cfg.gamma, cfg.gae_lambda, value_fn=agent.value)

        # ---- learn: n_epochs over shuffled minibatches
        clip_fracs, kls = [], []
        for _ in range(cfg.n_epochs):
            for b in rb.minibatches(cfg.batch_size):
                d, v = agent.dist(b["obs"])
                log_prob = d.log_prob(b["action"]).sum(-1)
                ratio = (log_prob - b["log_prob"]).exp()
                adv = b["advantage"]
                if cfg.normalize_advantage and len(adv) > 1:
                    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                pg_loss = -torch.min(adv * ratio, adv * ratio.clamp(1 - cfg.clip_range, 1 + cfg.clip_range)).mean()
                v_loss = ((b["return"] - v) ** 2).mean()
                entropy = d.entropy().sum(-1).mean()
                loss = pg_loss + cfg.vf_coef * v_loss - cfg.ent_coef * entropy
                opt.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), cfg.max_grad_norm)
                opt.step()
                n_updates += 1
                with torch.no_grad():
                    clip_fracs.append(((ratio - 1).abs() > cfg.clip_range).float().mean().item())
                    kls.append(((ratio - 1) - (ratio.log())).mean().item())
        if rollouts % cfg.log_every == 0:
            values, returns = rb.value[: len(rb)].flatten(), rb.returns.flatten()
            explained = float(1 - (returns - values).var() / returns.var()) if returns.var() > 0 else float("nan")
            logger.log("train", step, {"actor_loss": pg_loss.item(), "critic_loss": v_loss.item(),
                                       "entropy": entropy.item(), "ent_coef": cfg.ent_coef,
                                       "approx_kl": float(np.mean(kls)), "clip_fraction": float(np.mean(clip_fracs)),
                                       "explained_variance": explained, "std": agent.log_std.exp().mean().item(),
                                       "n_updates": n_updates})
            if stats.buf:
                logger.log("rollout", step, stats.means())

        # ---- evaluate, checkpoint (at rollout boundaries)
        if step - last_eval >= cfg.eval_every or step >= cfg.total_steps:
            last_eval = step
            res = evaluate(policy, eval_env, cfg.eval_episodes, seed=cfg.eval_seed)
            last_success = res["success_rate"]
            logger.log("eval", step, eval_row(res))
            bar.set_postfix(fmt_postfix(last_success))
        if step - last_ckpt >= cfg.checkpoint_every or step >= cfg.total_steps:
            last_ckpt = step
            save_checkpoint(out / CHECKPOINT, {
                "algo": "ppo", "config": dataclasses.asdict(cfg), "agent": agent.state_dict(),
                "opt": opt.state_dict(), "buffer": rb.state_dict(), "env": env.state_dict(),
                "episode_stats": list(stats.buf), "step": step, "n_updates": n_updates, "rollouts": rollouts,
                "last_eval": last_eval, "last_ckpt": last_ckpt, "last_success": last_success,
                "wall_s": wall_before + time.perf_counter() - t0, "rng": rng_state()})
    bar.close()

    if res is None:
        res = evaluate(policy, eval_env, cfg.eval_episodes, seed=cfg.eval_seed)
    logger.close()
    return write_results(out, "ppo", cfg, res, step, wall_before + time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    return run_cli(PPOConfig, "ppo", __doc__, train, argv)


if __name__ == "__main__":
    sys.exit(main())
