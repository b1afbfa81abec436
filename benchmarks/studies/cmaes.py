"""A small CMA-ES (Hansen, "The CMA Evolution Strategy: A Tutorial", 2016, the (mu/mu_w, lambda) variant with
rank-one and rank-mu updates and cumulative step-size adaptation): the black-box baseline that
benchmarks/studies/calibration.py runs against the Levenberg-Marquardt fit over the same loss. A few dimensions only (the
covariance is decomposed every generation)."""
from __future__ import annotations

import math
from typing import Callable

import torch


def cma_es(objective: Callable[[torch.Tensor], torch.Tensor], x0: torch.Tensor, sigma0: float, *,
           popsize: int | None = None, generations: int = 200, seed: int = 0,
           stop: Callable[[torch.Tensor], bool] | None = None,
           bounds: tuple[float, float] | None = None) -> dict:
    """Minimize ``objective`` (P, n) -> (P,) from ``x0`` (n,) with initial step ``sigma0``. Each generation is one
    call of the objective on the whole population (``popsize``, default 4 + 3 ln n). Candidates are clipped to
    ``bounds``. Stops after ``generations`` or once ``stop(best_x)`` is true. Returns best_x, best_f,
    evaluations, generations and per-generation history of (evaluations, best_f, best_x)."""
    n = x0.numel()
    lam = popsize or 4 + int(3 * math.log(n))
    mu = lam // 2
    w = torch.log(torch.tensor(mu + 0.5, dtype=torch.float64)) - torch.log(torch.arange(1, mu + 1, dtype=torch.float64))
    w = w / w.sum()
    mueff = float(1 / (w ** 2).sum())
    cc = (4 + mueff / n) / (n + 4 + 2 * mueff / n)
    cs = (mueff + 2) / (n + mueff + 5)
    c1 = 2 / ((n + 1.3) ** 2 + mueff)
    cmu = min(1 - c1, 2 * (mueff - 2 + 1 / mueff) / ((n + 2) ** 2 + mueff))
    damps = 1 + 2 * max(0.0, math.sqrt((mueff - 1) / (n + 1)) - 1) + cs
    chi_n = math.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n * n))
    g = torch.Generator().manual_seed(seed)
    mean, sigma = x0.to(torch.float64).clone(), float(sigma0)
    pc, ps = torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
    cov = torch.eye(n, dtype=torch.float64)
    best_x, best_f, evaluations, history = mean.clone(), math.inf, 0, []
    for gen in range(generations):
        eigenvalues, basis = torch.linalg.eigh(cov)
        scale = eigenvalues.clamp_min(1e-20).sqrt()
        z = torch.randn(lam, n, generator=g, dtype=torch.float64)
        x = mean + sigma * (z * scale) @ basis.T
        if bounds is not None:
            x = x.clamp(*bounds)
        f = objective(x).to(torch.float64)
        evaluations += lam
        order = torch.argsort(f)
        if float(f[order[0]]) < best_f:
            best_f, best_x = float(f[order[0]]), x[order[0]].clone()
        history.append((evaluations, best_f, best_x.clone()))
        old = mean
        chosen = x[order[:mu]]
        mean = (w[:, None] * chosen).sum(0)
        step = (mean - old) / sigma
        inv_sqrt = basis @ torch.diag(1 / scale) @ basis.T
        ps = (1 - cs) * ps + math.sqrt(cs * (2 - cs) * mueff) * (inv_sqrt @ step)
        hsig = float(ps.norm()) / math.sqrt(1 - (1 - cs) ** (2 * (gen + 1))) / chi_n < 1.4 + 2 / (n + 1)
        pc = (1 - cc) * pc + hsig * math.sqrt(cc * (2 - cc) * mueff) * step
        spread = (chosen - old) / sigma
        cov = ((1 - c1 - cmu) * cov + c1 * (torch.outer(pc, pc) + (1 - hsig) * cc * (2 - cc) * cov)
               + cmu * spread.T @ (w[:, None] * spread))
        cov = (cov + cov.T) / 2
        sigma *= math.exp((cs / damps) * (float(ps.norm()) / chi_n - 1))
        if stop is not None and stop(best_x):
            break
    return {"best_x": best_x, "best_f": best_f, "evaluations": evaluations, "generations": len(history),
            "history": history}
