"""Proximal Policy Optimization (Schulman et al. 2017; thesis Algorithm 4), CleanRL-style in one file:
config -> networks -> loop.

    python -m agents.ppo --target random --obs points --action node --total-steps 1000000 --num-envs 16 --out runs/ppo

Env: ``BatchedShapeControl`` directly (tensors end to end) through ``agents.common.envs.TrainEnv`` (one batched step, one
masked reset of the ended ropes). Each rollout fills the shared ``ReplayBuffer`` from row 0 (n_steps rows x num_envs)
with log-probs and values; GAE(lambda) bootstraps a truncated step from V(true final observation) and never a
terminated one.

Two presets (``--preset``): ``tuned`` (the default, params/ppo.yaml) and ``sb3-default`` (params/ppo-sb3-default.yaml:
SB3's and the thesis's settings, kept as the comparison's labelled baseline). Their differences are config keys:

- ``policy: hybrid`` (tuned): a categorical over the N nodes plus a Gaussian drag per node with a state-independent
  log-std, mapped exactly onto the env's node action (agents/models/hybrid.py); the stored action is (k, d_x, d_y) and its
  log-probability is log Cat(k) + log N(d | mu_k, std). ``policy: gaussian`` (sb3-default): a diagonal Gaussian over
  the env's box with a state-independent log-std (SB3/CleanRL); the raw sample u is stored and its log-probability
  used in the ratio, the env receives clip(u, 0, 1); the mean starts at 0.5 and the std at 0.5 (half of SB3's 1.0:
  our box [0, 1] is half as wide as SB3's usual [-1, 1]). Deterministic actions: the mode (argmax node, mean drag)
  or clip(mean, 0, 1).
- ``features: relative`` + ``normalize_obs`` (tuned): target-relative features, running-normalized
  (agents/models/hybrid.py); ``raw``: the observation flattened in rope lengths (and images through a CNN).
- the task's episode-end rules (``reward``, ``success_bonus``, ``on_exit``, ``exit_penalty``, ``step_penalty``: env
  keyword arguments, see BatchedShapeControl) and the scale of the rollouts (``num_envs``, ``n_steps``), the lr
  schedule (``anneal_lr``) and the discount.
"""
from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn

from agents.models import hybrid
from agents.common.buffer import ReplayBuffer
from agents.common.cli import run_cli
from agents.common.config import POLICIES, InputOptions, RunOptions, TaskOptions, check_model_free, part
from agents.models.networks import Features, mlp, shift_images
from agents.common.run import Run, learner
from diffdlo.utils.checks import option


# ====================================================================== config (defaults: params/ppo.yaml)
@dataclasses.dataclass
class PPOConfig:
    task: TaskOptions = part(TaskOptions)
    run: RunOptions = part(RunOptions, total_steps=1_000_000, eval_every=20_000, checkpoint_every=50_000, log_every=1)
    inputs: InputOptions = part(InputOptions)
    # checkpoints and evaluations are checked after each rollout + update; log_every counts rollouts
    policy: str = option("gaussian", choices=POLICIES, help='"hybrid" (node categorical + drag) | "gaussian"')
    anneal_lr: bool = option(False, help="lr decays linearly to 0 over total_steps (CleanRL anneal_lr)")
    lr: float = option(3e-4, "(0, inf)", help="Adam's learning rate")
    n_steps: int = option(2048, "[1, inf)", help="rows per rollout (per env)")
    batch_size: int = option(64, "[1, inf)", help="transitions per minibatch")
    n_epochs: int = option(10, "[1, inf)", help="passes over each rollout")
    gamma: float = option(0.99, "[0, 1]", help="discount")
    gae_lambda: float = option(0.95, "[0, 1]", help="GAE's lambda")
    clip_range: float = option(0.2, "(0, inf)", help="the surrogate's ratio clip")
    ent_coef: float = option(0.0, "[0, inf)", help="entropy bonus weight")
    vf_coef: float = option(0.5, "[0, inf)", help="value loss weight")
    max_grad_norm: float = option(0.5, "(0, inf)", help="gradient norm clip")
    normalize_advantage: bool = option(True, help="advantages normalized per minibatch")
    log_std_init: float = option(-0.6931471805599453, "(-inf, inf)", help="the Gaussian's initial log std (log 0.5)")
    hidden: list = option(factory=lambda: [64, 64], layers=True, help="the policy's and value's hidden layers")

    def check(self) -> None:
        check_model_free(self, pin=True)


# ====================================================================== networks
def ortho(layer: nn.Module, gain: float) -> nn.Module:
    for m in layer.modules():
        if isinstance(m, (nn.Linear, nn.Conv2d)):
            nn.init.orthogonal_(m.weight, gain)
            nn.init.zeros_(m.bias)
    return layer


class GaussianDist:
    """A diagonal Gaussian over the env's box; log-prob and entropy summed over the action dimensions."""

    def __init__(self, mean: torch.Tensor, std: torch.Tensor):
        self.normal = torch.distributions.Normal(mean, std.expand_as(mean))

    def sample(self) -> torch.Tensor:
        return self.normal.sample()

    def log_prob(self, u: torch.Tensor) -> torch.Tensor:
        return self.normal.log_prob(u).sum(-1)

    def entropy(self) -> torch.Tensor:
        return self.normal.entropy().sum(-1)

    def mode(self) -> torch.Tensor:
        return self.normal.mean


class HybridDist:
    """Node k ~ Cat(logits), drag d ~ N(mean[k], std): a stored action is the row (k, d_x, d_y). With the second
    gripper (``pin_logits`` (B, N, N + 1), "node_pin" actions) the pin choice c ~ Cat(pin_logits[k]) (0: none, c: node
    c - 1), conditioned on the grasped node, is a fourth entry: (k, d_x, d_y, c)."""

    def __init__(self, logits: torch.Tensor, mean: torch.Tensor, std: torch.Tensor,
                 pin_logits: torch.Tensor | None = None):
        self.cat = torch.distributions.Categorical(logits=logits)
        self.mean, self.std = mean, std                 # (B, N, 2), (2,)
        self.pin_logits = pin_logits

    def _drag(self, node: torch.Tensor) -> torch.distributions.Normal:
        mu = self.mean[torch.arange(len(node), device=node.device), node]
        return torch.distributions.Normal(mu, self.std.expand_as(mu))

    def _pin(self, node: torch.Tensor) -> torch.distributions.Categorical:
        return torch.distributions.Categorical(
            logits=self.pin_logits[torch.arange(len(node), device=node.device), node])

    def _with_pin(self, node: torch.Tensor, row: torch.Tensor, mode: bool) -> torch.Tensor:
        if self.pin_logits is None:
            return row
        pin = self._pin(node)
        choice = pin.logits.argmax(-1) if mode else pin.sample()
        return torch.cat([row, choice.to(row.dtype).unsqueeze(-1)], dim=-1)

    def sample(self) -> torch.Tensor:
        node = self.cat.sample()
        return self._with_pin(node, hybrid.join(node, self._drag(node).sample()), mode=False)

    def log_prob(self, a: torch.Tensor) -> torch.Tensor:
        node, drag = hybrid.split(a)
        lp = self.cat.log_prob(node) + self._drag(node).log_prob(drag).sum(-1)
        return lp if self.pin_logits is None else lp + self._pin(node).log_prob(hybrid.split_pin(a))

    def entropy(self) -> torch.Tensor:
        """H(node) + H(drag | node) (+ E_k H(pin | k) with the pin): the drag's std does not depend on the node."""
        h = self.cat.entropy() + torch.distributions.Normal(0.0, self.std).entropy().sum(-1)
        if self.pin_logits is not None:
            pin_h = torch.distributions.Categorical(logits=self.pin_logits).entropy()      # (B, N)
            h = h + (self.cat.probs * pin_h).sum(-1)
        return h

    def mode(self) -> torch.Tensor:
        node = self.cat.logits.argmax(-1)
        return self._with_pin(node, hybrid.join(node, self._drag(node).mean), mode=True)


class ActorCritic(nn.Module):
    """Observation features (relative + running normalization, or SB3's encoder: flattened floats / NatureCNN),
    separate tanh MLPs for pi and V (SB3 net_arch pi, vf), orthogonal init (gains sqrt 2, 0.01 for pi, 1 for V), and
    a Gaussian head over the env's box or a hybrid (node categorical + per-node drag) head."""

    def __init__(self, obs_example: Any, action_dim: int, cfg: PPOConfig, length: float, n_nodes: int):
        super().__init__()
        self.hybrid, self.n_nodes = cfg.policy == "hybrid", n_nodes
        self.pin = self.hybrid and cfg.task.action == "node_pin"      # a pin choice per node: N x (N + 1) logits
        self.features = Features(obs_example, cfg.inputs, length)
        feat_dim = self.features.out_dim
        last = cfg.hidden[-1] if cfg.hidden else feat_dim
        self.pi = ortho(mlp(feat_dim, cfg.hidden, None, nn.Tanh), math.sqrt(2))
        self.vf = ortho(mlp(feat_dim, cfg.hidden, None, nn.Tanh), math.sqrt(2))
        out = n_nodes * 3 if self.hybrid else action_dim      # hybrid: N logits + N drag means (x, y)
        out += n_nodes * (n_nodes + 1) if self.pin else 0
        self.mean = ortho(nn.Linear(last, out), 0.01)
        self.value_head = ortho(nn.Linear(last, 1), 1.0)
        self.log_std = nn.Parameter(torch.full((2 if self.hybrid else action_dim,), float(cfg.log_std_init)))

    def value(self, obs: Any) -> torch.Tensor:
        return self.value_head(self.vf(self.features(obs))).squeeze(-1)

    def dist(self, obs: Any, update_norm: bool = False) -> tuple[GaussianDist | HybridDist, torch.Tensor]:
        h = self.features(obs, update_norm)
        out = self.mean(self.pi(h))
        std = self.log_std.exp()
        if self.hybrid:
            n = self.n_nodes
            d = HybridDist(out[:, :n], out[:, n:3 * n].reshape(-1, n, 2), std,
                           out[:, 3 * n:].reshape(-1, n, n + 1) if self.pin else None)
        else:
            d = GaussianDist(0.5 + out, std)
        return d, self.value_head(self.vf(h)).squeeze(-1)

    def env_action(self, stored: torch.Tensor) -> torch.Tensor:
        """A stored action (the sample) -> the env's action in [0, 1]^A."""
        if self.hybrid:
            node, drag = hybrid.split(stored)
            if self.pin:
                return hybrid.to_env_pin_action(node, drag, hybrid.split_pin(stored), self.n_nodes)
            return hybrid.to_env_action(node, drag, self.n_nodes)
        return stored.clamp(0.0, 1.0)

    def act(self, obs: Any, deterministic: bool = False) -> torch.Tensor:
        d, _ = self.dist(obs)
        return self.env_action(d.mode() if deterministic else d.sample())


def clipped_surrogate(log_prob: torch.Tensor, old_log_prob: torch.Tensor, advantage: torch.Tensor,
                      clip_range: float) -> tuple[torch.Tensor, torch.Tensor]:
    """PPO's policy loss -E[min(r A, clip(r, 1 - eps, 1 + eps) A)] with r = exp(log_prob - old_log_prob); and r."""
    ratio = (log_prob - old_log_prob).exp()
    return -torch.min(advantage * ratio, advantage * ratio.clamp(1 - clip_range, 1 + clip_range)).mean(), ratio


# ====================================================================== training loop
@learner
def train(cfg: PPOConfig, out: Path | str, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    run = Run("ppo", cfg, out, resume, progress)
    env, device, obs, num_envs = run.env, run.device, run.obs, cfg.run.num_envs
    action_dim = env.core.action_dim
    agent = ActorCritic(obs, action_dim, cfg, run.params.length, run.params.n_nodes).to(device)
    opt = torch.optim.Adam(agent.parameters(), lr=cfg.lr, eps=1e-5)   # SB3 PPO uses Adam eps 1e-5
    rb = ReplayBuffer(cfg.n_steps, num_envs, obs, action_dim, device, store_log_prob=True, store_value=True)
    ck = run.start(agent=agent, opt=opt, buffer=rb)
    n_updates, rollouts = (ck["n_updates"], ck["rollouts"]) if ck else (0, 0)
    obs, logger, bar = run.obs, run.logger, run.bar

    def policy(o: Any, deterministic: bool) -> torch.Tensor:
        return agent.act(o, deterministic)

    per_rollout = cfg.n_steps * num_envs
    if cfg.run.total_steps % num_envs:
        print(f"ppo: {cfg.run.total_steps} steps are not a whole number of batched steps of {num_envs} ropes: the "
              f"run makes {-(-cfg.run.total_steps // num_envs) * num_envs}", file=sys.stderr)
    while run.step < cfg.run.total_steps:
        if cfg.anneal_lr:
            for group in opt.param_groups:
                group["lr"] = cfg.lr * max(0.0, 1.0 - run.step / cfg.run.total_steps)
        # ---- collect one rollout into rows [0, n_steps): the last one shorter, so the run makes total_steps
        rb.reset()
        for _ in range(min(cfg.n_steps, -(-(cfg.run.total_steps - run.step) // num_envs))):
            seen = shift_images(obs, cfg.inputs.augment_shift)   # DrQ shift: stored as seen, so the ratio is of one obs
            with torch.no_grad():
                d, value = agent.dist(seen, update_norm=True)
                u = d.sample()
                log_prob = d.log_prob(u)
            next_obs, reward, term, trunc, info, final_obs = env.step(agent.env_action(u))
            rb.add(seen, u, reward, term, trunc, final_obs=final_obs, log_prob=log_prob, value=value)
            run.count(info, term, trunc, update_bar=False)
            obs = next_obs
        bar.update(min(per_rollout, cfg.run.total_steps - bar.n))
        rollouts += 1
        with torch.no_grad():
            last_value = agent.value(obs)
        rb.compute_gae(last_value, cfg.gamma, cfg.gae_lambda, value_fn=agent.value)

        # ---- learn: n_epochs over shuffled minibatches
        clip_fracs, kls = [], []
        for _ in range(cfg.n_epochs):
            for b in rb.minibatches(cfg.batch_size):
                d, v = agent.dist(b["obs"])
                adv = b["advantage"]
                if cfg.normalize_advantage and len(adv) > 1:
                    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                pg_loss, ratio = clipped_surrogate(d.log_prob(b["action"]), b["log_prob"], adv, cfg.clip_range)
                v_loss = ((b["return"] - v) ** 2).mean()
                entropy = d.entropy().mean()
                loss = pg_loss + cfg.vf_coef * v_loss - cfg.ent_coef * entropy
                opt.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), cfg.max_grad_norm)
                opt.step()
                n_updates += 1
                with torch.no_grad():
                    clip_fracs.append(((ratio - 1).abs() > cfg.clip_range).float().mean().item())
                    kls.append(((ratio - 1) - (ratio.log())).mean().item())
        if rollouts % cfg.run.log_every == 0:
            values, returns = rb.value[: len(rb)].flatten(), rb.returns.flatten()
            explained = float(1 - (returns - values).var() / returns.var()) if returns.var() > 0 else float("nan")
            logger.log("train", run.step, {"actor_loss": pg_loss.item(), "critic_loss": v_loss.item(),
                                           "entropy": entropy.item(), "ent_coef": cfg.ent_coef,
                                           "approx_kl": float(np.mean(kls)),
                                           "clip_fraction": float(np.mean(clip_fracs)),
                                           "explained_variance": explained, "std": agent.log_std.exp().mean().item(),
                                           "n_updates": n_updates, "lr": opt.param_groups[0]["lr"]})
            run.log_rollout()

        # ---- evaluate, checkpoint (at rollout boundaries)
        run.evaluate_if_due(lambda: run.evaluate(policy))
        run.checkpoint_if_due(lambda: {"agent": agent, "opt": opt, "buffer": rb, "n_updates": n_updates,
                                       "rollouts": rollouts})
    return run.finish(policy)


def main(argv: list[str] | None = None) -> int:
    return run_cli(PPOConfig, "ppo", __doc__, train, argv)


if __name__ == "__main__":
    sys.exit(main())
