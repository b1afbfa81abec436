"""The fused C++ kernel of the 3-D chain's gripper move and its adjoint (diffdlo/chain3d/kernel.py) against the eager
chain, its reference: the same moves, settles, rest frames, gradients and refusals; gradcheck of the adjoint; where
it is not used (parameters' gradients, a residual) and what happens without a compiler."""
import dataclasses
import warnings

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import diffdlo
from diffdlo.chain3d import grippers as gr
from diffdlo.chain3d import kernel
from diffdlo.chain3d.cables import load_cable
from diffdlo.chain3d.chain import ChainDivergedError, ChainError
from diffdlo.envs.cable3d import BatchedCable3D
from diffdlo.tasks import cable3d as rules

pytestmark = pytest.mark.skipif(not kernel.available(), reason="no C++ compiler: the kernel is not built")
SETTLE = {"rest_speed": 0.01, "check_frames": 10}


def start_and_goal(cable, batch, dtype, seed=0):
    generator = torch.Generator().manual_seed(seed)
    start = rules.random_grippers(batch, cable, generator, dtype)
    x = gr.settle(rules.hang(start, cable).to(dtype), None, start, cable, settle_frames=500, **SETTLE).x   # a start
    action = (torch.rand(batch, rules.ACTION_DIM, generator=generator, dtype=torch.float64) * 2 - 1).to(dtype)
    return x, rules.decode_action(action, gr.poses_of(x), cable)


def with_floor_and_own_stiffness(cable, batch):
    """The cable over a floor its hanging middle reaches, each chain of the batch with its own EI."""
    ei = float(cable.params.EI) * torch.linspace(0.5, 2.0, batch, dtype=torch.float64)
    params = dataclasses.replace(cable.params, EI=ei, floor_height=0.30, floor_stiffness=50.0, floor_damping=0.5,
                                 floor_width=2e-3)
    return dataclasses.replace(cable, params=params)


@pytest.mark.parametrize("name, batch", [("DLO3", 1), ("DLO3", 19), ("DLO5", 17)])
def test_the_kernel_moves_and_settles_as_the_eager_chain(name, batch):
    """float64: positions and velocities to rounding, the same frames and the same rest verdicts; a batch that is
    not a whole number of lane groups included (DLO5: the softest cable, 13 substeps)."""
    cable = load_cable(name)
    x, goal = start_and_goal(cable, batch, torch.float64)
    runs = {e: gr.move(x, None, goal, cable, move_frames=60, settle_frames=150, engine=e, **SETTLE)
            for e in ("eager", "kernel")}
    eager, fast = runs["eager"], runs["kernel"]
    assert torch.allclose(fast.x, eager.x, rtol=0, atol=1e-12)
    assert torch.allclose(fast.v, eager.v, rtol=0, atol=1e-10)
    assert torch.equal(fast.frames, eager.frames) and torch.equal(fast.settled, eager.settled)
    assert bool(eager.settled.any()) and bool((eager.frames > 60).all())     # the settle ran and some came to rest
    settled = {e: gr.settle(x, None, gr.poses_of(x), cable, settle_frames=40, engine=e, **SETTLE)
               for e in ("eager", "kernel")}
    assert torch.allclose(settled["kernel"].x, settled["eager"].x, rtol=0, atol=1e-12)
    assert torch.equal(settled["kernel"].frames, settled["eager"].frames)


def test_the_kernel_has_the_floor_and_per_chain_parameters_of_the_eager_chain():
    cable = with_floor_and_own_stiffness(load_cable("DLO2"), 20)
    x, goal = start_and_goal(cable, 20, torch.float64, seed=3)
    eager, fast = (gr.move(x, None, goal, cable, move_frames=50, settle_frames=60, engine=e, **SETTLE)
                   for e in ("eager", "kernel"))
    assert float(eager.x[..., 2].min()) < 0.30                                # the floor was reached
    assert torch.allclose(fast.x, eager.x, rtol=0, atol=1e-11)
    assert torch.equal(fast.frames, eager.frames)


def test_float32_stays_within_micrometres_of_float64():
    cable = load_cable("DLO3")
    x, goal = start_and_goal(cable, 16, torch.float64, seed=1)
    exact = gr.move(x, None, goal, cable, move_frames=100, settle_frames=100, engine="kernel", **SETTLE)
    single = gr.move(x.float(), None, gr.Grippers(goal.pos.float(), goal.dirs.float()), cable, move_frames=100,
                     settle_frames=100, engine="kernel", **SETTLE)
    assert single.x.dtype == torch.float32
    assert float((single.x.double() - exact.x).abs().max()) < 1e-5


def test_the_kernels_gradients_are_the_eager_chains():
    """float64, chains stopping at different frames (the settle's rest check), a floor, per-chain EI, a start moving:
    the gradients w.r.t. the action (through the path and the hold), the start positions and velocities agree."""
    cable = with_floor_and_own_stiffness(load_cable("DLO2"), 12)
    x, _ = start_and_goal(cable, 12, torch.float64, seed=3)
    generator = torch.Generator().manual_seed(4)
    action = torch.rand(12, rules.ACTION_DIM, generator=generator, dtype=torch.float64) * 2 - 1
    v0 = 0.02 * torch.randn(x.shape, generator=generator, dtype=torch.float64)
    weights = torch.randn(2, *x.shape, generator=generator, dtype=torch.float64)
    grads = {}
    for engine in ("eager", "kernel"):
        inputs = [t.clone().requires_grad_(True) for t in (action, x, v0)]
        goal = rules.decode_action(inputs[0], gr.poses_of(inputs[1]), cable)
        out = gr.move(inputs[1], inputs[2], goal, cable, move_frames=30, settle_frames=150, engine=engine,
                      rest_speed=0.02, check_frames=10)
        ((weights[0] * out.x).sum() + (weights[1] * out.v).sum()).backward()
        grads[engine] = [t.grad for t in inputs] + [out.frames]
    assert len(set(grads["eager"][3].tolist())) > 3                         # the chains stopped at different frames
    assert torch.equal(grads["kernel"][3], grads["eager"][3])
    for fast, slow in zip(grads["kernel"][:3], grads["eager"][:3]):
        assert torch.allclose(fast, slow, rtol=1e-9, atol=1e-12 * float(slow.abs().max()))


def test_the_kernels_adjoint_passes_gradcheck():
    """float64 central differences of the kernel's own move (a settle capped, so the stop frames stay put) against
    its adjoint: start positions and velocities, every frame of the grippers' path and the hold."""
    cable = load_cable("DLO3")
    x, goal = start_and_goal(cable, 2, torch.float64, seed=5)
    path = gr.gripper_path(gr.poses_of(x), goal, cable, 4)
    hold = gr.held_markers(goal, cable)
    v0 = 0.01 * torch.ones_like(x)

    def run(x, v, path, hold):
        out = kernel.move(x, v, cable.held, path, hold, cable.params, cable.substeps, frame_dt=0.01,
                          rest_speed=1e-9, check_frames=10, settle_frames=3)
        return out[0], out[1]
    inputs = [t.clone().requires_grad_(True) for t in (x, v0, path, hold)]
    assert torch.autograd.gradcheck(run, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_parameters_wanting_gradients_or_a_residual_take_the_eager_path_and_kernel_refuses_them():
    cable = load_cable("DLO3")
    x, goal = start_and_goal(cable, 2, torch.float64)
    ei = torch.tensor(float(cable.params.EI), dtype=torch.float64, requires_grad=True)
    fitted = dataclasses.replace(cable, params=dataclasses.replace(cable.params, EI=ei))
    out = gr.move(x, None, goal, fitted, move_frames=20, settle_frames=10, **SETTLE)       # auto: eager
    out.x.sum().backward()
    assert ei.grad is not None and float(ei.grad.abs()) > 0
    with pytest.raises(ValueError, match="engine='kernel' needs .*parameters requiring grad: True"):
        gr.move(x, None, goal, fitted, move_frames=20, settle_frames=10, engine="kernel", **SETTLE)
    with pytest.raises(ValueError, match="accel given"):
        gr.move(x, None, goal, cable, move_frames=20, settle_frames=10, engine="kernel",
                accel=lambda x, v: torch.zeros_like(x), **SETTLE)
    with pytest.raises(ValueError, match="engine must be one of .*'fast'"):
        gr.move(x, None, goal, cable, move_frames=20, settle_frames=10, engine="fast", **SETTLE)
    with torch.no_grad():                                             # no gradient wanted: the kernel runs
        assert gr.move(x, None, goal, fitted, move_frames=20, settle_frames=10, engine="kernel", **SETTLE) \
            .x.shape == x.shape


def test_a_diverging_chain_is_reported_with_its_member_and_frame():
    cable = load_cable("DLO3")
    unstable = dataclasses.replace(cable, substeps=1)
    x, goal = start_and_goal(cable, 3, torch.float64)
    with pytest.raises(ChainDivergedError, match=r"batch members \[0, 1, 2\] at frame \d+ of the move"):
        gr.move(x, None, goal, unstable, move_frames=20, settle_frames=10, engine="kernel", **SETTLE)
    with pytest.raises(ChainDivergedError):                                   # as the eager chain does
        gr.move(x, None, goal, unstable, move_frames=20, settle_frames=10, engine="eager", **SETTLE)


def test_env_episodes_are_the_same_on_both_engines():
    envs = {e: BatchedCable3D(3, cable="DLO3", move_time=0.3, settle_time=0.5, engine=e) for e in ("auto", "eager")}
    for env in envs.values():
        env.seed([0, 1, 2])
        env.reset()
    actions = torch.rand(2, 3, rules.ACTION_DIM, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for a in actions * 2 - 1:
        (_, r_fast, *_), (_, r_slow, *_) = (env.step(a) for env in envs.values())
        assert torch.allclose(r_fast, r_slow, atol=1e-9)
    assert torch.allclose(envs["auto"].x, envs["eager"].x, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="engine must be one of"):
        BatchedCable3D(1, engine="triton")


def test_without_a_compiler_one_warning_then_the_eager_path(monkeypatch, tmp_path):
    cable = load_cable("DLO3")
    x, goal = start_and_goal(cable, 1, torch.float64)
    monkeypatch.setattr(kernel._library, "lib", None)
    monkeypatch.setattr(kernel._library, "error", None)
    monkeypatch.setenv("DIFFDLO_CACHE", str(tmp_path))
    monkeypatch.setattr(kernel, "_compiler", lambda: None)
    with pytest.warns(diffdlo.KernelUnavailableWarning, match=r"(?s)3-D chain is unavailable \(no C\+\+ compiler"):
        out = gr.move(x, None, goal, cable, move_frames=10, settle_frames=10, **SETTLE)
    assert out.x.shape == x.shape
    with warnings.catch_warnings():
        warnings.simplefilter("error", diffdlo.KernelUnavailableWarning)
        gr.move(x, None, goal, cable, move_frames=10, settle_frames=10, **SETTLE)
    with pytest.raises(ValueError, match="no C\\+\\+ compiler"):
        gr.move(x, None, goal, cable, move_frames=10, settle_frames=10, engine="kernel", **SETTLE)


@settings(max_examples=8, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2 ** 31 - 1), name=st.sampled_from(["DLO1", "DLO2", "DLO3", "DLO4", "DLO5"]))
def test_every_move_is_a_valid_start_of_the_next(seed, name):
    """Property, 8 examples x 256 random starts and actions (2,048 moves on the five cables): a move's result is
    finite, its held markers exactly at the goal, no link stretched 5 %, at rest where it says so, the kernel equal
    to the eager chain on a few of them, and the next move from it accepted."""
    cable = load_cable(name)
    generator = torch.Generator().manual_seed(seed)
    start = rules.random_grippers(256, cable, generator, torch.float64)
    x = rules.hang(start, cable)
    action = torch.rand(256, rules.ACTION_DIM, generator=generator, dtype=torch.float64) * 2 - 1
    goal = rules.decode_action(action, gr.poses_of(x), cable)
    kw = dict(move_frames=30, settle_frames=60, rest_speed=0.02, check_frames=10)
    out = gr.move(x, None, goal, cable, engine="kernel", **kw)
    assert bool(torch.isfinite(out.x).all() and torch.isfinite(out.v).all())
    assert torch.equal(out.x[:, list(cable.held)], gr.held_markers(goal, cable))
    stretch = (out.x[:, 1:] - out.x[:, :-1]).norm(dim=-1) / cable.params.rest_lengths - 1
    assert float(stretch.abs().max()) < 0.05
    free = [j for j in range(cable.n_nodes) if j not in cable.held]
    speed = out.v[:, free].norm(dim=-1).amax(-1)
    assert bool((speed[out.settled] < 0.02).all()) and bool((out.frames <= 90).all() & (out.frames > 30).all())
    eager = gr.move(x[:3], None, gr.Grippers(goal.pos[:3], goal.dirs[:3]), cable, engine="eager", **kw)
    assert torch.allclose(out.x[:3], eager.x, rtol=0, atol=1e-10) and torch.equal(out.frames[:3], eager.frames)
    again = gr.move(out.x, out.v, rules.decode_action(-action, gr.poses_of(out.x), cable), cable, engine="kernel", **kw)
    assert bool(torch.isfinite(again.x).all())


def test_the_kernel_refuses_what_the_eager_chain_refuses():
    cable = load_cable("DLO3")
    x, goal = start_and_goal(cable, 2, torch.float64)
    bad = x.clone()
    bad[1, 4, 2] = float("nan")
    for engine in ("kernel", "eager"):
        with pytest.raises(ChainError, match="x0 must be finite, got 1 non-finite"):
            gr.move(bad, None, goal, cable, move_frames=5, settle_frames=5, engine=engine, **SETTLE)
    broken = dataclasses.replace(cable, params=dataclasses.replace(cable.params, EA=-1.0))
    with pytest.raises(ChainError, match="'EA'.*-1"):
        gr.move(x, None, goal, broken, move_frames=5, settle_frames=5, engine="kernel", **SETTLE)
