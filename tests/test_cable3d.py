"""The 3-D two-gripper task (issue 69, a first step): the cables' parameter files, the grippers' move on the chain
(held markers on their path, at rest at the end, gradients against finite differences), the task's rules on
hand-made states, and the env (gymnasium's and SB3's checkers, the native vector env, seeding). No recordings."""
import dataclasses
import math

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml

from diffdlo.chain3d import grippers as gr
from diffdlo.chain3d.cables import CableError, cable_names, load_cable
from diffdlo.envs import CABLE3D_ENV_ID
from diffdlo.envs.cable3d import BatchedCable3D
from diffdlo.tasks import cable3d as rules

F64 = torch.float64
FAST = {"move_time": 0.1, "settle_time": 0.2, "max_steps": 3}


@pytest.fixture(scope="module")
def short_cable(tmp_path_factory):
    """A 7-marker, 0.44 m cable with DLO3's fitted numbers: the env's rules at a fraction of the cost."""
    path = tmp_path_factory.mktemp("cables") / "cables.yaml"
    data = yaml.safe_load(open(load_cable.__globals__["PARAMS_DIR"] / "cables3d.yaml"))
    short = dict(data["cables"]["DLO3"], rest_lengths=[0.03, 0.1, 0.1, 0.1, 0.1, 0.03], length=0.46, mass=0.045)
    path.write_text(yaml.safe_dump({**data, "default": "short", "cables": {"short": short}}))
    return load_cable(None, path)


# ------------------------------------------------------------------ the cables
def test_the_five_cables_load_with_their_fitted_numbers_and_the_default_is_dlo3():
    assert cable_names() == ["DLO1", "DLO2", "DLO3", "DLO4", "DLO5"]
    cables = {n: load_cable(n) for n in cable_names()}
    assert load_cable().name == "DLO3"
    assert cables["DLO1"].n_nodes == 13 and all(cables[n].n_nodes == 12 for n in ("DLO2", "DLO3", "DLO4", "DLO5"))
    ei = [float(cables[n].params.EI) for n in ("DLO5", "DLO4", "DLO1", "DLO2", "DLO3")]
    assert ei == sorted(ei)                                           # the fitted stiffness order (REAL_CABLE.md)
    assert cables["DLO3"].spread["EA"] is None and cables["DLO3"].spread["EI"] == pytest.approx(1.03)
    for c in cables.values():                                         # the markers span most of the paper's length
        assert 0.85 * c.length < float(c.params.rest_lengths.sum()) < c.length


@pytest.mark.parametrize("change, match", [
    (lambda d: d["cables"]["DLO3"].update(EI={"value": -1.0, "spread": 1.0}), r"cable DLO3: EI must be .*>= 0.*-1"),
    (lambda d: d["cables"]["DLO3"].update(substeps=1), r"1 substeps per 10 ms frame are unstable"),
    (lambda d: d["cables"]["DLO3"].update(colour="red"), r"unknown \['colour'\]"),
    (lambda d: d["cables"]["DLO3"].pop("EA"), r"missing \['EA'\]"),
    (lambda d: d["cables"]["DLO3"].update(rest_lengths=[0.1, 0.0, 0.1, 0.1]), r"rest_lengths\[1\] \[m\] must be"),
    (lambda d: d.update(held_markers=[0, 2, -2, -1]), r"held_markers must be the two markers at each end"),
    (lambda d: d.update(default="DLO9"), r"unknown cable 'DLO9': use one of"),
])
def test_a_bad_cables_file_is_refused_naming_the_value(tmp_path, change, match):
    data = yaml.safe_load(open(load_cable.__globals__["PARAMS_DIR"] / "cables3d.yaml"))
    change(data)
    path = tmp_path / "cables.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(CableError, match=match):
        load_cable(None, path)


# ------------------------------------------------------------------ the grippers' move
def test_a_move_carries_the_held_markers_on_their_path_and_ends_at_rest(short_cable):
    start = gr.Grippers(torch.tensor([[[0.3, -0.3, 0.7], [0.6, -0.3, 0.7]]], dtype=F64),
                        torch.tensor([[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]], dtype=F64))
    x = gr.settle(rules.hang(start, short_cable), None, start, short_cable, rest_speed=0.01, check_frames=10,
                  settle_frames=500)
    assert bool(x.settled[0])
    goal = gr.Grippers(start.pos + torch.tensor([0.03, 0.02, -0.05], dtype=F64),
                       gr.rotate(start.dirs, torch.tensor([0.2, 0.0, 0.0], dtype=F64)))
    path = gr.gripper_path(gr.poses_of(x.x), goal, short_cable, 20)
    torch.testing.assert_close(path[-1], gr.held_markers(goal, short_cable))
    out = gr.move(x.x, None, goal, short_cable, move_frames=20, rest_speed=0.01, check_frames=10,
                  settle_frames=500)
    torch.testing.assert_close(out.x[:, [0, 1, -2, -1]], gr.held_markers(goal, short_cable), rtol=0, atol=1e-12)
    assert bool(out.settled[0]) and int(out.frames[0]) > 20
    rest = short_cable.params.rest_lengths
    stretch = (out.x[0, 1:] - out.x[0, :-1]).norm(dim=-1) / rest - 1
    assert float(stretch.abs().max()) < 0.01                          # hanging, barely stretched (EA 60 N)
    assert float(out.x[0, 3, 2]) < float(out.x[0, 1, 2]) - 0.05         # the middle sags below the grippers


def test_a_move_is_differentiable_in_the_goal_against_finite_differences(short_cable):
    start = gr.Grippers(torch.tensor([[[0.3, -0.3, 0.7], [0.6, -0.3, 0.7]]], dtype=F64),
                        torch.tensor([[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]], dtype=F64))
    x = rules.hang(start, short_cable)
    weights = torch.randn(1, short_cable.n_nodes, 3, generator=torch.Generator().manual_seed(0), dtype=F64)

    def loss(shift):
        goal = gr.Grippers(start.pos + shift, start.dirs)
        out = gr.move(x, None, goal, short_cable, move_frames=4, rest_speed=1e-9, check_frames=2, settle_frames=2)
        return (out.x * weights).sum()

    shift = torch.tensor([[[0.01, 0.0, -0.02], [0.0, 0.01, 0.0]]], dtype=F64, requires_grad=True)
    (grad,) = torch.autograd.grad(loss(shift), shift)
    eps = 1e-6
    for index in [(0, 0, 0), (0, 0, 2), (0, 1, 1)]:
        e = torch.zeros_like(shift)
        e[index] = eps
        fd = (loss(shift.detach() + e) - loss(shift.detach() - e)) / (2 * eps)
        assert float(grad[index]) == pytest.approx(float(fd), rel=1e-5, abs=1e-9)


# ------------------------------------------------------------------ the rules
def test_an_action_is_bounded_per_axis_kept_in_the_workspace_and_within_the_span(short_cable):
    g = gr.Grippers(torch.tensor([[[0.3, -0.3, 0.7], [0.6, -0.3, 0.7]], [[0.02, 0.18, 0.88], [0.3, 0.18, 0.88]]],
                                 dtype=F64), torch.tensor([[0.0, 0.0, -1.0]], dtype=F64).expand(2, 2, 3))
    a = torch.tensor([[1.0, -1.0, 0.5, 0, 0, 0, -1.0, 0, 0, 1.0, 0, 0], [-1.0, 1.0, 1.0, 0, 0, 0, 1.0, 1, 1, 0, 0, 0]],
                     dtype=F64)
    goal = rules.decode_action(rules.check_action(a, 2), g, short_cable)
    shift = goal.pos - g.pos
    assert float(shift.abs().max()) <= rules.MAX_SHIFT + 1e-12
    torch.testing.assert_close(shift[0, 0], torch.tensor([0.05, -0.05, 0.025], dtype=F64))
    low, high = (torch.tensor(w, dtype=F64) for w in rules.WORKSPACE)
    assert bool(((goal.pos >= low - 1e-12) & (goal.pos <= high + 1e-12)).all())   # rope 1 clipped at the box
    assert float(goal.pos[1, 0, 0]) == 0.0 and float(goal.pos[1, 0, 2]) == 0.9
    angle = torch.acos((goal.dirs[0, 1] * g.dirs[0, 1]).sum().clamp(-1, 1))
    assert float(angle) == pytest.approx(rules.MAX_TURN)              # the turn's full size about x
    far = rules.keep_reachable(torch.tensor([[[0.0, -0.3, 0.7], [1.1, -0.3, 0.7]]], dtype=F64), short_cable)
    assert float((far[0, 1] - far[0, 0]).norm()) == pytest.approx(rules.span_limit(short_cable))
    with pytest.raises(ValueError, match=r"actions must be finite, got NaN/inf in rows \[1\]"):
        rules.check_action(torch.tensor([[0.0] * 12, [float("nan")] + [0.0] * 11]), 2)
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 12\) in \[-1, 1\], got \(2, 6\)"):
        rules.check_action(torch.zeros(2, 6), 2)


def test_success_needs_rest_and_both_tolerances():
    target = torch.zeros(4, 5, 3, dtype=F64)
    x = target.clone()
    x[1, :, 0] = 0.012                                                # mean 1.2 cm
    x[2, 0, 0] = 0.045                                                # mean 0.9 cm, worst 4.5 cm
    at_rest = torch.tensor([True, True, True, False])
    assert rules.success(x, target, at_rest, 0.01, 0.02).tolist() == [True, False, False, False]
    assert float(rules.reward(x, target, target)[1]) == pytest.approx(1.2)


def test_a_hung_start_lies_between_its_grippers_near_the_cables_link_lengths(short_cable):
    g = rules.random_grippers(3, short_cable, torch.Generator().manual_seed(1), F64)
    x = rules.hang(g, short_cable)
    lengths = (x[:, 1:] - x[:, :-1]).norm(dim=-1)
    share = lengths / short_cable.params.rest_lengths                # chords of a curve of the cable's length:
    assert bool((share <= 1 + 1e-9).all()) and float(share.min()) > 0.9   # never stretched, at most 10 % short
    torch.testing.assert_close(gr.poses_of(x).pos, g.pos)
    span = (g.pos[:, 1] - g.pos[:, 0]).norm(dim=-1) / float(short_cable.params.rest_lengths.sum())
    assert bool(((span >= rules.SPAN_RANGE[0] - 1e-9) & (span <= rules.SPAN_RANGE[1] + 1e-9)).all())
    tilt = torch.acos(-g.dirs[..., 2])
    assert float(tilt.max()) <= rules.START_TILT + 1e-9


# ------------------------------------------------------------------ the env
def test_the_env_passes_gymnasiums_and_sb3s_checkers(short_cable):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check
    env = gym.make(CABLE3D_ENV_ID, cable=short_cable, **FAST)
    check_env(env.unwrapped, skip_render_check=True)
    sb3_check(env.unwrapped, warn=False)


def test_an_episode_is_reproducible_and_the_vector_env_matches_the_single_one(short_cable):
    single = [gym.make(CABLE3D_ENV_ID, cable=short_cable, **FAST) for _ in range(2)]
    firsts = [env.reset(seed=7)[0] for env in single]
    for key in rules.OBS_KEYS:
        np.testing.assert_array_equal(firsts[0][key], firsts[1][key])
    venv = gym.make_vec(CABLE3D_ENV_ID, num_envs=2, cable=short_cable, **FAST)
    obs, info = venv.reset(seed=[7, 8])
    np.testing.assert_array_equal(obs["markers"][0], firsts[0]["markers"])
    np.testing.assert_array_equal(obs["target_markers"][0], firsts[0]["target_markers"])
    action = np.linspace(-1, 1, 12, dtype=np.float32)
    o1, r1, *_ = single[0].step(action)
    ov, rv, term, trunc, vinfo = venv.step(np.stack([action, -action]))
    np.testing.assert_allclose(ov["markers"][0], o1["markers"], rtol=0, atol=1e-6)
    assert rv[0] == pytest.approx(r1, abs=1e-5) and vinfo["marker_error"].shape == (2,)
    for _ in range(3):                                                # max_steps 3: truncated, then reset
        ov, rv, term, trunc, vinfo = venv.step(venv.action_space.sample())
    assert not trunc.any() and (rv == 0).all()                       # the step after the end: a reset, reward 0


def test_bad_env_options_are_refused_by_name(short_cable):
    for kwargs, match in [({"target": "drawn"}, r"target must be one of \['reachable', 'recorded'\], got 'drawn'"),
                          ({"move_time": 0}, r"move_time must be a positive number of seconds, got 0"),
                          ({"success_tol": -1.0}, r"success_tol must be a positive finite number, got -1.0"),
                          ({"max_steps": 0}, r"max_steps must be a positive integer, got 0")]:
        with pytest.raises(ValueError, match=match):
            BatchedCable3D(1, cable=short_cable, **kwargs)
    with pytest.raises(CableError, match=r"unknown cable 'DLO7'"):
        BatchedCable3D(1, cable="DLO7")
    core = BatchedCable3D(1, cable=short_cable, **FAST)
    core.reset()
    with pytest.raises(ValueError, match=r"actions must have shape \(1, 12\)"):
        core.step(torch.zeros(12))
    assert math.isfinite(float(core.info()["marker_error"][0]))


# ------------------------------------------------------------------ the planners through the chain
def test_cem_and_the_gradient_planner_bring_the_cable_closer_to_its_target(short_cable):
    from planners.cable3d import CEMPlanner, GradientPlanner, run_episode
    core = BatchedCable3D(1, cable=short_cable, move_time=0.1, settle_time=0.3, max_steps=2)
    for planner in (CEMPlanner(core, seed=0, candidates=16, elites=4, iterations=2, plan_settle=0.1),
                    GradientPlanner(core, seed=0, starts=2, steps=3, plan_settle=0.1)):
        ep = run_episode(core, planner, seed=3, progress=False)
        assert ep["steps"] >= 1 and len(ep["errors"]) == ep["steps"] + 1 and ep["sim_moves"] > 0
        assert min(ep["errors"][1:]) < ep["errors"][0]                # its moves make progress on the target
        assert len(ep["final"]) == short_cable.n_nodes and len(ep["target"]) == short_cable.n_nodes
        run_episode(core, planner, seed=5, progress=False, open_loop=planner.name == "cem")     # another episode,
        again = run_episode(core, planner, seed=3, progress=False)              # then episode 3 again: the same
        assert again["actions"] == ep["actions"] and again["errors"] == ep["errors"]


def test_the_planners_command_writes_its_results_and_refuses_bad_flags(tmp_path, capsys):
    import json

    from planners import cable3d as cli
    out = tmp_path / "run"
    argv = ["--cable", "DLO3", "--episodes", "1", "--max-steps", "1", "--move-time", "0.05", "--settle-time", "0.1",
            "--plan-settle", "0.05", "--candidates", "4", "--elites", "2", "--iterations", "1", "--quiet",
            "--out", str(out)]
    assert cli.main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["cable"] == "DLO3" and results["episodes"] == 1 and len(results["episode_records"]) == 1
    episode = results["episode_records"][0]
    assert len(episode["actions"]) == len(episode["frames"]) == episode["steps"] == 1
    core = BatchedCable3D(1, cable="DLO3", move_time=0.05, settle_time=0.1)
    frames = cli.replay(core, episode, every=2)              # the GIF's frames: the episode replayed on the chain
    assert float((frames[-1] - torch.tensor(episode["final"], dtype=F64)).abs().max()) < 1e-5
    assert len(frames) == 1 + episode["frames"][0] // 2 + 1 and (out / "episode_0.gif").stat().st_size > 0
    with pytest.raises(SystemExit):
        cli.main(argv)                                                # an earlier run is not replaced
    assert "--overwrite" in capsys.readouterr().err
    for bad, match in [(["--cable", "DLO8"], "unknown cable 'DLO8'"), (["--elites", "9"], "--elites \\(9\\)"),
                       (["--iterations", "0"], "--iterations must be >= 1")]:
        with pytest.raises(SystemExit):
            cli.main(argv[:-1] + [str(tmp_path / "other")] + bad + ["--overwrite"])
        assert match.replace("\\", "") in capsys.readouterr().err


def test_the_stand_in_adds_its_residual_to_the_physics_and_a_wrong_one_is_refused(short_cable):
    from diffdlo.chain3d.residual import ResidualConfig, ResidualNet
    net = ResidualNet(ResidualConfig(n=short_cable.n_nodes, held=short_cable.held)).double()
    physics = BatchedCable3D(1, cable=short_cable, engine="eager", **FAST)   # the residual's path, to the bit
    stand_in = BatchedCable3D(1, cable=short_cable, residual=net, **FAST)
    for core in (physics, stand_in):
        core.seed([5])
        core.reset()
    torch.testing.assert_close(stand_in.x, physics.x, rtol=0, atol=0)       # a fresh residual is zero: the physics
    with torch.no_grad():
        net.net[-1].bias.fill_(0.5)                                           # now it pushes every free marker
    action = torch.full((1, 12), 0.5, dtype=F64)
    assert float((stand_in.step(action)[0]["markers"] - physics.step(action)[0]["markers"]).abs().max()) > 1e-3
    wrong = ResidualNet(ResidualConfig(n=short_cable.n_nodes + 1, held=(0, 1, 6, 7)))
    with pytest.raises(ValueError, match=r"residual: a diffdlo.chain3d.residual network for 7 markers"):
        BatchedCable3D(1, cable=short_cable, residual=wrong)


def test_the_planners_command_refuses_what_cannot_be_planned(tmp_path, capsys):
    from planners import cable3d as cli
    base = ["--episodes", "1", "--max-steps", "1", "--quiet", "--out", str(tmp_path / "x")]
    for bad, match in [(["--cable", "DLO3", "--model-cable", "DLO1"], "--model-cable DLO1 has 13 markers"),
                       (["--plan-with", "stand-in"], "--plan-with stand-in needs --stand-in"),
                       (["--planner", "gradient", "--open-loop"], "--open-loop plans a whole sequence"),
                       (["--stand-in", str(tmp_path / "none.pt")], "--stand-in: residual checkpoint")]:
        with pytest.raises(SystemExit):
            cli.main(base + bad)
        assert match in capsys.readouterr().err


def test_the_cables_command_reads_rest_lengths_and_speeds_from_recordings(tmp_path, capsys):
    """Synthetic recordings in DEFORM's format (a pickled (T, 3, n) nested list): markers 0.1 m apart translating
    at 0.5 m/s give rest lengths of 0.1 m and every speed 0.5 m/s."""
    import pickle

    from diffdlo.chain3d import cables
    from diffdlo.chain3d.deform import CABLES
    for number, spec in CABLES.items():
        frames = [[[0.1 * j + 0.005 * t for j in range(spec.n_markers)], [0.0] * spec.n_markers,
                   [0.5] * spec.n_markers] for t in range(20)]
        for split in ("train", "eval"):
            folder = tmp_path / f"DLO{number}" / split
            folder.mkdir(parents=True)
            (folder / "1.pkl").write_bytes(pickle.dumps(frames))
    assert cables.main(["--data", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "DLO3: rest_lengths: [0.10000, 0.10000" in out and out.count("rest_lengths") == 5
    assert cables.main(["--data", str(tmp_path), "--speeds"]) == 0
    out = capsys.readouterr().out
    assert "DLO5: 18 frames; free markers [0.5, 0.5, 0.5, 0.5], held ends [0.5, 0.5, 0.5, 0.5]" in out
    with pytest.raises(SystemExit):
        cables.main(["--speeds"])
    assert "--speeds needs --data" in capsys.readouterr().err


def test_the_grid_collects_its_cells_and_skips_finished_ones(tmp_path, capsys):
    import json

    from benchmarks import cable3d_grid
    for seed, wins in ((0, [True, True]), (1, [True, False])):
        folder = cable3d_grid.cell(tmp_path, "cem", "DLO3", seed)
        folder.mkdir(parents=True)
        records = [{"seed": 1000 * seed + i, "success": w, "steps": 2 if w else 20, "errors": [0.05, 0.008 if w else 0.02],
                    "worst_errors": [0.07, 0.012 if w else 0.03]} for i, w in enumerate(wins)]
        (folder / "results.json").write_text(json.dumps({"planner": "cem", "cable": "DLO3", "argv": [], "options": {},
                                                         "plan_seconds_per_move": 2.0, "sim_moves_per_episode": 640,
                                                         "episode_records": records}))
    assert cable3d_grid.run(tmp_path, "cem", ["DLO3"], [0, 1], 2) == 0          # both done: nothing run
    assert cable3d_grid.main(["--collect", str(tmp_path), "--record", str(tmp_path / "record.json")]) == 0
    out = capsys.readouterr().out
    assert "| cem DLO3 | 2 x 2 | 75 % | 2.0 | 0.80 / 2.00 | 2.00 |" in out
    record = json.loads((tmp_path / "record.json").read_text())
    assert len(record["rows"]["cem DLO3"]) == 2


def fake_recordings(folder, cable, n_recordings=2, frames=300, seed=0):
    """DEFORM-format eval recordings of ``cable``: the markers swept from one hung shape to another along a
    minimum-jerk path, so the slowest frames are known (near both ends) and every frame's grippers are in reach."""
    import pickle
    generator = torch.Generator().manual_seed(seed)
    folder.mkdir(parents=True)
    for r in range(n_recordings):
        a, b = (rules.hang(rules.random_grippers(1, cable, generator, F64), cable)[0] for _ in range(2))
        s = gr.min_jerk(torch.linspace(0, 1, frames, dtype=F64)).view(-1, 1, 1)
        x = a + s * (b - a)                                                   # (T, N, 3)
        (folder / f"{r + 1}.pkl").write_bytes(pickle.dumps(x.transpose(1, 2).tolist()))


def test_recorded_targets_are_the_slowest_frames_and_starts_come_from_the_same_recording(tmp_path):
    cable = load_cable("DLO3")
    fake_recordings(tmp_path / "DLO3" / "eval", cable)
    recorded = rules.recorded_targets(tmp_path, cable)
    assert len(recorded.targets) == 2 * rules.RECORDED_PER_RECORDING
    for (r, k), speed in zip(recorded.targets, recorded.speeds):
        assert 1 <= k < 299 and speed > 0
    first = [k for r, k in recorded.targets if r == 0]
    assert sorted(first[:2]) == [1, 298]                                      # the path's two slow ends first
    assert recorded.speeds[:2] == sorted(recorded.speeds[:5])[:2]
    assert all(abs(i - j) >= rules.RECORDED_GAP for i in first for j in first if i != j)
    env = BatchedCable3D(3, cable=cable, target="recorded", data=tmp_path, **FAST)
    env.seed([0, 1, 2])
    env.reset()
    for i in range(3):                                  # each target is a recorded frame, its start another of the same
        hits = [(r, k) for r, k in recorded.targets if torch.equal(recorded.recordings[r][k], env.target[i])]
        assert len(hits) == 1
        r, k = hits[0]
        start = gr.poses_of(env.x[i:i + 1]).pos[0]
        frames = recorded.recordings[r][:, [0, -1]]
        j = int((frames - start).norm(dim=-1).amax(-1).argmin())
        assert float((frames[j] - start).norm(dim=-1).max()) < 1e-9 and abs(j - k) >= rules.START_GAP
    with pytest.raises(ValueError, match="data .* goes with target='recorded'"):
        BatchedCable3D(1, cable=cable, target="recorded")
    with pytest.raises(ValueError, match="recorded targets need one of DEFORM's cables .* 'short'"):
        rules.recorded_targets(tmp_path, dataclasses.replace(cable, name="short"))
    with pytest.raises(ValueError, match="DLO5/eval: no such folder"):
        rules.recorded_targets(tmp_path, load_cable("DLO5"))


def test_the_planners_command_plans_towards_recorded_shapes_and_wants_data_with_them(tmp_path, capsys):
    from planners.cable3d import main
    fake_recordings(tmp_path / "data" / "DLO3" / "eval", load_cable("DLO3"))
    assert main(["--target", "recorded", "--data", str(tmp_path / "data"), "--move-time", "0.2", "--settle-time",
                 "0.3", "--plan-settle", "0.2", "--candidates", "8", "--elites", "2", "--iterations", "1",
                 "--max-steps", "1", "--out", str(tmp_path / "run"), "--quiet"]) == 0
    import json
    assert json.loads((tmp_path / "run" / "results.json").read_text())["target"] == "recorded"
    for argv in (["--target", "recorded"], ["--data", str(tmp_path / "data")]):
        with pytest.raises(SystemExit):
            main(argv + ["--out", str(tmp_path / "never")])
        assert "--data goes with --target recorded and only with it" in capsys.readouterr().err


def test_the_recorded_benchmark_puts_the_chain_at_rest_at_the_recorded_grippers(tmp_path, capsys):
    """On recordings of hung (not settled) shapes: the chain at rest differs from them, the row says so and is
    written once; a second write needs --overwrite."""
    import json

    from benchmarks import cable3d_recorded
    fake_recordings(tmp_path / "data" / "DLO3" / "eval", load_cable("DLO3"))
    out = tmp_path / "static.json"
    argv = ["--data", str(tmp_path / "data"), "--cables", "DLO3", "--out", str(out)]
    assert cable3d_recorded.main(argv) == 0
    row = json.loads(out.read_text())["rows"][0]
    assert row["cable"] == "DLO3" and row["targets"] == 2 * rules.RECORDED_PER_RECORDING
    assert row["mean_error_cm_q10_50_90"][1] > 0 and "| DLO3 | 10 |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cable3d_recorded.main(argv)
    assert "exists: give --overwrite" in capsys.readouterr().err
    assert cable3d_recorded.main(argv + ["--overwrite"]) == 0
