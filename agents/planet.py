"""PlaNet (Hafner et al. 2019; thesis Chapter 3): learn a world model from replayed chunks and act by CEM planning
through it. CleanRL-style: config -> model -> planner -> loop.

    python -m agents.planet --out runs/planet                     # tuned: the ensemble on points, 10k env steps
    python -m agents.planet --preset rssm --obs image --action pixel --out runs/planet-rssm-image

Two world models (``model``):
- "ensemble" (default, params/planet.yaml; agents/dynamics.py): PETS-style MLPs predicting one move's change of the
  rope from the rope, the grasped node and the drag; planned through by ``agents.dynamics.ModelPlanner`` with the
  planners' cost (shape error of the predicted rope against the observed target). Points and node actions only.
- "rssm" (params/planet-rssm.yaml; agents/rssm.py): PlaNet's recurrent state-space model, any observation, planned
  in latent space by ``LatentPlanner`` below.

Data: the ONE shared replay storage (agents/buffer.py). Its chunk sampler returns L contiguous rows of one rope that
never cross an episode end (an end only at the last row) nor the write head; the observation after the last row is
added from ``ReplayBuffer.next_obs`` (the stored final observation where the episode ended there, so the success
reward is learned), masked out only when that row is the newest one and its next observation is not written yet.
The ensemble draws ``batch_size`` chunks per member.

Loop: ``seed_episodes`` x max_steps env transitions of uniform random actions, then ``updates_per_train`` model
updates every ``train_every`` env transitions, collecting with the planner plus Gaussian exploration noise.

Latent planning (RSSM): the project's generic ``planners.cem.CEM`` (categorical over the grasped node for node
actions, Gaussians for the drags) minimises ``LatentObjective``: from the current posterior state, roll the prior
mean forward under each candidate sequence and return minus the sum of predicted rewards (``plan_objective:
reward``, PlaNet) or, for points/distance observations, the shape error of the decoded rope against the (observed)
target (``plan_objective: shape``, the planners' cost in planners/objective.py). The prior MEAN is used so that a
candidate's cost is deterministic, as CEM's elitism assumes.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from agents.buffer import ReplayBuffer, as_dict, index_obs
from agents.common import (CHECKPOINT, EpisodeStats, Logger, eval_row, evaluate, evaluate_heldout, fmt_postfix,
                           heldout_envs, load_checkpoint, make_env, make_params, rng_state, run_cli, save_checkpoint,
                           seed_everything, set_rng_state, torch_threads, warn_if_large_buffer, write_results)
from agents.dynamics import EnsembleDynamics, ModelPlanner, check_settings, k_step_errors
from agents.rssm import RSSM
from diffdlo.rewards import shape_error
from planners.cem import CEM, optimize_together


# ====================================================================== config (defaults: params/planet.yaml)
@dataclasses.dataclass
class PlaNetConfig:
    # task
    target: Any = "random"
    obs: str = "points"
    action: str = "node"
    reward: str = "position_orientation"
    max_steps: int | None = None
    params: str = "cable"
    param_overrides: dict | None = None
    start: Any = None
    success_tol: float | None = None
    image_size: int = 64
    # run
    total_steps: int = 100_000
    num_envs: int = 16
    seed: int = 0
    device: str = "cpu"                   # networks and buffer
    env_device: str = ""                  # the simulator ("": same as device; "cpu" with device "cuda": fused CPU kernel)
    threads: int = 1
    eval_every: int = 10_000
    eval_episodes: int = 20
    eval_seed: int = 10_000
    eval_targets: list = dataclasses.field(default_factory=list)
    checkpoint_every: int = 10_000
    log_every: int = 25                   # model updates between train-loss rows
    # model: "ensemble" (agents/dynamics.py, points only) or "rssm" (agents/rssm.py, PlaNet's)
    model: str = "ensemble"
    members: int = 5
    model_hidden: list = dataclasses.field(default_factory=lambda: [200, 200, 200])
    augment: list = dataclasses.field(default_factory=lambda: ["mirror", "reverse"])
    frame: str = "grasp"
    propagation: str = "members"
    running_weight: float = 0.5
    deter: int = 200
    stoch: int = 30
    hidden: int = 200
    embed: int = 200
    image_embed: int = 1024
    cnn_channels: list = dataclasses.field(default_factory=lambda: [32, 64, 64])
    deconv_channels: list = dataclasses.field(default_factory=lambda: [64, 32, 16])
    min_std: float = 0.1
    obs_std: float = 0.02
    free_nats: float = 3.0
    # learning
    lr: float = 1e-3
    adam_eps: float = 1e-4
    grad_clip: float = 1000.0
    batch_size: int = 50
    chunk_length: int = 16
    buffer_size: int = 1_000_000
    seed_episodes: int = 40
    train_every: int = 250
    updates_per_train: int = 100
    # planning
    horizon: int = 3
    candidates: int = 300
    elites: int = 30
    iterations: int = 5
    plan_objective: str = "reward"
    explore_noise: float = 0.15
    # open-loop prediction evaluation
    openloop_episodes: int = 32
    openloop_context: int = 5
    openloop_seed: int = 20_000


def check_planet_config(cfg: PlaNetConfig) -> None:
    if cfg.model not in ("ensemble", "rssm"):
        raise ValueError(f"unknown model {cfg.model!r}: use 'ensemble' or 'rssm'")
    if cfg.model == "ensemble":
        if cfg.obs != "points" or cfg.action != "node":
            raise ValueError(f"model 'ensemble' predicts node positions from node actions: it needs obs 'points' and "
                             f"action 'node', got obs {cfg.obs!r} and action {cfg.action!r} (use --preset rssm)")
        check_settings(cfg.members, cfg.model_hidden, cfg.augment, cfg.frame, cfg.propagation)
    if cfg.plan_objective not in ("reward", "shape"):
        raise ValueError(f"plan_objective must be 'reward' or 'shape', got {cfg.plan_objective!r}")
    if cfg.plan_objective == "shape" and cfg.obs not in ("points", "distance"):
        raise ValueError("plan_objective 'shape' needs points or distance observations (it decodes node positions)")
    for key in ("chunk_length", "batch_size", "horizon", "candidates", "elites", "iterations", "train_every"):
        if int(getattr(cfg, key)) < 1:
            raise ValueError(f"{key} must be >= 1")


def build_model(cfg: PlaNetConfig, obs: Any, action_dim: int) -> RSSM | EnsembleDynamics:
    p = make_params(cfg)
    if cfg.model == "ensemble":
        return EnsembleDynamics(p, cfg.members, cfg.model_hidden, cfg.augment, cfg.frame).to(cfg.device)
    return RSSM(obs, action_dim, action_type=cfg.action, n_nodes=p.n_nodes, scale=1.0 / p.length,
                deter=cfg.deter, stoch=cfg.stoch, hidden=cfg.hidden, embed=cfg.embed,
                cnn_channels=cfg.cnn_channels, image_embed=cfg.image_embed, deconv_channels=cfg.deconv_channels,
                min_std=cfg.min_std, obs_std=cfg.obs_std, free_nats=cfg.free_nats).to(cfg.device)


# ====================================================================== planning in latent space
def decoded_positions(model: RSSM, feat: torch.Tensor, obs_type: str, target: torch.Tensor | None = None):
    """Rope node positions [m] (..., N, 2) decoded from features, for points (node_poses) or distance (+ target)."""
    dec = model.decode(feat)
    if obs_type == "points":
        return dec["node_poses"] / model.scale
    if obs_type == "distance":
        return dec["obs"] / model.scale + target
    raise ValueError(f"no node positions in {obs_type!r} observations")


class LatentObjective:
    """cost(actions) from latent states through the prior mean: R ropes' states (R, ...) and candidates
    (R, C, H, A) -> (R, C), all in one batched model call; or one rope's state (1, ...) and (C, H, A) -> (C,).
    ``target`` (R, N, 2) or (N, 2): the ropes' targets for the "shape" cost."""

    def __init__(self, model: RSSM, state: dict[str, torch.Tensor], kind: str = "reward", obs_type: str = "points",
                 target: torch.Tensor | None = None):
        self.model, self.state, self.kind, self.obs_type = model, state, kind, obs_type
        self.target = None if target is None else target.reshape(-1, *target.shape[-2:])
        self.calls = 0

    @torch.no_grad()
    def __call__(self, actions: torch.Tensor) -> torch.Tensor:
        single = actions.dim() == 3
        x = actions[None] if single else actions
        r, c = x.shape[:2]
        dev = self.state["h"].device
        st = {k: v[:, None].expand(r, c, *v.shape[1:]).reshape(r * c, *v.shape[1:]) for k, v in self.state.items()}
        traj = self.model.imagine(st, x.reshape(r * c, *x.shape[2:]).to(dev, torch.float32), sample=False)
        feat = torch.stack([RSSM.feature(s) for s in traj], 1)                  # (R C, H, F)
        self.calls += 1
        if self.kind == "reward":
            cost = -self.model.reward(feat).sum(1)
        else:
            tgt = self.target[:, None].expand(r, c, *self.target.shape[1:]).reshape(r * c, *self.target.shape[1:])
            pos = decoded_positions(self.model, feat[:, -1], self.obs_type, tgt)
            cost = shape_error(pos, tgt)
        cost = cost.view(r, c)
        return cost[0] if single else cost


class LatentPlanner:
    """The acting policy: filters the belief state of every rope and plans each rope's next move with its own
    (warm-started) CEM. Knows a rope started a new episode from the env core's step counter (0 after a reset), so
    it works inside ``agents.common.evaluate`` too; ropes whose counter did not move since the last call (finished
    in an evaluation wave) keep their last action without planning."""

    def __init__(self, model: RSSM, cfg: PlaNetConfig, core, seed: int):
        self.model, self.cfg, self.core = model, cfg, core
        self.b, self.A = core.num_envs, core.action_dim
        discrete = {0: core.params.n_nodes} if cfg.action == "node" else None
        self.cems = [CEM(self.A, cfg.horizon, cfg.candidates, cfg.elites, cfg.iterations, discrete=discrete,
                         generator=torch.Generator().manual_seed(seed + i), dtype=torch.float32)
                     for i in range(self.b)]
        self.state: dict[str, torch.Tensor] | None = None
        self.prev_action = torch.zeros(self.b, self.A, device=cfg.device)
        self.last_steps = torch.full((self.b,), -1, dtype=torch.int64)

    def state_dict(self) -> dict[str, Any]:
        """Belief, last action and every rope's CEM (distribution, warm start, generator): a resumed run plans
        exactly as the uninterrupted one."""
        return {"state": None if self.state is None else {k: v.clone() for k, v in self.state.items()},
                "prev_action": self.prev_action.clone(), "last_steps": self.last_steps.clone(),
                "cems": [c.state_dict() for c in self.cems]}

    def load_state_dict(self, s: dict[str, Any]) -> None:
        if len(s["cems"]) != self.b:
            raise ValueError(f"planner state for {len(s['cems'])} ropes, this planner has {self.b}")
        dev = self.cfg.device
        self.state = None if s["state"] is None else {k: v.to(dev) for k, v in s["state"].items()}
        self.prev_action = s["prev_action"].to(dev)
        self.last_steps = s["last_steps"].clone()
        for c, cs in zip(self.cems, s["cems"]):
            c.load_state_dict(cs)

    @torch.no_grad()
    def __call__(self, obs: Any, deterministic: bool = True) -> torch.Tensor:
        m, dev = self.model, self.cfg.device
        steps = self.core.steps.cpu().long()
        new = steps == 0
        moved = (steps != self.last_steps) | new
        emb = m.embed(obs)
        sample = not deterministic      # evaluation filters with the posterior mean
        post, _ = m.obs_step(self.state if self.state is not None else m.initial(self.b, dev), self.prev_action, emb,
                             sample)
        if self.state is None or bool(new.any()):
            fresh, _ = m.obs_step(None, None, emb, sample)
            nd = new.to(dev)
            if self.state is None:
                post = fresh
            else:
                post = {k: torch.where(nd[:, None], fresh[k], post[k]) for k in post}
            for i in new.nonzero().flatten().tolist():
                self.cems[i].reset()
        if self.state is not None:     # ropes that did not move keep their state
            keep = (~moved).to(dev)
            post = {k: torch.where(keep[:, None], self.state[k], post[k]) for k in post}
        self.state = post
        action = self.prev_action.clone()
        target = self.core.target.to(dev).float() if self.cfg.plan_objective == "shape" else None
        rows = moved.nonzero().flatten().tolist()
        if rows:                                   # every moving rope's CEM in lockstep, one model call per iteration
            idx = torch.tensor(rows, device=dev)
            obj = LatentObjective(m, {k: v[idx] for k, v in post.items()}, self.cfg.plan_objective, self.cfg.obs,
                                  None if target is None else target[idx])
            bests = optimize_together([self.cems[i] for i in rows], obj)
            for i, (best, _) in zip(rows, bests):
                self.cems[i].shift()
                action[i] = best[0].to(dev)
        if not deterministic and self.cfg.explore_noise > 0:
            noise = self.cfg.explore_noise * torch.randn(self.b, self.A, device=dev)
            action = torch.where(moved.to(dev)[:, None], (action + noise).clamp(0.0, 1.0), action)
        self.prev_action = action
        self.last_steps = steps.clone()
        return action


def make_planner(model: RSSM | EnsembleDynamics, cfg: PlaNetConfig, core, seed: int):
    return ModelPlanner(model, cfg, core, seed) if cfg.model == "ensemble" else LatentPlanner(model, cfg, core, seed)


# ====================================================================== data
def sample_sequences(rb: ReplayBuffer, batch: int, length: int, generator: torch.Generator | None = None):
    """Chunks of ``length`` rows plus the observation after the last row: obs (B, L+1, ...), actions (B, L, A),
    rewards (B, L), mask (B, L+1) (0 only for that extra observation where it is not written yet)."""
    c = rb.sample_chunks(batch, length, generator)
    t_last, e = c["t"][:, -1], c["e"][:, -1]
    ended = rb.terminated[t_last, e] | rb.truncated[t_last, e]
    head = (t_last == (rb.pos - 1) % rb.capacity)
    nxt = rb.next_obs(t_last, e) if not bool((head & ~ended).any()) else _safe_next(rb, t_last, e, head & ~ended)
    obs = {k: torch.cat([v, nxt[k][:, None]], 1) for k, v in as_dict(c["obs"]).items()}
    mask = torch.ones(batch, length + 1, device=rb.device)
    mask[:, -1] = (~(head & ~ended)).float()
    return (obs if rb.is_dict else obs["obs"]), c["action"], c["reward"], mask


def _safe_next(rb: ReplayBuffer, t: torch.Tensor, e: torch.Tensor, unknown: torch.Tensor):
    nxt = index_obs(rb.obs, (t + 1) % rb.capacity, e)
    for i in (~unknown).nonzero().flatten().tolist():
        one = rb.next_obs(t[i:i + 1], e[i:i + 1])
        for k in nxt:
            nxt[k][i] = one[k][0]
    return nxt


# ====================================================================== open-loop prediction evaluation
@torch.no_grad()
def open_loop_eval(model: RSSM | EnsembleDynamics, cfg: PlaNetConfig, n_episodes: int | None = None,
                   context: int | None = None, horizons: tuple[int, ...] = (1, 2, 5, 10),
                   seed: int | None = None) -> dict[str, Any]:
    """Open-loop prediction error on held-out episodes (fresh ropes, uniform random moves, never in the buffer).

    Filter the posterior over ``context`` moves (context + 1 observations), then roll the prior mean forward under
    the next K = max(horizons) executed moves and decode. Returns, for each k in horizons, ``pred_err_k`` (mean node
    distance [m] between the decoded and the true rope after k open-loop moves) and ``base_err_k`` (the "nothing
    moves" baseline: the last observed rope), for points and distance observations; for images the same keys hold
    the mean squared pixel error (model units, [-0.5, 0.5]) of the decoded image vs the last observed image.
    Ropes whose episode ends before the last move are left out. Also returns the trajectories for pictures.
    The ensemble needs no filter: it predicts from the rope observed after ``context`` moves.
    """
    n = n_episodes or cfg.openloop_episodes
    context = cfg.openloop_context if context is None else context
    k_max = max(horizons)
    max_steps = max(context + k_max + 1, cfg.max_steps or 0)
    env = make_env(dataclasses.replace(cfg, max_steps=max_steps, env_device=cfg.device), n)
    obs = env.reset(seed=cfg.openloop_seed if seed is None else seed)
    g = torch.Generator().manual_seed(cfg.openloop_seed if seed is None else seed)
    dev = cfg.device
    obs_seq, pos_seq, acts = [obs], [env.core.pos.clone()], []
    alive = torch.ones(n, dtype=torch.bool)
    for _ in range(context + k_max):
        a = torch.rand(n, env.core.action_dim, generator=g).to(dev)
        obs, _, term, trunc, _ = env.core.step(a, mask=alive)
        alive &= ~(term | trunc).cpu()
        obs_seq.append(obs)
        pos_seq.append(env.core.pos.clone())
        acts.append(a)
    true = torch.stack(pos_seq[context + 1:], 1).float()                              # (n, K, N, 2)
    if isinstance(model, EnsembleDynamics):
        out = k_step_errors(model, pos_seq[context].float(), torch.stack(acts[context:], 1), true, horizons,
                            alive.to(true.device))
        out.update({"n": int(alive.sum()), "context": context, "true": true.cpu(), "alive": alive,
                    "target": env.core.target.float().cpu()})
        out["pred"] = out["pred"].cpu()
        return out
    state = None
    for t in range(context + 1):
        state, _ = model.obs_step(state, None if t == 0 else acts[t - 1], model.embed(obs_seq[t]), sample=False)
    traj = model.imagine(state, torch.stack(acts[context:], 1), sample=False)
    feat = torch.stack([RSSM.feature(s) for s in traj], 1)                            # (n, K, F)
    target = env.core.target.float()
    out: dict[str, Any] = {"n": int(alive.sum()), "context": context}
    a_ = alive.to(true.device)
    if cfg.obs in ("points", "distance"):
        pred = decoded_positions(model, feat, cfg.obs, target[:, None])
        last = pos_seq[context].float()[:, None].expand_as(true)
        for k in horizons:
            out[f"pred_err_{k}"] = float((pred[:, k - 1] - true[:, k - 1]).norm(dim=-1).mean(-1)[a_].mean())
            out[f"base_err_{k}"] = float((last[:, k - 1] - true[:, k - 1]).norm(dim=-1).mean(-1)[a_].mean())
        out["pred"], out["true"] = pred.cpu(), true.cpu()
    else:
        dec = model.decode(feat)
        for k in horizons:
            tgt = model.obs_target(as_dict(obs_seq[context + k]))
            lst = model.obs_target(as_dict(obs_seq[context]))
            pe = sum(((dec[key][:, k - 1] - tgt[key]) ** 2).flatten(1).mean(1) for key in dec)
            be = sum(((lst[key] - tgt[key]) ** 2).flatten(1).mean(1) for key in dec)
            out[f"pred_err_{k}"], out[f"base_err_{k}"] = float(pe[a_].mean()), float(be[a_].mean())
        key = model.image_keys[0]
        out["pred"] = (dec[key] + 0.5).clamp(0, 1).cpu()
        out["true"] = torch.stack([as_dict(o)[key] for o in obs_seq[context + 1:]], 1).float().cpu() / 255.0
    out["alive"], out["target"] = alive, target.cpu()
    return out


def plot_open_loop(res: dict[str, Any], path: Path | str, obs_type: str, ropes: int = 4,
                   steps: tuple[int, ...] = (1, 2, 5, 10)) -> None:
    """Real vs open-loop predicted rope shapes (or images) after k moves, one row per held-out rope."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no open-loop picture", file=sys.stderr)
        return
    idx = res["alive"].nonzero().flatten().tolist()[:ropes] or [0]
    K = res["pred"].shape[1]
    steps = tuple(s for s in steps if s <= K) or (K,)
    images = obs_type not in ("points", "distance")
    cols = len(steps) * (2 if images else 1)
    fig, axes = plt.subplots(len(idx), cols, figsize=(2.6 * cols, 2.6 * len(idx)), squeeze=False)
    for r, i in enumerate(idx):
        for c, k in enumerate(steps):
            if images:
                ax1, ax2 = axes[r][2 * c], axes[r][2 * c + 1]
                ax1.imshow(res["true"][i, k - 1].numpy())
                ax2.imshow(res["pred"][i, k - 1].numpy())
                ax1.set_title(f"real, +{k}", fontsize=8)
                ax2.set_title(f"predicted, +{k}", fontsize=8)
                for ax in (ax1, ax2):
                    ax.axis("off")
            else:
                ax = axes[r][c]
                t, p = res["true"][i, k - 1].numpy(), res["pred"][i, k - 1].numpy()
                ax.plot(t[:, 0], t[:, 1], "r.-", label="real")
                ax.plot(p[:, 0], p[:, 1], "b.--", label="predicted")
                err = float(np.linalg.norm(t - p, axis=-1).mean()) * 100
                ax.set_title(f"+{k} moves: {err:.1f} cm", fontsize=8)
                ax.set_aspect("equal")
                ax.tick_params(labelsize=6)
                if r == 0 and c == 0:
                    ax.legend(fontsize=6)
    fig.suptitle(f"open-loop prediction after {res['context']} observed moves")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def openloop_row(res: dict[str, Any]) -> dict[str, float]:
    return {k: v for k, v in res.items() if k.startswith(("pred_err", "base_err")) or k == "n"}


# ====================================================================== training loop
def train(cfg: PlaNetConfig, out: Path | str, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    check_planet_config(cfg)
    with torch_threads(cfg.threads):
        return _train(cfg, out, resume, progress)


def _train(cfg: PlaNetConfig, out: Path | str, resume: bool, progress: bool) -> dict[str, Any]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(cfg.device)
    seed_everything(cfg.seed)
    env = make_env(cfg, cfg.num_envs)
    eval_env = make_env(cfg, min(cfg.eval_episodes, 32))
    heldout = heldout_envs(cfg)
    obs = env.reset(seed=cfg.seed)
    action_dim = env.core.action_dim
    model = build_model(cfg, obs, action_dim)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, eps=cfg.adam_eps)
    rows = max(cfg.chunk_length + 2, cfg.buffer_size // cfg.num_envs)
    warn_if_large_buffer(rows, cfg.num_envs, obs)
    rb = ReplayBuffer(rows, cfg.num_envs, obs, action_dim, device)
    stats = EpisodeStats()
    seed_steps = cfg.seed_episodes * env.core.max_steps
    step, n_updates, last_eval, last_ckpt, last_train, wall_before = 0, 0, 0, 0, 0, 0.0
    last_success: float | None = None
    if resume:
        ck = load_checkpoint(out / CHECKPOINT)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        rb.load_state_dict(ck["buffer"])
        env.load_state_dict(ck["env"])
        obs = env.observe()
        stats.buf.extend(ck["episode_stats"])
        step, n_updates, last_eval, last_ckpt = ck["step"], ck["n_updates"], ck["last_eval"], ck["last_ckpt"]
        last_train, last_success, wall_before = ck["last_train"], ck["last_success"], ck["wall_s"]
        set_rng_state(ck["rng"])
    logger = Logger(out, resume_step=step if resume else None)
    actor = make_planner(model, cfg, env.core, cfg.seed)
    eval_planner = make_planner(model, cfg, eval_env.core, cfg.eval_seed)
    if resume:
        actor.load_state_dict(ck["actor"])
        eval_planner.load_state_dict(ck["eval_planner"])

    def checkpoint() -> None:
        save_checkpoint(out / CHECKPOINT, {
            "algo": "planet", "config": dataclasses.asdict(cfg), "model": model.state_dict(), "opt": opt.state_dict(),
            "buffer": rb.state_dict(), "env": env.state_dict(), "episode_stats": list(stats.buf), "step": step,
            "n_updates": n_updates, "last_eval": last_eval, "last_ckpt": last_ckpt, "last_train": last_train,
            "last_success": last_success, "actor": actor.state_dict(), "eval_planner": eval_planner.state_dict(),
            "wall_s": wall_before + time.perf_counter() - t0, "rng": rng_state()})

    def evaluate_all() -> dict[str, Any]:
        model.eval()
        ol = open_loop_eval(model, cfg)
        logger.log("openloop", step, openloop_row(ol))
        plot_open_loop(ol, out / "openloop.png", cfg.obs)
        r = evaluate(eval_planner, eval_env, cfg.eval_episodes, seed=cfg.eval_seed)
        model.train()
        return r

    t0 = time.perf_counter()
    res = None
    chunks = cfg.batch_size * (cfg.members if cfg.model == "ensemble" else 1)   # the ensemble: a minibatch per member
    bar = tqdm(total=cfg.total_steps, initial=min(step, cfg.total_steps), desc="planet", disable=not progress,
               dynamic_ncols=True, file=sys.stderr)
    while step < cfg.total_steps:
        # ---- act: random seed episodes, then the latent planner with exploration noise
        with torch.no_grad():
            if step < seed_steps:
                action = torch.rand(cfg.num_envs, action_dim, device=device)
                if isinstance(actor, LatentPlanner):
                    actor.state = None                  # the planner re-filters from the next episode start
            else:
                action = actor(obs, deterministic=False)
        next_obs, reward, term, trunc, info, final_obs = env.step(action)
        rb.add(obs, action, reward, term, trunc, final_obs=final_obs)
        done = (term | trunc).cpu()
        if bool(done.any()):
            stats.add(info, done)
        obs = next_obs
        step += cfg.num_envs
        bar.update(cfg.num_envs)

        # ---- learn
        if step >= seed_steps and step - last_train >= cfg.train_every and len(rb.chunk_starts(cfg.chunk_length)):
            last_train = step
            for _ in range(cfg.updates_per_train):
                o, a, r, m = sample_sequences(rb, chunks, cfg.chunk_length)
                L = model.loss(o, a, r, m)
                opt.zero_grad()
                L["loss"].backward()
                gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
                opt.step()
                n_updates += 1
                if n_updates % cfg.log_every == 0:
                    scalars = {k: v.item() for k, v in L.items() if torch.is_tensor(v) and v.numel() == 1}
                    logger.log("train", step, {**scalars, "grad_norm": float(gnorm), "n_updates": n_updates})
                    if stats.buf:
                        logger.log("rollout", step, stats.means())
                    shown = ("err_cm",) if cfg.model == "ensemble" else ("recon", "kl")
                    bar.set_postfix(fmt_postfix(last_success, **{k: L[k].item() for k in shown}))

        # ---- evaluate, checkpoint
        if step - last_eval >= cfg.eval_every or step >= cfg.total_steps:
            last_eval = step
            res = evaluate_all()
            last_success = res["success_rate"]
            logger.log("eval", step, eval_row(res))
            bar.set_postfix(fmt_postfix(last_success))
        if step - last_ckpt >= cfg.checkpoint_every or step >= cfg.total_steps:
            last_ckpt = step
            checkpoint()
    bar.close()
    if res is None:
        res = evaluate_all()
    logger.close()
    extra = {"model": cfg.model, "n_updates": n_updates}
    if getattr(actor, "planned", 0):          # the ensemble's planner times itself (training collection, all ropes)
        extra.update(plan_ms_per_step=1000 * actor.plan_s / actor.planned,
                     plan_env_steps_per_s=actor.planned / max(actor.plan_s, 1e-9))
    wall = wall_before + time.perf_counter() - t0
    model.eval()
    held = evaluate_heldout(None, heldout, cfg, policy_for=lambda e: make_planner(model, cfg, e.core, cfg.eval_seed))
    return write_results(out, "planet", cfg, res, step, wall, heldout=held, extra=extra)


def main(argv: list[str] | None = None) -> int:
    return run_cli(PlaNetConfig, "planet", __doc__, train, argv)


if __name__ == "__main__":
    sys.exit(main())
