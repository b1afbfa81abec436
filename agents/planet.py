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
from pathlib import Path
from typing import Any

import torch

from agents.buffer import ReplayBuffer, as_dict, index_obs
from agents.checkpoints import replay_rows
from agents.cli import run_cli
from agents.config import RunOptions, TaskOptions, check_layer_sizes, check_ranges, check_types, part
from agents.logs import fmt_postfix
from agents.run import Run, learner
from agents.dynamics import EnsembleDynamics, EpisodeTracker, ModelPlanner, check_settings
from agents.openloop import decoded_positions, open_loop_eval, openloop_row, plot_open_loop
from agents.rssm import RSSM
from diffdlo.params import CableParams
from diffdlo.rewards import shape_error
from diffdlo.task import COORDINATE_OBS, POINT_OBS
from planners.cem import CEM, optimize_together


# ====================================================================== config (defaults: params/planet.yaml)
@dataclasses.dataclass
class PlaNetConfig:
    task: TaskOptions = part(TaskOptions)
    run: RunOptions = part(RunOptions, total_steps=100_000, eval_every=10_000, checkpoint_every=10_000,
                           log_every=25)          # log_every: model updates
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

    def check(self) -> None:
        self.task.check()
        self.run.check()
        if self.model not in ("ensemble", "rssm"):
            raise ValueError(f"unknown model {self.model!r}: use 'ensemble' or 'rssm'")
        if self.model == "ensemble":
            if self.task.obs not in POINT_OBS or self.task.action != "node":
                raise ValueError(f"model 'ensemble' predicts node positions from node actions: it needs obs 'points' or 'perceived' "
                                 f"and action 'node', got obs {self.task.obs!r} and action {self.task.action!r} "
                                 "(use --preset rssm)")
            check_settings(self.members, self.model_hidden, self.augment, self.frame, self.propagation)
        if self.plan_objective not in ("reward", "shape"):
            raise ValueError(f"plan_objective must be 'reward' or 'shape', got {self.plan_objective!r}")
        if self.plan_objective == "shape" and self.task.obs not in COORDINATE_OBS:
            raise ValueError("plan_objective 'shape' needs points or distance observations, or perceived points (it "
                             "decodes node positions)")
        check_types(self)
        for key in ("model_hidden", "cnn_channels", "deconv_channels"):
            check_layer_sizes(key, getattr(self, key))
        at_least_one = ("members", "deter", "stoch", "hidden", "embed", "image_embed", "batch_size", "chunk_length",
                        "buffer_size", "train_every", "updates_per_train", "horizon", "candidates", "elites",
                        "iterations", "openloop_episodes")
        check_ranges(self, {**{k: "[1, inf)" for k in at_least_one}, "running_weight": "[0, inf)",
                            "min_std": "(0, inf)", "obs_std": "(0, inf)", "free_nats": "[0, inf)", "lr": "(0, inf)",
                            "adam_eps": "(0, inf)", "grad_clip": "(0, inf)", "seed_episodes": "[0, inf)",
                            "explore_noise": "[0, inf)", "openloop_context": "[0, inf)"})
        if self.elites > self.candidates:
            raise ValueError(f"elites must be at most candidates ({self.candidates}), got {self.elites}")


def build_model(cfg: PlaNetConfig, obs: Any, action_dim: int, p: CableParams) -> RSSM | EnsembleDynamics:
    if cfg.model == "ensemble":
        return EnsembleDynamics(p, cfg.members, cfg.model_hidden, cfg.augment, cfg.frame).to(cfg.run.device)
    return RSSM(obs, action_dim, action_type=cfg.task.action, n_nodes=p.n_nodes, scale=1.0 / p.length,
                deter=cfg.deter, stoch=cfg.stoch, hidden=cfg.hidden, embed=cfg.embed,
                cnn_channels=cfg.cnn_channels, image_embed=cfg.image_embed, deconv_channels=cfg.deconv_channels,
                min_std=cfg.min_std, obs_std=cfg.obs_std, free_nats=cfg.free_nats).to(cfg.run.device)


# ====================================================================== planning in latent space
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
    (warm-started) CEM. ``agents.dynamics.EpisodeTracker`` tells it which ropes started a new episode (so it works
    inside ``agents.evaluation.evaluate`` too) and which did not move (finished in an evaluation wave: they keep
    their last action without planning)."""

    def __init__(self, model: RSSM, cfg: PlaNetConfig, core, seed: int):
        self.model, self.cfg, self.core = model, cfg, core
        self.b, self.A = core.num_envs, core.action_dim
        discrete = {0: core.params.n_nodes} if cfg.task.action == "node" else None
        self.cems = [CEM(self.A, cfg.horizon, cfg.candidates, cfg.elites, cfg.iterations, discrete=discrete,
                         generator=torch.Generator().manual_seed(seed + i), dtype=torch.float32)
                     for i in range(self.b)]
        self.state: dict[str, torch.Tensor] | None = None
        self.prev_action = torch.zeros(self.b, self.A, device=cfg.run.device)
        self.tracker = EpisodeTracker(core)

    def state_dict(self) -> dict[str, Any]:
        """Belief, last action and every rope's CEM (distribution, warm start, generator): a resumed run plans
        exactly as the uninterrupted one."""
        return {"state": None if self.state is None else {k: v.clone() for k, v in self.state.items()},
                "prev_action": self.prev_action.clone(), "last_steps": self.tracker.last_steps.clone(),
                "cems": [c.state_dict() for c in self.cems]}

    def load_state_dict(self, s: dict[str, Any]) -> None:
        if len(s["cems"]) != self.b:
            raise ValueError(f"planner state for {len(s['cems'])} ropes, this planner has {self.b}")
        dev = self.cfg.run.device
        self.state = None if s["state"] is None else {k: v.to(dev) for k, v in s["state"].items()}
        self.prev_action = s["prev_action"].to(dev)
        self.tracker.last_steps = s["last_steps"].clone()
        for c, cs in zip(self.cems, s["cems"]):
            c.load_state_dict(cs)

    @torch.no_grad()
    def __call__(self, obs: Any, deterministic: bool = True) -> torch.Tensor:
        m, dev = self.model, self.cfg.run.device
        new, moved = self.tracker.update()
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
        target = None
        if self.cfg.plan_objective == "shape":
            target = self.core.get_state(generators=False).target.to(dev).float()
        rows = moved.nonzero().flatten().tolist()
        if rows:                                   # every moving rope's CEM in lockstep, one model call per iteration
            idx = torch.tensor(rows, device=dev)
            obj = LatentObjective(m, {k: v[idx] for k, v in post.items()}, self.cfg.plan_objective,
                                  self.cfg.task.obs, None if target is None else target[idx])
            bests = optimize_together([self.cems[i] for i in rows], obj)
            for i, (best, _) in zip(rows, bests):
                self.cems[i].shift()
                action[i] = best[0].to(dev)
        if not deterministic and self.cfg.explore_noise > 0:
            noise = self.cfg.explore_noise * torch.randn(self.b, self.A, device=dev)
            action = torch.where(moved.to(dev)[:, None], (action + noise).clamp(0.0, 1.0), action)
        self.prev_action = action
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


# ====================================================================== training loop
@learner
def train(cfg: PlaNetConfig, out: Path | str, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    run = Run("planet", cfg, out, resume, progress)
    env, device, obs, num_envs = run.env, run.device, run.obs, cfg.run.num_envs
    action_dim = env.core.action_dim
    model = build_model(cfg, obs, action_dim, run.params)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, eps=cfg.adam_eps)
    rows = replay_rows(cfg.buffer_size, cfg.run.total_steps, num_envs, obs, least=cfg.chunk_length + 2)
    rb = ReplayBuffer(rows, num_envs, obs, action_dim, device)
    actor = make_planner(model, cfg, env.core, cfg.run.seed)
    eval_planner = make_planner(model, cfg, run.eval_env.core, cfg.run.eval_seed)
    parts = dict(model=model, opt=opt, buffer=rb, actor=actor, eval_planner=eval_planner)
    ck = run.start(**parts)
    n_updates, last_train = (ck["n_updates"], ck["last_train"]) if ck else (0, 0)
    obs, logger, bar = run.obs, run.logger, run.bar
    seed_steps = cfg.seed_episodes * env.core.max_steps
    if cfg.run.total_steps <= seed_steps:
        print(f"warning: total_steps {cfg.run.total_steps} ends within the seed episodes (seed_episodes x max_steps "
              f"= {seed_steps} random steps): the model is never trained and plans untrained; raise --total-steps "
              "or lower seed_episodes", file=sys.stderr)

    def evaluate_all() -> dict[str, Any]:
        model.eval()
        ol = open_loop_eval(model, cfg, params=run.params)
        logger.log("openloop", run.step, openloop_row(ol))
        plot_open_loop(ol, run.out / "openloop.png", cfg.task.obs)
        r = run.evaluate(eval_planner)
        model.train()
        return r

    chunks = cfg.batch_size * (cfg.members if cfg.model == "ensemble" else 1)   # the ensemble: a minibatch per member
    # a phase's updates still to do: a stop between two of them (100 model updates from pictures take minutes) keeps
    # the rest in the checkpoint, and --resume does them first, as the uninterrupted run did
    pending = ck.get("pending_updates", 0) if ck else 0

    def parts_now() -> dict[str, Any]:
        return {**parts, "n_updates": n_updates, "last_train": last_train, "pending_updates": pending}

    while True:
        # ---- learn: the phase started by the last step
        while pending:
            run.stop_if_requested(parts_now)
            o, a, r, m = sample_sequences(rb, chunks, cfg.chunk_length)
            L = model.loss(o, a, r, m)
            opt.zero_grad()
            L["loss"].backward()
            gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            opt.step()
            n_updates += 1
            pending -= 1
            if n_updates % cfg.run.log_every == 0:
                scalars = {k: v.item() for k, v in L.items() if torch.is_tensor(v) and v.numel() == 1}
                logger.log("train", run.step, {**scalars, "grad_norm": float(gnorm), "n_updates": n_updates})
                run.log_rollout()
                shown = ("err_cm",) if cfg.model == "ensemble" else ("recon", "kl")
                bar.set_postfix(fmt_postfix(run.last_success, **{k: L[k].item() for k in shown}))

        # ---- evaluate (it plans every move of every episode: checkpointed first, so that a stop loses none of the
        # training before it), checkpoint
        run.evaluate_if_due(evaluate_all, save_first=parts_now)
        run.checkpoint_if_due(parts_now)
        if run.step >= cfg.run.total_steps:
            break

        # ---- act: random seed episodes, then the planner with exploration noise
        with torch.no_grad():
            if run.step < seed_steps:
                action = torch.rand(num_envs, action_dim, device=device)
                if isinstance(actor, LatentPlanner):
                    actor.state = None                  # the planner re-filters from the next episode start
            else:
                action = actor(obs, deterministic=False)
        next_obs, reward, term, trunc, info, final_obs = env.step(action)
        rb.add(obs, action, reward, term, trunc, final_obs=final_obs)
        run.count(info, term, trunc)
        obs = next_obs
        if (run.step >= seed_steps and run.step - last_train >= cfg.train_every
                and len(rb.chunk_starts(cfg.chunk_length))):
            last_train, pending = run.step, cfg.updates_per_train

    extra = {"model": cfg.model, "n_updates": n_updates}
    if getattr(actor, "planned", 0):          # the ensemble's planner times itself (training collection, all ropes)
        extra.update(plan_ms_per_step=1000 * actor.plan_s / actor.planned,
                     plan_env_steps_per_s=actor.planned / max(actor.plan_s, 1e-9))
    return run.finish(None, extra=extra, evaluate_fn=lambda: run.evaluate(eval_planner), before_heldout=model.eval,
                      policy_for=lambda e: make_planner(model, cfg, e.core, cfg.run.eval_seed))


def main(argv: list[str] | None = None) -> int:
    return run_cli(PlaNetConfig, "planet", __doc__, train, argv)


if __name__ == "__main__":
    sys.exit(main())
