"""A PETS-style world model on points: an ensemble of MLPs that predicts what one move does to the rope, and the
node-categorical CEM of ``planners.cem`` planning through it (the tuned model of agents/planet.py).

Why this model: a move changes the rope locally and almost deterministically, and planning needs it over one or two
moves (``planners.cem`` solves the task with H = 2 through the true simulator). So each member maps (rope, one-hot
grasped node, drag) to every node's displacement over the move, in units of the largest drag; the next rope is the
current one plus that displacement (the change of the rope, not the rope).

Symmetries: the simulator has no walls and the chain is uniform, so a move commutes with translations and rotations
of the plane, a mirror, and renumbering the nodes from the other end (node k <-> N-1-k). ``frame: grasp`` (default)
builds the first two in: the rope enters relative to the grasped node, rotated so that the drag points along +x
(the drag enters as its length), and the predicted displacement is rotated back. ``frame: centroid`` only centres
the rope (then ``rotate`` augmentation teaches rotations from data). ``augment`` draws one transform per training
chunk (``rotate``, ``mirror``, ``reverse``) — exact new data, checked against the simulator in tests/test_dynamics.py.

Among pegs (a route; ``max_pegs`` > 0) each member also takes every peg slot (x, y, radius; empty slots zeros) in
the same frame as the rope: the grasp frame carries the pegs with the rope, so translations, rotations and the mirror
stay exact (the pegs move with the plane; renumbering the nodes leaves them). With the second gripper (``pin``,
"node_pin" actions) it takes the held node one-hot (N + 1 entries, the first: none); ``reverse`` renumbers it too.
The planning cost is then the routing planners' (``planners.objective.route_cost``: the error on the board plus
SIDE_COST per peg on the wrong side) of each rope's own board.

Ensemble: E members, each fit on its own minibatch (a bootstrap in spirit). Planning cost ``propagation``: "members"
rolls every candidate through every member and averages the E costs (trajectory sampling with one particle per
member, deterministic, so CEM's elitism holds); "mean" rolls the members' mean prediction (E times cheaper per step
in memory, the same compute). ``risk`` > 0 (with "members") adds risk x the members' standard deviation of the cost:
a pessimistic cost, against the planner's choosing the moves the model gets wrong in its own favour.
"""
from __future__ import annotations

import math
import time
from typing import Any, Sequence

import torch
import torch.nn as nn

from agents.common.envs import EpisodeTracker
from diffdlo.planar.params import CableParams
from diffdlo.tasks.task import decode_node_action, decode_pin
from planners.cem import CEM, optimize_together
from planners.objective import sequence_cost

AUGMENTS = ("rotate", "mirror", "reverse")
FRAMES = ("grasp", "centroid")
PROPAGATIONS = ("members", "mean")


def check_settings(members: int = 5, hidden: Sequence[int] = (200,), augment: Sequence[str] = (),
                   frame: str = "grasp", propagation: str = "members", risk: float = 0.0) -> None:
    """The ensemble's settings, checked in one place (the model, its objective and PlaNet's config call it)."""
    if not (isinstance(risk, (int, float)) and not isinstance(risk, bool) and risk >= 0 and math.isfinite(risk)):
        raise ValueError(f"risk must be a number >= 0, got {risk!r}")
    if risk and propagation != "members":
        raise ValueError(f"risk {risk} weighs the members' spread of the cost: it needs propagation 'members', "
                         f"got {propagation!r}")
    if risk and members < 2:
        raise ValueError(f"risk {risk} weighs the members' spread of the cost: a model of {members} member has no "
                         f"members to spread")
    bad = sorted(set(augment) - set(AUGMENTS))
    if bad:
        raise ValueError(f"unknown augment {bad}: use some of {list(AUGMENTS)}")
    if frame not in FRAMES:
        raise ValueError(f"unknown frame {frame!r}: use one of {list(FRAMES)}")
    if propagation not in PROPAGATIONS:
        raise ValueError(f"unknown propagation {propagation!r}: use one of {list(PROPAGATIONS)}")
    if isinstance(members, bool) or not isinstance(members, int) or members < 1:
        raise ValueError(f"members must be an integer >= 1, got {members!r}")
    if (isinstance(hidden, str) or not hidden
            or not all(isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in hidden)):
        raise ValueError(f"need members >= 1 and positive hidden sizes, got {members} and {hidden!r}")


class EnsembleDynamics(nn.Module):
    """E MLPs: next rope (E, B, N, 2) from rope (B, N, 2) or (E, B, N, 2), node (.., B) int64 and drag (.., B, 2)
    [m]."""

    def __init__(self, p: CableParams, members: int = 5, hidden: Sequence[int] = (200, 200, 200),
                 augment: Sequence[str] = ("mirror", "reverse"), frame: str = "grasp", max_pegs: int = 0,
                 pin: bool = False):
        super().__init__()
        check_settings(members, hidden, augment, frame)
        self.frame = frame
        self.p, self.E, self.N = p, int(members), p.n_nodes
        self.length, self.scale = float(p.length), float(p.action_scale)
        self.augment = tuple(augment)
        self.max_pegs, self.pin = int(max_pegs), bool(pin)
        extra = 3 * self.max_pegs + (self.N + 1 if self.pin else 0)
        sizes = [2 * self.N + self.N + (1 if frame == "grasp" else 2) + extra, *hidden, 2 * self.N]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
            bound = 1.0 / math.sqrt(fan_in)                       # nn.Linear's default initialisation, per member
            self.weights.append(nn.Parameter(torch.empty(self.E, fan_in, fan_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(self.E, 1, fan_out).uniform_(-bound, bound)))

    # ------------------------------------------------------------------ prediction
    def _board(self, pegs: torch.Tensor | None, pin: torch.Tensor | None, b: int, like: torch.Tensor):
        """The pegs (.., B, K, 3) and pins (.., B) a move runs with: checked against the model's slots (none: zeros,
        no pin)."""
        if self.max_pegs:
            if pegs is None or pegs.shape[-2] != self.max_pegs:
                raise ValueError(f"this model takes {self.max_pegs} peg slots, got "
                                 f"{None if pegs is None else tuple(pegs.shape)}")
        elif pegs is not None:
            raise ValueError("this model was built without pegs (max_pegs 0): it cannot predict a move among them")
        if pin is not None and not self.pin:
            raise ValueError("this model was built without the second gripper (pin False)")
        if self.pin and pin is None:
            pin = torch.full(like.shape[:-2], -1, dtype=torch.int64, device=like.device)
        return pegs, pin

    def forward(self, rope: torch.Tensor, node: torch.Tensor, drag: torch.Tensor, pegs: torch.Tensor | None = None,
                pin: torch.Tensor | None = None) -> torch.Tensor:
        """Next ropes (E, B, N, 2); ``pegs`` (.., B, K, 3) and ``pin`` (.., B) (-1: none) where the model takes them."""
        pegs, pin = self._board(pegs, pin, rope.shape[-3], rope)
        if rope.dim() == 3:                                      # one batch for every member
            rope, node, drag = (x.unsqueeze(0).expand(self.E, *x.shape) for x in (rope, node, drag))
        e, b = rope.shape[:2]
        if pegs is not None and pegs.dim() == 3:
            pegs = pegs.unsqueeze(0).expand(e, *pegs.shape)
        if pin is not None and pin.dim() == 1:
            pin = pin.unsqueeze(0).expand(e, *pin.shape)
        onehot = torch.nn.functional.one_hot(node, self.N).to(rope.dtype)
        if self.frame == "grasp":
            grasped = (rope * onehot[..., None]).sum(-2, keepdim=True)
            dist = drag.norm(dim=-1, keepdim=True)
            unit = drag / dist.clamp_min(1e-12)
            moving = dist > 0                                                   # a zero drag keeps the x axis
            c = torch.where(moving, unit[..., :1], 1.0)[..., None]               # (E, B, 1, 1)
            s = torch.where(moving, unit[..., 1:], 0.0)[..., None]
            rel = rope - grasped
            local = torch.cat([c * rel[..., :1] + s * rel[..., 1:], c * rel[..., 1:] - s * rel[..., :1]], -1)
            x = torch.cat([local.reshape(e, b, -1) / self.length, onehot, dist / self.scale], -1)
            if pegs is not None:                                  # the pegs in the same frame (empty slots: zeros)
                prel = pegs[..., :2] - grasped
                plocal = torch.cat([c * prel[..., :1] + s * prel[..., 1:], c * prel[..., 1:] - s * prel[..., :1]], -1)
        else:
            centre = rope.mean(-2, keepdim=True)
            x = torch.cat([(rope - centre).reshape(e, b, -1) / self.length, onehot, drag / self.scale], -1)
            if pegs is not None:
                plocal = pegs[..., :2] - centre
        if pegs is not None:
            present = (pegs[..., 2:] > 0).to(x.dtype)
            slots = torch.cat([plocal * present, pegs[..., 2:]], -1) / self.length
            x = torch.cat([x, slots.reshape(e, b, -1)], -1)
        if pin is not None:
            x = torch.cat([x, torch.nn.functional.one_hot(pin + 1, self.N + 1).to(x.dtype)], -1)
        for i, (w, bias) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(bias.to(x.dtype), x, w.to(x.dtype))
            if i < len(self.weights) - 1:
                x = torch.relu(x)
        out = x.view(e, b, self.N, 2) * self.scale
        if self.frame == "grasp":                                               # back to the world frame
            out = torch.cat([c * out[..., :1] - s * out[..., 1:], s * out[..., :1] + c * out[..., 1:]], -1)
        return rope + out

    def mean_move(self, rope: torch.Tensor, node: torch.Tensor, drag: torch.Tensor, pegs: torch.Tensor | None = None,
                  pin: torch.Tensor | None = None) -> torch.Tensor:
        """The members' mean prediction (B, N, 2): the move of ``propagation: mean``, and of the k-step error."""
        return self(rope, node, drag, pegs, pin).mean(0)

    # ------------------------------------------------------------------ training
    def loss(self, obs: dict[str, torch.Tensor], actions: torch.Tensor, rewards: torch.Tensor | None = None,
             mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Open-loop error of each member over chunks: obs["node_poses"] (E B, L+1, N, 2), actions (E B, L, 3)
        (member e takes rows e B ... (e+1) B - 1), mask (E B, L+1). Member e predicts step l from its own
        prediction of step l-1 (L = 1: one-step error). Returns loss (mean squared node displacement error, in
        units of the largest drag) and err_cm (mean node distance)."""
        rope = obs["node_poses"].float()
        n, L = actions.shape[:2]
        if n % self.E:
            raise ValueError(f"the batch ({n} chunks) must split evenly over the {self.E} members")
        mask = torch.ones(n, L + 1, device=rope.device) if mask is None else mask.float()
        node, drag = decode_node_action(actions[..., :3].float(), self.p)
        pegs = obs["pegs"].float() if self.max_pegs else None                     # (n, L + 1, K, 3)
        pin = decode_pin(actions[..., 3].float(), node, self.N) if self.pin else None
        rope, node, drag, pegs, pin = self.transform(rope, node, drag, pegs, pin)
        b = n // self.E
        split = lambda x: None if x is None else x.reshape(self.E, b, *x.shape[1:])   # noqa: E731
        rope, node, drag, mask, pegs, pin = map(split, (rope, node, drag, mask, pegs, pin))
        pred, sq, dist = rope[:, :, 0], 0.0, 0.0
        for t in range(L):
            pred = self(pred, node[:, :, t], drag[:, :, t], None if pegs is None else pegs[:, :, t],
                        None if pin is None else pin[:, :, t])
            err = pred - rope[:, :, t + 1]
            m = mask[:, :, t + 1]
            sq = sq + (((err / self.scale) ** 2).sum(-1).mean(-1) * m).sum()
            dist = dist + (err.norm(dim=-1).mean(-1) * m).detach().sum()
        count = mask[:, :, 1:].sum().clamp_min(1)
        return {"loss": sq / count, "err_cm": 100 * dist / count}

    def transform(self, rope: torch.Tensor, node: torch.Tensor, drag: torch.Tensor,
                  pegs: torch.Tensor | None = None, pin: torch.Tensor | None = None):
        """One random symmetry per chunk (``augment``; ``symmetry_transform``), in training only."""
        if not self.training:
            return rope, node, drag, pegs, pin
        return symmetry_transform(rope, node, drag, self.augment, pegs, pin)

    def rollout(self, rope: torch.Tensor, node: torch.Tensor, drag: torch.Tensor,
                propagation: str = "members", pegs: torch.Tensor | None = None,
                pin: torch.Tensor | None = None) -> list[torch.Tensor]:
        """The ropes after each of H moves from ``rope`` (B, N, 2) under node (B, H) and drag (B, H, 2) (among
        ``pegs`` (B, K, 3), with ``pin`` (B, H) held: where the model takes them): H tensors (E, B, N, 2), one
        trajectory per member (``propagation: members``), or (B, N, 2) rolling the members' mean."""
        at = lambda t: None if pin is None else pin[..., t]                      # noqa: E731
        if propagation == "members":
            node, drag = (x.unsqueeze(0).expand(self.E, *x.shape) for x in (node, drag))
            pin = None if pin is None else pin.unsqueeze(0).expand(self.E, *pin.shape)
            pos = rope.unsqueeze(0).expand(self.E, *rope.shape)
            step = lambda x, t: self(x, node[:, :, t], drag[:, :, t], pegs, at(t))          # noqa: E731
        else:
            pos = rope
            step = lambda x, t: self.mean_move(x, node[:, t], drag[:, t], pegs, at(t))       # noqa: E731
        states = []
        for t in range(node.shape[-1]):
            pos = step(pos, t)
            states.append(pos)
        return states

    def predict(self, rope: torch.Tensor, node: torch.Tensor, drag: torch.Tensor, pegs: torch.Tensor | None = None,
                pin: torch.Tensor | None = None) -> torch.Tensor:
        """The model's point prediction (B, H, N, 2) of the ropes after each move (the members' mean, rolled)."""
        return torch.stack(self.rollout(rope, node, drag, "mean", pegs, pin), 1)


def symmetry_transform(rope: torch.Tensor, node: torch.Tensor, drag: torch.Tensor, augment: Sequence[str],
                       pegs: torch.Tensor | None = None, pin: torch.Tensor | None = None):
    """One random symmetry of the simulator per chunk, from torch's global generator: rope (B, L+1, N, 2), node
    (B, L), drag (B, L, 2), pegs (B, L+1, K, 3) and pins (B, L) where given. ``augment``: some of "reverse" (nodes
    numbered from the other end: the grasped and the held node renumbered, the pegs unchanged), "rotate" (a uniform
    rotation of the plane), "mirror" (x -> -x), the pegs' centres with the rope; exact new data
    (tests/test_dynamics.py). Returns (rope, node, drag, pegs, pin)."""
    if not augment:
        return rope, node, drag, pegs, pin
    b, dev, n = rope.shape[0], rope.device, rope.shape[-2]
    if "reverse" in augment:
        flip = torch.rand(b, device=dev) < 0.5
        rope = torch.where(flip[:, None, None, None], rope.flip(-2), rope)
        node = torch.where(flip[:, None], n - 1 - node, node)
        if pin is not None:
            pin = torch.where(flip[:, None] & (pin >= 0), n - 1 - pin, pin)
    m = torch.eye(2, device=dev, dtype=rope.dtype).expand(b, 2, 2)
    if "rotate" in augment:
        a = 2 * math.pi * torch.rand(b, device=dev, dtype=rope.dtype)
        c, s = torch.cos(a), torch.sin(a)
        m = torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    if "mirror" in augment:
        sign = torch.where(torch.rand(b, device=dev) < 0.5, -1.0, 1.0).to(rope.dtype)
        m = m * torch.stack([sign, torch.ones_like(sign)], -1)[:, None, :]      # x -> -x before the rotation
    rope = torch.einsum("bij,btnj->btni", m, rope)
    drag = torch.einsum("bij,btj->bti", m, drag)
    if pegs is not None:
        pegs = torch.cat([torch.einsum("bij,btkj->btki", m, pegs[..., :2]), pegs[..., 2:]], -1)
    return rope, node, drag, pegs, pin


# ====================================================================== planning through the model
class ModelObjective:
    """cost(actions (R, C, H, 3)) -> (R, C): the planners' cost (``planners.objective.sequence_cost``: shape error
    after the last move plus ``running_weight`` times the mean intermediate error) of each rope's candidates,
    rolled out through the model (its ``rollout``: this ensemble, or ``agents.models.latent.LatentWorldModel``,
    which plans in latent space) in one batched call per step; the members' mean cost, plus ``risk`` x their
    standard deviation."""

    def __init__(self, model: nn.Module, ropes: torch.Tensor, targets: torch.Tensor,
                 running_weight: float = 0.5, propagation: str = "members", pegs: torch.Tensor | None = None,
                 risk: float = 0.0):
        check_settings(members=getattr(model, "E", 1), propagation=propagation, risk=risk)   # the latent model: one
        self.model, self.ropes, self.targets = model, ropes.float(), targets.float()
        self.pegs = None if pegs is None else pegs.float()          # (R, K, 3): each rope's board (a route)
        self.running_weight, self.propagation, self.risk = float(running_weight), propagation, float(risk)
        self.calls = 0

    @torch.no_grad()
    def __call__(self, actions: torch.Tensor) -> torch.Tensor:
        r, c, h = actions.shape[:3]
        m = self.model
        actions = actions.to(self.ropes.device, torch.float32)
        node, drag = decode_node_action(actions[..., :3], m.p)
        node, drag = node.reshape(r * c, h), drag.reshape(r * c, h, 2)
        pos = self.ropes[:, None].expand(r, c, m.N, 2).reshape(r * c, m.N, 2)
        target = self.targets[:, None].expand(r, c, m.N, 2).reshape(r * c, m.N, 2)
        board = {}
        if self.pegs is not None:
            k = self.pegs.shape[-2]
            board["pegs"] = self.pegs[:, None].expand(r, c, k, 3).reshape(r * c, k, 3)
        if actions.shape[-1] == 4:
            board["pin"] = decode_pin(actions[..., 3].reshape(r * c, h), node, m.N)
        states = m.rollout(pos, node, drag, self.propagation, **board)      # H tensors ([E,] R C, N, 2)
        self.calls += 1
        cost = sequence_cost(states, target, self.running_weight, board.get("pegs"))
        if cost.dim() == 2:                                      # one trajectory per member: their mean cost
            cost = cost.mean(0) + self.risk * cost.std(0) if self.risk else cost.mean(0)
        return cost.view(r, c)


class ModelPlanner:
    """The acting policy of a model of node positions (the ensemble, the latent model): every rope's next move by its
    own warm-started node-categorical CEM (``planners.cem``), all ropes' CEMs in lockstep (one model call per
    iteration). Reads the rope and the target from the points observation; ``EpisodeTracker`` tells it which ropes
    are new and which moved."""

    def __init__(self, model: nn.Module, cfg, core, seed: int):
        self.model, self.cfg, self.core = model, cfg, core
        self.b = core.num_envs
        self.dim = core.action_dim                   # 3, or 4 with the second gripper (its node searched as planners.cem's)
        self.cems = [CEM(self.dim, cfg.horizon, cfg.candidates, cfg.elites, cfg.iterations,
                         discrete={0: model.N}, generator=torch.Generator().manual_seed(seed + i),
                         dtype=torch.float32) for i in range(self.b)]
        self.prev_action = torch.zeros(self.b, self.dim)
        self.tracker = EpisodeTracker(core)
        self.plan_s = 0.0
        self.planned = 0                                      # rope-moves planned

    def state_dict(self) -> dict[str, Any]:
        return {"prev_action": self.prev_action.clone(), "last_steps": self.tracker.last_steps.clone(),
                "cems": [c.state_dict() for c in self.cems], "plan_s": self.plan_s, "planned": self.planned}

    def load_state_dict(self, s: dict[str, Any]) -> None:
        if len(s["cems"]) != self.b:
            raise ValueError(f"planner state for {len(s['cems'])} ropes, this planner has {self.b}")
        self.prev_action, self.tracker.last_steps = s["prev_action"].clone(), s["last_steps"].clone()
        for c, cs in zip(self.cems, s["cems"]):
            c.load_state_dict(cs)
        self.plan_s, self.planned = float(s["plan_s"]), int(s["planned"])

    @torch.no_grad()
    def __call__(self, obs: dict[str, torch.Tensor], deterministic: bool = True) -> torch.Tensor:
        t0 = time.perf_counter()
        new, moved = self.tracker.update()
        for i in new.nonzero().flatten().tolist():
            self.cems[i].reset()
        action = self.prev_action.clone()
        rows = moved.nonzero().flatten().tolist()
        if rows:
            idx = torch.tensor(rows)
            dev = next(self.model.parameters()).device
            pegs = obs["pegs"][idx].to(dev) if "pegs" in obs else None
            obj = ModelObjective(self.model, obs["node_poses"][idx].to(dev), obs["target_poses"][idx].to(dev),
                                 self.cfg.running_weight, self.cfg.propagation, pegs, self.cfg.risk)
            bests = optimize_together([self.cems[i] for i in rows], obj)
            for i, (best, _) in zip(rows, bests):
                self.cems[i].shift()
                action[i] = best[0]
        if not deterministic and self.cfg.explore_noise > 0:
            noise = self.cfg.explore_noise * torch.randn(self.b, self.dim)
            action = torch.where(moved[:, None], (action + noise).clamp(0.0, 1.0), action)
        self.prev_action = action
        self.plan_s += time.perf_counter() - t0
        self.planned += len(rows)
        return action.to(obs["node_poses"].device)


# The open-loop error among pegs is split by each true node's distance to the nearest peg's surface: nodes nearer than
# this are "near" (in or about to be in contact: the rope's radius is 5 mm, a move drags up to 5 cm)
NEAR_PEG = 0.02        # m


def peg_clearance(pos: torch.Tensor, pegs: torch.Tensor) -> torch.Tensor:
    """(..., N) each node's distance [m] to the nearest peg's surface (``pegs`` (..., K, 3), empty slots ignored;
    inf with no peg)."""
    d = (pos.unsqueeze(-2) - pegs[..., None, :, :2]).norm(dim=-1) - pegs[..., None, :, 2]      # (..., N, K)
    return torch.where(pegs[..., None, :, 2] > 0, d, torch.full_like(d, float("inf"))).amin(-1)


@torch.no_grad()
def k_step_errors(model: EnsembleDynamics, start: torch.Tensor, actions: torch.Tensor, true: torch.Tensor,
                  horizons: Sequence[int], alive: torch.Tensor | None = None,
                  pegs: torch.Tensor | None = None) -> dict[str, float]:
    """Open-loop error of the members' mean from ``start`` (B, N, 2) under node ``actions`` (B, K, 3; 4 with the
    pin) against the true ropes (B, K, N, 2): ``pred_err_k`` (mean node distance [m] after k moves) and
    ``base_err_k`` ("nothing moves": the start rope) for each k in ``horizons``; ropes with ``alive`` False are
    left out. Among ``pegs`` (B, K, 3) also ``pred_err_near_k`` / ``pred_err_far_k``: the mean error of the nodes
    whose true position is within NEAR_PEG of a peg's surface / farther (nan where there is none)."""
    node, drag = decode_node_action(actions[..., :3].float(), model.p)
    board = {} if pegs is None else {"pegs": pegs.float()}
    if actions.shape[-1] == 4:
        board["pin"] = decode_pin(actions[..., 3].float(), node, model.N)
    pred = model.predict(start.float(), node, drag, **board)
    keep = torch.ones(start.shape[0], dtype=torch.bool) if alive is None else alive
    out = {}
    for k in horizons:
        node_err = (pred[:, k - 1] - true[:, k - 1]).norm(dim=-1)[keep]                   # (B', N)
        out[f"pred_err_{k}"] = float(node_err.mean(-1).mean())
        out[f"base_err_{k}"] = float((start - true[:, k - 1]).norm(dim=-1).mean(-1)[keep].mean())
        if pegs is not None:
            near = peg_clearance(true[:, k - 1].float(), pegs.float())[keep] < NEAR_PEG
            out[f"pred_err_near_{k}"] = float(node_err[near].mean()) if bool(near.any()) else float("nan")
            out[f"pred_err_far_{k}"] = float(node_err[~near].mean()) if bool((~near).any()) else float("nan")
    out["pred"] = pred
    return out
