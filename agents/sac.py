"""Soft Actor-Critic (Haarnoja et al. 2018; thesis Algorithm 5), CleanRL-style in one file: config -> networks -> loop.

    python -m agents.sac --target random --obs points --action node --total-steps 100000 --num-envs 16 --out runs/sac

Env: ``BatchedShapeControl`` directly (tensors end to end) through ``agents.common.envs.TrainEnv``: one batched step of
all ropes, then ONE masked reset of the ropes whose episode ended (same-step autoreset: the final observation is
returned separately and stored in the replay buffer, so a truncated transition bootstraps from its true last
observation; a terminated one does not bootstrap).

Two presets (``--preset``): ``tuned`` (the default, params/sac.yaml) and ``sb3-default`` (params/sac-sb3-default.yaml:
SB3's and the thesis's settings, the comparison's labelled baseline). Their policies:

- ``policy: gaussian`` (sb3-default): a tanh-squashed Gaussian mapped to the env's box, a = (tanh(u) + 1) / 2 in
  [0, 1]^A, with the change-of-variables correction log pi(a) = log N(u) - sum log(0.5 (1 - tanh(u)^2)). Twin Q
  critics Q(s, a), target copies (Polyak tau), one automatic entropy temperature with target entropy -|A|.
- ``policy: hybrid`` (tuned; a discrete-node SAC): the actor gives a categorical pi(k | s) over the N nodes and a
  tanh-Gaussian drag pi(d | s, k) for every node (agents/models/hybrid.py maps (k, d) onto the env's node action). Twin
  critics Q(s, k, d) in ONE batched call (an ensemble of two networks, agents.sac.EnsembleLinear): a state trunk,
  then a per-node head whose first layer adds a node embedding and the node's drag. The bootstrap target and the
  actor loss take the expectation over the N nodes exactly (every node's drag sampled), as discrete SAC does
  (Christodoulou 2019): V(s) = sum_k pi(k|s) [min_i Q_i(s, k, d_k) - a_d log pi(d_k|s,k) - a_k log pi(k|s)].
  Two temperatures: a_k for the node (target entropy ``target_entropy_node`` nats) and a_d for the drag (target
  ``target_entropy`` per node, default -2 = -dim, as SB3's -|A|).
"""
from __future__ import annotations

import copy
import dataclasses
import math
import sys
import time
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F

from agents.models import hybrid
from agents.common.buffer import ReplayBuffer
from agents.common.checkpoints import replay_rows
from agents.common.cli import run_cli
from agents.common.config import POLICIES, InputOptions, RunOptions, TaskOptions, check_model_free, part
from agents.models.networks import Features, mlp, shift_images
from agents.common.run import Run, learner
from diffdlo.utils.checks import option


# ====================================================================== config (defaults: params/sac.yaml)
@dataclasses.dataclass
class SACConfig:
    task: TaskOptions = part(TaskOptions)
    run: RunOptions = part(RunOptions, total_steps=100_000, eval_every=5_000, checkpoint_every=10_000, log_every=100)
    inputs: InputOptions = part(InputOptions)
    policy: str = option("gaussian", choices=POLICIES, help='"hybrid" (node categorical + drag) | "gaussian"')
    lr: float = option(3e-4, "(0, inf)", help="Adam's learning rate (actor, critics, entropy coefficient)")
    buffer_size: int = option(1_000_000, "[1, inf)", help="transitions (rows = buffer_size // num_envs)")
    batch_size: int = option(256, "[1, inf)", help="transitions per update")
    tau: float = option(0.005, "(0, 1]", help="the target critics' Polyak step")
    gamma: float = option(0.99, "[0, 1]", help="discount")
    learning_starts: int = option(100, "[0, inf)", help="transitions of uniform random actions before learning")
    train_freq: int = option(1, "[1, inf)", help="batched env steps between update phases")
    gradient_steps: int = option(1, "[1, inf)", help="updates per phase")
    ent_coef_init: float = option(1.0, "(0, inf)", help="the entropy coefficient's first value")
    target_entropy: float | None = option(None, "(-inf, inf)",
                                          help="None: -|A| (gaussian) or -2 per node's drag (hybrid)")
    target_entropy_node: float = option(0.5, "[0, inf)", help="hybrid: target entropy of the node categorical [nats]")
    hidden: list = option(factory=lambda: [256, 256], layers=True, help="the actor's and critics' hidden layers")
    head_hidden: int = option(256, "[1, inf)", help="hybrid: width of the critic's per-node head")
    log_std_min: float = option(-5.0, "(-inf, inf)", help="the actor's log-std bounds")
    log_std_max: float = option(2.0, "(-inf, inf)")

    def check(self) -> None:
        check_model_free(self)
        if not self.log_std_min < self.log_std_max:
            raise ValueError(f"log_std_min must be below log_std_max, got {self.log_std_min} and {self.log_std_max}")


# ====================================================================== networks
def squashed_log_prob(u: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log-density of y = tanh(u), u ~ N(mean, exp(log_std)), summed over the last dimension."""
    y = torch.tanh(u)
    log_n = -0.5 * ((u - mean) / log_std.exp()) ** 2 - log_std - 0.5 * math.log(2 * math.pi)
    return (log_n - torch.log(1 - y.pow(2) + 1e-6)).sum(-1)


class Actor(nn.Module):
    """Gaussian policy: a tanh-squashed Gaussian over the env's box [0, 1]^A."""

    def __init__(self, obs_example: Any, action_dim: int, cfg: SACConfig, length: float):
        super().__init__()
        self.feat = Features(obs_example, cfg.inputs, length)
        self.trunk = mlp(self.feat.out_dim, cfg.hidden, None)
        last = cfg.hidden[-1] if cfg.hidden else self.feat.out_dim
        self.mean, self.log_std = nn.Linear(last, action_dim), nn.Linear(last, action_dim)
        self.lo, self.hi = cfg.log_std_min, cfg.log_std_max

    def forward(self, obs: Any, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Actions in [0, 1]^A and their log-probabilities (B,)."""
        h = self.trunk(self.feat(obs))
        mean = self.mean(h)
        log_std = self.lo + 0.5 * (self.hi - self.lo) * (torch.tanh(self.log_std(h)) + 1)   # CleanRL's bound
        u = mean if deterministic else mean + log_std.exp() * torch.randn_like(mean)
        log_prob = squashed_log_prob(u, mean, log_std) + mean.shape[-1] * math.log(2.0)     # a = (y + 1) / 2
        return (torch.tanh(u) + 1) / 2, log_prob

    def env_action(self, obs: Any, deterministic: bool = False) -> torch.Tensor:
        """The env's action (B, A) in [0, 1]^A."""
        return self(obs, deterministic)[0]


class Critic(nn.Module):
    """Gaussian policy's twin Q networks Q(s, a) on one encoder (SB3 shares the critic's features extractor)."""

    def __init__(self, obs_example: Any, action_dim: int, cfg: SACConfig, length: float):
        super().__init__()
        self.feat = Features(obs_example, cfg.inputs, length)
        self.q1 = mlp(self.feat.out_dim + action_dim, cfg.hidden, 1)
        self.q2 = mlp(self.feat.out_dim + action_dim, cfg.hidden, 1)

    def forward(self, obs: Any, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.heads(self.feat(obs), action)

    def heads(self, features: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([features, action], dim=1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)


class HybridActor(nn.Module):
    """pi(k | s) over the N nodes and a tanh-Gaussian drag pi(d | s, k) in [-1, 1]^2 for every node."""

    def __init__(self, obs_example: Any, cfg: SACConfig, length: float, n_nodes: int):
        super().__init__()
        self.feat, self.n = Features(obs_example, cfg.inputs, length), n_nodes
        self.trunk = mlp(self.feat.out_dim, cfg.hidden, None)
        last = cfg.hidden[-1] if cfg.hidden else self.feat.out_dim
        self.out = nn.Linear(last, n_nodes * 5)             # N logits, N x 2 means, N x 2 log-stds
        self.lo, self.hi = cfg.log_std_min, cfg.log_std_max

    def forward(self, obs: Any, deterministic: bool = False):
        """(log pi(k|s) (B, N), drags d_k (B, N, 2) sampled for every node, their log pi(d_k|s,k) (B, N))."""
        out = self.out(self.trunk(self.feat(obs)))
        n = self.n
        log_pk = torch.log_softmax(out[:, :n], dim=-1)
        mean = out[:, n:3 * n].reshape(-1, n, 2)
        log_std = self.lo + 0.5 * (self.hi - self.lo) * (torch.tanh(out[:, 3 * n:].reshape(-1, n, 2)) + 1)
        u = mean if deterministic else mean + log_std.exp() * torch.randn_like(mean)
        return log_pk, torch.tanh(u), squashed_log_prob(u, mean, log_std)

    def act(self, obs: Any, deterministic: bool = False) -> torch.Tensor:
        """Stored hybrid actions (B, 3) = (k, d_x, d_y): k sampled (argmax when deterministic)."""
        log_pk, drags, _ = self(obs, deterministic)
        node = log_pk.argmax(-1) if deterministic else torch.distributions.Categorical(logits=log_pk).sample()
        return hybrid.join(node, drags[torch.arange(len(node), device=node.device), node])

    def env_action(self, obs: Any, deterministic: bool = False) -> torch.Tensor:
        """The env's node action (B, 3) of an ``act`` choice."""
        return hybrid.to_env_action(*hybrid.split(self.act(obs, deterministic)), self.n)


class EnsembleLinear(nn.Module):
    """E independent linear layers applied in one batched matmul: (E, B, in) -> (E, B, out)."""

    def __init__(self, ensemble: int, in_dim: int, out_dim: int):
        super().__init__()
        bound = 1.0 / math.sqrt(in_dim)                     # nn.Linear's default initialization
        self.weight = nn.Parameter(torch.empty(ensemble, in_dim, out_dim).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(ensemble, 1, out_dim).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class HybridCritic(nn.Module):
    """Twin Q(s, k, d) in one call. A state trunk (E x MLP) gives z; the per-node head is
    relu(W_z z + e_k + W_d d) -> linear, so z is computed once per state and each node costs one small layer."""

    def __init__(self, obs_example: Any, cfg: SACConfig, length: float, n_nodes: int, ensemble: int = 2):
        super().__init__()
        self.feat, self.e = Features(obs_example, cfg.inputs, length), ensemble
        dims = [self.feat.out_dim, *cfg.hidden]
        self.trunk = nn.ModuleList(EnsembleLinear(ensemble, a, b) for a, b in zip(dims[:-1], dims[1:]))
        h = cfg.head_hidden
        self.head_z = EnsembleLinear(ensemble, dims[-1], h)
        self.node_embed = nn.Parameter(torch.zeros(ensemble, 1, n_nodes, h))
        self.head_d = nn.Parameter(torch.empty(ensemble, 2, h).uniform_(-1 / math.sqrt(2), 1 / math.sqrt(2)))
        self.head_out = nn.Parameter(torch.empty(ensemble, h).uniform_(-1 / math.sqrt(h), 1 / math.sqrt(h)))
        self.head_bias = nn.Parameter(torch.zeros(ensemble, 1, 1))

    def state(self, features: torch.Tensor) -> torch.Tensor:
        """(B, F) -> the per-critic state code (E, B, h): the node-free part of the head's first layer."""
        z = features.unsqueeze(0).expand(self.e, -1, -1)
        for layer in self.trunk:
            z = F.relu(layer(z))
        return self.head_z(z)

    def all_nodes(self, z: torch.Tensor, drags: torch.Tensor) -> torch.Tensor:
        """Q of every node with its own drag: z (E, B, h), drags (B, N, 2) -> (E, B, N)."""
        pre = z.unsqueeze(2) + self.node_embed + torch.einsum("bnc,ech->ebnh", drags, self.head_d)
        return torch.einsum("ebnh,eh->ebn", F.relu(pre), self.head_out) + self.head_bias

    def taken(self, z: torch.Tensor, node: torch.Tensor, drag: torch.Tensor) -> torch.Tensor:
        """Q of the taken (node, drag): z (E, B, h), node (B,), drag (B, 2) -> (E, B)."""
        pre = z + self.node_embed[:, 0, node] + torch.einsum("bc,ech->ebh", drag, self.head_d)
        return torch.einsum("ebh,eh->eb", F.relu(pre), self.head_out) + self.head_bias[..., 0]


# ====================================================================== update rules (tested on hand-computed cases)
@torch.no_grad()
def polyak_update(online: nn.Module, target: nn.Module, tau: float) -> None:
    """target <- (1 - tau) target + tau online, parameter by parameter (buffers such as the normalizer copied)."""
    for p, pt in zip(online.parameters(), target.parameters()):
        pt.mul_(1 - tau).add_(p, alpha=tau)
    for b, bt in zip(online.buffers(), target.buffers()):
        bt.copy_(b)


def temperature_loss(log_alpha: torch.Tensor, entropy: torch.Tensor, target_entropy: float) -> torch.Tensor:
    """SAC's temperature objective: its gradient lowers log alpha while the policy's entropy is above the target
    (d loss / d log alpha = mean(entropy) - target)."""
    return (log_alpha * (entropy.detach() - target_entropy)).mean()


def hybrid_soft_value(log_pk: torch.Tensor, q: torch.Tensor, log_pd: torch.Tensor, alpha_node: torch.Tensor,
                      alpha_drag: torch.Tensor) -> torch.Tensor:
    """V(s) = sum_k pi(k|s) [Q(s, k, d_k) - a_d log pi(d_k|s,k) - a_k log pi(k|s)], the exact expectation over the
    nodes (the drags d_k sampled once per node); all (B, N) -> (B,)."""
    return (log_pk.exp() * (q - alpha_drag * log_pd - alpha_node * log_pk)).sum(-1)


# ====================================================================== training loop
@learner
def train(cfg: SACConfig, out: Path | str, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    run = Run("sac", cfg, out, resume, progress)
    env, device, obs = run.env, run.device, run.obs
    n_nodes, action_dim, length = run.params.n_nodes, env.core.action_dim, run.params.length
    is_hybrid = cfg.policy == "hybrid"

    if is_hybrid:
        actor = HybridActor(obs, cfg, length, n_nodes).to(device)
        critic = HybridCritic(obs, cfg, length, n_nodes).to(device)
    else:
        actor = Actor(obs, action_dim, cfg, length).to(device)
        critic = Critic(obs, action_dim, cfg, length).to(device)
    critic_target = copy.deepcopy(critic).requires_grad_(False)
    # the drag's temperature (hybrid) or the only one, and the node's (hybrid)
    temperatures = nn.ParameterDict({k: nn.Parameter(torch.tensor(float(math.log(cfg.ent_coef_init)), device=device))
                                     for k in ("log_alpha", "log_alpha_node")})
    log_alpha, log_alpha_node = temperatures["log_alpha"], temperatures["log_alpha_node"]
    target_entropy = (-2.0 if is_hybrid else -float(action_dim)) if cfg.target_entropy is None \
        else float(cfg.target_entropy)
    actor_opt = torch.optim.Adam(actor.parameters(), lr=cfg.lr)
    critic_opt = torch.optim.Adam(critic.parameters(), lr=cfg.lr)
    alpha_opt = torch.optim.Adam([log_alpha, log_alpha_node], lr=cfg.lr)
    rows = replay_rows(cfg.buffer_size, cfg.run.total_steps, cfg.run.num_envs, obs)
    rb = ReplayBuffer(rows, cfg.run.num_envs, obs, action_dim, device)
    parts = dict(actor=actor, critic=critic, critic_target=critic_target, temperatures=temperatures,
                 actor_opt=actor_opt, critic_opt=critic_opt, alpha_opt=alpha_opt, buffer=rb)
    ck = run.start(**parts)
    n_updates, update_s = (ck["n_updates"], ck["update_s"]) if ck else (0, 0.0)
    obs = run.obs
    logger = run.logger
    # the actor's normalizer is updated while collecting; the critics' follow it (Polyak copies buffers)
    critic_norms = [m.feat.norm for m in (critic, critic_target) if m.feat.norm is not None]

    def policy(o: Any, deterministic: bool) -> torch.Tensor:
        return actor.env_action(o, deterministic)

    def augmented(b: dict[str, Any]) -> dict[str, Any]:
        """DrQ: every sampled picture shifted at random, obs and next_obs independently (Kostrikov et al. 2021)."""
        if not cfg.inputs.augment_shift:
            return b
        return {**b, "obs": shift_images(b["obs"], cfg.inputs.augment_shift),
                "next_obs": shift_images(b["next_obs"], cfg.inputs.augment_shift)}

    def gaussian_update(b: dict[str, Any]) -> dict[str, torch.Tensor]:
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
            critic_features = critic.feat(b["obs"])
        q1_pi, q2_pi = critic.heads(critic_features, a_pi)
        actor_loss = (alpha * logp - torch.min(q1_pi, q2_pi)).mean()
        actor_opt.zero_grad()
        actor_loss.backward()
        actor_opt.step()
        alpha_loss = temperature_loss(log_alpha, -logp, target_entropy)
        return {"actor_loss": actor_loss, "critic_loss": critic_loss, "alpha_loss": alpha_loss,
                "q_mean": q1.mean(), "entropy": -logp.mean(), "ent_coef": alpha}

    def hybrid_update(b: dict[str, Any]) -> dict[str, torch.Tensor]:
        a_d, a_k = log_alpha.exp().detach(), log_alpha_node.exp().detach()
        with torch.no_grad():
            log_pk, drags, log_pd = actor(b["next_obs"])
            q_next = critic_target.all_nodes(critic_target.state(critic_target.feat(b["next_obs"])), drags).min(0)[0]
            y = b["reward"] + cfg.gamma * (~b["terminated"]).float() * hybrid_soft_value(log_pk, q_next, log_pd,
                                                                                         a_k, a_d)
        node, drag = hybrid.split(b["action"])
        features = critic.feat(b["obs"])      # an image encoder learns from the critic's loss only (DrQ, SAC-AE)
        z = critic.state(features)
        q = critic.taken(z, node, drag)                                   # (2, B)
        critic_loss = 0.5 * ((q - y) ** 2).mean(1).sum()
        critic_opt.zero_grad()
        critic_loss.backward()
        critic_opt.step()

        log_pk, drags, log_pd = actor(b["obs"])
        with torch.no_grad():   # the actor loss needs dQ/dd only: the state code is a constant here
            z = critic.state(features.detach())
        q_pi = critic.all_nodes(z, drags).min(0)[0]
        actor_loss = -hybrid_soft_value(log_pk, q_pi, log_pd, a_k, a_d).mean()
        actor_opt.zero_grad()
        actor_loss.backward()
        actor_opt.step()
        pk = log_pk.detach().exp()
        node_entropy = -(pk * log_pk.detach()).sum(-1)
        drag_entropy = -(pk * log_pd.detach()).sum(-1)                   # E_k[-log pi(d_k | s, k)]
        alpha_loss = (temperature_loss(log_alpha, drag_entropy, target_entropy)
                      + temperature_loss(log_alpha_node, node_entropy, cfg.target_entropy_node))
        return {"actor_loss": actor_loss, "critic_loss": critic_loss, "alpha_loss": alpha_loss,
                "q_mean": q[0].mean(), "entropy": drag_entropy.mean(), "ent_coef": a_d,
                "node_entropy": node_entropy.mean(), "ent_coef_node": a_k}

    while run.step < cfg.run.total_steps:
        # ---- act
        with torch.no_grad():
            if actor.feat.norm is not None:
                actor.feat(obs, update_norm=True)
                for norm in critic_norms:
                    norm.load_state_dict(actor.feat.norm.state_dict())
            if run.step < cfg.learning_starts:
                if is_hybrid:
                    action = hybrid.join(torch.randint(n_nodes, (cfg.run.num_envs,), device=device),
                                         torch.rand(cfg.run.num_envs, 2, device=device) * 2 - 1)
                else:
                    action = torch.rand(cfg.run.num_envs, action_dim, device=device)
            else:
                action = actor.act(obs) if is_hybrid else actor(obs)[0]
        env_action = hybrid.to_env_action(*hybrid.split(action), n_nodes) if is_hybrid else action
        next_obs, reward, term, trunc, info, final_obs = env.step(env_action)
        rb.add(obs, action, reward, term, trunc, final_obs=final_obs)
        run.count(info, term, trunc)
        obs = next_obs

        # ---- learn
        if run.step >= cfg.learning_starts and (run.step // cfg.run.num_envs) % cfg.train_freq == 0:
            for _ in range(cfg.gradient_steps):
                t_update = time.perf_counter()
                b = rb.sample(cfg.batch_size)
                b = augmented(b)
                logs = hybrid_update(b) if is_hybrid else gaussian_update(b)
                alpha_opt.zero_grad()
                logs["alpha_loss"].backward()
                alpha_opt.step()
                polyak_update(critic, critic_target, cfg.tau)
                update_s += time.perf_counter() - t_update
                n_updates += 1
                if n_updates % cfg.run.log_every == 0:
                    row = {("ent_coef_loss" if k == "alpha_loss" else k): v.item() for k, v in logs.items()}
                    logger.log("train", run.step, {**row, "n_updates": n_updates})
                    run.log_rollout()

        # ---- evaluate, checkpoint
        run.evaluate_if_due(lambda: run.evaluate(policy))
        run.checkpoint_if_due(lambda: {**parts, "n_updates": n_updates, "update_s": update_s})

    return run.finish(policy, extra={"n_updates": n_updates, "ms_per_update": 1000 * update_s / max(n_updates, 1)})


def main(argv: list[str] | None = None) -> int:
    return run_cli(SACConfig, "sac", __doc__, train, argv)


if __name__ == "__main__":
    sys.exit(main())
