"""The CMA-ES baseline of benchmarks/studies/calibration.py finds the minimum of an ill-conditioned rotated quadratic."""
import math

import torch

from benchmarks.studies.cmaes import cma_es


def test_cma_es_minimizes_a_rotated_ill_conditioned_quadratic():
    angle = 0.6
    rot = torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]], dtype=torch.float64)
    hessian = rot @ torch.diag(torch.tensor([1.0, 1e4], dtype=torch.float64)) @ rot.T
    optimum = torch.tensor([0.3, -0.7], dtype=torch.float64)

    def objective(x):
        d = x - optimum
        return ((d @ hessian) * d).sum(-1)

    result = cma_es(objective, torch.zeros(2, dtype=torch.float64), 0.5, generations=300, seed=1)
    assert (result["best_x"] - optimum).abs().max() < 1e-4
    assert result["evaluations"] == result["generations"] * 6          # 4 + 3 ln 2 = 6 per generation
    stopped = cma_es(objective, torch.zeros(2, dtype=torch.float64), 0.5, generations=300, seed=1,
                     stop=lambda x: float(objective(x[None])[0]) < 1e-2)
    assert stopped["generations"] < result["generations"] and stopped["best_f"] < 1e-2
