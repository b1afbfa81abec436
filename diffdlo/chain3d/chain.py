"""The cable as a chain in 3-D under gravity: masses, stretching springs, discrete bending, viscous damping, a floor,
and nodes held on prescribed paths (the robots' grippers of DEFORM's recordings, diffdlo/chain3d/deform.py).

Pure batched functions of tensors (x, v: (B, N, 3) [m], [m/s], z up); device and dtype follow ``x``; every
parameter of ``ChainParams`` may be a tensor requiring gradients, and whole rollouts are differentiable.

Model (SI units; links k = 0..N-2 with e_k = x_{k+1} - x_k, rest lengths lbar_k; interior nodes i = 1..N-2 with the
Voronoi length D_i = (lbar_{i-1} + lbar_i) / 2):

    stretching   E_s = sum_k EA / (2 lbar_k) (|e_k| - lbar_k)^2               EA [N]: a Hookean rod, EA eps^2 lbar / 2
    bending      E_b = sum_i EI |kb_i|^2 / (2 D_i),  kb_i = 2 e_{i-1} x e_i / (|e_{i-1}| |e_i| + e_{i-1}.e_i)
    gravity      E_g = sum_j m_j g z_j                                        g [m/s^2] pulls towards -z
    floor        E_f = sum_j k_f H(z_f - z_j)                                 k_f [N/m] per node, z_f [m]

kb_i is the discrete curvature binormal of Bergou et al., "Discrete Elastic Rods" (SIGGRAPH 2008), the bending
measure of the discrete elastic rods DEFORM builds on: |kb_i| = 2 tan(theta_i / 2) for the turning angle theta_i
between the links at node i, so kb_i / D_i is the curvature kappa and E_b is the rod's int EI kappa^2 / 2 ds lumped
on the Voronoi lengths (to O(theta^2); for a cable without twist and with a round section, DER's bending energy
exactly). EI [N m^2] is the rod's bending stiffness, independent of the discretisation. Unlike a 1 - cos(theta)
energy, it grows without bound as a node folds back on itself (theta -> pi), as a real cable resists folding.
H is the C2 "smoothed half square" of diffdlo/planar/contact.py with width ``floor_width``: the floor's push k_f H'(z)
sets in smoothly over the first ``floor_width`` of penetration and is a linear spring past it. It is frictionless;
a normal dashpot (``floor_damping``, below) makes an impact inelastic.

Masses: node j carries mass_per_length * (its half of each adjacent link's rest length) plus ``point_mass[j]``
(a marker: 0.4 g on DEFORM's cables, ``deform.MARKER_MASS``).

Damping, a Rayleigh dissipation R (force -dR/dv, power lost 2R):

    drag          R_d = sum_j c_d lambda_j |v_j|^2 / 2             c_d [N s/m^2]: per metre, lambda_j the node's length
    axial         R_a = sum_k eta_A / (2 lbar_k) (d|e_k|/dt)^2     eta_A [N s]: Kelvin-Voigt, EA eps + eta_A deps/dt
    bending       R_b = sum_i eta_B / (2 D_i) (d|kb_i|/dt)^2       eta_B [N m^2 s]: moment EI kappa + eta_B dkappa/dt
    floor         R_f = sum_j c_f H''(z_f - z_j) (dz_j/dt)^2 / 2     c_f [N s/m] per node, on as the push sets in

The drag is the planar model's damping (diffdlo/planar/integrate.py: absolute, treated implicitly); in air it stands for
the air's drag and for whatever else the model leaves out. The planar model needs nothing more because its table
drag dominates; a cable swinging in air is damped mostly inside itself, so the two internal (Kelvin-Voigt) terms
damp the rates of the same strains the energy stores. They vanish for every rigid motion of the chain (tested):
a damping of the neighbours' full relative velocity would also brake a sagging cable swinging as a whole, the very
motion DEFORM's robots make, and confound itself with the drag in a fit. Without twist, the bending rate sees only
d theta / dt: the rotation of a node's bending plane (whirl) is undamped inside, as the energy does not see it either.

Integrator: semi-implicit (symplectic) Euler with ``substeps`` substeps of h = frame_dt / substeps per recorded
frame, the drag implicit as in the planar model, the other forces explicit:

    v+ = (v + h F(x, v) / m) / (1 + h c_d lambda / m),    x+ = x + h v+

It is stable roughly while ``stability_margin`` < 1. Held nodes follow their path, linearly interpolated between
recorded frames, at every substep (their forces are ignored; their velocity is the path's, which the internal
damping of their neighbours sees). A non-finite or runaway state raises ChainDivergedError naming the frame.

Checks (tests/test_real_chain3d.py): forces equal -grad E and the damping forces -dR/dv (autograd); gradcheck of a
rollout; the settled hanging chain against the catenary y = a cosh(x / a) + c (e.g. Irvine, "Cable Structures",
1981, ch. 1); a cantilever's tip under its own weight against Euler-Bernoulli's w = q L^4 / (8 EI) (Timoshenko and
Gere, "Mechanics of Materials"); energy and momentum conservation; the floor; held nodes; refused inputs.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, NamedTuple

import torch

from ..planar.contact import penalty

FRAME_DT = 0.01            # [s] between recorded frames: DEFORM's 100 Hz
DIVERGENCE_RADIUS = 100.0  # [m] a node farther than this from the origin has diverged
_TINY = 1e-12              # below this sin(theta) a node is straight and its bending plane (and damping) undefined

# name -> (lower bound, whether the bound is allowed, unit)
_SCALAR_RANGES: dict[str, tuple[float, bool, str]] = {
    "EI": (0.0, True, "N m^2"),
    "EA": (0.0, False, "N"),
    "mass_per_length": (0.0, True, "kg/m"),
    "drag": (0.0, True, "N s/m^2"),
    "axial_damping": (0.0, True, "N s"),
    "bending_damping": (0.0, True, "N m^2 s"),
    "gravity": (0.0, True, "m/s^2"),
    "floor_height": (-math.inf, False, "m"),
    "floor_stiffness": (0.0, True, "N/m"),
    "floor_damping": (0.0, True, "N s/m"),
    "floor_width": (0.0, False, "m"),
}


class ChainError(ValueError):
    """A chain parameter or input of the wrong shape or value; the message names it and the value."""


class ChainDivergedError(RuntimeError):
    """A rollout's state became non-finite or ran away; the message names the batch members and the frame."""


@dataclasses.dataclass(frozen=True)
class ChainParams:
    """The chain's physical parameters (SI units). Scalars: a float, or a tensor of shape () or (B,) (one value per
    trajectory of a batch). ``rest_lengths``: (N-1,) or (B, N-1); ``point_mass``: a scalar, (N,) or (B, N)."""
    rest_lengths: Any             # [m] each link's rest length
    EI: Any                       # [N m^2] bending stiffness, >= 0
    EA: Any                       # [N] axial stiffness, > 0
    mass_per_length: Any          # [kg/m] the cable's, >= 0 (every node's total mass must be > 0)
    point_mass: Any = 0.0         # [kg] extra mass on each node (markers), >= 0
    drag: Any = 0.0               # [N s/m^2] absolute viscous drag per metre of cable, >= 0
    axial_damping: Any = 0.0      # [N s] Kelvin-Voigt damping of stretching, >= 0
    bending_damping: Any = 0.0    # [N m^2 s] Kelvin-Voigt damping of bending, >= 0
    gravity: Any = 9.81           # [m/s^2] towards -z, >= 0
    floor_height: Any = 0.0       # [m] the floor's z
    floor_stiffness: Any = 0.0    # [N/m] per node, >= 0 (0: no floor)
    floor_damping: Any = 0.0      # [N s/m] per node in contact, >= 0: the floor's normal dashpot
    floor_width: Any = 1e-3       # [m] penetration over which the floor's push sets in, > 0

    @classmethod
    def uniform(cls, n_nodes: int, length: float, **values: Any) -> "ChainParams":
        """N nodes spaced equally along ``length`` [m] (float64 rest lengths); the other fields as given."""
        if isinstance(n_nodes, bool) or not isinstance(n_nodes, int) or n_nodes < 3:
            raise ChainError(f"n_nodes must be an integer >= 3 (bending needs an interior node), got {n_nodes!r}")
        return cls(rest_lengths=torch.full((n_nodes - 1,), float(length) / (n_nodes - 1), dtype=torch.float64),
                   **values)

    def check(self, batch: int, n_nodes: int) -> None:
        """ChainError naming the first field of the wrong type, shape or value (and the value)."""
        for name, (bound, inclusive, unit) in _SCALAR_RANGES.items():
            values = _values(name, getattr(self, name), [(), (batch,)], f"a float or a tensor of shape () or "
                                                                       f"({batch},)")
            ok = (lambda v: v >= bound) if inclusive else (lambda v: v > bound)
            bad = [v for v in values if not (math.isfinite(v) and ok(v))]
            if bad:
                rule = "finite" if bound == -math.inf else f"{'>=' if inclusive else '>'} {bound:g} and finite"
                raise ChainError(f"chain parameter {name!r} [{unit}] must be {rule}, got {_show(bad)}")
        links = n_nodes - 1
        rest = _values("rest_lengths", self.rest_lengths, [(links,), (batch, links)],
                       f"({links},) or ({batch}, {links}) (one per link of {n_nodes} nodes)")
        bad = [v for v in rest if not (math.isfinite(v) and v > 0)]
        if bad:
            raise ChainError(f"chain parameter 'rest_lengths' [m] must be > 0 and finite, got {_show(bad)}")
        points = _values("point_mass", self.point_mass, [(), (n_nodes,), (batch, n_nodes)],
                         f"a float or a tensor of shape (), ({n_nodes},) or ({batch}, {n_nodes})")
        bad = [v for v in points if not (math.isfinite(v) and v >= 0)]
        if bad:
            raise ChainError(f"chain parameter 'point_mass' [kg] must be >= 0 and finite, got {_show(bad)}")
        masses = node_masses(self, n_nodes, torch.float64, torch.device("cpu"), detached=True)
        if bool((masses <= 0).any()):
            raise ChainError(f"every node needs a mass > 0 [kg], got {_show(masses[masses <= 0].tolist())} "
                             f"(mass_per_length={_show(_values('m', self.mass_per_length, None, ''))}, point_mass "
                             f"{_show(points)})")


def _show(values: list[float]) -> str:
    return str([float(f"{v:.4g}") for v in values[:4]]) + (" ..." if len(values) > 4 else "")


def _values(name: str, value: Any, shapes: list[tuple[int, ...]] | None, want: str) -> list[float]:
    """``value``'s numbers as floats, after checking it is a number or a real tensor of one of ``shapes``."""
    if isinstance(value, (list, tuple)):
        try:
            value = torch.tensor(value, dtype=torch.float64)
        except (TypeError, ValueError) as exc:
            raise ChainError(f"chain parameter {name!r} must be {want}, got {value!r} ({exc})") from None
    if torch.is_tensor(value):
        if value.is_complex() or not (value.is_floating_point() or value.dtype in (torch.int32, torch.int64)):
            raise ChainError(f"chain parameter {name!r} must be a real tensor, got dtype {value.dtype}")
        if shapes is not None and tuple(value.shape) not in shapes:
            raise ChainError(f"chain parameter {name!r} must be {want}, got a tensor of shape {tuple(value.shape)}")
        return value.detach().double().flatten().tolist()
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if shapes is not None and () not in shapes:
            raise ChainError(f"chain parameter {name!r} must be a tensor of shape {want}, got {value!r}")
        return [float(value)]
    raise ChainError(f"chain parameter {name!r} must be {want}, got {type(value).__name__} {value!r}")


def _as(value: Any, like: torch.Tensor) -> torch.Tensor:
    if torch.is_tensor(value):
        return value.to(device=like.device, dtype=like.dtype)
    return torch.tensor(value, device=like.device, dtype=like.dtype)


def _scalar(value: Any, like: torch.Tensor) -> torch.Tensor:
    """A () tensor, or a (B,) tensor shaped (B, 1) to broadcast over (B, N) arrays."""
    t = _as(value, like)
    return t.view(-1, 1) if t.ndim == 1 else t


def _is_zero(value: Any) -> bool:
    """A plain number 0 (a term that cannot matter, nor need a gradient, is skipped)."""
    return isinstance(value, (int, float)) and float(value) == 0.0


class _Resolved(NamedTuple):
    """The parameters as tensors of ``x``'s dtype and device, shaped to broadcast against (B, N) arrays."""
    rest: torch.Tensor         # (B|1, N-1) [m]
    voronoi: torch.Tensor      # (B|1, N-2) [m] D_i of the interior nodes
    lumped: torch.Tensor       # (B|1, N) [m] each node's share of the cable's length
    mass: torch.Tensor         # (B|1, N) [kg]
    EI: torch.Tensor
    EA: torch.Tensor
    drag: torch.Tensor         # (B|1, N) [N s/m] c_d lambda_j
    axial_damping: torch.Tensor | None
    bending_damping: torch.Tensor | None
    gravity: torch.Tensor
    floor_height: torch.Tensor
    floor_stiffness: torch.Tensor | None
    floor_damping: torch.Tensor | None
    floor_width: torch.Tensor


def _lengths(rest: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B|1, N-1) rest lengths -> the interior nodes' Voronoi lengths (B|1, N-2) and every node's share (B|1, N)."""
    pad = rest.new_zeros(rest.shape[0], 1)
    lumped = 0.5 * (torch.cat([pad, rest], 1) + torch.cat([rest, pad], 1))
    return lumped[:, 1:-1], lumped


def node_masses(params: ChainParams, n_nodes: int, dtype: torch.dtype = torch.float64,
                device: torch.device | str = "cpu", detached: bool = False) -> torch.Tensor:
    """(B|1, N) each node's mass [kg]: mass_per_length times its share of the length, plus its point mass."""
    like = torch.empty(0, dtype=dtype, device=device)
    rest = _as(params.rest_lengths, like)
    rest = rest.reshape(-1, n_nodes - 1) if rest.ndim >= 1 else rest
    point = _as(params.point_mass, like)
    point = point.view(-1, n_nodes) if point.ndim == 1 or point.ndim == 2 else point
    _, lumped = _lengths(rest)
    mass = _scalar(params.mass_per_length, like) * lumped + point
    return mass.detach() if detached else mass


def _resolve(params: ChainParams, x: torch.Tensor) -> _Resolved:
    n = x.shape[1]
    rest = _as(params.rest_lengths, x).reshape(-1, n - 1)
    voronoi, lumped = _lengths(rest)
    optional = {name: None if _is_zero(getattr(params, name)) else _scalar(getattr(params, name), x)
                for name in ("axial_damping", "bending_damping", "floor_stiffness", "floor_damping")}
    return _Resolved(rest=rest, voronoi=voronoi, lumped=lumped,
                     mass=node_masses(params, n, x.dtype, x.device), EI=_scalar(params.EI, x),
                     EA=_scalar(params.EA, x), drag=_scalar(params.drag, x) * lumped,
                     gravity=_scalar(params.gravity, x), floor_height=_scalar(params.floor_height, x),
                     floor_width=_scalar(params.floor_width, x), **optional)


def _check_state(x: torch.Tensor, name: str = "x") -> None:
    if not torch.is_tensor(x) or not x.is_floating_point() or x.ndim != 3 or x.shape[2] != 3 or x.shape[1] < 3:
        shape = tuple(x.shape) if torch.is_tensor(x) else type(x).__name__
        raise ChainError(f"{name} must be a floating-point tensor of shape (B, N, 3) with N >= 3, got {shape}")


# ====================================================================== energy and forces
def _links(x: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) -> (B, N-1, 3) link vectors e_k = x_{k+1} - x_k."""
    return x[:, 1:] - x[:, :-1]


def _to_nodes(per_link: torch.Tensor) -> torch.Tensor:
    """-(d/dx) of a function of the links given its gradient (B, N-1, 3) per link: node j gets g_j - g_{j-1}."""
    pad = per_link.new_zeros(per_link.shape[0], 1, 3)
    return torch.cat([per_link, pad], 1) - torch.cat([pad, per_link], 1)


def _curvature_binormal(x: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) -> (B, N-2, 3) kb_i = 2 e_{i-1} x e_i / (|e_{i-1}| |e_i| + e_{i-1}.e_i), |kb_i| = 2 tan(theta_i/2)."""
    e = _links(x)
    a, b = e[:, :-1], e[:, 1:]
    den = a.norm(dim=-1) * b.norm(dim=-1) + (a * b).sum(-1)
    return 2.0 * torch.linalg.cross(a, b) / den.unsqueeze(-1)


def _energy(x: torch.Tensor, p: _Resolved) -> torch.Tensor:
    length = _links(x).norm(dim=-1)
    stretching = (0.5 * p.EA / p.rest * (length - p.rest) ** 2).sum(-1)
    bending = (0.5 * p.EI / p.voronoi * (_curvature_binormal(x) ** 2).sum(-1)).sum(-1)
    gravity = (p.mass * p.gravity * x[..., 2]).sum(-1)
    total = stretching + bending + gravity
    if p.floor_stiffness is not None:
        h, _, _ = penalty(p.floor_height - x[..., 2], p.floor_width)
        total = total + (p.floor_stiffness * h).sum(-1)
    return total


def _unit_normals(a_hat: torch.Tensor, b_hat: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """In the plane of the links at each node: u_a (_|_ a, towards b) and u_b (_|_ b, towards a), unit vectors; zero
    where the links are parallel (sin theta < _TINY) and the plane is undefined."""
    def unit(w: torch.Tensor) -> torch.Tensor:
        n2 = (w * w).sum(-1, keepdim=True)
        return torch.where(n2 > _TINY ** 2, w / n2.clamp_min(_TINY ** 2).sqrt(), torch.zeros_like(w))
    c = c.unsqueeze(-1)
    return unit(b_hat - c * a_hat), unit(a_hat - c * b_hat)


def _forces(x: torch.Tensor, v: torch.Tensor | None, p: _Resolved, with_drag: bool) -> torch.Tensor:
    """Every force on every node [N] (B, N, 3) at (x, v): -grad E, minus dR/dv of the internal damping (v given),
    and the drag -c_d lambda v where ``with_drag`` (the integrator treats it implicitly instead)."""
    e = _links(x)
    length = e.norm(dim=-1)                                   # (B, N-1)
    unit = e / length.unsqueeze(-1)
    a_hat, b_hat = unit[:, :-1], unit[:, 1:]
    len_a, len_b = length[:, :-1].unsqueeze(-1), length[:, 1:].unsqueeze(-1)
    c = (a_hat * b_hat).sum(-1)                               # cos(theta_i), (B, N-2)
    pad = e.new_zeros(e.shape[0], 1, 3)
    # dE/de_k. Bending: E_i = 2 EI (1 - c) / (D (1 + c)), dE_i/dc = -4 EI / (D (1 + c)^2),
    # dc/da = (b^ - c a^) / |a|, dc/db = (a^ - c b^) / |b|.
    grad = (p.EA / p.rest * (length - p.rest)).unsqueeze(-1) * unit
    dE_dc = (-4.0 * p.EI / (p.voronoi * (1.0 + c) ** 2)).unsqueeze(-1)
    c3 = c.unsqueeze(-1)
    grad = grad + torch.cat([dE_dc * (b_hat - c3 * a_hat) / len_a, pad], 1) \
        + torch.cat([pad, dE_dc * (a_hat - c3 * b_hat) / len_b], 1)
    force = _to_nodes(grad)
    weight = p.mass * p.gravity
    if p.floor_stiffness is not None or (p.floor_damping is not None and v is not None):
        _, push, onset = penalty(p.floor_height - x[..., 2], p.floor_width)
        if p.floor_stiffness is not None:
            weight = weight - p.floor_stiffness * push
        if p.floor_damping is not None and v is not None:
            weight = weight + p.floor_damping * onset * v[..., 2]
    force = force - torch.stack([torch.zeros_like(x[..., 0]), torch.zeros_like(x[..., 0]),
                                 weight.expand_as(x[..., 2])], -1)
    if v is None:
        return force
    rate = _links(v)                                          # d e_k / dt
    damping = torch.zeros_like(rate)                          # dR/d(de_k/dt)
    if p.axial_damping is not None:
        stretch_rate = (unit * rate).sum(-1)                  # d|e_k|/dt
        damping = damping + (p.axial_damping / p.rest * stretch_rate).unsqueeze(-1) * unit
    if p.bending_damping is not None:
        # d theta/dt = -(u_a . da/dt / |a| + u_b . db/dt / |b|), d|kb|/dt = 2 / (1 + c) d theta/dt.
        u_a, u_b = _unit_normals(a_hat, b_hat, c)
        turn_a, turn_b = u_a / len_a, u_b / len_b
        ds_dtheta = 2.0 / (1.0 + c)
        bend_rate = -ds_dtheta * ((turn_a * rate[:, :-1]).sum(-1) + (turn_b * rate[:, 1:]).sum(-1))
        scale = (-p.bending_damping / p.voronoi * bend_rate * ds_dtheta).unsqueeze(-1)
        damping = damping + torch.cat([scale * turn_a, pad], 1) + torch.cat([pad, scale * turn_b], 1)
    force = force + _to_nodes(damping)
    if with_drag:
        force = force - p.drag.unsqueeze(-1) * v
    return force


def energy(x: torch.Tensor, params: ChainParams) -> torch.Tensor:
    """(B, N, 3) -> (B,) potential energy [J]: stretching, bending, gravity (zero at z = 0) and the floor."""
    _check_state(x)
    params.check(x.shape[0], x.shape[1])
    return _energy(x, _resolve(params, x))


def kinetic_energy(v: torch.Tensor, params: ChainParams) -> torch.Tensor:
    """(B, N, 3) -> (B,) kinetic energy [J] of the node masses."""
    _check_state(v, "v")
    params.check(v.shape[0], v.shape[1])
    return 0.5 * (node_masses(params, v.shape[1], v.dtype, v.device) * (v * v).sum(-1)).sum(-1)


def dissipation(x: torch.Tensor, v: torch.Tensor, params: ChainParams) -> torch.Tensor:
    """(B,) Rayleigh dissipation function R [W] (drag, axial and bending damping): the damping forces are -dR/dv
    and they take 2R of power from the chain. Written from the strains' rates, independently of ``forces``."""
    _check_state(x)
    _check_state(v, "v")
    params.check(x.shape[0], x.shape[1])
    p = _resolve(params, x)
    drag = 0.5 * (p.drag * (v * v).sum(-1)).sum(-1)
    e, rate = _links(x), _links(v)
    stretch_rate = (e * rate).sum(-1) / e.norm(dim=-1)
    total = drag + (0.5 * _scalar(params.axial_damping, x) / p.rest * stretch_rate ** 2).sum(-1)
    # d|kb|/dt as the derivative of |kb| along v (autograd), so this does not share the forces' formula
    _, bend_rate = torch.autograd.functional.jvp(lambda y: _curvature_binormal(y).norm(dim=-1), x, v,
                                                 create_graph=torch.is_grad_enabled())
    _, _, onset = penalty(p.floor_height - x[..., 2], p.floor_width)
    floor = 0.5 * (_scalar(params.floor_damping, x) * onset * v[..., 2] ** 2).sum(-1)
    return total + (0.5 * _scalar(params.bending_damping, x) / p.voronoi * bend_rate ** 2).sum(-1) + floor


def forces(x: torch.Tensor, v: torch.Tensor | None, params: ChainParams) -> torch.Tensor:
    """(B, N, 3) every force on every node [N] at positions x and velocities v (None: at rest): -grad ``energy``
    and -dR/dv of ``dissipation``."""
    _check_state(x)
    if v is not None:
        _check_state(v, "v")
        if v.shape != x.shape:
            raise ChainError(f"v must have x's shape {tuple(x.shape)}, got {tuple(v.shape)}")
    params.check(x.shape[0], x.shape[1])
    return _forces(x, v, _resolve(params, x), with_drag=True)


# ====================================================================== time stepping
def stability_margin(params: ChainParams, n_nodes: int, substep: float,
                     held_mask: torch.Tensor | None = None) -> float:
    """An estimate of the semi-implicit Euler step's stability: stable below 1, unstable well above it.

    For one mode x'' = -w^2 x - gamma x' with the damping explicit the step is stable iff h^2 w^2 / 4 + h gamma / 2
    < 1. The stiffest modes are the zigzags: w^2 <= (4 EA / lbar + 16 EI / (D lbar^2) + k_f) / m and
    gamma <= (4 eta_A / lbar + 16 eta_B / (D lbar^2) + c_f) / m, here with the shortest rest length for lbar and D and
    the lightest node not in ``held_mask``: an upper estimate (the implicit drag only helps, and is left out)."""
    if isinstance(n_nodes, bool) or not isinstance(n_nodes, int) or n_nodes < 3:
        raise ChainError(f"n_nodes must be an integer >= 3, got {n_nodes!r}")
    def most(name: str) -> float:
        return max(_values(name, getattr(params, name), None, ""))
    rest = min(_values("rest_lengths", params.rest_lengths, None, ""))
    masses = node_masses(params, n_nodes, detached=True)
    if held_mask is not None and not bool(held_mask.all()):
        masses = masses[:, ~held_mask.cpu()]
    mass = float(masses.min())
    w2 = (4.0 * most("EA") / rest + 16.0 * most("EI") / rest ** 3 + most("floor_stiffness")) / mass
    gamma = (4.0 * most("axial_damping") / rest + 16.0 * most("bending_damping") / rest ** 3
             + most("floor_damping")) / mass
    return substep ** 2 * w2 / 4.0 + substep * gamma / 2.0


def _check_rollout_inputs(x0: torch.Tensor, v0: torch.Tensor | None, held_mask: torch.Tensor | None,
                          held_path: torch.Tensor | None, substeps: int, frame_dt: float,
                          frames: int | None) -> tuple[torch.Tensor, int]:
    """The held mask as an (N,) bool tensor on x0's device, and the number of frames T."""
    _check_state(x0, "x0")
    batch, n = x0.shape[:2]
    if v0 is not None and (not torch.is_tensor(v0) or v0.shape != x0.shape or v0.dtype != x0.dtype):
        raise ChainError(f"v0 must be None or a {x0.dtype} tensor of x0's shape {tuple(x0.shape)}, got "
                         f"{tuple(v0.shape) if torch.is_tensor(v0) else type(v0).__name__}")
    for name, value in (("x0", x0), ("v0", v0)):
        if value is not None and not bool(torch.isfinite(value).all()):
            raise ChainError(f"{name} must be finite, got {int((~torch.isfinite(value)).sum())} non-finite values")
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise ChainError(f"substeps must be an integer >= 1 (substeps per recorded frame), got {substeps!r}")
    if isinstance(frame_dt, bool) or not isinstance(frame_dt, (int, float)) or not (0 < frame_dt < math.inf):
        raise ChainError(f"frame_dt must be a number > 0 [s], got {frame_dt!r}")
    if held_mask is None:
        held_mask = torch.zeros(n, dtype=torch.bool)
    if not torch.is_tensor(held_mask) or held_mask.dtype != torch.bool or tuple(held_mask.shape) != (n,):
        shape = tuple(held_mask.shape) if torch.is_tensor(held_mask) else type(held_mask).__name__
        raise ChainError(f"held_mask must be a bool tensor of shape ({n},) (True on the held nodes), got {shape}")
    held_mask = held_mask.to(x0.device)
    n_held = int(held_mask.sum())
    if n_held == 0:
        if held_path is not None and held_path.numel() > 0:
            raise ChainError(f"held_path must be None when no node is held, got shape {tuple(held_path.shape)}")
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
            raise ChainError(f"frames (an integer >= 1) is needed when no node is held, got {frames!r}")
        return held_mask, frames
    want = f"(T, {batch}, {n_held}, 3): the {n_held} held nodes' positions [m] per recorded frame"
    if not torch.is_tensor(held_path) or held_path.ndim != 4 or tuple(held_path.shape[1:]) != (batch, n_held, 3):
        shape = tuple(held_path.shape) if torch.is_tensor(held_path) else type(held_path).__name__
        raise ChainError(f"held_path must have shape {want}, got {shape}")
    if held_path.dtype != x0.dtype or held_path.device != x0.device:
        raise ChainError(f"held_path must be {x0.dtype} on {x0.device} like x0, got {held_path.dtype} on "
                         f"{held_path.device}")
    if held_path.shape[0] < 1 or not bool(torch.isfinite(held_path).all()):
        raise ChainError(f"held_path must hold at least one frame, all finite, got shape {tuple(held_path.shape)} "
                         f"with {int((~torch.isfinite(held_path)).sum())} non-finite values")
    if frames is not None and frames != held_path.shape[0]:
        raise ChainError(f"frames={frames!r} disagrees with held_path's {held_path.shape[0]} frames")
    return held_mask, held_path.shape[0]


def _check_diverged(x: torch.Tensor, frame: int, frame_dt: float, substep: float, margin: float) -> None:
    with torch.no_grad():
        flat = x.flatten(1)
        bad = ~torch.isfinite(flat).all(1) | (flat.abs().amax(1) > DIVERGENCE_RADIUS)
        if bool(bad.any()):
            ids = bad.nonzero().flatten().tolist()
            raise ChainDivergedError(
                f"the chain diverged (NaN/inf or farther than {DIVERGENCE_RADIUS} m) for batch members {ids} between "
                f"frame {frame - 1} and frame {frame} (t = {(frame - 1) * frame_dt:.4g} to {frame * frame_dt:.4g} s) "
                f"with substeps of {substep:.3g} s (stability_margin {margin:.3g}, stable below 1): use more substeps")


def rollout(x0: torch.Tensor, v0: torch.Tensor | None, held_mask: torch.Tensor | None,
            held_path: torch.Tensor | None, params: ChainParams, substeps: int, *, frame_dt: float = FRAME_DT,
            frames: int | None = None, return_velocities: bool = False,
            accel: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None
            ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Simulate T recorded frames of B chains; returns positions (T, B, N, 3) [m], frame 0 the start (with
    ``return_velocities`` also the velocities (T, B, N, 3) [m/s] at each frame, those of its last substep).

    x0, v0: (B, N, 3) the state at frame 0 (v0 None: at rest). held_mask: (N,) bool, the held nodes (None: none).
    held_path: (T, B, H, 3) the H held nodes' positions at each frame [m]; between frames k and k + 1 they move
    linearly (velocity (P_{k+1} - P_k) / frame_dt) and sit exactly on P_{k+1} at its end; their entries of x0 and
    v0 are replaced by the path's (the velocity of its first frame). With nothing held, ``frames`` gives T.
    ``substeps`` per frame of ``frame_dt`` [s]. ``accel(x, v) -> (B, N, 3)`` [m/s^2]: an extra acceleration (e.g. a
    learned correction, diffdlo.chain3d.residual), evaluated once per frame from the state at the frame's start (the
    held nodes' velocity that of their path over the frame) and held over its substeps, added in the velocity update.
    Differentiable with respect to x0, v0, held_path, every tensor of ``params`` (and accel's own parameters).
    Raises ChainError for bad inputs and ChainDivergedError, naming the frame, for a state that becomes non-finite
    or runs away."""
    held, n_frames = _check_rollout_inputs(x0, v0, held_mask, held_path, substeps, frame_dt, frames)
    batch, n = x0.shape[:2]
    params.check(batch, n)
    p = _resolve(params, x0)
    h = frame_dt / substeps
    margin = stability_margin(params, n, h, held)
    mass = p.mass.unsqueeze(-1)
    damp = 1.0 / (1.0 + h * p.drag.unsqueeze(-1) / mass)
    v = torch.zeros_like(x0) if v0 is None else v0
    index = held.nonzero().flatten()
    is_held = held.view(1, n, 1)

    def place(path_frame: torch.Tensor) -> torch.Tensor:
        return x0.new_zeros(batch, n, 3).index_copy(1, index, path_frame)

    x = x0 if held_path is None else torch.where(is_held, place(held_path[0]), x0)
    if held_path is not None and n_frames > 1:
        v = torch.where(is_held, (place(held_path[1]) - place(held_path[0])) / frame_dt, v)
    positions, velocities = [x], [v]
    for k in range(1, n_frames):
        if held_path is not None:
            start, end = place(held_path[k - 1]), place(held_path[k])
            v_held = (end - start) / frame_dt
            v = torch.where(is_held, v_held, v)
        kick = None if accel is None else h * accel(x, v)
        for s in range(1, substeps + 1):
            step = v + (h / mass) * _forces(x, v, p, with_drag=False)
            v = (step if kick is None else step + kick) * damp
            x = x + h * v
            if held_path is not None:
                alpha = s / substeps
                x = torch.where(is_held, (1.0 - alpha) * start + alpha * end, x)
                v = torch.where(is_held, v_held, v)
        _check_diverged(x, k, frame_dt, h, margin)
        positions.append(x)
        velocities.append(v)
    return (torch.stack(positions), torch.stack(velocities)) if return_velocities else torch.stack(positions)
