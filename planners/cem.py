"""Cross-entropy method over action sequences, and a receding-horizon CEM planner for the shape task.

``CEM`` is generic: it minimises any ``objective(actions (B, H, A)) -> (B,)`` over sequences in a box
[low, high]^A (PlaNet will give it a learned latent model's objective). Continuous dimensions get a Gaussian per
step, refit from the elites (mean/std, clipped samples). Optional discrete dimensions (``discrete={dim: K}``, the
value of category k being low + k (high - low) / (K - 1), e.g. the env's node action a0 = node / (N - 1)) get a
categorical per step refit from the elite counts; the Gaussians of the continuous dimensions are then kept per
category (the best drag depends on the grasped node: averaging the drags of elites that grasp different nodes
would blur them), refit from the elites of that category and left unchanged when a category has no elite.
Elitism: the elites of the previous iteration stay in the population with their (deterministic) costs, and the
best sequence ever seen is returned. Warm start (``shift``): the distribution and the best sequence move one step
forward; the new last step starts from the prior; the shifted best sequence is re-evaluated as one candidate.
"""
from __future__ import annotations

from typing import Callable

import torch

from .common import run_cli
from .objective import SimObjective


class CEM:
    def __init__(self, action_dim: int, horizon: int, candidates: int = 300, elites: int = 30, iterations: int = 5,
                 discrete: dict[int, int] | None = None, low: float = 0.0, high: float = 1.0,
                 init_std: float = 0.5, min_std: float = 0.01, cat_floor: float = 0.02, shift_mix: float = 0.5,
                 generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64):
        if not 1 <= elites <= candidates:
            raise ValueError(f"need 1 <= elites <= candidates, got elites={elites}, candidates={candidates}")
        discrete = dict(discrete or {})
        if len(discrete) > 1:
            raise ValueError("at most one discrete dimension is supported")
        self.A, self.H = int(action_dim), int(horizon)
        self.candidates, self.elites, self.iterations = int(candidates), int(elites), int(iterations)
        self.low, self.high = float(low), float(high)
        self.init_std, self.min_std, self.cat_floor, self.shift_mix = init_std, min_std, cat_floor, shift_mix
        self.ddim, self.K = (next(iter(discrete.items())) if discrete else (None, 1))
        self.cdims = [d for d in range(self.A) if d != self.ddim]
        self.gen = generator if generator is not None else torch.Generator().manual_seed(0)
        self.dtype = dtype
        self.history: list[dict[str, float]] = []
        self.reset()

    # ------------------------------------------------------------------ distribution
    def _prior(self, h: int):
        mid = (self.low + self.high) / 2
        mean = torch.full((h, self.K, len(self.cdims)), mid, dtype=self.dtype)
        std = torch.full_like(mean, self.init_std * (self.high - self.low))
        probs = torch.full((h, self.K), 1.0 / self.K, dtype=self.dtype)
        return mean, std, probs

    def reset(self) -> None:
        self.mean, self.std, self.probs = self._prior(self.H)
        self.best: torch.Tensor | None = None
        self.best_cost = float("inf")

    def state_dict(self) -> dict:
        """The search distribution, the warm-start plan and the generator: restoring it makes the next
        ``optimize`` bit-identical (checkpoints of learners that plan, agents/planet.py)."""
        return {"mean": self.mean.clone(), "std": self.std.clone(), "probs": self.probs.clone(),
                "best": None if self.best is None else self.best.clone(), "best_cost": self.best_cost,
                "gen": self.gen.get_state()}

    def load_state_dict(self, s: dict) -> None:
        if s["mean"].shape != self.mean.shape or s["probs"].shape != self.probs.shape:
            raise ValueError(f"CEM state of shape {tuple(s['mean'].shape)} does not fit this CEM "
                             f"({tuple(self.mean.shape)}): horizon, action or node count differ")
        self.mean, self.std, self.probs = s["mean"].clone(), s["std"].clone(), s["probs"].clone()
        self.best = None if s["best"] is None else s["best"].clone()
        self.best_cost = float(s["best_cost"])
        self.gen.set_state(s["gen"])

    def shift(self) -> None:
        """Warm start for the next control step: drop the executed first step, append a prior step."""
        mean, std, probs = self._prior(1)
        self.mean = torch.cat([self.mean[1:], mean])
        self.std = torch.cat([self.std[1:].clamp_min(0.5 * self.init_std * (self.high - self.low)), std])
        uniform = torch.full_like(self.probs[1:], 1.0 / self.K)
        self.probs = torch.cat([self.shift_mix * self.probs[1:] + (1 - self.shift_mix) * uniform, probs])
        if self.best is not None:
            self.best = torch.cat([self.best[1:], self._sample(1, mean, std, probs)[0]])
        self.best_cost = float("inf")                       # the state changed: the old cost is meaningless

    def _value(self, k: torch.Tensor) -> torch.Tensor:
        return self.low + k.to(self.dtype) * (self.high - self.low) / max(self.K - 1, 1)

    def _category(self, x: torch.Tensor) -> torch.Tensor:
        if self.ddim is None:
            return torch.zeros(x.shape[:-1], dtype=torch.int64)
        k = torch.round((x[..., self.ddim] - self.low) / (self.high - self.low) * (self.K - 1))
        return k.clamp(0, self.K - 1).to(torch.int64)

    def _sample(self, n: int, mean=None, std=None, probs=None) -> torch.Tensor:
        mean = self.mean if mean is None else mean
        std = self.std if std is None else std
        probs = self.probs if probs is None else probs
        h = mean.shape[0]
        x = torch.empty(n, h, self.A, dtype=self.dtype)
        if self.ddim is not None:
            k = torch.multinomial(probs, n, replacement=True, generator=self.gen).T          # (n, h)
            x[..., self.ddim] = self._value(k)
        else:
            k = torch.zeros(n, h, dtype=torch.int64)
        t = torch.arange(h).expand(n, h)
        m, s = mean[t, k], std[t, k]                                                          # (n, h, Ac)
        noise = torch.randn(n, h, len(self.cdims), dtype=self.dtype, generator=self.gen)
        x[..., self.cdims] = (m + s * noise).clamp(self.low, self.high)
        return x

    def _refit(self, elite: torch.Tensor) -> None:
        k = self._category(elite)                                                             # (E, H)
        xc = elite[..., self.cdims]
        if self.ddim is not None:
            counts = torch.nn.functional.one_hot(k, self.K).sum(0).to(self.dtype)             # (H, K)
            freq = counts / counts.sum(-1, keepdim=True)
            self.probs = (1 - self.cat_floor) * freq + self.cat_floor / self.K
        for t in range(self.H):
            for c in k[:, t].unique().tolist():
                sel = xc[k[:, t] == c, t]
                self.mean[t, c] = sel.mean(0)
                if sel.shape[0] > 1:
                    self.std[t, c] = sel.std(0, unbiased=False).clamp_min(self.min_std * (self.high - self.low))

    # ------------------------------------------------------------------ optimisation
    def _ask(self, it: int, n_kept: int) -> torch.Tensor:
        x = self._sample(self.candidates - n_kept)
        if it == 0 and self.best is not None:
            x[0] = self.best                                        # warm start: re-evaluate the shifted plan
        return x

    def _tell(self, pop, cost, x: torch.Tensor, c: torch.Tensor):
        c = c.detach().to("cpu", self.dtype)
        if not bool(torch.isfinite(c).all()):
            raise FloatingPointError(f"objective returned non-finite costs: {c[~torch.isfinite(c)][:5].tolist()}")
        pop = x if pop is None else torch.cat([pop, x])
        cost = c if cost is None else torch.cat([cost, c])
        order = cost.argsort()[: self.elites]
        pop, cost = pop[order], cost[order]                          # the elites survive into the next iteration
        if float(cost[0]) < self.best_cost:
            self.best, self.best_cost = pop[0].clone(), float(cost[0])
        self._refit(pop)
        self.history.append({"best": self.best_cost, "elite_mean": float(cost.mean())})
        return pop, cost

    @torch.no_grad()
    def optimize(self, objective: Callable[[torch.Tensor], torch.Tensor]) -> tuple[torch.Tensor, float]:
        """Run the iterations on ``objective``; returns the best sequence (H, A) and its cost. ``history`` gets one
        entry per iteration: the best cost so far and the mean elite cost."""
        return optimize_together([self], lambda x: objective(x[0])[None])[0]


@torch.no_grad()
def optimize_together(cems: list[CEM], objective: Callable[[torch.Tensor], torch.Tensor]
                      ) -> list[tuple[torch.Tensor, float]]:
    """Run several CEMs (one per rope, say) in lockstep: one ``objective(x (R, n, H, A)) -> (R, n)`` call per
    iteration evaluates every CEM's candidates together (one batched model call instead of R). Each CEM samples with
    its own generator and refits on its own costs, so every CEM does exactly what ``cem.optimize`` alone would do on
    the same costs. The CEMs must share horizon, action size, candidates, elites and iterations."""
    shape = {(c.H, c.A, c.candidates, c.elites, c.iterations) for c in cems}
    if len(shape) != 1:
        raise ValueError(f"optimize_together needs CEMs of one shape (H, A, candidates, elites, iterations), "
                         f"got {sorted(shape)}")
    pops: list = [None] * len(cems)
    costs: list = [None] * len(cems)
    for c in cems:
        c.history = []
    for it in range(cems[0].iterations):
        xs = [c._ask(it, 0 if pop is None else pop.shape[0]) for c, pop in zip(cems, pops)]
        cs = objective(torch.stack(xs))
        if tuple(cs.shape) != (len(cems), xs[0].shape[0]):
            raise ValueError(f"objective must return costs of shape {(len(cems), xs[0].shape[0])}, "
                             f"got {tuple(cs.shape)}")
        for i, c in enumerate(cems):
            pops[i], costs[i] = c._tell(pops[i], costs[i], xs[i], cs[i])
    return [(c.best.clone(), c.best_cost) for c in cems]


class CEMPlanner:
    """Receding-horizon CEM for the shape task: plan H moves through the simulator, execute the first, replan
    (warm-started by shifting the last solution)."""

    name = "cem"

    def __init__(self, sim, horizon: int = 2, candidates: int = 300, elites: int = 30, iterations: int = 5,
                 running_weight: float = 0.5, seed: int = 0, pin: int = 0, **cem_kw):
        self.sim, self.p = sim, sim.params
        self.pin = bool(pin)            # node_pin actions: a fourth entry, the second gripper's node, searched too
        self.cem = CEM(4 if self.pin else 3, horizon, candidates, elites, iterations, discrete={0: self.p.n_nodes},
                       generator=torch.Generator().manual_seed(seed), **cem_kw)
        self.running_weight = running_weight
        self.sim_evals = 0

    def reset(self, seed: int | None = None) -> None:
        """A new episode; ``seed``: re-seed the sampling generator (an episode's plan then depends on its own seed
        only, not on the episodes run before it in the same command)."""
        self.cem.reset()
        if seed is not None:
            self.cem.gen.manual_seed(int(seed))

    def plan(self, pos: torch.Tensor, target: torch.Tensor, pegs: torch.Tensor | None = None) -> torch.Tensor:
        """pos (N, 2), target (N, 2), a route's pegs (K, 3) -> the first action (3,), or (4,) with the pin, of the
        best plan, in [0, 1]."""
        obj = SimObjective(self.sim, pos, target, running_weight=self.running_weight, pegs=pegs)
        best, _ = self.cem.optimize(obj)
        self.sim_evals += obj.sim_evals
        self.cem.shift()
        return best[0]

    # the command line's options (planners/common.py): constructor argument -> (type, default, allowed, help)
    OPTIONS = {"horizon": (int, 2, "[1, inf)", "moves planned ahead"),
               "candidates": (int, 300, "[1, inf)", "sequences per iteration"),
               "elites": (int, 30, "[1, inf)", "elites refit per iteration (at most the candidates)"),
               "iterations": (int, 5, "[1, inf)", "CEM iterations per control step"),
               "running_weight": (float, 0.5, "[0, inf)", "weight of the intermediate states' error in the cost"),
               "pin": (int, 0, "[0, 1]", "1: plan node_pin actions (a second gripper's node, searched too)")}


def main(argv: list[str] | None = None) -> int:
    return run_cli(CEMPlanner, "cem", __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
