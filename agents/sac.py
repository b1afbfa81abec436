"""Soft Actor-Critic (Haarnoja et al. 2018; thesis Algorithm 5), CleanRL-style in one file: config -> networks -> loop.

    python -m agents.sac --target random --obs points --action node --total-steps 100000 --num-envs 16 --out runs/sac

Env: ``BatchedShapeControl`` directly (tensors end to end) through ``agents.common.TrainEnv``: one batched step of
all ropes, then ONE masked reset of the ropes whose episode ended (same-step autoreset: the final observation is
returned separately and stored in the replay buffer, so a truncated transition bootstraps from its true last
observation; a terminated one does not bootstrap).

Actions: a tanh-squashed Gaussian mapped to the env's box, a = (tanh(u) + 1) / 2 in [0, 1]^A, with the
change-of-variables correction log pi(a) = log N(u) - sum log(0.5 (1 - tanh(u)^2)).
Twin Q critics with target copies (Polyak tau), automatic entropy tuning with target entropy -|A| (SB3 defaults).
"""
from __future__ import annotations

import copy
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F
from tqdm import tqdm

from agents.buffer import ReplayBuffer
from agents.common import (CHECKPOINT, EpisodeStats, Logger, ObsEncoder, eval_row, evaluate, fmt_postfix,
                           load_checkpoint, make_env, make_params, mlp, rng_state, run_cli, save_checkpoint,
                           seed_everything, set_rng_state, torch_threads, warn_if_large_buffer, write_results)


# ====================================================================== config (defaults: params/sac.yaml)
@dataclasses.dataclass
class SACConfig:
    # task
    target: Any = "random"
    obs: str = "points"
    action: str = "node"
    reward: str = "position_orientation"
    max_steps: int | None = None          # actions per episode (None: params' 100)
    params: str = "cable"
    param_overrides: dict | None = None   # e.g. {n_nodes: 6, length: 0.15} for quick tests
    start: Any = None                     # None (random start) or a .npy path / (N, 2) list: a fixed start shape
    success_tol: float | None = None      # None: params' 0.01 m
    image_size: int = 64
    # run
    total_steps: int = 100_000            # env transitions, all envs together
    num_envs: int = 16
    seed: int = 0
    device: str = "cpu"                   # networks and buffer
    env_device: str = ""                  # the simulator ("": same as device; "cpu" with device "cuda": fused CPU kernel)
    threads: int = 1                      # torch CPU threads during training (restored afterwards)
    eval_every: int = 5_000
    eval_episodes: int = 20
    eval_seed: int = 10_000
    checkpoint_every: int = 10_000
    log_every: int = 100                  # gradient updates between train-loss rows
    # algorithm
    lr: float = 3e-4
    buffer_size: int = 1_000_000          # transitions (rows = buffer_size // num_envs)
    batch_size: int = 256
    tau: float = 0.005
    gamma: float = 0.99
    learning_starts: int = 100            # transitions of uniform random actions before learning
    train_freq: int = 1                   # batched env steps between update phases
    gradient_steps: int = 1               # updates per phase
    ent_coef_init: float = 1.0
    target_entropy: float | None = None   # None: -|A|
    hidden: list = dataclasses.field(default_factory=lambda: [256, 256])
    cnn_channels: list = dataclasses.field(default_factory=lambda: [32, 64, 64])
    features_dim: int = 256
    log_std_min: float = -5.0
    log_std_max: float = 2.0


# ====================================================================== networks
class Actor(nn.Module):
    def __init__(self, obs_example: Any, action_dim: int, cfg: SACConfig, scale: float):
        super().__init__()
        self.enc = ObsEncoder(obs_example, scale, cfg.cnn_channels, cfg.features_dim)
        self.trunk = mlp(self.enc.out_dim, cfg.hidden, None)
        last = cfg.hidden[-1] if cfg.hidden else self.enc.out_dim
        self.mean, self.log_std = nn.Linear(last, action_dim), nn.Linear(last, action_dim)
        self.lo, self.hi = cfg.log_std_min, cfg.log_std_max

    def forward(self, obs: Any, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Actions in [0, 1]^A and their log-probabilities (B,)."""
        h = self.trunk(self.enc(obs))
        mean = self.mean(h)
        log_std = self.lo + 0.5 * (self.hi - self.lo) * (torch.tanh(self.log_std(h)) + 1)   # CleanRL's bound
        std = log_std.exp()
        u = mean if deterministic else mean + std * torch.randn_like(mean)
        y = torch.tanh(u)
        log_prob = (-0.5 * ((u - mean) / std) ** 2 - log_std - 0.5 * torch.log(torch.tensor(2 * torch.pi))).sum(-1)
        log_prob = log_prob - torch.log(0.5 * (1 - y.pow(2)) + 1e-6).sum(-1)
        return (y + 1) / 2, log_prob


class Critic(nn.Module):
    """Twin Q networks on one encoder (SB3: the critic's features extractor is shared by its Q heads)."""

    def __init__(self, obs_example: Any, action_dim: int, cfg: SACConfig, scale: float):
        super().__init__()
        self.enc = ObsEncoder(obs_example, scale, cfg.cnn_channels, cfg.features_dim)
        self.q1 = mlp(self.enc.out_dim + action_dim, cfg.hidden, 1)
        self.q2 = mlp(self.enc.out_dim + action_dim, cfg.hidden, 1)

    def forward(self, obs: Any, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.heads(self.enc(obs), action)

    def heads(self, features: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([features, action], dim=1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)


# ====================================================================== training loop
def train(cfg: SACConfig, out: Path | str, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    with torch_threads(cfg.threads):
        return _train(cfg, out, resume, progress)


def _train(cfg: SACConfig, out: Path | str, resume: bool, progress: bool) -> dict[str, Any]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(cfg.device)
    seed_everything(cfg.seed)
    env = make_env(cfg, cfg.num_envs)
    eval_env = make_env(cfg, min(cfg.eval_episodes, 32))
    obs = env.reset(seed=cfg.seed)
    scale = 1.0 / make_params(cfg).length
    action_dim = env.core.action_dim

    actor = Actor(obs, action_dim, cfg, scale).to(device)
    critic = Critic(obs, action_dim, cfg, scale).to(device)
    critic_target = copy.deepcopy(critic).requires_grad_(False)
    log_alpha = torch.tensor(float(torch.log(torch.tensor(cfg.ent_coef_init))), device=device, requires_grad=True)
    target_entropy = -float(action_dim) if cfg.target_entropy is None else float(cfg.target_entropy)
    actor_opt = torch.optim.Adam(actor.parameters(), lr=cfg.lr)
    critic_opt = torch.optim.Adam(critic.parameters(), lr=cfg.lr)
    alpha_opt = torch.optim.Adam([log_alpha], lr=cfg.lr)
    rows = max(2, cfg.buffer_size // cfg.num_envs)
    warn_if_large_buffer(rows, cfg.num_envs, obs)
    rb = ReplayBuffer(rows, cfg.num_envs, obs, action_dim, device)
    stats = EpisodeStats()
    step, n_updates, last_eval, last_ckpt, wall_before = 0, 0, 0, 0, 0.0
    last_success: float | None = None

    if resume:
        ck = load_checkpoint(out / CHECKPOINT)
        actor.load_state_dict(ck["actor"])
        critic.load_state_dict(ck["critic"])
        critic_target.load_state_dict(ck["critic_target"])
        with torch.no_grad():
            log_alpha.copy_(ck["log_alpha"])
        actor_opt.load_state_dict(ck["actor_opt"])
        critic_opt.load_state_dict(ck["critic_opt"])
        alpha_opt.load_state_dict(ck["alpha_opt"])
        rb.load_state_dict(ck["buffer"])
        env.load_state_dict(ck["env"])
        obs = env.observe()
        stats.buf.extend(ck["episode_stats"])
        step, n_updates, last_eval, last_ckpt = ck["step"], ck["n_updates"], ck["last_eval"], ck["last_ckpt"]
        last_success, wall_before = ck["last_success"], ck["wall_s"]
        set_rng_state(ck["rng"])
    logger = Logger(out, resume_step=step if resume else None)

    def policy(o: Any, deterministic: bool) -> torch.Tensor:
        return actor(o, deterministic)[0]

    def checkpoint() -> None:
        save_checkpoint(out / CHECKPOINT, {
            "algo": "sac", "config": dataclasses.asdict(cfg), "actor": actor.state_dict(),
            "critic": critic.state_dict(), "critic_target": critic_target.state_dict(),
            "log_alpha": log_alpha.detach().clone(), "actor_opt": actor_opt.state_dict(),
            "critic_opt": critic_opt.state_dict(), "alpha_opt": alpha_opt.state_dict(), "buffer": rb.state_dict(),
            "env": env.state_dict(), "episode_stats": list(stats.buf), "step": step, "n_updates": n_updates,
            "last_eval": last_eval, "last_ckpt": last_ckpt, "last_success": last_success,
            "wall_s": wall_before + time.perf_counter() - t0, "rng": rng_state()})

    t0 = time.perf_counter()
    res = None
    bar = tqdm(total=cfg.total_steps, initial=min(step, cfg.total_steps), desc="sac", disable=not progress,
               dynamic_ncols=True, file=sys.stderr)
    while step < cfg.total_steps:
        # ---- act
        with torch.no_grad():
            if step < cfg.learning_starts:
                action = torch.rand(cfg.num_envs, action_dim, device=device)
            else:
                action = actor(obs)[0]
        next_obs, reward, term, trunc, info, final_obs = env.step(action)
        rb.add(obs, action, reward, term, trunc, final_obs=final_obs)
        done = (term | trunc).cpu()
        if bool(done.any()):
            stats.add(info, done, term)
        obs = next_obs
        step += cfg.num_envs
        bar.update(cfg.num_envs)

        # ---- learn
        if step >= cfg.learning_starts and (step // cfg.num_envs) % cfg.train_freq == 0:
            for _ in range(cfg.gradient_steps):
                b = rb.sample(cfg.batch_size)
                alpha = log_alpha.exp().detach()
                with torch.no_grad():
                    next_a, next_logp = actor(b["next_obs"])
                    q1_t, q2_t = critic_target(b["next_obs"], next_a)
                    q_next = torch.min(q1_t, q2_t) - alpha * next_logp
                    # Bootstrap unless TERMINATED: a truncated transition keeps gamma * Q(final_obs, .).
                    y = b["reward"] + cfg.gamma * (~b["terminated"]).float() * q_next
                q1, q2 = critic(b["obs"], b["action"])
                critic_loss = 0.5 * (F.mse_loss(q1, y) + F.mse_loss(q2, y))
                critic_opt.zero_grad()
                critic_loss.backward()
                critic_opt.step()

                a_pi, logp = actor(b["obs"])
                with torch.no_grad():   # the actor loss needs dQ/da only: no backward through the critic's encoder
                    critic_features = critic.enc(b["obs"])
                q1_pi, q2_pi = critic.heads(critic_features, a_pi)
                actor_loss = (alpha * logp - torch.min(q1_pi, q2_pi)).mean()
                actor_opt.zero_grad()
                actor_loss.backward()
                actor_opt.step()

                alpha_loss = -(log_alpha * (logp.detach() + target_entropy)).mean()
                alpha_opt.zero_grad()
                alpha_loss.backward()
                alpha_opt.step()

                with torch.no_grad():
                    for p, pt in zip(critic.parameters(), critic_target.parameters()):
                        pt.mul_(1 - cfg.tau).add_(p, alpha=cfg.tau)
                n_updates += 1
                if n_updates % cfg.log_every == 0:
                    logger.log("train", step, {"actor_loss": actor_loss.item(), "critic_loss": critic_loss.item(),
                                               "ent_coef": alpha.item(), "ent_coef_loss": alpha_loss.item(),
                                               "q_mean": q1.mean().item(), "entropy": -logp.mean().item(),
                                               "n_updates": n_updates})
                    if stats.buf:
                        logger.log("rollout", step, stats.means())

        # ---- evaluate, checkpoint
        if step - last_eval >= cfg.eval_every or step >= cfg.total_steps:
            last_eval = step
            res = evaluate(policy, eval_env, cfg.eval_episodes, seed=cfg.eval_seed)
            last_success = res["success_rate"]
            logger.log("eval", step, eval_row(res))
            bar.set_postfix(fmt_postfix(last_success))
        if step - last_ckpt >= cfg.checkpoint_every or step >= cfg.total_steps:
            last_ckpt = step
            checkpoint()
    bar.close()

    if res is None:   # nothing left to train (resumed at the end): evaluate the loaded policy
        res = evaluate(policy, eval_env, cfg.eval_episodes, seed=cfg.eval_seed)
    logger.close()
    return write_results(out, "sac", cfg, res, step, wall_before + time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    return run_cli(SACConfig, "sac", __doc__, train, argv)


if __name__ == "__main__":
    sys.exit(main())
