"""The cable's physical parameters as per-rope tensors, so a move can be differentiated with respect to them.

``Physics(k_s, k_b, k_d, mass)`` holds one value per rope of a batch (tensors of shape (B,), or floats shared by
all ropes), so a batch can hold many candidate parameter sets at once: the calibration's several starts, or a
population of a black-box fit. ``Simulator.move(..., physics=...)`` and ``integrate(..., physics=...)`` use them
instead of the params' numbers; gradients flow to every tensor that requires them. They run in the fused C++
kernel where it applies (CPU, kinematic controller: its adjoint carries the parameter gradients, and those of
recorded frames), else in the eager torch loop.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch

from .params import CableParams

PHYSICAL = ("k_s", "k_b", "k_d", "mass")     # mass: the whole rope's [kg], shared equally by its nodes


@dataclasses.dataclass(frozen=True)
class Physics:
    """Per-rope stiffnesses k_s [N/m], k_b [N m/rad^2], damping k_d [N s/m] and total mass [kg]."""
    k_s: Any
    k_b: Any
    k_d: Any
    mass: Any

    @classmethod
    def of(cls, params: CableParams, batch: int, device: torch.device | str = "cpu",
           dtype: torch.dtype = torch.float64, requires_grad: bool = False) -> "Physics":
        """The params' numbers repeated for ``batch`` ropes, as leaf tensors (requiring gradients if asked)."""
        values = {k: torch.full((batch,), float(getattr(params, k)), device=device, dtype=dtype,
                                requires_grad=requires_grad) for k in PHYSICAL}
        return cls(**values)

    def check(self, batch: int, n_nodes: int) -> None:
        """Each value a positive finite float or a (batch,) tensor of them (k_b may be 0: no bending stiffness)."""
        for key in PHYSICAL:
            v = getattr(self, key)
            if torch.is_tensor(v):
                if v.shape not in ((), (batch,)):
                    raise ValueError(f"physics.{key} must be a float or a tensor of shape ({batch},), got shape "
                                     f"{tuple(v.shape)}")
                values = v.detach().flatten().tolist()
            elif isinstance(v, (int, float)) and not isinstance(v, bool):
                values = [float(v)]
            else:
                raise ValueError(f"physics.{key} must be a float or a tensor, got {v!r}")
            least_ok = (lambda x: x >= 0) if key == "k_b" else (lambda x: x > 0)
            bad = [x for x in values if not (math.isfinite(x) and least_ok(x))]
            if bad:
                raise ValueError(f"physics.{key} must be {'>= 0' if key == 'k_b' else '> 0'} and finite, got {bad}")

    def take(self, ropes: torch.Tensor) -> "Physics":
        """The parameters of the ropes ``ropes`` (an index tensor) of the batch: per-rope tensors indexed, shared
        values as they are."""
        pick = lambda v: v[ropes] if torch.is_tensor(v) and v.ndim == 1 else v
        return Physics(**{key: pick(getattr(self, key)) for key in PHYSICAL})

    def node_mass(self, n_nodes: int) -> Any:
        return self.mass / n_nodes


def physical_values(params: CableParams) -> dict[str, float]:
    """The params' k_s, k_b, k_d and mass."""
    return {name: getattr(params, name) for name in PHYSICAL}


def scaled_params(params: CableParams, factors: dict[str, float], flag: str = "--scale") -> CableParams:
    """``params`` with each named physical parameter multiplied by its factor: a hidden "real" rope. ValueError for
    another name or a factor that is not a positive finite number (``flag`` names the option in the message);
    ParamsError if the result is unstable."""
    for name, factor in factors.items():
        if name not in PHYSICAL:
            raise ValueError(f"{flag} {name}={factor}: can scale only {', '.join(PHYSICAL)}, not {name!r}")
        if isinstance(factor, bool) or not (isinstance(factor, (int, float)) and math.isfinite(factor) and factor > 0):
            raise ValueError(f"{flag} {name}={factor}: the factor must be a positive finite number")
    return dataclasses.replace(params, **{name: getattr(params, name) * factor for name, factor in factors.items()})


def per_rope(value: Any, ndim: int) -> Any:
    """A float as it is; a (B,) tensor shaped (B, 1, ...) to broadcast against (B, ...) tensors of ``ndim`` dims."""
    if torch.is_tensor(value) and value.ndim == 1:
        return value.view(-1, *([1] * (ndim - 1)))
    return value
