"""PlaNet's recurrent state-space model (Hafner et al. 2019; thesis Chapter 3), a world model of agents/planet.py
(``model: rssm``), and its latent planner.

State s_t = (h_t, z_t): a deterministic GRU state h_t and a diagonal-Gaussian stochastic latent z_t.

    h_t = GRU(h_{t-1}, [z_{t-1}, a_{t-1}])          deterministic path
    p(z_t | h_t)                                      prior (transition), used for planning
    q(z_t | h_t, e(o_t))                              posterior (filter), e = observation encoder
    p(o_t | h_t, z_t), p(r_{t-1} | h_t, z_t)          observation decoder and reward model (unit-variance Gaussians;
                                                      float observations use a smaller std, ``obs_std``)

ELBO per step (maximised; we minimise its negative): E_q[ln p(o_t|s_t)] + E_q[ln p(r_{t-1}|s_t)]
- max(free_nats, KL[q(z_t|h_t,o_t) || p(z_t|h_t)]), the KL clamp taken per (sequence, step) as in PlaNet's code
(``tf.maximum(free_nats, divergence)`` before the mean): below free_nats the KL term is constant, with no gradient.

Observations: any env observation (dict of tensors). Float parts (points, distance) are scaled by 1 / rope length
and decoded by an MLP; uint8 images (image, target_image stacked along channels) are encoded by the project's
NatureCNN (``agents.models.networks.ObsEncoder``) and decoded by a transposed-conv decoder to pixels in [-0.5, 0.5].
Node actions enter the model as one-hot(node) + the two drags (the dynamics depend on which node is grasped, and
the env rounds a0 to a node anyway); pixel actions enter as they are.

Latent planning: the project's generic ``planners.cem.CEM`` (categorical over the grasped node for node actions,
Gaussians for the drags) minimises ``LatentObjective``: from the current posterior state, roll the prior mean forward
under each candidate sequence and return minus the sum of predicted rewards (``plan_objective: reward``, PlaNet) or,
for points/distance observations, the shape error of the decoded rope against the (observed) target
(``plan_objective: shape``, the planners' cost in planners/objective.py). The prior MEAN is used so that a
candidate's cost is deterministic, as CEM's elitism assumes. ``LatentPlanner`` filters every rope's belief and plans
its next move, all ropes' CEMs in lockstep.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from agents.common.buffer import as_dict
from agents.common.envs import EpisodeTracker
from agents.models.networks import ObsEncoder, mlp
from diffdlo.rewards import shape_error
from diffdlo.task import POINT_OBS, decode_node
from planners.cem import CEM, optimize_together

State = dict[str, torch.Tensor]   # {"h": (..., D), "z": (..., S), "mean": (..., S), "std": (..., S)}


def gauss_kl(m1: torch.Tensor, s1: torch.Tensor, m2: torch.Tensor, s2: torch.Tensor) -> torch.Tensor:
    """KL[N(m1, s1) || N(m2, s2)] summed over the last dim."""
    return (torch.log(s2 / s1) + (s1 ** 2 + (m1 - m2) ** 2) / (2 * s2 ** 2) - 0.5).sum(-1)


def free_nats_kl(kl: torch.Tensor, free_nats: float, mask: torch.Tensor | None = None) -> torch.Tensor:
    """PlaNet's clamp: mean over (sequence, step) of max(free_nats, kl); constant (zero gradient) where kl < free_nats."""
    k = kl.clamp_min(free_nats)
    if mask is None:
        return k.mean()
    return (k * mask).sum() / mask.sum().clamp_min(1)


class ImageDecoder(nn.Module):
    """features -> (B, S, S, C) images in [-0.5, 0.5] (PlaNet's deconv decoder, scaled to S = 8 * s0)."""

    def __init__(self, in_dim: int, size: int, out_channels: int, channels: Sequence[int] = (64, 32, 16)):
        super().__init__()
        self.size, self.s0 = size, max(1, math.ceil(size / 8))
        self.c0 = channels[0]
        self.fc = nn.Linear(in_dim, self.c0 * self.s0 * self.s0)
        layers: list[nn.Module] = []
        c = self.c0
        for out in list(channels[1:]) + [out_channels]:
            layers += [nn.ReLU(), nn.ConvTranspose2d(c, out, 4, 2, 1)]
            c = out
        self.deconv = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-1]
        y = self.fc(x.reshape(-1, x.shape[-1])).view(-1, self.c0, self.s0, self.s0)
        # channels-last: on a CPU the transposed convs then take oneDNN's kernels instead of the slow reference
        # ones (the image update ~1.5x faster, benchmarks/studies/planet_model.py --update-time), and the final permute to
        # (B, H, W, C) is free
        y = self.deconv(y.contiguous(memory_format=torch.channels_last))
        if y.shape[-1] != self.size:
            y = F.interpolate(y, size=(self.size, self.size), mode="bilinear", align_corners=False)
        return y.permute(0, 2, 3, 1).reshape(*lead, self.size, self.size, -1)


class RSSM(nn.Module):
    def __init__(self, obs_example: Any, action_dim: int, *, action_type: str = "node", n_nodes: int = 20,
                 scale: float = 1.0, deter: int = 200, stoch: int = 30, hidden: int = 200, embed: int = 200,
                 cnn_channels: Sequence[int] = (32, 64, 64), image_embed: int = 1024,
                 deconv_channels: Sequence[int] = (64, 32, 16), min_std: float = 0.1, obs_std: float = 0.02,
                 free_nats: float = 3.0):
        super().__init__()
        ex = as_dict(obs_example)
        self.float_keys = sorted(k for k, v in ex.items() if v.is_floating_point())
        self.image_keys = sorted(k for k, v in ex.items() if not v.is_floating_point())
        self.shapes = {k: tuple(v.shape[1:]) for k, v in ex.items()}
        self.scale, self.min_std, self.obs_std, self.free_nats = float(scale), float(min_std), float(obs_std), float(free_nats)
        self.deter, self.stoch = int(deter), int(stoch)
        self.action_type, self.n_nodes, self.action_dim = action_type, int(n_nodes), int(action_dim)
        self.model_action_dim = n_nodes + 2 if action_type == "node" else action_dim
        # encoder
        self.enc = ObsEncoder(obs_example, scale, cnn_channels, image_embed)
        if self.image_keys:
            self.embed_net, self.embed_dim = nn.Identity(), self.enc.out_dim
        else:
            self.embed_net, self.embed_dim = mlp(self.enc.out_dim, [hidden], embed, nn.ELU), embed
        # transition
        self.inp = nn.Sequential(nn.Linear(stoch + self.model_action_dim, hidden), nn.ELU())
        self.gru = nn.GRUCell(hidden, deter)
        self.prior_net = mlp(deter, [hidden], 2 * stoch, nn.ELU)
        self.post_net = mlp(deter + self.embed_dim, [hidden], 2 * stoch, nn.ELU)
        feat = deter + stoch
        # heads
        self.float_dims = [int(np.prod(self.shapes[k])) for k in self.float_keys]
        self.float_dec = mlp(feat, [hidden, hidden], sum(self.float_dims), nn.ELU) if self.float_keys else None
        self.image_dec = None
        if self.image_keys:
            size = self.shapes[self.image_keys[0]][0]
            self.image_dec = ImageDecoder(feat, size, 3 * len(self.image_keys), deconv_channels)
        self.reward_net = mlp(feat, [hidden, hidden], 1, nn.ELU)

    # ------------------------------------------------------------------ pieces
    def model_action(self, a: torch.Tensor) -> torch.Tensor:
        """Env actions (..., A) in [0, 1] -> the model's action input (one-hot node + drags for node actions)."""
        a = a.clamp(0.0, 1.0).float()
        if self.action_type != "node":
            return a
        node = decode_node(a[..., 0], self.n_nodes)
        return torch.cat([F.one_hot(node, self.n_nodes).float(), a[..., 1:]], dim=-1)

    def _dist(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, std = x.chunk(2, dim=-1)
        return mean, F.softplus(std) + self.min_std

    def initial(self, batch: int, device: Any = "cpu") -> State:
        z = torch.zeros(batch, self.stoch, device=device)
        return {"h": torch.zeros(batch, self.deter, device=device), "z": z, "mean": z, "std": torch.ones_like(z)}

    def embed(self, obs: Any) -> torch.Tensor:
        """(B, ...) observations -> (B, E)."""
        return self.embed_net(self.enc(obs))

    def step_h(self, state: State, action: torch.Tensor) -> torch.Tensor:
        """h_t from s_{t-1} and the env action a_{t-1}."""
        x = self.inp(torch.cat([state["z"], self.model_action(action)], -1))
        return self.gru(x, state["h"])

    def prior(self, h: torch.Tensor, sample: bool = True) -> State:
        mean, std = self._dist(self.prior_net(h))
        z = mean + std * torch.randn_like(std) if sample else mean
        return {"h": h, "z": z, "mean": mean, "std": std}

    def posterior(self, h: torch.Tensor, embed: torch.Tensor, sample: bool = True) -> State:
        mean, std = self._dist(self.post_net(torch.cat([h, embed], -1)))
        z = mean + std * torch.randn_like(std) if sample else mean
        return {"h": h, "z": z, "mean": mean, "std": std}

    @staticmethod
    def feature(state: State) -> torch.Tensor:
        return torch.cat([state["h"], state["z"]], -1)

    def obs_step(self, state: State | None, action: torch.Tensor | None, embed: torch.Tensor,
                 sample: bool = True) -> tuple[State, State]:
        """One filter step: (posterior, prior) at t given s_{t-1}, a_{t-1} and e(o_t). ``state=None``: episode or
        chunk start (h_0 = 0, no action)."""
        h = torch.zeros(embed.shape[0], self.deter, device=embed.device) if state is None else self.step_h(state, action)
        return self.posterior(h, embed, sample), self.prior(h, sample)

    def imagine(self, state: State, actions: torch.Tensor, sample: bool = False) -> list[State]:
        """Open-loop prior rollout from ``state`` (B, ...) under actions (B, H, A): the H next states."""
        out = []
        for t in range(actions.shape[1]):
            state = self.prior(self.step_h(state, actions[:, t]), sample)
            out.append(state)
        return out

    def decode(self, feat: torch.Tensor) -> dict[str, torch.Tensor]:
        """Features (..., F) -> predicted observations in model units (floats scaled, images in [-0.5, 0.5])."""
        out: dict[str, torch.Tensor] = {}
        if self.float_dec is not None:
            parts = self.float_dec(feat).split(self.float_dims, dim=-1)
            for k, p in zip(self.float_keys, parts):
                out[k] = p.reshape(*feat.shape[:-1], *self.shapes[k])
        if self.image_dec is not None:
            imgs = self.image_dec(feat).split(3, dim=-1)
            for k, p in zip(self.image_keys, imgs):
                out[k] = p
        return out

    def obs_target(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Observations in model units (what decode predicts)."""
        return {k: (obs[k].float() * self.scale if k in self.float_keys else obs[k].float().div_(255.0).sub_(0.5))
                for k in self.float_keys + self.image_keys}

    def reward(self, feat: torch.Tensor) -> torch.Tensor:
        return self.reward_net(feat).squeeze(-1)

    # ------------------------------------------------------------------ the ELBO
    def loss(self, obs: Any, actions: torch.Tensor, rewards: torch.Tensor,
             mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Negative ELBO on sequences. obs (B, T+1, ...), actions (B, T, A), rewards (B, T) (reward of a_t is
        predicted from s_{t+1}), mask (B, T+1) of valid observations (step t+1 masks both o_{t+1} and r_t).

        Returns loss (to minimise), recon (−ln p(o), per step, summed over obs dims), kl (true KL, per step),
        kl_loss (free-nats clamped), reward_loss (−ln p(r) + const = 0.5 err²), reward_mae."""
        o = as_dict(obs)
        b, t1 = actions.shape[0], actions.shape[1] + 1
        mask = torch.ones(b, t1, device=actions.device) if mask is None else mask.float()
        flat = {k: v.reshape(b * t1, *v.shape[2:]) for k, v in o.items()}
        emb = self.embed(flat if isinstance(obs, dict) else flat["obs"]).view(b, t1, -1)
        posts, priors = [], []
        state = None
        for t in range(t1):
            post, pri = self.obs_step(state, None if t == 0 else actions[:, t - 1], emb[:, t])
            posts.append(post)
            priors.append(pri)
            state = post
        stack = lambda states, key: torch.stack([s[key] for s in states], 1)   # noqa: E731
        feat = torch.cat([stack(posts, "h"), stack(posts, "z")], -1)            # (B, T+1, F)
        pred = self.decode(feat)
        target = self.obs_target(o)
        recon = 0
        for k in pred:
            err = pred[k] - target[k]
            if k in self.float_keys:            # pixels keep PlaNet's unit variance: no division (a full pass saved)
                err = err / self.obs_std
            recon = recon + 0.5 * err.square().sum(tuple(range(2, err.dim())))
        recon = (recon * mask).sum() / mask.sum().clamp_min(1)
        kl = gauss_kl(stack(posts, "mean"), stack(posts, "std"), stack(priors, "mean"), stack(priors, "std"))
        kl_loss = free_nats_kl(kl, self.free_nats, mask)
        r_pred = self.reward(feat[:, 1:])
        rm = mask[:, 1:]
        err = r_pred - rewards.float()
        reward_loss = (0.5 * err ** 2 * rm).sum() / rm.sum().clamp_min(1)
        reward_mae = (err.abs() * rm).sum() / rm.sum().clamp_min(1)
        kl_mean = (kl * mask).sum() / mask.sum().clamp_min(1)
        return {"loss": recon + kl_loss + reward_loss, "recon": recon, "kl": kl_mean, "kl_loss": kl_loss,
                "reward_loss": reward_loss, "reward_mae": reward_mae, "last_state": posts[-1]}


def decoded_positions(model: RSSM, feat: torch.Tensor, obs_type: str, target: torch.Tensor | None = None):
    """Rope node positions [m] (..., N, 2) decoded from features, for points (node_poses) or distance (+ target)."""
    dec = model.decode(feat)
    if obs_type in POINT_OBS:
        return dec["node_poses"] / model.scale
    if obs_type == "distance":
        return dec["obs"] / model.scale + target
    raise ValueError(f"no node positions in {obs_type!r} observations")


# ====================================================================== planning in latent space
class LatentObjective:
    """cost(actions) from latent states through the prior mean: R ropes' states (R, ...) and candidates
    (R, C, H, A) -> (R, C), all in one batched model call; or one rope's state (1, ...) and (C, H, A) -> (C,).
    ``target`` (R, N, 2) or (N, 2): the ropes' targets for the "shape" cost."""

    def __init__(self, model: RSSM, state: dict[str, torch.Tensor], kind: str = "reward", obs_type: str = "points",
                 target: torch.Tensor | None = None):
        self.model, self.state, self.kind, self.obs_type = model, state, kind, obs_type
        self.target = None if target is None else target.reshape(-1, *target.shape[-2:])
        self.calls = 0

    @torch.no_grad()
    def __call__(self, actions: torch.Tensor) -> torch.Tensor:
        single = actions.dim() == 3
        x = actions[None] if single else actions
        r, c = x.shape[:2]
        dev = self.state["h"].device
        st = {k: v[:, None].expand(r, c, *v.shape[1:]).reshape(r * c, *v.shape[1:]) for k, v in self.state.items()}
        traj = self.model.imagine(st, x.reshape(r * c, *x.shape[2:]).to(dev, torch.float32), sample=False)
        feat = torch.stack([RSSM.feature(s) for s in traj], 1)                  # (R C, H, F)
        self.calls += 1
        if self.kind == "reward":
            cost = -self.model.reward(feat).sum(1)
        else:
            tgt = self.target[:, None].expand(r, c, *self.target.shape[1:]).reshape(r * c, *self.target.shape[1:])
            pos = decoded_positions(self.model, feat[:, -1], self.obs_type, tgt)
            cost = shape_error(pos, tgt)
        cost = cost.view(r, c)
        return cost[0] if single else cost


class LatentPlanner:
    """The acting policy: filters the belief state of every rope and plans each rope's next move with its own
    (warm-started) CEM. ``agents.common.envs.EpisodeTracker`` tells it which ropes started a new episode (so it works
    inside ``agents.common.evaluation.evaluate`` too) and which did not move (finished in an evaluation wave: they keep
    their last action without planning). ``cfg``: an ``agents.planet.PlaNetConfig`` with ``model: rssm``."""

    def __init__(self, model: RSSM, cfg, core, seed: int):
        self.model, self.cfg, self.core = model, cfg, core
        self.b, self.A = core.num_envs, core.action_dim
        discrete = {0: core.params.n_nodes} if cfg.task.action == "node" else None
        self.cems = [CEM(self.A, cfg.horizon, cfg.candidates, cfg.elites, cfg.iterations, discrete=discrete,
                         generator=torch.Generator().manual_seed(seed + i), dtype=torch.float32)
                     for i in range(self.b)]
        self.state: dict[str, torch.Tensor] | None = None
        self.prev_action = torch.zeros(self.b, self.A, device=cfg.run.device)
        self.tracker = EpisodeTracker(core)

    def state_dict(self) -> dict[str, Any]:
        """Belief, last action and every rope's CEM (distribution, warm start, generator): a resumed run plans
        exactly as the uninterrupted one."""
        return {"state": None if self.state is None else {k: v.clone() for k, v in self.state.items()},
                "prev_action": self.prev_action.clone(), "last_steps": self.tracker.last_steps.clone(),
                "cems": [c.state_dict() for c in self.cems]}

    def load_state_dict(self, s: dict[str, Any]) -> None:
        if len(s["cems"]) != self.b:
            raise ValueError(f"planner state for {len(s['cems'])} ropes, this planner has {self.b}")
        dev = self.cfg.run.device
        self.state = None if s["state"] is None else {k: v.to(dev) for k, v in s["state"].items()}
        self.prev_action = s["prev_action"].to(dev)
        self.tracker.last_steps = s["last_steps"].clone()
        for c, cs in zip(self.cems, s["cems"]):
            c.load_state_dict(cs)

    @torch.no_grad()
    def __call__(self, obs: Any, deterministic: bool = True) -> torch.Tensor:
        m, dev = self.model, self.cfg.run.device
        new, moved = self.tracker.update()
        emb = m.embed(obs)
        sample = not deterministic      # evaluation filters with the posterior mean
        post, _ = m.obs_step(self.state if self.state is not None else m.initial(self.b, dev), self.prev_action, emb,
                             sample)
        if self.state is None or bool(new.any()):
            fresh, _ = m.obs_step(None, None, emb, sample)
            nd = new.to(dev)
            if self.state is None:
                post = fresh
            else:
                post = {k: torch.where(nd[:, None], fresh[k], post[k]) for k in post}
            for i in new.nonzero().flatten().tolist():
                self.cems[i].reset()
        if self.state is not None:     # ropes that did not move keep their state
            keep = (~moved).to(dev)
            post = {k: torch.where(keep[:, None], self.state[k], post[k]) for k in post}
        self.state = post
        action = self.prev_action.clone()
        target = None
        if self.cfg.plan_objective == "shape":
            target = self.core.get_state(generators=False).target.to(dev).float()
        rows = moved.nonzero().flatten().tolist()
        if rows:                                   # every moving rope's CEM in lockstep, one model call per iteration
            idx = torch.tensor(rows, device=dev)
            obj = LatentObjective(m, {k: v[idx] for k, v in post.items()}, self.cfg.plan_objective,
                                  self.cfg.task.obs, None if target is None else target[idx])
            bests = optimize_together([self.cems[i] for i in rows], obj)
            for i, (best, _) in zip(rows, bests):
                self.cems[i].shift()
                action[i] = best[0].to(dev)
        if not deterministic and self.cfg.explore_noise > 0:
            noise = self.cfg.explore_noise * torch.randn(self.b, self.A, device=dev)
            action = torch.where(moved.to(dev)[:, None], (action + noise).clamp(0.0, 1.0), action)
        self.prev_action = action
        return action
