"""Gradient-based shape planner: optimise the drag vector of the next move by backpropagating the shape error
through the differentiable simulator (Adam), in one batch over candidate grasp nodes and restarts.

Node choice: the grasped node is discrete, so every node of the rope is a candidate (N = 20 rows of the batch,
times ``restarts`` initial drags: restart 0 drags the node straight towards its place in the centroid-aligned target
(the greedy move), the others are uniform in the action box). All rows are optimised together; successive halving
drops the worse half of the rows every ``iters // (halvings + 1)`` iterations, so most of the budget goes to the
promising nodes. The drag is parametrised as d = s tanh(u) (s = action_scale, the env's per-axis box), so every
iterate is a valid env action. The move executed is the best (node, drag) seen over all iterates (each forward
pass gives the cost of the current iterate for free). Gradient norms are recorded; a non-finite gradient or cost
raises FloatingPointError (never silently zeroed).

A route among pegs: the cost is the route's (planners/objective.py: on the board, plus SIDE_COST per peg on the wrong
side, which has no gradient), the greedy start drags towards each node's place on the board. With ``--pin 1`` every
row is also tried with a second gripper holding: no node, either end, or the node nearest each peg (the pin is
discrete: the rows cover it, the gradient the drag).

    python -m planners.gradient --target diagonal
    python -m planners.gradient --target route:u_two_pegs --pin 1
"""
from __future__ import annotations

import math

import torch

from diffdlo.tasks.task import encode_node_action, encode_pin, greedy_drags

from .common import run_cli
from .objective import SimObjective


class GradientPlanner:
    name = "gradient"

    def __init__(self, sim, iters: int = 12, restarts: int = 2, lr: float = 0.3, halvings: int = 2, seed: int = 0,
                 nodes: list[int] | None = None, pin: int = 0):
        self.sim, self.p = sim, sim.params
        self.pin = bool(pin)
        self.iters, self.restarts, self.lr, self.halvings = int(iters), int(restarts), float(lr), int(halvings)
        self.nodes = list(range(self.p.n_nodes)) if nodes is None else list(nodes)
        self.gen = torch.Generator().manual_seed(seed)
        self.sim_evals = 0           # forward rope-moves
        self.grad_evals = 0          # rope-moves backpropagated (each costs ~1-2 forward moves)
        self.grad_norms: list[float] = []      # per Adam iteration: the largest per-row |dcost/du|
        self.last: dict = {}

    def reset(self, seed: int | None = None) -> None:
        """A new episode; ``seed``: re-seed the restarts' generator (as CEMPlanner.reset)."""
        if seed is not None:
            self.gen.manual_seed(int(seed))

    def episode_stats(self) -> dict:
        g = torch.tensor(self.grad_norms or [float("nan")])
        return {"grad_evals": self.grad_evals, "grad_norm_median": float(g.median()), "grad_norm_max": float(g.max())}

    def _init_u(self, pos: torch.Tensor, target: torch.Tensor, align: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        s = self.p.action_scale
        nodes = torch.tensor(self.nodes, dtype=torch.int64)
        inits = [greedy_drags(pos, target, self.p.max_disp, align)[0][nodes] / s]    # the greedy move of each node
        for _ in range(self.restarts - 1):
            inits.append(torch.rand(len(nodes), 2, generator=self.gen, dtype=pos.dtype) * 2 - 1)
        d = torch.cat(inits).clamp(-0.9, 0.9)
        return nodes.repeat(self.restarts), torch.atanh(d).to(pos.dtype)

    def pin_candidates(self, pos: torch.Tensor, pegs: torch.Tensor | None) -> torch.Tensor:
        """The second gripper's options: no pin (-1), either end, and the node nearest each peg."""
        options = [-1, 0, self.p.n_nodes - 1]
        if pegs is not None:
            options += (pos[None] - pegs[:, None, :2]).norm(dim=-1).argmin(-1).tolist()
        return torch.tensor(sorted(set(options)), dtype=torch.int64)

    def optimize(self, obj: SimObjective, node: torch.Tensor, u: torch.Tensor, pin: torch.Tensor | None = None):
        """Adam on u (B, 2) for the one-move problem with fixed nodes (B,) (and pins (B,)). Returns the best node,
        drag, cost and pin."""
        s = self.p.action_scale
        u = u.clone().requires_grad_(True)
        opt = torch.optim.Adam([u], lr=self.lr)
        best_cost = torch.full((u.shape[0],), math.inf, dtype=u.dtype)
        best_d = torch.zeros_like(u)
        rows = torch.arange(u.shape[0])                                          # rows still optimised
        stage = max(self.iters // (self.halvings + 1), 1)
        trace = []
        for it in range(self.iters):
            opt.zero_grad()
            d = s * torch.tanh(u[rows])
            cost = obj.rollout_deltas(node[rows, None], d[:, None], pin=None if pin is None else pin[rows, None])
            self.grad_evals += len(rows)
            if not bool(torch.isfinite(cost).all()):
                raise FloatingPointError(f"non-finite cost in the gradient planner: {cost.tolist()}")
            c = cost.detach()
            better = c < best_cost[rows]
            best_cost[rows[better]] = c[better]
            best_d[rows[better]] = d.detach()[better]
            cost.sum().backward()
            g = u.grad[rows]
            if not bool(torch.isfinite(g).all()):
                raise FloatingPointError(f"non-finite gradient in the gradient planner at iteration {it}")
            self.grad_norms.append(float(g.norm(dim=-1).max()))
            trace.append(float(best_cost.min()))
            opt.step()
            if (it + 1) % stage == 0 and (it + 1) // stage <= self.halvings and len(rows) > 1:
                keep = best_cost[rows].argsort()[: max(len(rows) // 2, 1)]
                rows = rows[keep]
        k = int(best_cost.argmin())
        self.last = {"trace": trace, "cost": float(best_cost[k])}
        return node[k], best_d[k], float(best_cost[k]), (None if pin is None else pin[k])

    def plan(self, pos: torch.Tensor, target: torch.Tensor, pegs: torch.Tensor | None = None) -> torch.Tensor:
        obj = SimObjective(self.sim, pos, target, pegs=pegs)
        node, u = self._init_u(obj.start, obj.target, align=pegs is None)
        pin = None
        if self.pin:
            pins = self.pin_candidates(obj.start, obj.pegs)
            node, u = node.repeat(len(pins)), u.repeat(len(pins), 1)
            pin = pins.repeat_interleave(len(node) // len(pins))
            pin = torch.where(pin == node, torch.full_like(pin, -1), pin)
        n, d, _, held = self.optimize(obj, node, u, pin)
        self.sim_evals += obj.sim_evals
        action = encode_node_action(n, d, self.p.n_nodes, self.p.action_scale)
        return action if held is None else torch.cat([action, encode_pin(held, self.p.n_nodes, action.dtype)[None]])

    # the command line's options (planners/common.py): constructor argument -> (type, default, allowed, help)
    OPTIONS = {"iters": (int, 12, "[1, inf)", "Adam iterations per control step"),
               "restarts": (int, 2, "[1, inf)", "initial drags per node"),
               "lr": (float, 0.3, "(0, inf)", "Adam learning rate on u, d = s tanh(u)"),
               "halvings": (int, 2, "[0, inf)", "successive halvings of the rows"),
               "pin": (int, 0, "[0, 1]", "1: node_pin actions, the rows also tried with each pin candidate")}


def main(argv: list[str] | None = None) -> int:
    return run_cli(GradientPlanner, "gradient", __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
