"""agents.planet / agents.models.rssm: RSSM shapes and ELBO terms, free nats, chunk sampling, overfitting, latent CEM,
open-loop evaluation, CLI smoke runs (points and images) with resume."""
import json
import math

import pytest
import torch

import diffdlo
from agents.models import openloop
from agents import planet
from agents.common.buffer import ReplayBuffer
from agents.common.checkpoints import CHECKPOINT
from agents.common.config import load_config
from agents.common.envs import make_env
from agents.common.logs import read_csv
from agents.models.rssm import RSSM, LatentObjective, LatentPlanner, free_nats_kl, gauss_kl
from planners.cem import CEM

PO = dict(n_nodes=6, length=0.15, max_speed=1.0, settle_max_substeps=30, settle_check_every=10)
TINY = "param_overrides={n_nodes: 6, length: 0.15, max_speed: 1.0, settle_max_substeps: 30, settle_check_every: 10}"
SMALL_MODEL = dict(deter=24, stoch=6, hidden=24, embed=24)


pytestmark = pytest.mark.usefixtures("one_thread")


def tiny_cfg(**kw):
    base = dict(param_overrides=PO, num_envs=4, max_steps=6, total_steps=64, **SMALL_MODEL)
    base.update(kw)
    return load_config(planet.PlaNetConfig, "planet-rssm", base)


def collect(cfg, rows, seed=0):
    env = make_env(cfg.task, cfg.run, cfg.task.cable_params(), cfg.run.num_envs)
    obs = env.reset(seed=seed)
    rb = ReplayBuffer(rows, cfg.run.num_envs, obs, env.core.action_dim)
    g = torch.Generator().manual_seed(seed)
    for _ in range(rows):
        a = torch.rand(cfg.run.num_envs, env.core.action_dim, generator=g)
        nxt, r, te, tr, _, fo = env.step(a)
        rb.add(obs, a, r, te, tr, final_obs=fo)
        obs = nxt
    return rb, obs


def sequences(rb, batch, length, generator=None):
    """``ReplayBuffer.sample_sequences`` as the models' loss takes it: obs, actions, rewards, mask."""
    s = rb.sample_sequences(batch, length, generator)
    return s["obs"], s["action"], s["reward"], s["mask"]


@pytest.mark.parametrize("obs_type,action", [("points", "node"), ("distance", "pixel"), ("image", "node")])
def test_rssm_shapes_and_loss_terms(obs_type, action):
    cfg = tiny_cfg(obs=obs_type, action=action, image_size=40, image_embed=32, cnn_channels=[4, 8, 8],
                   deconv_channels=[8, 4])
    rb, obs = collect(cfg, 12)
    a_dim = 3 if action == "node" else 4
    m = planet.build_model(cfg, obs, a_dim, cfg.task.cable_params())
    o, a, r, mask = sequences(rb, 5, 4)
    first = next(iter(o.values())) if isinstance(o, dict) else o
    assert first.shape[:2] == (5, 5) and a.shape == (5, 4, a_dim) and r.shape == (5, 4) and mask.shape == (5, 5)
    L = m.loss(o, a, r, mask)
    for k in ("loss", "recon", "kl", "kl_loss", "reward_loss", "reward_mae"):
        assert L[k].ndim == 0 and torch.isfinite(L[k]), k
    assert L["kl_loss"].item() >= cfg.free_nats
    assert torch.allclose(L["loss"], L["recon"] + L["kl_loss"] + L["reward_loss"])
    L["loss"].backward()
    st = L["last_state"]
    assert st["h"].shape == (5, cfg.deter) and st["z"].shape == (5, cfg.stoch)
    traj = m.imagine({k: v.detach() for k, v in st.items()}, torch.rand(5, 3, a_dim))
    feat = torch.stack([RSSM.feature(s) for s in traj], 1)
    assert feat.shape == (5, 3, cfg.deter + cfg.stoch)
    dec = m.decode(feat)
    for k, v in (o.items() if isinstance(o, dict) else [("obs", o)]):
        assert dec[k].shape == (5, 3, *v.shape[2:])
    assert m.reward(feat).shape == (5, 3)


@pytest.mark.parametrize("obs_type", ["points", "image"])
def test_reconstruction_term_is_the_gaussian_log_likelihood(obs_type, monkeypatch):
    """recon = 0.5 ((prediction - target) / std)^2 summed over an observation's dims, averaged over the valid steps;
    std is obs_std for coordinates and 1 for pixels (PlaNet's unit variance)."""
    cfg = tiny_cfg(obs=obs_type, image_size=40, image_embed=32, cnn_channels=[4, 8, 8], deconv_channels=[8, 4])
    rb, obs = collect(cfg, 12)
    m = planet.build_model(cfg, obs, 3, cfg.task.cable_params())
    o, a, r, mask = sequences(rb, 5, 4)
    delta = 0.03
    monkeypatch.setattr(m, "decode", lambda feat: {k: v + delta for k, v in m.obs_target(o if isinstance(o, dict)
                                                                                         else {"obs": o}).items()})
    dims = {k: math.prod(v.shape[2:]) for k, v in (o.items() if isinstance(o, dict) else [("obs", o)])}
    expected = sum(0.5 * (delta / (cfg.obs_std if k in m.float_keys else 1.0)) ** 2 * n for k, n in dims.items())
    assert m.loss(o, a, r, mask)["recon"].item() == pytest.approx(expected, rel=1e-5)


def test_free_nats_clamp_constant_and_no_gradient():
    mean = torch.zeros(4, 3, 5, requires_grad=True)
    kl = gauss_kl(mean, torch.ones(4, 3, 5), torch.full((4, 3, 5), 0.1), torch.ones(4, 3, 5))   # 0.025 nats
    assert kl.max().item() < 3.0
    k = free_nats_kl(kl, 3.0)
    assert k.item() == 3.0
    (g,) = torch.autograd.grad(k, mean)
    assert torch.count_nonzero(g) == 0
    kl_big = gauss_kl(mean + 5, torch.ones(4, 3, 5), torch.zeros(4, 3, 5), torch.ones(4, 3, 5))   # 62.5 nats
    k2 = free_nats_kl(kl_big, 3.0)
    assert float(k2.detach()) == pytest.approx(62.5) and torch.autograd.grad(k2, mean)[0].abs().sum() > 0
    # inside the model: a huge free_nats makes the KL term a constant with no gradient to any parameter
    cfg = tiny_cfg(free_nats=1e6)
    rb, obs = collect(cfg, 10)
    m = planet.build_model(cfg, obs, 3, cfg.task.cable_params())
    L = m.loss(*sequences(rb, 4, 4))
    assert float(L["kl_loss"].detach()) == 1e6 and float(L["kl"].detach()) < 1e6
    grads = torch.autograd.grad(L["kl_loss"], list(m.parameters()), allow_unused=True)
    assert all(g is None or torch.count_nonzero(g) == 0 for g in grads)


def test_chunk_sampler_feeds_valid_sequences():
    cfg = tiny_cfg(max_steps=3)                       # episodes of 3 moves: many ends in the buffer
    rb, _ = collect(cfg, 20)
    g = torch.Generator().manual_seed(0)
    c = rb.sample_sequences(200, 3, g)
    ends = c["terminated"] | c["truncated"]
    assert not bool(ends[:, :-1].any())             # an episode end only at the chunk's last row
    assert bool(ends[:, -1].any())                  # ... and those chunks are sampled
    assert bool((c["e"] == c["e"][:, :1]).all())
    assert bool(((c["t"][:, 1:] - c["t"][:, :-1]) % rb.capacity == 1).all())
    o, a, r, mask = sequences(rb, 200, 3, torch.Generator().manual_seed(0))
    assert torch.equal(a, c["action"]) and torch.equal(r, c["reward"])
    t, e = c["t"][:, -1], c["e"][:, -1]
    for i in range(200):                            # the extra observation is the step's true next observation
        key = (int(t[i]), int(e[i]))
        if key in rb.final_obs:
            assert torch.equal(o["node_poses"][i, -1], rb.final_obs[key]["node_poses"])
        elif mask[i, -1] > 0:
            assert torch.equal(o["node_poses"][i, -1], rb.obs["node_poses"][(t[i] + 1) % rb.capacity, e[i]])
    # within an episode consecutive observations are consecutive env states: the rope moved by at most one drag
    step = (o["node_poses"][:, 1:] - o["node_poses"][:, :-1]).norm(dim=-1).max()
    assert float(step) < 0.25
    # the write head: the newest row's next observation is unknown unless its episode ended -> masked
    head = (t == (rb.pos - 1) % rb.capacity) & ~(c["terminated"][:, -1] | c["truncated"][:, -1])
    assert bool((mask[head, -1] == 0).all()) and bool((mask[~head, -1] == 1).all())


def test_tiny_model_overfits_a_fixed_sequence():
    torch.manual_seed(0)
    cfg = tiny_cfg(obs_std=0.1, deter=32, stoch=8, hidden=64, embed=32)
    rb, obs = collect(cfg, 12)
    batch = sequences(rb, 4, 6, torch.Generator().manual_seed(1))
    m = planet.build_model(cfg, obs, 3, cfg.task.cable_params())
    opt = torch.optim.Adam(m.parameters(), lr=3e-3, eps=1e-4)
    losses = []
    for _ in range(300):
        L = m.loss(*batch)
        opt.zero_grad()
        L["loss"].backward()
        opt.step()
        losses.append(float((L["recon"] + L["reward_loss"]).detach()))
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])


def test_latent_cem_improves_a_known_objective():
    """CEM (planners/cem.py) through a latent-space objective: reach the latent state that a hidden action sequence
    leads to. The best cost must fall far below the cost of random sequences."""
    torch.manual_seed(0)
    cfg = tiny_cfg()
    env = make_env(cfg.task, cfg.run, cfg.task.cable_params(), 1)
    obs = env.reset(seed=0)
    m = planet.build_model(cfg, obs, 3, cfg.task.cable_params())
    with torch.no_grad():
        st, _ = m.obs_step(None, None, m.embed(obs), sample=False)
        secret = torch.tensor([[[0.4, 0.9, 0.2], [1.0, 0.1, 0.7]]])
        goal = RSSM.feature(m.imagine(st, secret)[-1])

    def objective(actions):
        s = {k: v.expand(actions.shape[0], -1) for k, v in st.items()}
        return (RSSM.feature(m.imagine(s, actions.float())[-1]) - goal).pow(2).sum(-1)

    cem = CEM(3, 2, candidates=100, elites=10, iterations=6, discrete={0: 6}, generator=torch.Generator().manual_seed(0))
    best, cost = cem.optimize(objective)
    with torch.no_grad():
        random_cost = objective(torch.rand(200, 2, 3)).mean()
    assert cost < 0.1 * float(random_cost)
    assert cem.history[-1]["best"] < cem.history[0]["best"]
    # the same through the agent's LatentObjective (reward form) and planner: valid actions, node and pixel
    obj = LatentObjective(m, st)
    assert obj(torch.rand(7, 2, 3)).shape == (7,)
    for action in ("node", "pixel"):
        c2 = tiny_cfg(action=action, horizon=2, candidates=16, elites=4, iterations=2)
        e2 = make_env(c2.task, c2.run, c2.task.cable_params(), 3)
        o2 = e2.reset(seed=1)
        m2 = planet.build_model(c2, o2, e2.core.action_dim, c2.task.cable_params())
        pl = LatentPlanner(m2, c2, e2.core, 0)
        for _ in range(2):
            a = pl(o2, deterministic=False)
            assert a.shape == (3, e2.core.action_dim) and bool(((a >= 0) & (a <= 1)).all())
            o2, *_ = e2.step(a)


def test_open_loop_eval_reports_model_and_baseline():
    cfg = tiny_cfg(openloop_episodes=6, openloop_context=2)
    env = make_env(cfg.task, cfg.run, cfg.task.cable_params(), 1)
    m = planet.build_model(cfg, env.reset(seed=0), 3, cfg.task.cable_params())
    res = openloop.open_loop_eval(m, cfg, horizons=(2, 4))
    for k in ("pred_err_2", "base_err_2", "pred_err_4", "base_err_4"):
        assert res[k] >= 0 and res[k] == res[k]
    assert res["pred"].shape == res["true"].shape == (6, 4, 6, 2)


def argv(out, total, *extra):
    return ["--out", str(out), "--preset", "rssm", "--total-steps", str(total), "--num-envs", "4", "--set", TINY, "--max-steps", "8",
            "--eval-every", "10000", "--eval-episodes", "4", "--checkpoint-every", "64", "--no-progress",
            "--set", "deter=16", "--set", "stoch=4", "--set", "hidden=16", "--set", "embed=16",
            "--set", "horizon=2", "--set", "candidates=12", "--set", "elites=3", "--set", "iterations=2",
            "--set", "seed_episodes=4", "--set", "train_every=32", "--set", "updates_per_train=4",
            "--set", "batch_size=8", "--set", "chunk_length=4", "--set", "log_every=2",
            "--set", "openloop_episodes=4", "--set", "openloop_context=2", *extra]


@pytest.mark.parametrize("obs,action", [("points", "node"), ("image", "pixel")])
def test_cli_smoke_writes_everything_and_resumes(obs, action, tmp_path):
    extra = ["--obs", obs, "--action", action, "--target", "random"]
    if obs == "image":
        extra += ["--set", "image_size=40", "--set", "cnn_channels=[4,8,8]", "--set", "image_embed=32",
                  "--set", "deconv_channels=[8,4]", "--set", "buffer_size=2048"]
    assert planet.main(argv(tmp_path, 96, *extra)) == 0
    for name in ("results.json", "train.csv", "eval.csv", "openloop.csv", CHECKPOINT, "openloop.png",
                 "eval_episodes.png"):
        assert (tmp_path / name).exists(), name
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["method"] == "planet" and res["env_steps"] == 96 and len(res["episodes"]) == 4
    row = read_csv(tmp_path / "train.csv")[-1]
    for k in ("recon", "kl", "reward_loss", "reward_mae"):
        assert float(row[k]) == float(row[k])
    ol = read_csv(tmp_path / "openloop.csv")[-1]
    assert {"pred_err_5", "base_err_5", "pred_err_10", "base_err_10"} <= set(ol)
    n_before = torch.load(tmp_path / CHECKPOINT, weights_only=False)["n_updates"]
    assert planet.main(["--out", str(tmp_path), "--resume", "--total-steps", "160", "--no-progress"]) == 0
    ck = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    assert ck["step"] == 160 and ck["n_updates"] > n_before and len(ck["buffer"]["action"]) == 40
    assert json.loads((tmp_path / "results.json").read_text())["env_steps"] == 160


def test_bad_plan_objective_is_refused(tmp_path):
    with pytest.raises(ValueError, match="plan_objective"):
        planet.train(tiny_cfg(plan_objective="nope"), tmp_path, progress=False)
    with pytest.raises(ValueError, match="points or distance"):
        planet.train(tiny_cfg(obs="image", plan_objective="shape"), tmp_path, progress=False)


def test_resume_equals_uninterrupted(tmp_path):
    """Killed right after its checkpoint, resumed: the same losses, evaluations and results as one run (the planners'
    beliefs, warm starts and generators are in the checkpoint)."""
    a, b = tmp_path / "a", tmp_path / "b"
    every = ["--eval-every", "64"]
    assert planet.main(argv(a, 128, *every)) == 0
    assert planet.main(argv(b, 64, *every)) == 0
    assert planet.main(["--out", str(b), "--resume", "--total-steps", "128", "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv", "openloop.csv"):
        assert (a / name).read_text() == (b / name).read_text(), name
    ra, rb = json.loads((a / "results.json").read_text()), json.loads((b / "results.json").read_text())
    assert ra["episodes"] == rb["episodes"] and rb["env_steps"] == 128
    assert len([r for r in read_csv(b / "train.csv") if float(r["step"]) > 64]) > 0


def stop_when(calls_of, obj, name, after, when=lambda *a, **k: True):
    """Wrap ``obj.name`` so that its ``after``-th call among those where ``when(*args)`` holds asks the running
    learner to stop, as the first SIGTERM does (agents/common/run.py's stop request)."""
    from agents.common import run as run_mod
    inner = getattr(obj, name)

    def wrapped(*args, **kw):
        if when(*args, **kw):
            calls_of.append(1)
            if len(calls_of) == after:
                run_mod._stop[-1].signal = "SIGTERM"
        return inner(*args, **kw)
    return wrapped


STOP_RUN = ["--eval-every", "64", "--set", "eval_targets=[diagonal]"]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    a = tmp_path_factory.mktemp("uninterrupted")
    assert planet.main(argv(a, 128, *STOP_RUN)) == 0
    return a


@pytest.mark.parametrize("where", ["between-updates", "in-evaluation", "in-heldout"])
def test_a_stop_within_a_step_resumes_as_the_uninterrupted_run(where, uninterrupted, tmp_path, monkeypatch, capsys):
    """A stop between two of a phase's updates (a checkpoint with the updates left), during an evaluation (the
    checkpoint saved just before it) or during the held-out evaluation after training (the end's checkpoint): each
    stops at once with a checkpoint, and --resume writes the same logs and results as one run."""
    a, b, extra = uninterrupted, tmp_path / "b", STOP_RUN
    calls = []
    if where == "between-updates":      # asked in the 2nd phase's 2nd update (updates_per_train=4): stops after it
        monkeypatch.setattr(ReplayBuffer, "sample_sequences", stop_when(calls, ReplayBuffer, "sample_sequences", 6))
    else:                                # a planned move of the 2nd evaluation (step 128) or of the held-out one
        eval_call = lambda self, obs, deterministic=True: deterministic
        after = {"in-evaluation": 8 + 3, "in-heldout": 16 + 3}[where]   # 8 evaluation moves at most (max_steps)
        monkeypatch.setattr(LatentPlanner, "__call__",
                            stop_when(calls, LatentPlanner, "__call__", after, eval_call))
    assert planet.main(argv(b, 128, *extra)) == 143                  # as a shell reports SIGTERM
    monkeypatch.undo()
    assert "stopped by SIGTERM at env step" in capsys.readouterr().err
    ck = torch.load(b / CHECKPOINT, weights_only=False)
    assert not (b / "results.json").exists()
    if where == "between-updates":
        assert ck["pending_updates"] == 2 and ck["step"] == 64
    elif where == "in-evaluation":
        assert ck["step"] == 128 and ck["last_eval"] == 64
    else:
        assert ck["step"] == 128 and ck["last_eval"] == 128
    assert planet.main(["--out", str(b), "--resume", "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv", "openloop.csv", "rollout.csv"):
        assert (a / name).read_text() == (b / name).read_text(), name
    ra, rb = json.loads((a / "results.json").read_text()), json.loads((b / "results.json").read_text())
    assert ra["episodes"] == rb["episodes"] and ra["heldout"] == rb["heldout"] and rb["env_steps"] == 128


def test_world_model_benchmark_runs(capsys):
    from benchmarks.studies import planet_model
    assert planet_model.main(["--preset", "rssm", "--updates", "2", "--moves", "12", "--envs", "3", "--set", TINY, "--set", "batch_size=4",
                              "--set", "chunk_length=4", "--set", "openloop_episodes=3", "--set", "deter=8",
                              "--set", "stoch=2", "--set", "hidden=8", "--set", "embed=8"]) == 0
    out = capsys.readouterr().out
    assert "2 updates" in out and "k=10:" in out
    assert planet_model.main(["--preset", "rssm", "--plan-time", "--envs", "2", "--set", TINY, "--set", "candidates=8",
                              "--set", "elites=2", "--set", "iterations=1", "--set", "deter=8", "--set", "stoch=2",
                              "--set", "hidden=8", "--set", "embed=8"]) == 0
    assert capsys.readouterr().out.count("planned move") == 3


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("obs,env_device", [("points", "cpu"), ("points", ""), ("image", "cpu")])
def test_planet_on_cuda_with_env_on_cpu_or_cuda(obs, env_device, tmp_path):
    extra = ["--obs", obs, "--target", "random", "--set", "device=cuda"]
    extra += ["--set", f"env_device={env_device}"] if env_device else []
    if obs == "image":
        extra += ["--action", "pixel", "--set", "image_size=40", "--set", "cnn_channels=[4,8,8]",
                  "--set", "image_embed=32", "--set", "deconv_channels=[8,4]", "--set", "buffer_size=2048"]
    assert planet.main(argv(tmp_path, 96, *extra)) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["env_steps"] == 96 and len(res["episodes"]) == 4
    assert all(e["final_error"] == e["final_error"] for e in res["episodes"])
    assert planet.main(["--out", str(tmp_path), "--resume", "--total-steps", "160", "--no-progress"]) == 0
