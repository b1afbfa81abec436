"""A latent world model that plans (issue 47): encoder -> deterministic latent dynamics -> decoder of the rope,
planned through by CEM in latent space. ``model: latent`` of agents/planet.py (params/planet-latent.yaml).

Why not PlaNet's RSSM as it is: it predicts one move at 1.24 cm where "nothing moves" is 1.46 cm
(docs/WORLD_MODELS.md). What the accurate models of this task have, and this one takes over:

- **A canonical frame** (equivariance by canonicalisation, as in Kaba et al. 2023 "Equivariance with learned
  canonicalization functions", here a fixed one): a rollout is encoded in the frame of its FIRST move, ``frame:
  grasp`` — origin at the grasped node, x along the drag (the ensemble's frame, agents/models/ensemble.py) — or
  ``frame: centroid`` (origin at the rope's centroid, world axes); every drag of the sequence is rotated into it and
  the decoded ropes are rotated back. Translations (and, in the grasp frame, rotations) of the plane are exact by
  construction. The frame depends on the first action, so each planned candidate is encoded in its own frame (one
  small MLP call per candidate).
- **Latent keypoints** (``kind: keypoints``, the preset's; as in Manuelli et al. 2020 "Keypoints into the Future"):
  the latent is K = latent / 2 learned points of the plane, the decoder an affine mix of them (so it commutes with
  every rigid motion), and each move is stepped in ITS OWN grasp frame — the keypoints relative to the decoded
  grasped node, rotated so that the drag points along +x — as the ensemble re-frames every move. ``kind: vector``
  is an unstructured latent vector stepped in the first move's frame (its later moves come in any direction).
- **Deterministic residual latent dynamics** z' = z + f(...) (TD-MPC / TD-MPC2, Hansen et al. 2022, 2024: a move
  changes the rope almost deterministically; the RSSM's stochastic latent bought nothing, step 1 of the issue),
  trained through ``chunk_length`` moves open loop.
- **A decoder of the change** (``residual_decoder``): the rope after t latent steps is x_0 + D(z_t) - D(z_0), the
  observed rope plus the decoded change, so the autoencoder's own error cancels (the RSSM's change-of-the-rope
  decoder was its one option that helped, 1.24 -> 0.86 cm).
- **The simulator's symmetries** as data (``augment``: mirror, reverse; ``ensemble.symmetry_transform``).
- **Among pegs** (``max_pegs`` > 0, a route; issue 60) the dynamics also take every peg slot (x, y, radius) in the
  frame the move is stepped in (keypoints: the move's own grasp frame; vector: the first move's), so the frame
  carries the pegs with the rope and the symmetries stay exact; with the second gripper (``pin``) the held node
  one-hot (N + 1, the first: none). The encoder and decoder see the rope alone: the pegs do not move.

Loss per chunk of L moves (all in the frame of the chunk's first move, in units of the largest drag), each step's
term weighted rho^t (TD-MPC2's horizon discount, 0.5):
  prediction  || decoded rope after t+1 latent steps - observed rope t+1 ||^2       (open loop from z_0 = E(x_0))
  consistency || z_{t+1} - sg(E(x_{t+1})) ||^2 x ``consistency``                     (TD-MPC2's latent consistency)
  reconstruction || D(E(x_t)) - x_t ||^2 for every observed rope                      (keeps E and D an autoencoder)

Planning: ``agents.models.ensemble.ModelPlanner`` / ``ModelObjective`` call ``rollout`` — encode each candidate's
start once, step the latent H times, decode each step — and score the decoded ropes with the planners' cost
(``planners.objective.sequence_cost``: shape error against the observed target). The acting model sees only the
observation: the rope and the target (from pictures, obs "perceived": the points the perception network reads).
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F

from agents.models.ensemble import symmetry_transform
from agents.models.networks import mlp
from diffdlo.planar.params import CableParams
from diffdlo.tasks.task import decode_node_action, decode_pin

FRAMES = ("grasp", "centroid")
KINDS = ("vector", "keypoints")
AUGMENTS = ("mirror", "reverse")       # rotations are exact by construction in the grasp frame


def check_latent_settings(latent: int, hidden: Sequence[int], augment: Sequence[str], frame: str,
                          kind: str = "vector") -> None:
    """The latent model's settings, named when wrong (the model and PlaNet's config call it)."""
    if kind not in KINDS:
        raise ValueError(f"unknown latent_kind {kind!r}: use one of {list(KINDS)}")
    if frame not in FRAMES:
        raise ValueError(f"unknown frame {frame!r} for the latent model: use one of {list(FRAMES)}")
    bad = sorted(set(augment) - set(AUGMENTS) - ({"rotate"} if frame == "centroid" else set()))
    if bad:
        raise ValueError(f"unknown augment {bad} for the latent model: use some of {list(AUGMENTS)}"
                         + (" (or rotate, with frame centroid)" if frame == "grasp" else ""))
    if isinstance(latent, bool) or not isinstance(latent, int) or latent < 1:
        raise ValueError(f"latent_dim must be an integer >= 1, got {latent!r}")
    if kind == "keypoints" and latent % 2:
        raise ValueError(f"latent_kind 'keypoints' holds latent_dim / 2 points of the plane: latent_dim must be even, "
                         f"got {latent}")
    if (isinstance(hidden, str) or not hidden
            or not all(isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in hidden)):
        raise ValueError(f"latent_hidden must be a list of positive layer sizes, got {hidden!r}")


class Frame:
    """A rigid frame of the plane per rope: origin (B, 1, 2) and the rotation (c, s) (B, 1, 1) of its x axis."""

    def __init__(self, origin: torch.Tensor, c: torch.Tensor, s: torch.Tensor):
        self.origin, self.c, self.s = origin, c, s

    @staticmethod
    def of(rope: torch.Tensor, node: torch.Tensor, drag: torch.Tensor, kind: str) -> "Frame":
        """The frame of a move: ``grasp`` (origin at rope[node], x along the drag; a zero drag keeps the world x
        axis) or ``centroid`` (the rope's centroid, world axes). rope (B, N, 2), node (B,), drag (B, 2)."""
        if kind == "centroid":
            origin = rope.mean(-2, keepdim=True)
            one = torch.ones_like(origin[..., :1])
            return Frame(origin, one, torch.zeros_like(one))
        origin = rope.gather(-2, node.long()[:, None, None].expand(-1, 1, 2))
        dist = drag.norm(dim=-1, keepdim=True)
        moving = dist > 0
        unit = drag / dist.clamp_min(1e-12)
        c = torch.where(moving, unit[..., :1], 1.0)[:, None]
        s = torch.where(moving, unit[..., 1:], 0.0)[:, None]
        return Frame(origin, c, s)

    def _expand(self, x: torch.Tensor):
        extra = x.dim() - 3                                  # points (B, [T,] N, 2): broadcast over T
        shape = (x.shape[0],) + (1,) * extra + (1, -1)
        return (self.origin.reshape(*shape[:-1], 2), self.c.reshape(*shape[:-1], 1), self.s.reshape(*shape[:-1], 1))

    def points_in(self, x: torch.Tensor) -> torch.Tensor:
        o, c, s = self._expand(x)
        return self.rotate_in(x - o, c, s)

    def points_out(self, x: torch.Tensor) -> torch.Tensor:
        o, c, s = self._expand(x)
        return self.rotate_out(x, c, s) + o

    def vectors_in(self, v: torch.Tensor) -> torch.Tensor:
        """Vectors (B, [T,] 2) into the frame (drags)."""
        shape = (v.shape[0],) + (1,) * (v.dim() - 1)
        return self.rotate_in(v, self.c.reshape(shape), self.s.reshape(shape))

    @staticmethod
    def rotate_in(v, c, s):
        return torch.cat([c * v[..., :1] + s * v[..., 1:], c * v[..., 1:] - s * v[..., :1]], -1)

    @staticmethod
    def rotate_out(v, c, s):
        return torch.cat([c * v[..., :1] - s * v[..., 1:], s * v[..., :1] + c * v[..., 1:]], -1)


class LatentWorldModel(nn.Module):
    """Encoder E: rope in the frame (N x 2, in rope lengths) -> z; dynamics z' = z + f(...); decoder D: z -> rope in
    the frame. ``rollout`` and ``predict`` take world-frame ropes and node actions, as ``EnsembleDynamics``'s, so the
    same planner plans through either.

    ``kind``: "vector" — z is a vector, f(z, one-hot node, drag in the frame / largest drag), D an MLP; or
    "keypoints" — z is latent / 2 learned points of the plane (latent keypoints, as in Manuelli et al. 2020 "Keypoints
    into the Future"), D a learned affine combination of them (weights summing to 1 per node, so D commutes with
    every rigid motion), and each move is stepped in ITS OWN grasp frame: the keypoints relative to the decoded
    grasped node, rotated so that the drag points along +x, f(those, one-hot node, drag length), rotated back. Every
    move of a rollout then sees what the first one sees in the vector kind."""

    def __init__(self, p: CableParams, latent: int = 128, hidden: Sequence[int] = (256, 256),
                 augment: Sequence[str] = ("mirror", "reverse"), frame: str = "grasp", residual_decoder: bool = True,
                 consistency: float = 1.0, rho: float = 0.5, kind: str = "vector", max_pegs: int = 0,
                 pin: bool = False):
        super().__init__()
        check_latent_settings(latent, hidden, augment, frame, kind)
        self.kind = kind
        self.max_pegs, self.pin = int(max_pegs), bool(pin)
        self.p, self.N = p, p.n_nodes
        self.length, self.scale = float(p.length), float(p.action_scale)
        self.frame, self.augment = frame, tuple(augment)
        self.residual_decoder, self.consistency, self.rho = bool(residual_decoder), float(consistency), float(rho)
        self.latent = int(latent)
        self.encoder = mlp(2 * self.N, list(hidden), self.latent, nn.ELU)
        board = 3 * self.max_pegs + (self.N + 1 if self.pin else 0)       # the pegs in the frame, the held node
        if kind == "keypoints":
            self.K = self.latent // 2
            self.dynamics = mlp(self.latent + self.N + 1 + board, list(hidden), self.latent, nn.ELU)
            self.mixing = nn.Parameter(torch.randn(self.N, self.K) / self.K ** 0.5)    # D: affine mix of keypoints
        else:
            self.dynamics = mlp(self.latent + self.N + 2 + board, list(hidden), self.latent, nn.ELU)
            self.decoder = mlp(self.latent, list(hidden), 2 * self.N, nn.ELU)

    # ------------------------------------------------------------------ pieces
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Ropes in the frame [m] (..., N, 2) -> latents (..., latent) (keypoints: (K, 2) flattened, in rope
        lengths)."""
        return self.encoder(x.flatten(-2) / self.length)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latents (..., latent) -> ropes in the frame [m] (..., N, 2)."""
        if self.kind == "keypoints":
            w = self.mixing - self.mixing.mean(-1, keepdim=True) + 1.0 / self.K         # rows sum to 1
            return torch.einsum("nk,...kd->...nd", w, z.unflatten(-1, (self.K, 2))) * self.length
        return self.decoder(z).unflatten(-1, (self.N, 2)) * self.length

    def _board(self, pegs_in_frame: torch.Tensor | None, pin: torch.Tensor | None, like: torch.Tensor,
                 move: Frame | None = None) -> list[torch.Tensor]:
        """The dynamics' extra inputs: the pegs (B, K, 3) given in the rollout's frame [m] (taken further into a
        move's own frame ``move``, whose points are in rope lengths), in rope lengths, empty slots zeros; the held
        node one-hot."""
        extra = []
        if self.max_pegs:
            if pegs_in_frame is None or pegs_in_frame.shape[-2] != self.max_pegs:
                raise ValueError(f"this model takes {self.max_pegs} peg slots, got "
                                 f"{None if pegs_in_frame is None else tuple(pegs_in_frame.shape)}")
            centres = pegs_in_frame[..., :2] / self.length
            if move is not None:
                centres = move.points_in(centres)
            present = (pegs_in_frame[..., 2:] > 0).to(like.dtype)
            extra.append(torch.cat([centres * present, pegs_in_frame[..., 2:] / self.length], -1).flatten(-2))
        elif pegs_in_frame is not None:
            raise ValueError("this model was built without pegs (max_pegs 0): it cannot predict a move among them")
        if self.pin:
            pin = torch.full(like.shape[:1], -1, dtype=torch.int64, device=like.device) if pin is None else pin
            extra.append(F.one_hot(pin + 1, self.N + 1).to(like.dtype))
        elif pin is not None:
            raise ValueError("this model was built without the second gripper (pin False)")
        return extra

    def step(self, z: torch.Tensor, node: torch.Tensor, drag_in_frame: torch.Tensor,
             pegs_in_frame: torch.Tensor | None = None, pin: torch.Tensor | None = None) -> torch.Tensor:
        """One move in latent space: z (B, latent), node (B,) int64, drag in the frame [m] (B, 2); among pegs, the
        pegs (B, K, 3) in the frame [m] and the held node (B,) (-1: none)."""
        onehot = F.one_hot(node, self.N).to(z.dtype)
        if self.kind == "keypoints":                      # in this move's own grasp frame
            pts = z.unflatten(-1, (self.K, 2))
            grasped = self.decode(z).gather(-2, node[:, None, None].expand(-1, 1, 2)) / self.length
            move = Frame.of(torch.cat([grasped, pts], -2), torch.zeros_like(node), drag_in_frame, "grasp")
            local = move.points_in(pts)
            dist = drag_in_frame.norm(dim=-1, keepdim=True) / self.scale
            board = self._board(pegs_in_frame, pin, z, move)
            d = self.dynamics(torch.cat([local.flatten(-2), onehot, dist, *board], -1)).unflatten(-1, (self.K, 2))
            return z + Frame.rotate_out(d, move.c, move.s).flatten(-2)
        a = torch.cat([onehot, drag_in_frame / self.scale, *self._board(pegs_in_frame, pin, z)], -1)
        return z + self.dynamics(torch.cat([z, a], -1))

    def rollout_in_frame(self, x0: torch.Tensor, node: torch.Tensor, drag: torch.Tensor,
                         pegs: torch.Tensor | None = None, pin: torch.Tensor | None = None,
                         ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """From the rope x0 (B, N, 2) in the frame, H moves (node (B, H), drags in the frame (B, H, 2); among
        ``pegs`` (B, K, 3) in the frame, with ``pin`` (B, H) held): the decoded ropes in the frame and the latents, H
        each."""
        z = self.encode(x0)
        base = x0 - self.decode(z) if self.residual_decoder else 0.0
        ropes, latents = [], []
        for t in range(node.shape[1]):
            z = self.step(z, node[:, t], drag[:, t], pegs, None if pin is None else pin[:, t])
            ropes.append(base + self.decode(z))
            latents.append(z)
        return ropes, latents

    # ------------------------------------------------------------------ prediction (world frame)
    def rollout(self, rope: torch.Tensor, node: torch.Tensor, drag: torch.Tensor,
                propagation: str = "mean", pegs: torch.Tensor | None = None,
                pin: torch.Tensor | None = None) -> list[torch.Tensor]:
        """The ropes after each of H moves from ``rope`` (B, N, 2) under node (B, H) and drag (B, H, 2) [m] (among
        ``pegs`` (B, K, 3), with ``pin`` (B, H) held), in the world frame: H tensors (B, N, 2). One model:
        ``propagation`` is accepted and has nothing to choose."""
        fr = Frame.of(rope, node[:, 0], drag[:, 0], self.frame)
        ropes, _ = self.rollout_in_frame(fr.points_in(rope), node, fr.vectors_in(drag), self._pegs_in(fr, pegs), pin)
        return [fr.points_out(x) for x in ropes]

    @staticmethod
    def _pegs_in(fr: Frame, pegs: torch.Tensor | None) -> torch.Tensor | None:
        """Pegs (B, [T,] K, 3) into the frame: centres moved, radii kept."""
        return None if pegs is None else torch.cat([fr.points_in(pegs[..., :2]), pegs[..., 2:]], -1)

    def predict(self, rope: torch.Tensor, node: torch.Tensor, drag: torch.Tensor, pegs: torch.Tensor | None = None,
                pin: torch.Tensor | None = None) -> torch.Tensor:
        """(B, H, N, 2): the ropes after each move, world frame."""
        return torch.stack(self.rollout(rope, node, drag, pegs=pegs, pin=pin), 1)

    # ------------------------------------------------------------------ training
    def loss(self, obs: dict[str, torch.Tensor], actions: torch.Tensor, rewards: torch.Tensor | None = None,
             mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """obs["node_poses"] (B, L+1, N, 2), actions (B, L, 3), mask (B, L+1) of valid observations. Returns loss,
        its parts (pred, consistency, recon, in squared largest-drag units) and err_cm (mean node distance of the
        first predicted move)."""
        dtype = self.dynamics[0].weight.dtype                   # the model's: float32, or float64 for checks
        rope = obs["node_poses"].to(dtype)
        b, L = actions.shape[:2]
        mask = torch.ones(b, L + 1, device=rope.device, dtype=dtype) if mask is None else mask.to(dtype)
        node, drag = decode_node_action(actions[..., :3].to(dtype), self.p)
        pegs = obs["pegs"].to(dtype)[:, 0] if self.max_pegs else None         # a chunk is one episode: one board
        pin = decode_pin(actions[..., 3].to(dtype), node, self.N) if self.pin else None
        if self.training:
            peg_rows = None if pegs is None else pegs[:, None]
            rope, node, drag, peg_rows, pin = symmetry_transform(rope, node, drag, self.augment, peg_rows, pin)
            pegs = None if peg_rows is None else peg_rows[:, 0]
        fr = Frame.of(rope[:, 0], node[:, 0], drag[:, 0], self.frame)
        x = fr.points_in(rope)                                       # (B, L+1, N, 2) in the first move's frame
        drag = fr.vectors_in(drag)
        pegs = self._pegs_in(fr, pegs)
        z_obs = self.encode(x)                                       # (B, L+1, latent)
        sq = lambda err: (err / self.scale).square().sum(-1).mean(-1)   # noqa: E731  (B, ...) per rope
        recon = (sq(self.decode(z_obs) - x) * mask).sum() / mask.sum().clamp_min(1)
        z = z_obs[:, 0]
        base = x[:, 0] - self.decode(z) if self.residual_decoder else 0.0
        pred = cons = weight = 0.0
        first_err = None
        for t in range(L):
            z = self.step(z, node[:, t], drag[:, t], pegs, None if pin is None else pin[:, t])
            m = mask[:, t + 1]
            w = self.rho ** t
            err = base + self.decode(z) - x[:, t + 1]
            pred = pred + w * (sq(err) * m).sum()
            cons = cons + w * ((z - z_obs[:, t + 1].detach()).square().mean(-1) * m).sum()
            weight = weight + w * m.sum()
            if t == 0:
                first_err = (err.norm(dim=-1).mean(-1) * m).detach().sum() / m.sum().clamp_min(1)
        weight = torch.as_tensor(weight).clamp_min(1)
        pred, cons = pred / weight, cons / weight
        return {"loss": pred + self.consistency * cons + recon, "pred": pred, "consistency": cons, "recon": recon,
                "err_cm": 100 * first_err}

