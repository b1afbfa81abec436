"""Planners through the diffdlo simulator: a batched objective over action sequences, CEM, a gradient planner
through the differentiable simulator, a greedy baseline, and the shared receding-horizon (MPC) episode loop.

    python -m planners.cem --target diagonal
    python -m planners.gradient --target diagonal
    python -m planners.greedy --target diagonal --max-steps 40
"""
from .objective import SimObjective

_LAZY = {"CEM": "cem", "CEMPlanner": "cem", "GradientPlanner": "gradient", "GreedyPlanner": "greedy"}


def __getattr__(name):   # lazy, so that `python -m planners.cem` does not import planners.cem twice
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["CEM", "CEMPlanner", "GradientPlanner", "GreedyPlanner", "SimObjective"]
