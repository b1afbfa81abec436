"""The cable model's parameters as an elastic rod's, and back (docs/SIMULATOR.md "The physics against the literature").

The model (the thesis "Robotic Manipulation of Deformable Linear Objects: A Model-Free Control Using Reinforcement
Learning Algorithms", Table 2.1; diffdlo/planar/forces.py) has N nodes joined by N - 1 links of rest length
l0 = length / (N - 1), the energy

    E = sum_links k_s (l - l0)^2 / 2 + sum_interior k_b beta_i^2 / 2,

and N equal node masses mass / N. A rod of bending stiffness EI, axial stiffness EA and mass per length mu stores
int EI kappa^2 / 2 ds + int EA eps^2 / 2 ds. A link stretched by the strain eps stores k_s (eps l0)^2 / 2, which is
EA eps^2 l0 / 2 for EA = k_s l0. An interior node turns the rope by beta ~ kappa l0 over its share l0 of the
length, storing k_b (kappa l0)^2 / 2 = (k_b l0) kappa^2 l0 / 2: EI = k_b l0. Both hold to O(l0^2) (the turning
angle is the rod's turn over one link to second order). So at fixed EI a finer rope needs a stiffer k_b: the same
k_b with more nodes is a softer rope. The mass per length is mass / length; the model puts mass / N on every node,
where a rod's lumped masses are mu l0 inside and mu l0 / 2 at the ends, an O(1/N) redistribution.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

from .params import CableParams, ParamsError


@dataclasses.dataclass(frozen=True)
class RodProperties:
    """The elastic rod a CableParams stands for (SI units)."""

    EI: float                 # bending stiffness [N m^2] = k_b l0
    EA: float                 # axial stiffness [N] = k_s l0
    mass_per_length: float    # mu = rho A [kg/m] = mass / length
    length: float             # L [m] = (N - 1) l0, end node to end node
    n_nodes: int
    rest_length: float        # l0 [m]
    drag_per_length: float    # the table's viscous drag per metre [N s/m^2]: N k_d / L

    @property
    def bending_length(self) -> float:
        """sqrt(EI / EA) [m]: below it the rod is as soft in stretching as in bending."""
        return math.sqrt(self.EI / self.EA)


def rod_properties(params: CableParams) -> RodProperties:
    """The rod that ``params`` discretise: EI = k_b l0, EA = k_s l0, mu = mass / length."""
    l0 = params.rest_length
    return RodProperties(EI=params.k_b * l0, EA=params.k_s * l0, mass_per_length=params.mass / params.length,
                         length=params.length, n_nodes=params.n_nodes, rest_length=l0,
                         drag_per_length=params.n_nodes * params.k_d / params.length)


def _positive(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParamsError(f"rod property {name!r} must be a number, got {value!r}")
    if not math.isfinite(value) or value <= 0:
        raise ParamsError(f"rod property {name!r} must be finite and > 0, got {value!r}")
    return float(value)


def params_for_rod(EI: float, EA: float, mass_per_length: float, length: float, n_nodes: int,
                   base: CableParams) -> CableParams:
    """The CableParams of ``base`` with k_b, k_s, mass, length and n_nodes set so that the model discretises the
    rod (EI [N m^2], EA [N], mass_per_length [kg/m], length [m]) with ``n_nodes`` nodes: the inverse of
    ``rod_properties``. Raises ParamsError naming a non-positive or non-finite value, and, as every CableParams,
    where the result breaks the integrator's stability bound (then lower ``base.dt``)."""
    EI, EA = _positive("EI", EI), _positive("EA", EA)
    mass_per_length, length = _positive("mass_per_length", mass_per_length), _positive("length", length)
    if isinstance(n_nodes, bool) or not isinstance(n_nodes, int) or n_nodes < 3:
        raise ParamsError(f"rod property 'n_nodes' must be an integer >= 3 (bending needs an interior node), "
                          f"got {n_nodes!r}")
    if not isinstance(base, CableParams):
        raise TypeError(f"base must be a CableParams, got {type(base).__name__}")
    l0 = length / (n_nodes - 1)
    return dataclasses.replace(base, n_nodes=n_nodes, length=length, mass=mass_per_length * length,
                               k_s=EA / l0, k_b=EI / l0)
