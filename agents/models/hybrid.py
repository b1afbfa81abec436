"""What the tuned learners share about the task: the hybrid (node, drag) action, target-relative features and a
running normalizer. Used by agents/ppo.py and agents/sac.py (policy "hybrid", features "relative").

Hybrid action. The env's node action (eq 2.6) picks the node through a continuous scalar a0, node = round(a0 (N-1)),
so a small change of a0 jumps to another node and a Gaussian over a0 spreads its mass over neighbours. The hybrid
policy chooses the node k from a categorical over the N nodes and the drag of THAT node from its own distribution,
and maps (k, drag) exactly onto the env action: a0 = k / (N-1) (which decodes to k again), a_{1,2} = (d + 1) / 2
with d in [-1, 1] the drag in units of action_scale (d = +-1 is +-action_scale metres). A stored hybrid action is
the row (k, d_x, d_y): three numbers, like an env node action, so it fits the one replay buffer.

Relative features. The success metric compares node i with target node i after centring both, so the policy gets
exactly that: the centred rope minus the centred target, the centred rope, and the rope's centroid (how close the
workspace edge is), each in rope lengths: 4N + 2 numbers. They are the same for every target shape, which is what a
policy trained on random curves needs to generalize.

Among pegs (a route: the points observation carries "pegs") the error is measured on the board, so the difference is
NOT centred (rope - route), and each peg slot adds four numbers: its centre relative to the rope's centroid and its
radius (rope lengths), and its side gap, (the rope's winding round it - the route's) / 2 pi
(``diffdlo.tasks.routing.winding``; about 0 on the route's side, about +-1 on the other): 4N + 2 + 4 K numbers, an empty
slot all zeros. The side gap is the success test's own quantity, read from the observation (no privileged input).
"""
from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn as nn

from diffdlo.tasks.routing import winding
from diffdlo.tasks.task import decode_drag, decode_node, encode_node_action, encode_pin


# ====================================================================== hybrid action <-> env action (eq 2.6, task)
def to_env_action(node: torch.Tensor, drag: torch.Tensor, n_nodes: int) -> torch.Tensor:
    """(B,) node ids and (B, 2) drags in [-1, 1] (clipped) -> (B, 3) env node actions in [0, 1]."""
    if node.numel() and (int(node.min()) < 0 or int(node.max()) >= n_nodes):
        raise ValueError(f"node ids must lie in [0, {n_nodes - 1}], got {node.tolist()}")
    return encode_node_action(node, drag, n_nodes, 1.0)


def from_env_action(action: torch.Tensor, n_nodes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 3) env node actions -> (B,) node ids (as the env decodes them) and (B, 2) drags in [-1, 1]."""
    return decode_node(action[:, 0], n_nodes), decode_drag(action[:, 1:].clamp(0.0, 1.0), 1.0)


def split(stored: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A stored hybrid action row (B, 3) = (k, d_x, d_y) -> node ids (B,) int64 and raw drags (B, 2)."""
    return stored[:, 0].round().to(torch.int64), stored[:, 1:3]


def join(node: torch.Tensor, drag: torch.Tensor) -> torch.Tensor:
    """Node ids (B,) and raw drags (B, 2) -> the stored row (B, 3)."""
    return torch.cat([node.to(drag.dtype).unsqueeze(-1), drag], dim=-1)


# The second gripper ("node_pin" actions, a route): the stored row gains a fourth entry, the pin choice c in [0, N]:
# 0 holds nothing, c holds node c - 1 (a choice of the grasped node holds nothing too: the env's rule).
def split_pin(stored: torch.Tensor) -> torch.Tensor:
    """A stored row (B, 4) = (k, d_x, d_y, c) -> the pin choices c (B,) int64 in [0, N]."""
    return stored[:, 3].round().to(torch.int64)


def to_env_pin_action(node: torch.Tensor, drag: torch.Tensor, choice: torch.Tensor, n_nodes: int) -> torch.Tensor:
    """Node ids (B,), drags (B, 2) in [-1, 1] and pin choices (B,) in [0, N] -> (B, 4) "node_pin" env actions: the
    node action, then ``diffdlo.tasks.task.encode_pin`` of node c - 1 (-1: none)."""
    if choice.numel() and (int(choice.min()) < 0 or int(choice.max()) > n_nodes):
        raise ValueError(f"pin choices must lie in [0, {n_nodes}], got {choice.tolist()}")
    pin = encode_pin(choice - 1, n_nodes, drag.dtype).unsqueeze(-1)
    return torch.cat([to_env_action(node, drag, n_nodes), pin], dim=-1)


# ====================================================================== features


def relative_features(obs: Any, length: float) -> torch.Tensor:
    """Target-relative features (B, F) of a points observation (4N + 2: centred rope - centred target, centred rope,
    centroid; with pegs, a route: rope - route on the board, centred rope, centroid, then per peg slot its centre
    from the centroid, radius and side gap: 4N + 2 + 4K) or of a distance observation (2N: the centred difference
    only), in rope lengths (the side gap in turns)."""
    if isinstance(obs, dict):
        rope, target = obs["node_poses"].float(), obs["target_poses"].float()
        centroid = rope.mean(1, keepdim=True)
        rope_c = rope - centroid
        if "pegs" not in obs:
            diff = rope_c - (target - target.mean(1, keepdim=True))
            return torch.cat([diff.flatten(1), rope_c.flatten(1), centroid.flatten(1)], dim=1) / length
        pegs = obs["pegs"].float()
        present = (pegs[..., 2] > 0).to(rope.dtype)                       # (B, K): 0 for an empty slot
        centres = pegs[..., :2]
        gap = (winding(rope, centres) - winding(target, centres)) / (2 * math.pi) * present
        rel = (centres - centroid) * present.unsqueeze(-1)
        return torch.cat([((rope - target).flatten(1) / length), rope_c.flatten(1) / length,
                          centroid.flatten(1) / length, rel.flatten(1) / length,
                          pegs[..., 2] / length, gap], dim=1)
    diff = obs.float()
    return (diff - diff.mean(1, keepdim=True)).flatten(1) / length


class RunningNorm(nn.Module):
    """Per-feature running mean and variance (Chan et al.'s parallel update, as SB3's VecNormalize), applied as
    clip((x - mean) / sqrt(var + eps), -clip, clip). Its statistics are buffers: they live in the state_dict, so a
    checkpoint keeps them and a resumed run normalizes exactly as before. ``update`` only when collecting data; the
    updates of the networks and evaluation use the statistics as they are."""

    def __init__(self, dim: int, clip: float = 10.0, eps: float = 1e-8):
        super().__init__()
        self.clip, self.eps = clip, eps
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float64))
        self.register_buffer("var", torch.ones(dim, dtype=torch.float64))
        self.register_buffer("count", torch.tensor(1e-4, dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        x = x.detach().to(torch.float64).reshape(-1, self.mean.numel())
        n = x.shape[0]
        if n == 0:
            return
        b_mean, b_var = x.mean(0), x.var(0, unbiased=False)
        delta, total = b_mean - self.mean, self.count + n
        self.mean += delta * n / total
        self.var.copy_((self.var * self.count + b_var * n + delta.pow(2) * self.count * n / total) / total)
        self.count.copy_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = (x - self.mean.to(x.dtype)) / torch.sqrt(self.var.to(x.dtype) + self.eps)
        return z.clamp(-self.clip, self.clip)
