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

Options for the diagnosis of issue 47 (why the RSSM predicts imprecisely; the defaults are PlaNet's model exactly):
- ``frame: centroid`` (points observations): the encoder sees the rope and the target relative to the rope's
  centroid, and the decoder predicts them so; the centroid is carried beside the latent state (``state["c"]``) and
  moved by a small head, c_t = c_{t-1} + dc(h_t, z_t). The latent then never sees where the rope lies: translations
  of the plane are exact by construction, as in the ensemble's frame (agents/models/ensemble.py).
- ``residual: True`` (float observations): the decoder predicts the change of the observation, o_t = o_{t-1} +
  dec(h_t, z_t), on the previous OBSERVED one while filtering (training, the posterior) and on the previous DECODED
  one in a prior rollout (planning, open loop): ``state["x"]`` carries it (the observation itself in a posterior
  state). At a sequence start the "previous" observation is the first one (no move: the decoder should say 0).
- ``kl_balance: dreamerv3``: DreamerV3's KL (Hafner et al. 2023), 0.5 max(free, KL[sg(q) || p]) + 0.1 max(free,
  KL[q || sg(p)]), each clamped per (sequence, step) by free_nats (DreamerV3's free bits: 1 nat); "planet" is
  max(free_nats, KL[q || p]) with gradients to both.
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
from diffdlo.tasks.rewards import shape_error
from diffdlo.tasks.task import POINT_OBS, decode_node
from planners.cem import CEM, optimize_together

State = dict[str, torch.Tensor]   # {"h": (..., D), "z": (..., S), "mean": (..., S), "std": (..., S)}
#                                   and, with frame "centroid" or residual, "x" (..., O) (+ "c" (..., 2)): the rope
FRAMES = ("world", "centroid")
KL_BALANCES = ("planet", "dreamerv3")
POINT_KEYS = ("node_poses", "target_poses")     # the float keys moved into the centroid frame


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
                 free_nats: float = 3.0, frame: str = "world", residual: bool = False, kl_balance: str = "planet"):
        super().__init__()
        ex = as_dict(obs_example)
        self.float_keys = sorted(k for k, v in ex.items() if v.is_floating_point())
        self.image_keys = sorted(k for k, v in ex.items() if not v.is_floating_point())
        self.shapes = {k: tuple(v.shape[1:]) for k, v in ex.items()}
        if frame not in FRAMES or kl_balance not in KL_BALANCES:
            raise ValueError(f"frame must be one of {FRAMES} and kl_balance one of {KL_BALANCES}, got {frame!r}, "
                             f"{kl_balance!r}")
        if frame == "centroid" and "node_poses" not in self.float_keys:
            raise ValueError("frame 'centroid' needs points observations (node_poses)")
        if (frame == "centroid" or residual) and self.image_keys:
            raise ValueError("frame 'centroid' and residual need float observations only (points or distance)")
        self.frame, self.residual, self.kl_balance = frame, bool(residual), kl_balance
        self.carries = frame == "centroid" or self.residual       # states carry the rope ("x", "c")
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
        # built last, so that the default model's parameters (and their initial values) are today's
        self.centroid_net = mlp(feat, [hidden], 2, nn.ELU) if frame == "centroid" else None

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
        s = {"h": torch.zeros(batch, self.deter, device=device), "z": z, "mean": z, "std": torch.ones_like(z)}
        if self.carries:
            s["x"] = torch.zeros(batch, sum(self.float_dims), device=device)
        if self.frame == "centroid":
            s["c"] = torch.zeros(batch, 2, device=device)
        return s

    def embed(self, obs: Any) -> torch.Tensor:
        """(B, ...) observations -> (B, E)."""
        if self.frame == "centroid":
            return self.embed_net(self.frame_obs(obs)[0])
        return self.embed_net(self.enc(obs))

    # ------------------------------------------------------------------ the centroid frame and the residual decoder
    def frame_obs(self, obs: Any) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(B, ...) observations -> x (B, O): the float parts in model units, flattened in float_keys order (the
        encoder's layout), point keys relative to the rope's centroid with frame "centroid"; and that centroid c
        (B, 2) in model units (None in the world frame)."""
        o = as_dict(obs)
        c = o["node_poses"].float().mean(-2) * self.scale if self.frame == "centroid" else None
        parts = []
        for k in self.float_keys:
            v = o[k].float() * self.scale
            if c is not None and k in POINT_KEYS:
                v = v - c[:, None]
            parts.append(v.flatten(1))
        return torch.cat(parts, -1), c

    def unframe(self, x: torch.Tensor, c: torch.Tensor | None) -> dict[str, torch.Tensor]:
        """frame_obs's inverse: x (..., O) and c (..., 2) -> float observations in model units."""
        out = {}
        for k, p in zip(self.float_keys, x.split(self.float_dims, dim=-1)):
            v = p.reshape(*x.shape[:-1], *self.shapes[k])
            out[k] = v + c[..., None, :] if c is not None and k in POINT_KEYS else v
        return out

    def advance(self, prev: State, state: State) -> State:
        """A prior state carrying the rope decoded from it: x_t = [x_{t-1} +] dec(s_t), c_t = c_{t-1} + dc(s_t)."""
        feat = self.feature(state)
        dx = self.float_dec(feat)
        state["x"] = prev["x"] + dx if self.residual else dx
        if self.frame == "centroid":
            state["c"] = prev["c"] + self.centroid_net(feat)
        return state

    def decode_traj(self, traj: list[State]) -> dict[str, torch.Tensor]:
        """States of a rollout -> predicted observations (B, H, ...) in model units (as decode)."""
        if not self.carries:
            return self.decode(torch.stack([self.feature(s) for s in traj], 1))
        x = torch.stack([s["x"] for s in traj], 1)
        return self.unframe(x, torch.stack([s["c"] for s in traj], 1) if self.frame == "centroid" else None)

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
                 sample: bool = True, obs: Any = None) -> tuple[State, State]:
        """One filter step: (posterior, prior) at t given s_{t-1}, a_{t-1} and e(o_t). ``state=None``: episode or
        chunk start (h_0 = 0, no action). ``obs``: o_t itself, which the posterior carries when ``carries``."""
        h = torch.zeros(embed.shape[0], self.deter, device=embed.device) if state is None else self.step_h(state, action)
        post = self.posterior(h, embed, sample)
        if self.carries:
            if obs is None:
                raise ValueError("frame 'centroid' and residual carry the observed rope: pass obs to obs_step")
            post["x"], c = self.frame_obs(obs)
            if c is not None:
                post["c"] = c
        return post, self.prior(h, sample)

    def imagine(self, state: State, actions: torch.Tensor, sample: bool = False) -> list[State]:
        """Open-loop prior rollout from ``state`` (B, ...) under actions (B, H, A): the H next states."""
        out = []
        for t in range(actions.shape[1]):
            nxt = self.prior(self.step_h(state, actions[:, t]), sample)
            state = self.advance(state, nxt) if self.carries else nxt
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
        seq_obs = [{k: v[:, t] for k, v in o.items()} for t in range(t1)] if self.carries else [None] * t1
        posts, priors = [], []
        state = None
        for t in range(t1):
            post, pri = self.obs_step(state, None if t == 0 else actions[:, t - 1], emb[:, t], obs=seq_obs[t])
            posts.append(post)
            priors.append(pri)
            state = post
        stack = lambda states, key: torch.stack([s[key] for s in states], 1)   # noqa: E731
        feat = torch.cat([stack(posts, "h"), stack(posts, "z")], -1)            # (B, T+1, F)
        if self.carries:     # decoded from the previous OBSERVED rope (the first one at t = 0)
            x, prev = stack(posts, "x"), lambda v: torch.cat([v[:, :1], v[:, :-1]], 1)   # noqa: E731
            dx = self.float_dec(feat)
            c = prev(stack(posts, "c")) + self.centroid_net(feat) if self.frame == "centroid" else None
            pred = self.unframe(prev(x) + dx if self.residual else dx, c)
        else:
            pred = self.decode(feat)
        target = self.obs_target(o)
        recon = 0
        for k in pred:
            err = pred[k] - target[k]
            if k in self.float_keys:            # pixels keep PlaNet's unit variance: no division (a full pass saved)
                err = err / self.obs_std
            recon = recon + 0.5 * err.square().sum(tuple(range(2, err.dim())))
        recon = (recon * mask).sum() / mask.sum().clamp_min(1)
        qm, qs, pm, ps = stack(posts, "mean"), stack(posts, "std"), stack(priors, "mean"), stack(priors, "std")
        kl = gauss_kl(qm, qs, pm, ps)
        if self.kl_balance == "dreamerv3":    # dynamics loss trains the prior, representation loss the posterior
            dyn = gauss_kl(qm.detach(), qs.detach(), pm, ps)
            rep = gauss_kl(qm, qs, pm.detach(), ps.detach())
            kl_loss = 0.5 * free_nats_kl(dyn, self.free_nats, mask) + 0.1 * free_nats_kl(rep, self.free_nats, mask)
        else:
            kl_loss = free_nats_kl(kl, self.free_nats, mask)
        r_pred = self.reward(feat[:, 1:])
        rm = mask[:, 1:]
        err = r_pred - rewards.float()
        reward_loss = (0.5 * err ** 2 * rm).sum() / rm.sum().clamp_min(1)
        reward_mae = (err.abs() * rm).sum() / rm.sum().clamp_min(1)
        kl_mean = (kl * mask).sum() / mask.sum().clamp_min(1)
        return {"loss": recon + kl_loss + reward_loss, "recon": recon, "kl": kl_mean, "kl_loss": kl_loss,
                "reward_loss": reward_loss, "reward_mae": reward_mae, "last_state": posts[-1]}


def decoded_positions(model: RSSM, feat: torch.Tensor, obs_type: str, target: torch.Tensor | None = None,
                      dec: dict[str, torch.Tensor] | None = None):
    """Rope node positions [m] (..., N, 2) decoded from features, for points (node_poses) or distance (+ target).
    ``dec``: the decoded observations when already at hand (``RSSM.decode_traj``; needed when the model carries
    the rope)."""
    dec = model.decode(feat) if dec is None else dec
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
            dec = {k: v[:, -1] for k, v in self.model.decode_traj(traj[-1:]).items()} if self.model.carries else None
            pos = decoded_positions(self.model, feat[:, -1], self.obs_type, tgt, dec)
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
                             sample, obs=obs)
        if self.state is None or bool(new.any()):
            fresh, _ = m.obs_step(None, None, emb, sample, obs=obs)
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
