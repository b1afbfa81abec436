"""The routing env (DiffDLO/Routing-v0, or any env with target "route" / "route:NAME"): gymnasium's and SB3's
checkers, the native vector env, seeding, success = on the route on the board AND every peg on its side, the pegs
in the observations and pictures, the pin action, and bad options refused by name."""
import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import diffdlo
from diffdlo.tasks import routing, task
from diffdlo.envs import ROUTING_ENV_ID, BatchedShapeControl
from diffdlo.planar.shapes import TargetError


def test_the_routing_env_passes_gymnasiums_and_sb3s_checkers():
    for kwargs in ({}, {"obs_type": "image"}, {"action_type": "node_pin", "target": "route:s_three_pegs"},
                   {"reward": "route_side_gain"}):
        env = gym.make(ROUTING_ENV_ID, **kwargs)
        check_env(env.unwrapped, skip_render_check=True)
    from stable_baselines3.common.env_checker import check_env as sb3_check
    sb3_check(gym.make(ROUTING_ENV_ID).unwrapped, warn=False)


def test_a_route_episode_is_reproducible_and_its_board_is_in_the_observation():
    a, b = gym.make(ROUTING_ENV_ID), gym.make(ROUTING_ENV_ID)
    oa, _ = a.reset(seed=3)
    ob, _ = b.reset(seed=3)
    for key in ("node_poses", "target_poses", "pegs"):
        np.testing.assert_array_equal(oa[key], ob[key])
    pegs = oa["pegs"]
    present = pegs[:, 2] > 0
    assert 2 <= present.sum() <= 4 and (pegs[~present] == 0).all()            # padded with rows of zeros
    action = a.action_space.sample()
    for env in (a, b):
        obs, reward, *_ = env.step(action)
    assert reward != 0.0
    other, _ = a.reset(seed=4)
    assert not np.array_equal(other["pegs"], pegs)


def test_success_needs_the_route_on_the_board_and_every_peg_on_its_side():
    core = BatchedShapeControl(3, target="route:u_two_pegs", reward="route_gain")
    core.reset(seed=0)
    layout = routing.load_layout("u_two_pegs", core.params)
    route = layout.route.float()
    wrong = route.clone()
    centre = layout.pegs[0, :2].float()
    # the U's bend swung to the pegs' far side: the pegs now lie outside the bend (node 7-11 mirrored through the
    # line of the two pegs), the rest of the route in place
    far = (wrong[7:12] - centre) * torch.tensor([-1.0, 1.0]) + centre
    wrong[7:12] = far
    shifted = route + torch.tensor([0.0, 0.3])                   # the route's shape, away from the board
    core.set_state(pos=torch.stack([route, wrong, shifted]))
    info = core.info()
    assert info["is_success"].tolist() == [True, False, False]
    assert info["sides_kept"].tolist()[0] and not info["sides_kept"].tolist()[1]
    assert float(info["shape_error"][2]) == pytest.approx(0.3, abs=1e-6)     # measured on the board
    assert float(diffdlo.shape_error(shifted[None], route[None])) < 1e-6    # though the shape matches


def test_the_pictures_draw_the_pegs():
    env = BatchedShapeControl(1, target="route:hook_wrap", reward="route_gain", obs_type="image", image_size=128,
                              view_size=0.5)
    obs, _ = env.reset(seed=0)
    grey = torch.tensor(diffdlo.tasks.image.PEG_COLOR, dtype=torch.int32)
    near = ((obs["image"][0].to(torch.int32) - grey).abs().amax(-1) < 40).sum()
    assert int(near) >= 4


def test_a_pin_action_moves_the_rope_as_the_simulator_with_that_pin():
    core = BatchedShapeControl(2, target="route:u_two_pegs", reward="route_gain", action_type="node_pin")
    core.reset(seed=0)
    state = core.get_state()
    n = core.params.n_nodes
    a = torch.tensor([[0.0, 1.0, 0.5, 0.0], [0.0, 1.0, 0.5, 0.0]])
    a[1, 3] = float(task.encode_pin(torch.tensor(3), n))                   # rope 1: node 3 pinned, rope 0: none
    assert task.decode_pin(a[:, 3], torch.tensor([0, 0]), n).tolist() == [-1, 3]
    assert task.decode_pin(torch.tensor([float(task.encode_pin(torch.tensor(0), n))]), torch.tensor([0]), n).item() == -1
    core.step(a)
    node, drag = torch.tensor([0, 0]), torch.tensor([[0.1, 0.0], [0.1, 0.0]])          # node 0 by (0.1, 0)
    pegs = state.pegs
    pinned = core.sim.move(state.pos, node, drag, pegs, torch.tensor([-1, 3]))
    torch.testing.assert_close(core.get_state().pos, pinned, rtol=0, atol=1e-6)
    free = core.sim.move(state.pos, node, drag, pegs)
    assert float((pinned[1] - free[1]).abs().max()) > 1e-3 and torch.equal(pinned[0], free[0])


@pytest.mark.parametrize("kwargs, error, match", [
    ({"target": "route", "obs_type": "distance"}, ValueError, r"obs_type='distance' cannot show a route's pegs"),
    ({"target": "route", "reward": "position_orientation"}, ValueError,
     r"reward='position_orientation' does not see where the rope lies"),
    ({"target": "route", "reward": "shape_gain"}, ValueError, r"reward='shape_gain'"),
    ({"target": "route:nope", "reward": "route_gain"}, TargetError, r"no layout 'nope'"),
    ({"target": "route:zigzag_four", "reward": "route_gain", "max_pegs": 3}, routing.LayoutError,
     r"a layout of 4 pegs does not fit the env's max_pegs=3"),
    ({"target": "route", "reward": "route_gain", "max_pegs": 0}, ValueError, r"max_pegs"),
    ({"target": "random", "reward": "route_side_gain"}, ValueError,
     r"reward='route_side_gain' scores the sides a rope passes pegs on: it needs a route"),
])
def test_bad_route_options_are_refused_by_name(kwargs, error, match):
    with pytest.raises(error, match=match):
        BatchedShapeControl(1, **kwargs).reset(seed=0)


def test_a_route_env_keeps_routes_and_a_shape_env_keeps_shapes():
    route = BatchedShapeControl(1, target="route", reward="route_gain")
    with pytest.raises(ValueError, match="a route env's targets stay routes"):
        route.set_target("diagonal")
    route.set_target("route:hook_wrap")
    shape = BatchedShapeControl(1)
    with pytest.raises(ValueError, match="a shape env's targets stay shapes"):
        shape.set_target("route")


def test_the_native_vector_env_runs_routes_with_pins():
    venv = gym.make_vec(ROUTING_ENV_ID, num_envs=4, action_type="node_pin")
    obs, info = venv.reset(seed=0)
    assert obs["pegs"].shape == (4, 4, 3) and "sides_kept" in info
    for _ in range(2):
        obs, reward, terminated, truncated, info = venv.step(venv.action_space.sample())
    assert reward.shape == (4,) and np.isfinite(reward).all()
    assert math.isfinite(float(info["shape_error"].max()))


def test_a_pixel_pin_action_holds_the_node_nearest_its_point():
    core = BatchedShapeControl(2, target="route:u_two_pegs", reward="route_gain", action_type="pixel_pin",
                               obs_type="image")
    check_env(gym.make(ROUTING_ENV_ID, action_type="pixel_pin", obs_type="image").unwrapped, skip_render_check=True)
    core.reset(seed=0)
    state = core.get_state()
    half = core.view_size / 2

    def point(xy):                               # world [m] -> (column, row) fractions of the view
        return [(xy[0] + half) / core.view_size, (half - xy[1]) / core.view_size]

    a = torch.tensor([point(state.pos[0, 19].tolist()) + [0.5, 1.0] + point(state.pos[0, 10].tolist()),
                      point(state.pos[1, 19].tolist()) + [0.5, 1.0] + point(state.pos[1, 19].tolist())])
    node, drag = task.decode_action("pixel_pin", a, state.pos, core.params, core.view_size)
    pin = task.decode_action_pin("pixel_pin", a, node, state.pos, core.params, core.view_size)
    assert node.tolist() == [19, 19] and pin.tolist() == [10, -1]            # on the grasped node: no pin
    torch.testing.assert_close(drag, torch.tensor([[0.0, 0.1], [0.0, 0.1]]))
    core.step(a)
    expect = core.sim.move(state.pos, node, drag, state.pegs, pin)
    torch.testing.assert_close(core.get_state().pos, expect, rtol=0, atol=1e-6)


def test_a_start_across_the_board_lies_among_the_pegs_and_clear_of_them():
    beside = BatchedShapeControl(8, target="route", reward="route_gain")
    across = BatchedShapeControl(8, target="route", reward="route_gain", route_start="across")
    for env in (beside, across):
        env.reset(seed=0)
    a, b = across.get_state(), beside.get_state()
    torch.testing.assert_close(a.pegs, b.pegs, rtol=0, atol=0)                 # the same boards
    centre = lambda s: (s.pos.mean(1) - s.target.mean(1)).norm(dim=-1)
    assert (centre(a) < 0.06).all() and (centre(b) > 0.15).all()
    for s in (a, b):                 # drawn clear of the pegs; the settle may bring it into light contact
        depth = diffdlo.planar.contact.depth(s.pos, s.pegs, across.params.rope_radius)
        assert (depth < across.params.contact_width).all()
    with pytest.raises(ValueError, match="route_start"):
        BatchedShapeControl(1, target="route", reward="route_gain", route_start="on_top")


def test_an_episode_among_pegs_never_stops_on_a_rope_put_down_inside_a_peg(tmp_path, params):
    """The env's side of issue 68: a board with a small peg on the grasped node's path (benchmarks.contact_checks's
    path_scenes, a case whose settle alone leaves the rope inside the peg) and a rope started there. The step that
    carries the lifted links over the peg and the steps after it run (before the fix, the next step raised "lies
    ... deep in peg"), every state a valid start; then random steps on random boards with pins."""
    import yaml

    from benchmarks.contact_checks import path_scenes
    pos, pegs, node, delta, pin = (x[41] for x in path_scenes(params, 512, 1))      # let go at half its drag
    board = pegs[pegs[:, 2] > 0]
    route = torch.stack([torch.linspace(-0.25, 0.25, params.n_nodes, dtype=torch.float64),
                         torch.full((params.n_nodes,), 0.45, dtype=torch.float64)], -1)   # clear of the pegs
    (tmp_path / "board.yaml").write_text(yaml.safe_dump({"pegs": board.tolist(), "route": route.tolist()}))
    env = gym.make(ROUTING_ENV_ID, target=f"route:{tmp_path / 'board.yaml'}", start=pos.numpy(),
                   action_type="node_pin", max_steps=5)
    env.reset(seed=0)
    core = env.unwrapped.core
    state = core.get_state(generators=False)
    sim = core.sim
    settled, _ = sim._run_move(state.pos, torch.zeros_like(state.pos), node[None], delta[None].to(sim.dtype),
                               sim._check_pegs(state.pos, state.pegs), pin[None], None, 0, False, False)
    depth = float(diffdlo.planar.contact.depth(settled, state.pegs, params.rope_radius))
    assert depth > params.rope_radius                                  # the case: the settle leaves it inside
    action = torch.cat([task.encode_node_action(node, delta, params.n_nodes, params.action_scale),
                        task.encode_pin(pin[None], params.n_nodes, torch.float64)]).numpy()
    for step in range(3):
        env.step(action if step == 0 else env.action_space.sample())
        s = core.get_state(generators=False)
        assert float(diffdlo.planar.contact.depth(s.pos, s.pegs, params.rope_radius)) < params.rope_radius
    venv = gym.make_vec(ROUTING_ENV_ID, num_envs=32, action_type="node_pin", route_start="across")
    venv.reset(seed=0)
    venv.action_space.seed(0)
    for _ in range(40):
        venv.step(venv.action_space.sample())
