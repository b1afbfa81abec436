"""PlaNet (Hafner et al. 2019; thesis Chapter 3): learn a world model from replayed chunks and act by CEM planning
through it. CleanRL-style: config -> the chosen world model and its planner -> loop.

    python -m agents.planet --out runs/planet                     # tuned: the ensemble on points, 10k env steps
    python -m agents.planet --preset latent --out runs/planet-latent   # the latent world model on points
    python -m agents.planet --preset rssm --obs image --action pixel --out runs/planet-rssm-image

Three world models (``model``):
- "ensemble" (default, params/planet.yaml; agents/models/ensemble.py): PETS-style MLPs predicting one move's change of the
  rope from the rope, the grasped node and the drag; planned through by ``agents.models.ensemble.ModelPlanner`` with the
  planners' cost (shape error of the predicted rope against the observed target). Points and node actions only.
- "latent" (params/planet-latent.yaml; agents/models/latent.py): an encoder to latent keypoints, deterministic
  latent dynamics (each move in its own grasp frame) and a decoder of the rope's change (TD-MPC-style latent,
  PlaNet's decoder); planned in latent space by the same ``ModelPlanner`` on the decoded rope's shape error. Points
  and node actions (from pictures: the points the perception reads, obs "perceived").
- "rssm" (params/planet-rssm.yaml; agents/models/rssm.py): PlaNet's recurrent state-space model, any observation, planned
  in latent space by ``agents.models.rssm.LatentPlanner`` (``LatentObjective``: minus the predicted rewards, or the decoded
  rope's shape error).

Data: the ONE shared replay storage (agents/common/buffer.py). ``ReplayBuffer.sample_sequences`` returns L contiguous rows
of one rope that never cross an episode end (an end only at the last row) nor the write head, plus the observation
after the last row (the stored final observation where the episode ended there, so the success reward is learned),
masked out only when that row is the newest one and its next observation is not written yet. The ensemble draws
``batch_size`` chunks per member.

Loop: ``seed_episodes`` x max_steps env transitions of uniform random actions, then ``updates_per_train`` model
updates every ``train_every`` env transitions, collecting with the planner plus Gaussian exploration noise.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

import torch

from agents.common.buffer import ReplayBuffer
from agents.common.checkpoints import replay_rows
from agents.common.cli import run_cli
from agents.common.config import SECTIONS, RunOptions, TaskOptions, part
from agents.common.logs import fmt_postfix
from agents.common.run import Run, learner
from agents.models.ensemble import EnsembleDynamics, ModelPlanner, check_settings
from agents.models.openloop import open_loop_eval, openloop_row, plot_open_loop
from agents.models.latent import LatentWorldModel, check_latent_settings
from agents.models.rssm import RSSM, LatentPlanner
from diffdlo.utils.checks import check_fields, option
from diffdlo.planar.params import CableParams
from diffdlo.tasks.task import COORDINATE_OBS, POINT_OBS


MODELS = ("ensemble", "latent", "rssm")
WorldModel = EnsembleDynamics | LatentWorldModel | RSSM


# ====================================================================== config (defaults: params/planet.yaml)
@dataclasses.dataclass
class PlaNetConfig:
    task: TaskOptions = part(TaskOptions)
    run: RunOptions = part(RunOptions, total_steps=100_000, eval_every=10_000, checkpoint_every=10_000,
                           log_every=25)          # log_every: model updates
    # model: "ensemble" (agents/models/ensemble.py, PETS-style), "latent" (agents/models/latent.py), both on points;
    # or "rssm" (agents/models/rssm.py, PlaNet's)
    model: str = option("ensemble", choices=MODELS,
                        help='"ensemble" (points only), "latent" (points only) or "rssm"')
    # the ensemble (agents/models/ensemble.py); augment, frame and propagation are checked by check_settings (and
    # augment and frame, which the latent model shares, by check_latent_settings)
    members: int = option(5, "[1, inf)", help="ensemble: its MLPs")
    model_hidden: list = option(factory=lambda: [200, 200, 200], layers=True, help="ensemble: each MLP's hidden layers")
    augment: list = option(factory=lambda: ["mirror", "reverse"],
                           help="ensemble and latent: the symmetries trained on")
    frame: str = option("grasp", help='ensemble and latent: "grasp" or "centroid", the frame each move (the latent '
                                      'model: each rollout) is predicted in')
    propagation: str = option("members", help='ensemble: "members" or "mean", how the planning cost uses it')
    running_weight: float = option(0.5, "[0, inf)",
                                   help="ensemble's planning cost: weight of the mean intermediate shape error")
    risk: float = option(0.0, "[0, inf)", help="ensemble's planning cost: + risk x the members' std of the cost "
                                               "(pessimism; propagation 'members')")
    # the latent world model (agents/models/latent.py)
    latent_dim: int = option(128, "[1, inf)", help="latent: the latent state's size")
    latent_kind: str = option("vector", help='latent: "vector" (an MLP latent, stepped in the first move\'s frame) or '
                                             '"keypoints" (latent_dim / 2 points, each move in its own grasp frame)')
    latent_hidden: list = option(factory=lambda: [256, 256], layers=True,
                                 help="latent: hidden layers of its encoder, dynamics and decoder")
    residual_decoder: bool = option(True, help="latent: decode the change of the rope (x_0 + D(z_t) - D(z_0))")
    consistency: float = option(1.0, "[0, inf)", help="latent: weight of the latent consistency loss (TD-MPC2)")
    rho: float = option(0.5, "(0, 1]", help="latent: weight of move t of a chunk's loss is rho^t (TD-MPC2)")
    # the RSSM (agents/models/rssm.py)
    deter: int = option(200, "[1, inf)", help="rssm: deterministic state size")
    stoch: int = option(30, "[1, inf)", help="rssm: stochastic state size")
    hidden: int = option(200, "[1, inf)", help="rssm: hidden layer width")
    embed: int = option(200, "[1, inf)", help="rssm: observation embedding size (points, distance)")
    image_embed: int = option(1024, "[1, inf)", help="rssm: observation embedding size (images)")
    cnn_channels: list = option(factory=lambda: [32, 64, 64], layers=True, help="rssm: the image encoder's channels")
    deconv_channels: list = option(factory=lambda: [64, 32, 16], layers=True,
                                   help="rssm: the image decoder's channels")
    min_std: float = option(0.1, "(0, inf)", help="rssm: the stochastic state's smallest std")
    obs_std: float = option(0.02, "(0, inf)", help="rssm: the std of float observations' likelihood")
    free_nats: float = option(3.0, "[0, inf)", help="rssm: the KL term is constant below this")
    # the RSSM's diagnosis options (issue 47; agents/models/rssm.py's docstring): the defaults are PlaNet's model
    rssm_frame: str = option("world", choices=("world", "centroid"),
                             help='rssm: "world" or "centroid" (rope and target relative to the rope\'s centroid, '
                                  'carried beside the latent; points only)')
    rssm_residual: bool = option(False, help="rssm: decode the change of the observation from the previous "
                                             "observed (filter) or decoded (prior rollout) one; float obs only")
    kl_balance: str = option("planet", choices=("planet", "dreamerv3"),
                             help='rssm: "planet" (max(free_nats, KL)) or "dreamerv3" (0.5 dynamics + 0.1 '
                                  'representation KL, each clamped by free_nats)')
    # learning
    lr: float = option(1e-3, "(0, inf)", help="the model's Adam")
    adam_eps: float = option(1e-4, "(0, inf)", help="the model's Adam eps")
    grad_clip: float = option(1000.0, "(0, inf)", help="gradient norm clip")
    batch_size: int = option(50, "[1, inf)", help="chunks per update (per member for the ensemble)")
    chunk_length: int = option(16, "[1, inf)", help="rows per chunk")
    buffer_size: int = option(1_000_000, "[1, inf)", help="transitions kept")
    seed_episodes: int = option(40, "[0, inf)", help="episodes of uniform random actions before training")
    train_every: int = option(250, "[1, inf)", help="env transitions between training phases")
    updates_per_train: int = option(100, "[1, inf)", help="model updates per training phase")
    # planning
    horizon: int = option(3, "[1, inf)", help="CEM: moves planned")
    candidates: int = option(300, "[1, inf)", help="CEM: sequences per iteration")
    elites: int = option(30, "[1, inf)", help="CEM: sequences refit to (at most candidates)")
    iterations: int = option(5, "[1, inf)", help="CEM: iterations per move")
    plan_objective: str = option("reward", choices=("reward", "shape"), says="'reward' or 'shape'",
                                 help='"reward" (predicted rewards, PlaNet) or "shape" (decoded rope\'s shape error)')
    explore_noise: float = option(0.15, "[0, inf)", help="std of the Gaussian noise added to planned actions")
    # open-loop prediction evaluation
    openloop_episodes: int = option(32, "[1, inf)", help="episodes of the open-loop prediction evaluation")
    openloop_context: int = option(5, "[0, inf)", help="its observed moves before predicting")
    openloop_seed: int = option(20_000, help="its first episode's seed")

    def check(self) -> None:
        self.task.check()
        self.run.check()
        if self.model in ("ensemble", "latent"):
            if self.task.obs not in POINT_OBS or self.task.action not in ("node", "node_pin"):
                raise ValueError(f"model {self.model!r} predicts node positions from node actions: it needs obs "
                                 f"'points' or 'perceived' and action 'node' or 'node_pin', got obs "
                                 f"{self.task.obs!r} and action {self.task.action!r} (use --preset rssm)")
        if self.model == "ensemble":
            check_settings(self.members, self.model_hidden, self.augment, self.frame, self.propagation, self.risk)
        elif self.risk:
            raise ValueError(f"risk {self.risk} weighs the ensemble's members' spread of the cost: model "
                             f"{self.model!r} has no members")
        if self.model == "latent":
            check_latent_settings(self.latent_dim, self.latent_hidden, self.augment, self.frame, self.latent_kind)
            if self.plan_objective != "shape":
                raise ValueError(f"model 'latent' plans on the decoded rope's shape error: plan_objective must be "
                                 f"'shape', got {self.plan_objective!r}")
        check_fields(self, skip=SECTIONS)   # after check_settings, whose message names the ensemble's layer sizes
        if self.plan_objective == "shape" and self.task.obs not in COORDINATE_OBS:
            raise ValueError("plan_objective 'shape' needs points or distance observations, or perceived points (it "
                             "decodes node positions)")
        if self.rssm_frame == "centroid" and self.task.obs not in POINT_OBS:
            raise ValueError(f"rssm_frame 'centroid' needs obs 'points' or 'perceived', got {self.task.obs!r}")
        if self.rssm_residual and self.task.obs not in COORDINATE_OBS:
            raise ValueError(f"rssm_residual needs float observations (points, distance, perceived), got "
                             f"{self.task.obs!r}")
        if self.elites > self.candidates:
            raise ValueError(f"elites must be at most candidates ({self.candidates}), got {self.elites}")


# ====================================================================== the world model and its planner
def build_model(cfg: PlaNetConfig, obs: Any, action_dim: int, p: CableParams) -> WorldModel:
    # among pegs: the observation's peg slots; node_pin actions: the held node
    max_pegs = obs["pegs"].shape[-2] if isinstance(obs, dict) and "pegs" in obs else 0
    pin = cfg.task.action == "node_pin"
    if cfg.model == "ensemble":
        return EnsembleDynamics(p, cfg.members, cfg.model_hidden, cfg.augment, cfg.frame, max_pegs,
                                pin=pin).to(cfg.run.device)
    if cfg.model == "latent":
        return LatentWorldModel(p, cfg.latent_dim, cfg.latent_hidden, cfg.augment, cfg.frame, cfg.residual_decoder,
                                cfg.consistency, cfg.rho, cfg.latent_kind, max_pegs, pin).to(cfg.run.device)
    return RSSM(obs, action_dim, action_type=cfg.task.action, n_nodes=p.n_nodes, scale=1.0 / p.length,
                deter=cfg.deter, stoch=cfg.stoch, hidden=cfg.hidden, embed=cfg.embed,
                cnn_channels=cfg.cnn_channels, image_embed=cfg.image_embed, deconv_channels=cfg.deconv_channels,
                min_std=cfg.min_std, obs_std=cfg.obs_std, free_nats=cfg.free_nats, frame=cfg.rssm_frame,
                residual=cfg.rssm_residual, kl_balance=cfg.kl_balance).to(cfg.run.device)


def make_planner(model: WorldModel, cfg: PlaNetConfig, core, seed: int):
    return LatentPlanner(model, cfg, core, seed) if cfg.model == "rssm" else ModelPlanner(model, cfg, core, seed)


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
            seq = rb.sample_sequences(chunks, cfg.chunk_length)
            L = model.loss(seq["obs"], seq["action"], seq["reward"], seq["mask"])
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
                shown = ("recon", "kl") if cfg.model == "rssm" else ("err_cm",)
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
