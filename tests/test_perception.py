"""Perception (diffdlo/perception/network.py): training lowers the error, refinement inverts the renderer, checkpoints are
safe and named, the env's "perceived" observation is read from pictures only, and a learner trains on it."""
import argparse
import dataclasses
import json
import warnings

import gymnasium as gym

import numpy as np
import pytest
import torch

import diffdlo
from agents import ppo
from agents.common.config import load_config
from agents.common.envs import make_env
from agents.common.evaluation import evaluate
from diffdlo.envs import BatchedShapeControl
from diffdlo.perception import (Perception, PerceptionError, PerceptionNet, TrainConfig, held_out, main, node_error,
                                refine, render_uint8, sample_shapes, train)

PO = dict(n_nodes=6, length=0.15, max_speed=1.0, settle_max_substeps=30, settle_check_every=10)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A perception of the 6-node rope at 32 px, trained for 150 steps of 32 pictures (4800 pictures)."""
    out = tmp_path_factory.mktemp("perception")
    p = dataclasses.replace(diffdlo.load_params(), **PO)
    cfg = TrainConfig(image_size=32, steps=150, batch=32, pool=64, eval_pictures=32, eval_every=75, refine_iters=0,
                      lr=2e-3)
    torch.manual_seed(0)
    before = Perception(PerceptionNet(32, p.n_nodes, 1.0), p.rest_length, 0)
    test = held_out(p, cfg, diffdlo.Simulator(p), 1.0)
    with torch.no_grad():
        untrained = float(node_error(before.net(test["rope_images"]), test["ropes"]).mean())
    results = train(out, cfg, p, progress=False)
    return out, p, untrained, results


def test_training_lowers_the_held_out_error(tiny):
    out, _, untrained, r = tiny
    assert r["net_node_error_mm"] < 0.6 * 1000 * untrained, (r, untrained)
    assert {"node_error_mm", "target_error_mm", "image_size", "train_images", "wall_s"} <= set(r)
    assert r["image_size"] == 32 and r["train_images"] == 150 * 32
    assert json.loads((out / "results.json").read_text())["node_error_mm"] == r["node_error_mm"]
    rows = (out / "log.csv").read_text().splitlines()
    assert len(rows) == 3                            # header + the evaluations at steps 75 and 150


def test_refine_moves_nearby_nodes_onto_the_picture(params, one_thread):
    g = torch.Generator().manual_seed(0)
    truth = sample_shapes(8, params, g, None).float()
    pictures = render_uint8(truth, 64, 1.0)
    start = truth + 0.004 * torch.randn(truth.shape, generator=g)
    done = refine(start, pictures, params.rest_length, 1.0, iters=30)
    before, after = node_error(start, truth).mean(), node_error(done, truth).mean()
    assert after < 0.6 * before, (before, after)
    assert torch.equal(refine(start, pictures, params.rest_length, 1.0, iters=0), start)     # the net alone


def test_checkpoint_round_trip_and_named_refusals(tiny, tmp_path):
    out, p, _, _ = tiny
    perception = Perception.load(out)
    pictures = render_uint8(sample_shapes(4, p, torch.Generator().manual_seed(3), None).float(), 32, 1.0)
    again = Perception.load(out / "perception.pt")
    assert torch.equal(perception.read(pictures), again.read(pictures))
    with pytest.raises(PerceptionError, match="not found"):
        Perception.load(tmp_path / "missing.pt")
    torch.save({"weights": torch.zeros(1)}, tmp_path / "other.pt")
    with pytest.raises(PerceptionError, match="not a perception checkpoint"):
        Perception.load(tmp_path / "other.pt")
    torch.save({"format": "x", "code": argparse.Namespace(run="anything")}, tmp_path / "pickled.pt")
    with pytest.raises(PerceptionError, match="cannot be read"):          # weights_only: no object is rebuilt
        Perception.load(tmp_path / "pickled.pt")
    with pytest.raises(PerceptionError, match="image_size=32, the pictures have image_size=64"):
        Perception.load(out, image_size=64)
    with pytest.raises(PerceptionError, match=r"\(B, 32, 32, 3\) uint8"):
        perception.read(torch.zeros(1, 64, 64, 3, dtype=torch.uint8))


@pytest.mark.parametrize("size", [48, 8, 100])
def test_bad_image_sizes_are_named(size, tmp_path, capsys):
    with pytest.raises(PerceptionError, match=f"got {size}"):
        PerceptionNet(size, 6, 1.0)
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "p"), "--image-size", str(size)])
    assert "--image-size: image_size must be 8 times a power of two" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_env_perceived_observation_is_read_from_the_pictures_only(tiny):
    out, p, _, _ = tiny
    perception = Perception.load(out)
    kw = dict(num_envs=3, params=p, image_size=32, target="random")
    env = BatchedShapeControl(obs_type="perceived", perception=out, **kw)
    pictures_only = BatchedShapeControl(obs_type="image", mark_end=True, **kw)
    obs, pics = env.reset(seed=7)[0], pictures_only.reset(seed=7)[0]
    assert set(obs) == {"node_poses", "target_poses"}
    seen = perception.perceive(pics)
    for k in obs:
        assert torch.equal(obs[k], seen[k]), k
    true_pos = env.get_state(generators=False).pos
    assert not torch.allclose(obs["node_poses"], true_pos.float(), atol=1e-4)    # what was read, not the state
    action = torch.rand(3, 3, generator=torch.Generator().manual_seed(0))
    obs = env.step(action)[0]
    pics = pictures_only.step(action)[0]
    assert torch.equal(obs["node_poses"], perception.read(pics["image"]))
    with pytest.raises(ValueError, match="perception_refine must be None or an integer >= 0, got -1"):
        BatchedShapeControl(obs_type="perceived", perception=out, perception_refine=-1, **kw)
    with pytest.raises(ValueError, match="perception_refine are read only by obs_type='perceived'"):
        BatchedShapeControl(obs_type="points", perception_refine=3, **kw)
    refined = BatchedShapeControl(obs_type="perceived", perception=out, perception_refine=5, **kw)
    assert refined.perception.refine_iters == 5 and env.perception.refine_iters == 0
    with pytest.raises(PerceptionError, match="needs perception=PATH"):
        BatchedShapeControl(obs_type="perceived", **kw)
    with pytest.raises(PerceptionError, match="image_size=32, the pictures have image_size=64"):
        BatchedShapeControl(obs_type="perceived", perception=out, **dict(kw, image_size=64))


def test_gymnasium_check_env_on_perceived_points(tiny):
    from gymnasium.utils.env_checker import check_env
    out, p, _, _ = tiny
    env = gym.make(diffdlo.envs.ENV_ID, obs_type="perceived", perception=str(out), params=p, image_size=32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)


def test_a_tiny_perceived_task_learns_and_acts_from_pixels_alone(tiny, tmp_path):
    """PPO on obs "perceived" (points read from the pictures by the tiny perception) learns the one-move task; its
    trained policy, fed the perception's reading of pictures from an env that shows pictures only, acts exactly as
    it does in training: no simulator state reaches the acting network."""
    out, p, _, _ = tiny
    sim = diffdlo.Simulator(p)
    start = sim.move(sim.target_shape("horizontal")[None], torch.tensor([5]), torch.tensor([[0.0, 0.1]]))[0]
    np.save(tmp_path / "start.npy", start.numpy())
    common = dict(target="horizontal", start=str(tmp_path / "start.npy"), param_overrides=PO, max_steps=3,
                  success_tol=0.02, eval_episodes=32, num_envs=8, checkpoint_every=10**9, obs="perceived",
                  perception=str(out), image_size=32)
    cfg = load_config(ppo.PPOConfig, "ppo", dict(common, total_steps=3072, eval_every=1024, n_steps=32,
                                                 batch_size=64, n_epochs=4, lr=1e-3))
    env = make_env(cfg.task, cfg.run, cfg.task.cable_params(), 32)
    g = torch.Generator().manual_seed(0)
    random_res = evaluate(lambda o, d: torch.rand(32, 3, generator=g), env, 64, seed=123)
    res = ppo.train(cfg, tmp_path / "ppo", progress=False)
    assert res["success_rate"] >= random_res["success_rate"] + 0.5, (res["success_rate"], random_res)

    from agents.tools.policy import load_policy
    policy = load_policy(tmp_path / "ppo")
    perceived = BatchedShapeControl(num_envs=4, obs_type="perceived", perception=out, params=p, image_size=32,
                                    target="random")
    pictures_only = BatchedShapeControl(num_envs=4, obs_type="image", mark_end=True, params=p, image_size=32,
                                        target="random")
    reading, act = Perception.load(out), policy.batched()
    for seed in (1, 2):
        obs = perceived.reset(seed=seed)[0]
        from_pixels = reading.perceive(pictures_only.reset(seed=seed)[0])
        assert torch.equal(act(obs, True), act(from_pixels, True))


def test_training_resumes_exactly(tmp_path, monkeypatch):
    import diffdlo.perception.network as perception_module
    p = dataclasses.replace(diffdlo.load_params(), **PO)
    cfg = TrainConfig(image_size=32, steps=8, batch=8, pool=16, eval_pictures=8, eval_every=4, refine_iters=2)
    train(tmp_path / "a", cfg, p, progress=False)
    real, calls = perception_module.evaluate, []

    def die_at_the_second_evaluation(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(perception_module, "evaluate", die_at_the_second_evaluation)
    with pytest.raises(KeyboardInterrupt):
        train(tmp_path / "b", cfg, p, progress=False)
    monkeypatch.setattr(perception_module, "evaluate", real)
    assert not (tmp_path / "b" / "perception.pt").exists()
    train(tmp_path / "b", cfg, p, progress=False, resume=True)
    a, b = (torch.load(tmp_path / x / "perception.pt", weights_only=True)["state_dict"] for x in "ab")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert (tmp_path / "a" / "log.csv").read_text().splitlines()[1:] != []
    with pytest.raises(PerceptionError, match="--resume"):
        train(tmp_path / "b", dataclasses.replace(cfg, lr=0.5), p, progress=False, resume=True)


@pytest.mark.parametrize("algo", ["sac", "ppo", "planet"])
def test_obs_image_alone_gives_a_config_that_reads_pictures(algo, tmp_path, capsys):
    """``python -m agents.<algo> --obs image`` needs no other flag: the points-only input options of the tuned
    presets follow it (features raw, no normalization), and PlaNet takes its picture preset (the RSSM)."""
    import importlib

    from agents.common.cli import config_from_args, make_parser
    module = importlib.import_module(f"agents.{algo}")
    cls = {"sac": "SACConfig", "ppo": "PPOConfig", "planet": "PlaNetConfig"}[algo]
    ap = make_parser(f"python -m agents.{algo}", None)
    cfg = config_from_args(getattr(module, cls), algo, ap.parse_args(["--obs", "image", "--out", str(tmp_path)]), ap)
    assert cfg.task.obs == "image"
    if algo == "planet":
        assert cfg.model == "rssm" and "takes the preset 'rssm'" in capsys.readouterr().err
    else:
        assert cfg.inputs.features == "raw" and cfg.inputs.normalize_obs is False
    with pytest.raises(SystemExit):           # asked for explicitly, the points-only setting is still refused
        config_from_args(getattr(module, cls), algo, ap.parse_args(
            ["--obs", "image", "--out", str(tmp_path), "--set", "features=relative"] if algo != "planet" else
            ["--obs", "image", "--out", str(tmp_path), "--preset", "tuned"]), ap)


def test_refine_stays_finite_when_two_nodes_coincide(params):
    g = torch.Generator().manual_seed(1)
    truth = sample_shapes(4, params, g, None).float()
    start = truth.clone()
    start[:, 3] = start[:, 2]                      # a link of length 0: the norm's gradient is NaN there
    done = refine(start, render_uint8(truth, 64, 1.0), params.rest_length, 1.0, iters=5)
    assert torch.isfinite(done).all()


def test_latent_world_model_acts_from_pictures_alone(tiny, tmp_path, monkeypatch):
    """The latent world model from pictures (agents.planet --preset latent, obs "perceived"): it trains on the points
    the perception reads, and its planner, bound to an env, reads of the simulator's state only the move counters
    (which ropes started an episode): with the ropes and targets the env holds replaced by NaN while it plans, it
    acts on the perception's reading of a pictures-only env exactly as on the env's own observation."""
    from agents import planet
    from agents.tools.policy import load_policy
    out, p, _, _ = tiny
    cfg = load_config(planet.PlaNetConfig, "planet-latent", dict(
        param_overrides=PO, obs="perceived", perception=str(out), image_size=32, num_envs=4, max_steps=4,
        total_steps=48, eval_every=48, eval_episodes=4, checkpoint_every=48, latent_dim=8, latent_hidden=[16, 16],
        chunk_length=2, batch_size=8, seed_episodes=2, train_every=16, updates_per_train=2, candidates=8, elites=2,
        iterations=2, openloop_episodes=2, openloop_context=1))
    res = planet.train(cfg, tmp_path / "latent", progress=False)
    assert res["env_steps"] == 48 and res["model"] == "latent"
    policy = load_policy(tmp_path / "latent")
    perceived = BatchedShapeControl(num_envs=3, obs_type="perceived", perception=out, params=p, image_size=32,
                                    target="random")
    pictures_only = BatchedShapeControl(num_envs=3, obs_type="image", mark_end=True, params=p, image_size=32,
                                        target="random")
    reading = Perception.load(out)

    real = perceived.get_state

    def counters_only(*args, **kwargs):
        state = real(*args, **kwargs)
        return dataclasses.replace(state, pos=torch.full_like(state.pos, float("nan")),
                                   target=torch.full_like(state.target, float("nan")), info={})

    for seed in (1, 2):
        obs = perceived.reset(seed=seed)[0]
        from_pixels = reading.perceive(pictures_only.reset(seed=seed)[0])
        with monkeypatch.context() as m:
            m.setattr(perceived, "get_state", counters_only)
            a1 = policy.batched(perceived)(obs, True)
            a2 = policy.batched(perceived)(from_pixels, True)
        assert torch.equal(a1, a2) and a1.shape == (3, 3) and torch.isfinite(a1).all()
