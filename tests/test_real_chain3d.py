"""The chain in 3-D (diffdlo/chain3d/chain.py): forces against autograd, gradients through rollouts, the statics against
theory (the catenary, the Euler-Bernoulli cantilever), conservation laws and dissipation, the floor, held nodes, and
refused inputs."""
import math

import pytest
import torch

from diffdlo.chain3d import chain as chain3d
from diffdlo.chain3d.chain import ChainDivergedError, ChainError, ChainParams

F64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")     # tests/conftest.py: one torch thread, restored after


def bent_chain(batch, n, seed=0, spacing=0.1, wiggle=0.8, dtype=F64):
    """(B, N, 3) random 3-D chains: links of length spacing * (1 +- 10 %), turning at random (some past 90 degrees)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(batch, 3, generator=g, dtype=F64), dim=-1)
    steps = []
    for _ in range(n - 1):
        d = torch.nn.functional.normalize(d + wiggle * torch.randn(batch, 3, generator=g, dtype=F64), dim=-1)
        steps.append(d * spacing * (1 + 0.1 * (2 * torch.rand(batch, 1, generator=g, dtype=F64) - 1)))
    x = torch.cat([torch.zeros(batch, 1, 3, dtype=F64), torch.cumsum(torch.stack(steps, 1), 1)], 1)
    return x.to(dtype)


def turning_angles(x):
    e = x[:, 1:] - x[:, :-1]
    c = torch.nn.functional.cosine_similarity(e[:, :-1], e[:, 1:], dim=-1)
    return torch.arccos(c.clamp(-1, 1))


def full_params(batch, n, seed=0, **changes):
    """Every term on, per-trajectory EI, per-link rest lengths and per-node point masses."""
    g = torch.Generator().manual_seed(seed)
    values = dict(rest_lengths=0.09 + 0.02 * torch.rand(batch, n - 1, generator=g, dtype=F64),
                  EI=torch.linspace(1e-3, 3e-3, batch, dtype=F64), EA=20.0, mass_per_length=0.03,
                  point_mass=4e-4 * torch.rand(n, generator=g, dtype=F64), drag=0.2, axial_damping=0.05,
                  bending_damping=2e-4, gravity=9.81, floor_height=0.0, floor_stiffness=50.0, floor_damping=0.05,
                  floor_width=0.02)
    values.update(changes)
    return ChainParams(**values)


# ============================================================================ (a) forces are -grad E, -dR/dv
def test_forces_equal_minus_the_energy_gradient_and_the_damping_minus_the_dissipation_gradient():
    batch, n = 4, 9
    x = bent_chain(batch, n, seed=1)
    assert turning_angles(x).max() > math.radians(90), "test shapes must bend beyond 90 degrees"
    x[..., 2] -= x[..., 2].mean(1, keepdim=True)       # about half the nodes below the floor
    x[:, 0, 2] = -0.005                                # and one in its ramp (the first 2 cm)
    depth = -x[..., 2]
    assert ((depth > 0) & (depth < 0.02)).any() and (depth > 0.02).any()
    params = full_params(batch, n)
    xr = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(chain3d.energy(xr, params).sum(), xr)
    at_rest = chain3d.forces(x, None, params)
    assert grad.abs().max() > 1e-2
    torch.testing.assert_close(at_rest, -grad, rtol=1e-10, atol=1e-10 * grad.abs().max().item())

    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(2), dtype=F64)
    vr = v.clone().requires_grad_(True)
    (dR,) = torch.autograd.grad(chain3d.dissipation(x, vr, params).sum(), vr)
    damping = chain3d.forces(x, v, params) - at_rest
    assert dR.abs().max() > 1e-2
    torch.testing.assert_close(damping, -dR, rtol=1e-10, atol=1e-10 * dR.abs().max().item())
    # every damping term takes power out: F_d . v = -2R <= 0 per trajectory
    power = (damping * v).sum((1, 2))
    torch.testing.assert_close(power, -2 * chain3d.dissipation(x, v, params), rtol=1e-10, atol=0)
    assert (power < 0).all()


def test_dtype_and_device_follow_the_inputs():
    x = bent_chain(2, 6, seed=3, dtype=torch.float32)
    params = full_params(2, 6)                          # float64 tensors in the parameters
    f = chain3d.forces(x, torch.zeros_like(x), params)
    assert f.dtype == torch.float32 and f.device == x.device
    f64 = chain3d.forces(x.double(), None, params)
    torch.testing.assert_close(f.double(), f64, rtol=1e-4, atol=1e-5)
    out = chain3d.rollout(x, None, None, None, params, substeps=10, frames=3)
    assert out.dtype == torch.float32 and out.shape == (3, 2, 6, 3)


# ============================================================================ (b) gradients through a rollout
def test_gradcheck_through_a_rollout_wrt_the_physical_parameters_the_start_and_the_held_path():
    batch, n, frames = 2, 5, 3
    held = torch.tensor([True, False, False, False, False])
    x0 = bent_chain(batch, n, seed=4, spacing=0.1)
    x0[..., 2] += 0.01 - x0[:, 1:, 2].min()             # the lowest free node 2 mm deep in the floor (at 1.2 cm)
    v0 = 0.1 * torch.randn(x0.shape, generator=torch.Generator().manual_seed(5), dtype=F64)
    path = x0[:, :1].unsqueeze(0) + 0.02 * torch.arange(frames, dtype=F64).view(-1, 1, 1, 1) * torch.tensor(
        [1.0, -0.5, 0.3], dtype=F64)
    # the physical parameters as multiples of nominal values, so one finite-difference step suits them all
    nominal = {"EI": torch.tensor([2e-3, 3e-3], dtype=F64), "EA": 5.0, "mass_per_length": 0.03,
               "point_mass": torch.full((n,), 4e-4, dtype=F64), "drag": 0.2, "axial_damping": 0.02,
               "bending_damping": 1e-4, "gravity": 9.81, "floor_height": 0.012, "floor_stiffness": 40.0,
               "floor_damping": 0.05}
    values = [torch.ones_like(torch.as_tensor(v, dtype=F64)) for v in nominal.values()]
    rest = torch.full((n - 1,), 0.1, dtype=F64)

    def run(x0, v0, path, *factors):
        physical = {name: scale * factor for (name, scale), factor in zip(nominal.items(), factors)}
        params = ChainParams(rest_lengths=rest, floor_width=0.01, **physical)
        return chain3d.rollout(x0, v0, held, path, params, substeps=4)

    run_out = run(x0, v0, path, *values)
    assert (run_out[:, :, 1:, 2] < 0.012).any(), "a node must be in the floor, so its term is checked"
    inputs = [t.clone().requires_grad_(True) for t in (x0, v0, path, *values)]
    # fast mode checks the Jacobian along random directions (1 s); the full Jacobian passes too (3 s)
    assert torch.autograd.gradcheck(run, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


# ============================================================================ (c) statics against theory
def catenary_parameter(length, span):
    """a of the catenary z = a cosh(x / a) + c of ``length`` hanging between two points ``span`` apart at one height:
    length = 2 a sinh(span / (2 a)), solved by bisection."""
    lo, hi = 1e-3, 1e3
    for _ in range(200):
        a = math.sqrt(lo * hi)
        lo, hi = (a, hi) if 2 * a * math.sinh(span / (2 * a)) > length else (lo, a)
    return a


def catenary_chain(n, length, span):
    """(1, N, 3) nodes at equal arc lengths on the catenary, the ends at z = 0, x = -+span / 2; and its a."""
    a = catenary_parameter(length, span)
    arc = (torch.linspace(0, 1, n, dtype=F64) - 0.5) * length     # from the lowest point: x = a asinh(arc / a)
    x = torch.zeros(1, n, 3, dtype=F64)
    x[0, :, 0] = a * torch.asinh(arc / a)
    x[0, :, 2] = catenary_height(x[0, :, 0], a, span)
    return x, a


def catenary_height(x, a, span):
    return a * torch.cosh(x / a) - a * math.cosh(span / (2 * a))


def energy_minimum(x, held, params, iterations=30):
    """The chain's static equilibrium: Newton's method (Levenberg-Marquardt safeguarded) on the energy over the free
    nodes, starting from x."""
    free = ~held

    def total(y):
        return chain3d.energy(torch.where(free.view(1, -1, 1), y.view(x.shape), x), params).sum()

    y = x.reshape(-1).clone()
    mask = free.view(1, -1, 1).expand_as(x).reshape(-1)
    lam = 1e-9
    for _ in range(iterations):
        grad = torch.autograd.functional.jacobian(total, y)[mask]
        hess = torch.autograd.functional.hessian(total, y)[mask][:, mask]
        scale = hess.diagonal().abs().max()
        e0 = total(y)
        while True:
            step = torch.linalg.solve(hess + lam * scale * torch.eye(len(grad), dtype=F64), -grad)
            trial = y.clone()
            trial[mask] += step
            if total(trial) <= e0:
                y, lam = trial, max(lam / 10, 1e-12)
                break
            lam *= 10
        if step.abs().max() < 1e-12:
            break
    return y.view(x.shape)


def test_a_hanging_chain_minimises_its_energy_on_the_catenary_converging_as_n_squared():
    """A heavy, nearly inextensible chain of 1 m with next to no bending stiffness hung between two points 0.8 m
    apart: the energy's minimum against the catenary through the same ends with the same length (sag 265 mm)."""
    length, span, errors = 1.0, 0.8, {}
    for n in (11, 21, 41):
        start, a = catenary_chain(n, length, span)
        held = torch.zeros(n, dtype=torch.bool)
        held[[0, -1]] = True
        params = ChainParams.uniform(n, length, EI=1e-6, EA=1e5, mass_per_length=0.03)
        x = energy_minimum(start, held, params)[0]
        errors[n] = (x[:, 2] - catenary_height(x[:, 0], a, span)).abs().max().item()
    # measured: 1.43 mm (N = 11), 0.35 mm (N = 21), 0.089 mm (N = 41), second order in the link length
    assert errors[21] < 0.5e-3 and errors[41] < 0.12e-3
    assert 3.5 < errors[21] / errors[41] < 4.5 and 3.5 < errors[11] / errors[21] < 4.5


def test_a_chain_released_between_its_ends_settles_on_the_catenary():
    """The dynamics reach that minimum: a chain hanging 0.6 m wide is pulled to 0.8 m by its held ends over 0.2 s
    and left to settle (a heavy drag) for 1 s more."""
    n, length, span, frames = 21, 1.0, 0.8, 120
    start, _ = catenary_chain(n, length, 0.6)
    held = torch.zeros(n, dtype=torch.bool)
    held[[0, -1]] = True
    half = 0.3 + 0.1 * torch.clamp(torch.arange(frames, dtype=F64) / 20, max=1.0)
    path = torch.zeros(frames, 1, 2, 3, dtype=F64)
    path[:, 0, 0, 0], path[:, 0, 1, 0] = -half, half
    params = ChainParams.uniform(n, length, EI=1e-6, EA=500.0, mass_per_length=0.03, drag=1.0)
    assert chain3d.stability_margin(params, n, 0.01 / 32, held) < 0.7
    with torch.no_grad():
        out = chain3d.rollout(start, None, held, path, params, substeps=32)
    x = out[-1, 0]
    assert (out[-1] - out[-2]).abs().max() < 1e-6, "settled: under 1 micron per frame"
    a = catenary_parameter(length, span)
    error = (x[:, 2] - catenary_height(x[:, 0], a, span)).abs().max().item()
    # measured 0.55 mm: the discrete chain's 0.35 mm (above) and the 0.1 % stretch of EA = 500 N under ~0.3 N
    assert error < 1e-3, f"{error * 1e3:.3f} mm from the catenary"
    assert abs(x[:, 2].min().item() + (a * math.cosh(span / (2 * a)) - a)) < 2e-3, "the sag, 265 mm"
    static = energy_minimum(x[None].clone(), held, params)[0]
    assert (x - static).abs().max() < 1e-6, "the rollout's rest is the model's energy minimum"


def test_a_cantilever_under_its_own_weight_bends_as_euler_bernoulli_says():
    """A rod clamped by two held nodes (as DEFORM's grippers hold two markers), 0.5 m free, with its tip 5 mm below
    the clamp by Euler-Bernoulli (w = q L^4 / (8 EI), small deflection). The discrete rod counts a whole Voronoi
    length at the clamp node where the free rod has half of it, so the tip sags by a relative ~2 l / L too much:
    first order in the link length l."""
    free_length, q, errors = 0.5, 0.03 * 9.81, {}
    EI = q * free_length ** 4 / (8 * 5e-3)
    for n in (11, 21, 41):
        link = free_length / (n - 2)
        params = ChainParams.uniform(n, (n - 1) * link, EI=EI, EA=1e6, mass_per_length=0.03)
        held = torch.zeros(n, dtype=torch.bool)
        held[[0, 1]] = True
        start = torch.zeros(1, n, 3, dtype=F64)
        start[0, :, 0] = torch.arange(n, dtype=F64) * link
        s = (start[0, 1:, 0] - link).clamp_min(0)         # from the clamp; start on Euler-Bernoulli's deflection
        start[0, 1:, 2] = -q * s ** 2 * (6 * free_length ** 2 - 4 * free_length * s + s ** 2) / (24 * EI)
        tip = -energy_minimum(start, held, params)[0, -1, 2].item()
        errors[n] = tip / 5e-3 - 1
        assert 0 < errors[n] < 2.5 * link / free_length
    # measured: +23.4 % (N = 11), +10.8 % (N = 21), +5.2 % (N = 41)
    assert 1.8 < errors[21] / errors[41] < 2.3


# ============================================================================ (d) invariants
def test_without_gravity_floor_or_damping_energy_is_conserved_to_first_order_and_momentum_exactly():
    batch, n, frames = 2, 8, 30
    x = bent_chain(batch, n, seed=6)
    v = 0.3 * torch.randn(x.shape, generator=torch.Generator().manual_seed(7), dtype=F64)
    params = ChainParams(rest_lengths=torch.full((n - 1,), 0.095, dtype=F64), EI=2e-3, EA=10.0,
                         mass_per_length=0.03, point_mass=4e-4, gravity=0.0)
    mass = chain3d.node_masses(params, n).unsqueeze(-1)
    drifts, modified_drifts = [], []
    for substeps in (10, 20):
        h = 0.01 / substeps

        def energy(x, v, modified=False):
            """The energy [J]; ``modified``: plus h/2 v.F(x), semi-implicit Euler's modified energy to O(h^2)."""
            total = chain3d.energy(x, params) + chain3d.kinetic_energy(v, params)
            return total + 0.5 * h * (v * chain3d.forces(x, None, params)).sum((1, 2)) if modified else total

        xs, vs = chain3d.rollout(x, v, None, None, params, substeps=substeps, frames=frames, return_velocities=True)
        for kind, drift in ((False, drifts), (True, modified_drifts)):
            energies = torch.stack([energy(a, b, kind) for a, b in zip(xs, vs)])
            drift.append(((energies - energy(x, v, kind)).abs().amax(0) / energy(x, v, kind)).max().item())
        assert (xs[-1] - x).abs().max() > 0.05, "the chains must actually move"
        for a, b in zip(xs, vs):
            torch.testing.assert_close((mass * b).sum(1), (mass * v).sum(1), rtol=0, atol=1e-14)
            # semi-implicit Euler: sum m x+ x v+ = sum m x x v+ = L + h sum x x F(x) = L (no internal torque)
            torch.testing.assert_close((mass * torch.linalg.cross(a, b)).sum(1),
                                       (mass * torch.linalg.cross(x, v)).sum(1), rtol=0, atol=1e-14)
    # measured over 0.3 s: the energy within 4.2 % (h = 1 ms) and 2.0 % (0.5 ms), first order in h; the modified
    # energy within 1.9e-3 and 5.2e-4, second order: the integrator is the symplectic Euler it claims to be
    assert drifts[0] < 0.05 and 1.8 < drifts[0] / drifts[1] < 2.3, drifts
    assert modified_drifts[0] < 2.5e-3 and 3.4 < modified_drifts[0] / modified_drifts[1] < 4.3, modified_drifts


def test_with_damping_the_energy_never_rises():
    batch, n = 2, 10
    x = bent_chain(batch, n, seed=8)
    x[..., 2] += 0.05 - x[..., 2].min()
    v = 0.5 * torch.randn(x.shape, generator=torch.Generator().manual_seed(9), dtype=F64)
    params = full_params(batch, n, rest_lengths=torch.full((n - 1,), 0.1, dtype=F64), floor_stiffness=200.0)
    xs, vs = chain3d.rollout(x, v, None, None, params, substeps=20, frames=40, return_velocities=True)
    total = torch.stack([chain3d.energy(a, params) + chain3d.kinetic_energy(b, params) for a, b in zip(xs, vs)])
    assert (total[-1] < total[0] - 0.1).all(), "the chains must fall onto the floor and lose energy"
    assert (xs[..., 2].min(-1).values[-1] < 0).all(), "and press into it"
    rises = (total[1:] - total[:-1]).max().item()
    assert rises < 0, f"the energy rose by {rises:.3g} J in a frame"     # measured: it falls by >= 2.2e-4 J a frame


def test_rigid_motions_give_no_force():
    n = 7
    params = full_params(1, n, rest_lengths=torch.full((n - 1,), 0.1, dtype=F64), gravity=0.0, floor_stiffness=0.0,
                         floor_damping=0.0, drag=0.0)
    straight = torch.zeros(1, n, 3, dtype=F64)
    straight[0, :, 0] = 0.1 * torch.arange(n, dtype=F64)
    angle, axis = 0.9, torch.nn.functional.normalize(torch.tensor([0.3, -1.0, 0.5], dtype=F64), dim=0)
    cross = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=F64)
    rotation = torch.eye(3, dtype=F64) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross
    moved = straight @ rotation.T + torch.tensor([0.3, -2.0, 1.1], dtype=F64)
    assert chain3d.forces(moved, None, params).abs().max() < 1e-12
    # the internal damping: zero for every rigid velocity field, on any shape
    bent = bent_chain(1, n, seed=10)
    omega, drift = torch.tensor([0.7, -1.3, 2.1], dtype=F64), torch.tensor([0.5, 0.2, -0.4], dtype=F64)
    rigid = drift + torch.linalg.cross(omega.expand_as(bent), bent)
    damping = chain3d.forces(bent, rigid, params) - chain3d.forces(bent, None, params)
    assert damping.abs().max() < 1e-12 and chain3d.dissipation(bent, rigid, params).abs().max() < 1e-12
    # the elastic forces turn with the shape
    torch.testing.assert_close(chain3d.forces(bent @ rotation.T, None, params),
                               chain3d.forces(bent, None, params) @ rotation.T, rtol=1e-10, atol=1e-12)


# ============================================================================ (e) the floor, (f) held nodes
def test_the_floor_stops_a_falling_chain():
    n = 11
    params = ChainParams.uniform(n, 1.0, EI=1e-3, EA=50.0, mass_per_length=0.03, point_mass=4e-4, drag=0.05,
                                 axial_damping=0.02, bending_damping=1e-4, floor_height=-0.2,
                                 floor_stiffness=500.0, floor_damping=2.0, floor_width=2e-3)
    x = torch.zeros(2, n, 3, dtype=F64)
    x[:, :, 0] = torch.linspace(0, 1, n, dtype=F64)
    x[1, :, 2] = 0.1 * torch.sin(torch.linspace(0, math.pi, n, dtype=F64))    # a bowed one too
    out = chain3d.rollout(x, None, None, None, params, substeps=20, frames=50)
    lowest = out[..., 2].min().item()
    # a node's weight, ~3.3 g x 9.81 = 0.032 N, presses it 0.5 mm into the floor's ramp; the impact at ~2 m/s deeper
    assert lowest > -0.2 - 5e-3, f"a node sank {(-0.2 - lowest) * 1e3:.2f} mm into the floor"     # measured 2.5 mm
    assert (out[35:, :, :, 2] + 0.2).abs().max() < 1e-3, "the chains lie on the floor: stopped, no bounce"


def test_held_nodes_follow_their_path_exactly():
    n, frames = 12, 6
    held = torch.zeros(n, dtype=torch.bool)
    held[[0, 1, -2, -1]] = True
    x0 = bent_chain(3, n, seed=11)
    g = torch.Generator().manual_seed(12)
    path = x0[:, held].unsqueeze(0) + torch.cumsum(0.01 * torch.randn(frames, 3, 4, 3, generator=g, dtype=F64), 0)
    params = full_params(3, n)
    out = chain3d.rollout(x0, None, held, path, params, substeps=7)
    assert torch.equal(out[:, :, held], path), "the held nodes sit exactly on their recorded positions"
    assert torch.equal(out[0, :, ~held], x0[:, ~held])
    assert (out[-1, :, ~held] - x0[:, ~held]).abs().max() > 1e-3


# ============================================================================ (g) refused inputs, divergence
@pytest.mark.parametrize("change, message", [
    (dict(EI=-1.0), r"'EI' \[N m\^2\] must be >= 0 and finite, got \[-1.0\]"),
    (dict(EA=float("nan")), r"'EA' \[N\] must be > 0 and finite, got \[nan\]"),
    (dict(EA=0.0), r"'EA' \[N\] must be > 0 and finite, got \[0.0\]"),
    (dict(drag=torch.tensor([0.1, -0.2])), r"'drag' \[N s/m\^2\] must be >= 0 and finite, got \[-0.2\]"),
    (dict(floor_height=float("inf")), r"'floor_height' \[m\] must be finite, got \[inf\]"),
    (dict(floor_width=0.0), r"'floor_width' \[m\] must be > 0"),
    (dict(EI=torch.ones(3)), r"'EI' must be a float or a tensor of shape \(\) or \(2,\), got a tensor of shape \(3,\)"),
    (dict(rest_lengths=torch.full((5,), 0.1)), r"'rest_lengths' must be \(4,\) or \(2, 4\).*got a tensor of shape"),
    (dict(rest_lengths=torch.tensor([0.1, 0.1, -0.1, 0.1])), r"'rest_lengths' \[m\] must be > 0 .*\[-0.1\]"),
    (dict(point_mass=torch.ones(2, 3)), r"'point_mass' must be .* got a tensor of shape \(2, 3\)"),
    (dict(mass_per_length=0.0), r"every node needs a mass > 0"),
    (dict(gravity="9.81"), r"'gravity' must be .* got str"),
])
def test_bad_parameters_are_refused_naming_the_value(change, message):
    values = dict(rest_lengths=torch.full((4,), 0.1), EI=1e-3, EA=10.0, mass_per_length=0.03)
    values.update(change)
    x = bent_chain(2, 5, seed=13)
    for call in (lambda p: chain3d.energy(x, p), lambda p: chain3d.forces(x, None, p),
                 lambda p: chain3d.rollout(x, None, None, None, p, substeps=2, frames=2)):
        with pytest.raises(ChainError, match=message):
            call(ChainParams(**values))


def test_bad_rollout_inputs_are_refused_naming_them():
    n = 5
    x = bent_chain(2, n, seed=14)
    params = ChainParams.uniform(n, 0.4, EI=1e-3, EA=10.0, mass_per_length=0.03)
    held = torch.tensor([True, False, False, False, True])
    path = x[:, held].unsqueeze(0).repeat(3, 1, 1, 1)
    with pytest.raises(ChainError, match=r"held_mask must be a bool tensor of shape \(5,\)"):
        chain3d.rollout(x, None, torch.ones(4, dtype=torch.bool), path, params, substeps=2)
    with pytest.raises(ChainError, match=r"held_path must have shape \(T, 2, 2, 3\)"):
        chain3d.rollout(x, None, held, path[:, :, :1], params, substeps=2)
    with pytest.raises(ChainError, match="held_path must hold at least one frame, all finite"):
        chain3d.rollout(x, None, held, path.clone().fill_(float("nan")), params, substeps=2)
    with pytest.raises(ChainError, match="substeps must be an integer >= 1"):
        chain3d.rollout(x, None, held, path, params, substeps=0)
    with pytest.raises(ChainError, match="frames .* is needed when no node is held"):
        chain3d.rollout(x, None, None, None, params, substeps=2)
    with pytest.raises(ChainError, match=r"x0 must be a floating-point tensor of shape \(B, N, 3\)"):
        chain3d.rollout(x[..., :2], None, held, path, params, substeps=2)
    with pytest.raises(ChainError, match="v0 must be None or"):
        chain3d.rollout(x, torch.zeros(2, n, 2, dtype=F64), held, path, params, substeps=2)


def test_a_run_with_too_large_a_substep_raises_naming_the_frame():
    n = 8
    params = ChainParams.uniform(n, 0.7, EI=1e-3, EA=1000.0, mass_per_length=0.03)
    x = bent_chain(2, n, seed=15)
    assert chain3d.stability_margin(params, n, 0.01) > 10
    with pytest.raises(ChainDivergedError, match=r"diverged .* for batch members \[0, 1\] between frame \d+ and "
                                                 r"frame \d+ .*stability_margin .*use more substeps"):
        chain3d.rollout(x, None, None, None, params, substeps=1, frames=200)
    assert chain3d.stability_margin(params, n, 0.01 / 40) < 1
    assert torch.isfinite(chain3d.rollout(x, None, None, None, params, substeps=40, frames=20)).all()
