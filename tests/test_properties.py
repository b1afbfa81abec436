"""Property-based tests (hypothesis): the simulator, the env, the target loaders and the learners' configs fed
generated valid and extreme inputs. Invariants hold (momentum and angular momentum of the internal forces, a move
commutes with translations and rotations, rest stays at rest, success does not depend on where the rope lies), no NaN
or inf is ever returned, and every invalid input gets the named error, never another exception.

Deterministic in CI: the profile below derandomizes the examples (the same ones every run) and keeps no database;
examples are few and ropes small (6 nodes) so the file takes seconds.
"""
import dataclasses
import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import diffdlo
from agents import ppo, sac
from agents.common.config import flat_names, flat_value, load_config
from diffdlo.envs import BatchedShapeControl
from diffdlo.planar.forces import internal_forces
from diffdlo.planar.shapes import TargetError, straight_shape, target_shape
from diffdlo.planar.simulator import SimulationError
from diffdlo.tasks.task import task_metrics

settings.register_profile("diffdlo", derandomize=True, database=None, deadline=None, max_examples=25,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
settings.load_profile("diffdlo")

SMALL = dataclasses.replace(diffdlo.load_params("cable"), n_nodes=6, length=0.15, max_speed=1.0,
                            settle_max_substeps=30, settle_check_every=10)
SIM = diffdlo.Simulator(SMALL, dtype=torch.float64)
N = SMALL.n_nodes

coords = st.floats(-1.0, 1.0, allow_nan=False)
angles = st.floats(0.0, 2 * math.pi, allow_nan=False)


@st.composite
def ropes(draw, spread: float = 0.6):
    """A rope of N nodes whose links are at least 1/5 of their rest length (a crumpled but physical shape)."""
    turns = draw(st.lists(st.floats(-spread * math.pi, spread * math.pi), min_size=N - 1, max_size=N - 1))
    stretch = draw(st.lists(st.floats(0.8, 1.25), min_size=N - 1, max_size=N - 1))
    heading = np.cumsum(turns)
    steps = SMALL.rest_length * np.array(stretch)[:, None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    pos = np.concatenate([np.zeros((1, 2)), np.cumsum(steps, 0)]) + np.array([draw(coords), draw(coords)]) * 0.3
    return torch.tensor(pos, dtype=torch.float64)


def rotation(t: float) -> torch.Tensor:
    return torch.tensor([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]], dtype=torch.float64)


# ------------------------------------------------------------------ physics
@given(ropes(spread=0.9))
def test_internal_forces_carry_no_momentum_and_no_torque(pos):
    f = internal_forces(pos[None], SMALL.rest_length, SMALL.k_s, SMALL.k_b)[0]
    scale = float(f.abs().max()) + 1e-12
    assert torch.isfinite(f).all()
    assert float(f.sum(0).abs().max()) <= 1e-9 * scale * N
    torque = (pos[:, 0] * f[:, 1] - pos[:, 1] * f[:, 0]).sum()
    assert abs(float(torque)) <= 1e-9 * scale * N


@settings(max_examples=12)
@given(ropes(), st.integers(0, N - 1), st.floats(-0.06, 0.06), st.floats(-0.06, 0.06), coords, coords, angles)
def test_a_move_commutes_with_translation_and_rotation(pos, node, dx, dy, tx, ty, t):
    rot, shift = rotation(t), torch.tensor([tx, ty], dtype=torch.float64)
    nodes, delta = torch.tensor([node]), torch.tensor([[dx, dy]], dtype=torch.float64)
    moved = SIM.move(pos[None], nodes, delta)[0]
    assert torch.isfinite(moved).all()
    there = SIM.move((pos @ rot.T + shift)[None], nodes, delta @ rot.T)[0]
    torch.testing.assert_close(there, moved @ rot.T + shift, rtol=0, atol=1e-7)


@settings(max_examples=10)
@given(angles, coords, coords, st.integers(0, N - 1))
def test_a_rope_at_rest_stays_at_rest(angle, tx, ty, node):
    straight = straight_shape(math.degrees(angle), SMALL).double() + torch.tensor([tx, ty], dtype=torch.float64)
    moved = SIM.move(straight[None], torch.tensor([node]), torch.zeros(1, 2, dtype=torch.float64))[0]
    torch.testing.assert_close(moved, straight, rtol=0, atol=1e-9)


@settings(max_examples=15)
@given(st.floats(1e-3, 1e3), st.floats(-1e9, 1e9, allow_nan=False), st.floats(-1e9, 1e9, allow_nan=False),
       st.integers(0, N - 1), st.integers(0, 2**31 - 1))
def test_a_move_returns_finite_positions_or_says_why_not(scale, dx, dy, node, seed):
    """Ropes from tiny to kilometre-sized links, drags up to 1e9 m: a finite result, or a refusal naming the problem
    (ValueError for a rope with coincident nodes, SimulationError for one that diverges); never a NaN or inf."""
    g = torch.Generator().manual_seed(seed)
    pos = torch.cumsum(scale * SMALL.rest_length * torch.randn(N, 2, generator=g, dtype=torch.float64), 0)
    try:
        moved = SIM.move(pos[None], torch.tensor([node]), torch.tensor([[dx, dy]], dtype=torch.float64))
    except SimulationError as exc:
        assert "diverg" in str(exc) or "not finite" in str(exc) or "NaN" in str(exc), str(exc)
        return
    except ValueError as exc:
        assert str(exc).startswith("pos:"), str(exc)
        return
    assert torch.isfinite(moved).all()


# ------------------------------------------------------------------ the task and the env
@given(ropes(spread=0.9), coords, coords)
def test_success_does_not_depend_on_where_the_rope_lies(pos, tx, ty):
    target = straight_shape(30.0, SMALL).double()
    here = task_metrics(pos[None], target, 0.01)
    there = task_metrics(pos[None] + torch.tensor([tx, ty], dtype=torch.float64), target, 0.01)
    torch.testing.assert_close(here["shape_error"], there["shape_error"], rtol=0, atol=1e-12)
    assert bool(here["is_success"]) == bool(there["is_success"])


ENV = BatchedShapeControl(3, params=SMALL, target="random", max_steps=3)
ENV.reset(seed=0)
finite_or_not = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=20)
@given(st.lists(finite_or_not, min_size=9, max_size=9))
def test_env_actions_are_clipped_or_refused_by_name(values):
    actions = torch.tensor(values, dtype=torch.float64).view(3, 3)
    if not torch.isfinite(actions).all():
        with pytest.raises(ValueError, match="action"):
            ENV.step(actions, autoreset="same_step")
        return
    obs, reward, term, trunc, info = ENV.step(actions, autoreset="same_step")
    for v in (obs if isinstance(obs, dict) else {"obs": obs}).values():
        assert torch.isfinite(v.double()).all()
    assert torch.isfinite(reward).all() and torch.isfinite(info["shape_error"]).all()


# ------------------------------------------------------------------ target loaders
@given(st.integers(1, 12), st.integers(1, 3), st.lists(finite_or_not, min_size=36, max_size=36))
def test_a_target_loads_or_is_refused_by_name(rows, cols, values):
    points = np.array(values[: rows * cols]).reshape(rows, cols)
    try:
        t = target_shape(points, SMALL, dtype=torch.float64)
    except TargetError as exc:
        assert "target" in str(exc)
        return
    assert t.shape == (N, 2) and torch.isfinite(t).all()


@settings(max_examples=15)
@given(suffix=st.sampled_from([".npy", ".yaml", ".txt", ""]), content=st.binary(max_size=64))
def test_a_target_file_loads_or_is_refused_by_name(suffix, content, tmp_path_factory):
    path = tmp_path_factory.mktemp("target") / f"t{suffix}"
    path.write_bytes(content)
    with pytest.raises(TargetError) as exc:
        target_shape(str(path), SMALL)
    assert str(path) in str(exc.value) or "unknown target" in str(exc.value)


# ------------------------------------------------------------------ the learners' configs
any_value = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
                      st.text(max_size=8), st.lists(st.integers(-5, 5), max_size=3))


@settings(max_examples=40)
@given(st.sampled_from([("sac", sac.SACConfig), ("ppo", ppo.PPOConfig)]), st.data())
def test_a_config_value_is_taken_or_refused_by_name(learner, data):
    name, cls = learner
    key = data.draw(st.sampled_from(sorted(flat_names(cls))))
    value = data.draw(any_value)
    try:
        cfg = load_config(cls, name, {key: value})
    except (ValueError, TypeError) as exc:
        assert key in str(exc), (key, value, str(exc))
        return
    assert load_config(cls, name, {key: flat_value(cfg, key)}) == cfg      # what was taken reads back the same
