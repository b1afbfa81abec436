"""Analytic policy gradients (APG; SHAC-style with ``critic: true``, Xu et al. 2022): a reactive policy trained by
backpropagating the task's reward through H chained ``Simulator.move`` calls (the fused kernel's adjoint), in one
file: config -> networks -> loop.

    python -m agents.apg --target random --total-steps 5000 --out runs/apg

Each update rolls the training env's ropes H moves on with the current policy, keeping the autograd graph:
observation (built from the rope's positions, differentiable, as ``diffdlo.tasks.task.observe`` builds it) -> policy ->
drag -> ``Simulator.move`` (float32, the env's dtype: the env replays the same move without a graph for its
bookkeeping and gives the identical rope) -> the env's reward (``diffdlo.tasks.rewards.reward``, e.g. shape_gain: the cm
of shape error removed). The pathwise objective J = sum_t gamma^t r_t (restarted at each episode end; a reset rope
carries no gradient back) is maximized by Adam on the actor. With ``critic: true`` a learned V(s) adds gamma^H V(s_H)
(and V at a truncation) differentiably: the value beyond the horizon, trained on TD(lambda) targets of the rollouts.

The node is discrete; ``Simulator.move`` takes an integer node, so no gradient reaches the node choice through the
simulator. ``node`` says how it is chosen and learned:

- ``score``: sampled from the policy's categorical over the N nodes; its logits learn from a score-function term
  -log pi(k_t | s_t) A_t (REINFORCE; A_t: GAE(lambda) on the env's rewards with the critic as baseline, or, without
  a critic, the discounted return within the window minus its batch mean), normalized, plus an entropy bonus. The
  drag of the chosen node gets the pathwise gradient. Evaluation: the argmax node.
- ``greedy``: the node farthest from its place in the centroid-aligned target (``diffdlo.tasks.task.greedy_drags``, the
  greedy planner's choice); only the drag is learned, pathwise. A relaxation by a fixed rule: nothing is learned
  about the node.
- ``gain``: a head G(s, k) predicts the reward of moving node k with the policy's drag; it regresses the reward of
  the node moved (MSE), the node is argmax_k G in evaluation and in training except for a share ``gain_explore`` of
  uniformly random nodes (decaying linearly to 0 over the run). A contextual bandit over the nodes beside the
  pathwise drag; the drag of the chosen node gets the pathwise gradient. Its (s, k, r) samples are kept in the
  shared replay buffer (``gain_replay`` of them; no extra simulation) and each update regresses a minibatch of them.

The actor is SAC tuned's ``HybridActor`` (agents/sac.py: relative features, running normalization, an MLP, per-node
logits and tanh drags), acting with its mean drag: the gradient is exact, so no drag noise is needed to explore, and
the policy trained is the policy evaluated. The preset "tuned" (params/apg.yaml, where each choice's measurement is
written) is node ``gain``, H = 1, no critic, 4 ropes per update and a linearly decaying lr.
Gradient norms (pathwise, score-function, total before clipping; the critic's) are logged in train.csv every update;
clipping happens only with ``max_grad_norm`` > 0, and each update logs whether it clipped. A non-finite gradient
raises FloatingPointError (never zeroed). Env steps count every rope-move simulated in training (B x H per update);
``sim_backward`` counts the rope-moves backpropagated.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn

from agents.models import hybrid
from agents.common.cli import run_cli
from agents.common.config import SECTIONS, InputOptions, RunOptions, TaskOptions, part
from agents.common.buffer import ReplayBuffer
from agents.models.networks import Features, mlp
from agents.common.run import Run, learner
from agents.sac import HybridActor
from diffdlo.utils.checks import check_fields, option
from diffdlo.tasks.rewards import reward as move_reward, shape_error
from diffdlo.tasks.routing import route_errors
from diffdlo.tasks.task import decode_node_action, greedy_drags

NODE_RULES = ("score", "greedy", "gain")
OBJECTIVES = ("reward", "log_error")


# ====================================================================== config (defaults: params/apg.yaml)
@dataclasses.dataclass
class APGConfig:
    task: TaskOptions = part(TaskOptions)
    run: RunOptions = part(RunOptions, total_steps=5000, num_envs=4, eval_every=1000, checkpoint_every=1000,
                           log_every=1)
    inputs: InputOptions = part(InputOptions)
    # checkpoints and evaluations are checked after each update; log_every counts updates
    horizon: int = option(1, "[1, inf)", help="H: moves chained in one differentiable rollout")
    node: str = option("gain", choices=NODE_RULES, help='"gain" | "greedy" | "score" (see the module\'s docstring)')
    gain_explore: float = option(0.5, "[0, 1]", help='node "gain": the share of random nodes in training, decaying '
                                                     "linearly to 0")
    gain_replay: int = option(5000, "[0, inf)",
                              help='node "gain": (s, k, r) samples kept for its regression (0: online only)')
    gain_batch: int = option(256, "[1, inf)", help='node "gain": samples per regression step (one step per update)')
    critic: bool = option(False, help="SHAC: learned V(s) beyond the horizon (and as the node's baseline)")
    objective: str = option("reward", choices=OBJECTIVES,
                            help='"reward": the env\'s reward; "log_error": log e_t - log e_{t+1} per move')
    lr: float = option(1e-3, "(0, inf)", help="actor's Adam")
    anneal_lr: bool = option(True, help="the actor's lr decays linearly to 0 over total_steps (PPO's anneal_lr)")
    critic_lr: float = option(1e-3, "(0, inf)", help="critic's Adam")
    critic_epochs: int = option(4, "[1, inf)",
                                help="full-batch critic steps per update, on the rollout's TD(lambda) targets")
    gamma: float = option(0.97, "[0, 1]", help="discount")
    gae_lambda: float = option(0.95, "[0, 1]", help="the critic's TD(lambda)")
    node_coef: float = option(1.0, "[0, inf)", help='weight of the score-function term (node "score")')
    ent_coef: float = option(0.01, "[0, inf)", help='node entropy bonus (node "score")')
    max_grad_norm: float = option(0.0, "[0, inf)",
                                  help="> 0: clip the actor's gradient norm to it (logged); 0: never clip")
    hidden: list = option(factory=lambda: [256, 256], layers=True, help="the actor's and critic's hidden layers")
    log_std_min: float = option(-5.0, "(-inf, inf)",
                                help="HybridActor's log-std bounds (unused: APG acts with the mean drag)")
    log_std_max: float = option(2.0, "(-inf, inf)")

    def check(self) -> None:
        self.task.check()
        self.run.check()
        self.inputs.check(self.task)
        check_fields(self, skip=SECTIONS)
        if self.task.action != "node":
            raise ValueError(f"apg chooses a node and backpropagates through its drag: it needs action 'node', got "
                             f"{self.task.action!r}")
        if self.task.obs not in ("points", "distance"):
            raise ValueError(f"apg builds its observation from the rope's positions (differentiably): it needs obs "
                             f"'points' or 'distance', got {self.task.obs!r}")
        if not self.log_std_min < self.log_std_max:
            raise ValueError(f"log_std_min must be below log_std_max, got {self.log_std_min} and {self.log_std_max}")


# ====================================================================== networks
def graph_obs(obs_type: str, pos: torch.Tensor, target: torch.Tensor, pegs: torch.Tensor | None = None) -> Any:
    """The observation of ropes ``pos`` (B, N, 2) as ``diffdlo.tasks.task.observe`` gives it, but keeping pos's graph
    (with ``pegs`` (B, K, 3), a route: the pegs too)."""
    if obs_type == "points":
        obs = {"node_poses": pos.float(), "target_poses": target.detach().float()}
        return obs if pegs is None else {**obs, "pegs": pegs.detach().float()}
    return (pos - target.detach()).float()


def greedy_node(obs: Any) -> torch.Tensor:
    """(B,) the node farthest from its place in the centroid-aligned target (on a route, its place on the board:
    ``diffdlo.tasks.task.greedy_drags``)."""
    pos, target = (obs["node_poses"], obs["target_poses"]) if isinstance(obs, dict) else (obs, torch.zeros_like(obs))
    align = not (isinstance(obs, dict) and "pegs" in obs)
    return greedy_drags(pos.detach(), target.detach(), 1.0, align=align)[1].argmax(-1)


class Actor(nn.Module):
    """SAC tuned's ``HybridActor`` and the node rule: ``dist(obs)`` -> (log pi(k|s) (B, N), the mean drags (B, N, 2)
    in (-1, 1)). APG needs no drag noise: its gradient is exact, and without noise the policy trained is the policy
    evaluated."""

    def __init__(self, obs_example: Any, cfg: APGConfig, length: float, n_nodes: int):
        super().__init__()
        self.net, self.rule, self.n = HybridActor(obs_example, cfg, length, n_nodes), cfg.node, n_nodes
        self.gain = mlp(self.net.feat.out_dim, cfg.hidden, n_nodes) if cfg.node == "gain" else None

    def gains(self, obs: Any) -> torch.Tensor:
        """Node "gain": G(s, k) (B, N), the predicted reward of moving each node with the policy's drag."""
        return self.gain(self.net.feat(obs))

    def dist(self, obs: Any) -> tuple[torch.Tensor, torch.Tensor]:
        log_pk, drags, _ = self.net(obs, True)
        return log_pk, drags

    def choose(self, obs: Any, log_pk: torch.Tensor, deterministic: bool, explore: float = 0.0) -> torch.Tensor:
        if self.rule == "greedy":
            return greedy_node(obs)
        if self.rule == "gain":
            with torch.no_grad():
                best = self.gains(obs).argmax(-1)
            if deterministic or explore <= 0:
                return best
            wild = torch.rand(len(best), device=best.device) < explore
            return torch.where(wild, torch.randint_like(best, self.n), best)
        return log_pk.argmax(-1) if deterministic else torch.distributions.Categorical(logits=log_pk).sample()

    def env_action(self, obs: Any, deterministic: bool = True) -> torch.Tensor:
        """The env's node action (B, 3): the chosen node and its drag (the mean drag when deterministic)."""
        log_pk, drags = self.dist(obs)
        node = self.choose(obs, log_pk, deterministic)
        return hybrid.to_env_action(node, drags[torch.arange(len(node), device=node.device), node], self.n)


class Critic(nn.Module):
    """V(s): the actor's input features (their normalizer follows the actor's) and an MLP."""

    def __init__(self, obs_example: Any, cfg: APGConfig, length: float):
        super().__init__()
        self.feat = Features(obs_example, cfg.inputs, length)
        self.v = mlp(self.feat.out_dim, cfg.hidden, 1)

    def forward(self, obs: Any) -> torch.Tensor:
        return self.v(self.feat(obs)).squeeze(-1)


def move_graph(sim, p, pos: torch.Tensor, target: torch.Tensor, node: torch.Tensor, drag: torch.Tensor,
               reward_kind: str, objective: str = "reward", pegs: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One differentiable move of ropes ``pos`` (B, N, 2): node ids (B,) and drags (B, 2) in [-1, 1] become the env's
    node action and are decoded by the env's own arithmetic (so the rope is the one the env's step gives), then
    ``sim.move`` (among ``pegs`` (B, K, 3), the env's padded rows, on a route). Returns (the env action (B, 3), the
    new ropes, the move's objective (B,): the env's reward, or log e_t - log e_{t+1} with e the env's error: on a
    route the error on the board), all with the graph from drag and pos."""
    action = hybrid.to_env_action(node, drag, p.n_nodes)
    k, delta = decode_node_action(action.to(sim.device, sim.dtype), p)
    new = sim.move(pos, k, delta, None if pegs is None else pegs.to(sim.device, sim.dtype))
    error = shape_error if pegs is None else (lambda x, y: route_errors(x, y).mean(-1))
    r = (move_reward(reward_kind, pos, new, target, pegs) if objective == "reward"
         else error(pos, target).log() - error(new, target).log())
    return action, new, r


def actor_losses(J: torch.Tensor, log_prob: torch.Tensor, entropy: torch.Tensor, adv: torch.Tensor,
                 cfg: APGConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The pathwise loss -mean J / H and the node's score-function loss (advantages (H, B) normalized, raw in)."""
    adv = (adv - adv.mean()) / (adv.std() + 1e-8) if adv.numel() > 1 else adv
    node_loss = -(log_prob * adv.detach()).mean() * cfg.node_coef - cfg.ent_coef * entropy.mean()
    return -J.mean() / len(log_prob), node_loss


def rec_obs(o: Any) -> Any:
    """An observation without its graph, to keep."""
    return o.detach() if torch.is_tensor(o) else {k: v.detach() for k, v in o.items()}


def grad_norm(params: list[torch.Tensor]) -> float:
    grads = [p.grad for p in params if p.grad is not None]
    return float(torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))) if grads else 0.0


def advantages(rewards: torch.Tensor, values: torch.Tensor, next_values: torch.Tensor, done: torch.Tensor,
               gamma: float, lam: float) -> torch.Tensor:
    """GAE(lambda) over a window (H, B): ``next_values`` V(s_{t+1}) already 0 after a termination and V(final
    observation) after a truncation; ``done`` cuts the sum at an episode end."""
    adv, last = torch.zeros_like(rewards), torch.zeros_like(rewards[0])
    for t in reversed(range(len(rewards))):
        delta = rewards[t] + gamma * next_values[t] - values[t]
        last = delta + gamma * lam * (~done[t]).float() * last
        adv[t] = last
    return adv


# ====================================================================== training loop
@learner
def train(cfg: APGConfig, out: Path | str, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    run = Run("apg", cfg, out, resume, progress)
    env, device, p, num_envs = run.env, run.device, run.params, cfg.run.num_envs
    sim, obs_type, reward_kind = env.core.sim, cfg.task.obs, cfg.task.reward
    actor = Actor(run.obs, cfg, p.length, p.n_nodes).to(device)
    actor_opt = torch.optim.Adam(actor.parameters(), lr=cfg.lr)
    parts: dict[str, Any] = dict(actor=actor, actor_opt=actor_opt)
    critic = Critic(run.obs, cfg, p.length).to(device) if cfg.critic else None
    if critic is not None:
        parts.update(critic=critic, critic_opt=torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr))
    gain_buf = None
    if cfg.node == "gain" and cfg.gain_replay > 0:
        gain_buf = ReplayBuffer(-(-cfg.gain_replay // num_envs), num_envs, run.obs, 1, device)
        parts["gain_buffer"] = gain_buf
    ck = run.start(**parts)
    counts = dict(ck["counts"]) if ck else {"n_updates": 0, "sim_backward": 0, "clipped_updates": 0}
    actor_params = list(actor.parameters())
    value = critic if critic is not None else (lambda o: torch.zeros(len(o if torch.is_tensor(o) else o["node_poses"]),
                                                                     device=device))

    def policy(o: Any, deterministic: bool) -> torch.Tensor:
        return actor.env_action(o, deterministic)

    def rollout(h: int) -> dict[str, Any]:
        """h moves of every training rope with the graph kept; the env steps along (same moves, its bookkeeping)."""
        state = env.core.get_state(generators=False)
        pos, target, pegs = state.pos, state.target, state.pegs
        disc = torch.ones(num_envs, device=device)
        J = torch.zeros(num_envs, device=device)
        rec: dict[str, list] = {k: [] for k in ("obs", "log_prob", "entropy", "reward", "done", "value", "next_value",
                                                   "gain_loss")}
        for _ in range(h):
            o = env.to_learner(graph_obs(obs_type, pos, target, pegs))
            with torch.no_grad():
                if actor.net.feat.norm is not None:
                    actor.net.feat(o, update_norm=True)
                    if critic is not None:
                        critic.feat.norm.load_state_dict(actor.net.feat.norm.state_dict())
            log_pk, drags = actor.dist(o)
            node = actor.choose(o, log_pk, deterministic=False,
                                explore=cfg.gain_explore * max(0.0, 1.0 - run.step / cfg.run.total_steps))
            rows = torch.arange(num_envs, device=device)
            action, new, r = move_graph(sim, p, pos, target, node, drags[rows, node], reward_kind, cfg.objective,
                                        pegs)
            r = r.to(device)
            _, r_env, term, trunc, info, final_obs = env.step(action.detach())
            run.count(info, term, trunc, update_bar=True)
            done = term | trunc
            J = J + disc * r
            with torch.no_grad():
                v_final = torch.where(term, 0.0, value(final_obs))
                rec["value"].append(value(env.to_learner(graph_obs(obs_type, pos.detach(), target, pegs))))
            if critic is not None:                   # truncated: the value of its true final state, through it
                cut = (trunc & ~term).float()
                J = J + disc * cfg.gamma * cut * critic(env.to_learner(graph_obs(obs_type, new, target, pegs)))
            disc = torch.where(done, 1.0, disc * cfg.gamma)
            rec["obs"].append(rec_obs(o))
            rec["log_prob"].append(log_pk[rows, node])
            rec["entropy"].append(-(log_pk.exp() * log_pk).sum(-1))
            rec["reward"].append(r_env.float())
            if gain_buf is not None:                                               # node "gain": (s, k, r) kept
                no = torch.zeros(num_envs, dtype=torch.bool, device=device)
                gain_buf.add(rec_obs(o), node.float()[:, None], r.detach(), no, no)
            elif actor.gain is not None:                                           # online: G(s, k) -> r
                rec["gain_loss"].append((actor.gains(o)[rows, node] - r.detach()) ** 2)
            rec["done"].append(done)
            rec["next_value"].append(v_final)                                        # fixed below where not done
            now = env.core.get_state(generators=False)                               # the reset ropes' new starts
            pos, target, pegs = torch.where(done.to(sim.device).view(-1, 1, 1), now.pos, new), now.target, now.pegs
        o_last = env.to_learner(graph_obs(obs_type, pos, target, pegs))
        if critic is not None:                       # the value beyond the horizon of the ropes still going
            J = J + disc * (~rec["done"][-1]).float() * critic(o_last)
        with torch.no_grad():
            rec["next_value"] = [torch.where(rec["done"][t], rec["next_value"][t],
                                             rec["value"][t + 1] if t + 1 < h else value(o_last)) for t in range(h)]
        out = {k: torch.stack(v) for k, v in rec.items() if k != "obs" and v}
        out["obs"], out["J"] = rec["obs"], J
        return out

    while run.step < cfg.run.total_steps:
        h = min(cfg.horizon, -(-(cfg.run.total_steps - run.step) // num_envs))
        if cfg.anneal_lr:
            for group in actor_opt.param_groups:
                group["lr"] = cfg.lr * max(0.0, 1.0 - run.step / cfg.run.total_steps)
        ro = rollout(h)
        # ---- actor: pathwise -J, plus the node's score-function term
        adv = advantages(ro["reward"], ro["value"], ro["next_value"], ro["done"], cfg.gamma,
                         cfg.gae_lambda if critic is not None else 1.0)
        if critic is None:
            adv = adv - adv.mean(1, keepdim=True)                                    # a batch-mean baseline per t
        path_loss, node_loss = actor_losses(ro["J"], ro["log_prob"], ro["entropy"], adv, cfg)
        actor_opt.zero_grad()
        node_grads = None                            # the score-function gradient, kept apart to log its norm
        if cfg.node == "score":
            node_grads = torch.autograd.grad(node_loss, actor_params, retain_graph=True, allow_unused=True)
        gain_loss = ro["gain_loss"].mean() if "gain_loss" in ro else None
        if gain_buf is not None and len(gain_buf) > 1:                         # node "gain": a replayed minibatch
            b = gain_buf.sample(cfg.gain_batch)
            pred = actor.gains(b["obs"])[torch.arange(cfg.gain_batch, device=device), b["action"][:, 0].long()]
            gain_loss = ((pred - b["reward"]) ** 2).mean()
        (path_loss if gain_loss is None else path_loss + gain_loss).backward()
        counts["sim_backward"] += h * num_envs
        g_path = grad_norm(list(actor.net.parameters()))             # the policy net's pathwise gradient
        g_node = 0.0
        if node_grads is not None:
            g_node = float(torch.linalg.vector_norm(torch.stack([g.norm() for g in node_grads if g is not None])))
            for prm, g in zip(actor_params, node_grads):
                if g is not None:
                    prm.grad = g if prm.grad is None else prm.grad + g
        g_total = grad_norm(actor_params)
        if not all(torch.isfinite(prm.grad).all() for prm in actor_params if prm.grad is not None):
            raise FloatingPointError(f"apg: non-finite actor gradient at update {counts['n_updates']} (pathwise norm "
                                     f"{g_path}, score-function norm {g_node})")
        clipped = cfg.max_grad_norm > 0 and g_total > cfg.max_grad_norm
        if cfg.max_grad_norm > 0:
            nn.utils.clip_grad_norm_(actor_params, cfg.max_grad_norm)
        actor_opt.step()
        counts["clipped_updates"] += int(clipped)
        counts["n_updates"] += 1
        # ---- critic: TD(lambda) targets of this rollout
        critic_loss, g_critic = float("nan"), float("nan")
        if critic is not None:
            returns = advantages(ro["reward"], ro["value"], ro["next_value"], ro["done"], cfg.gamma,
                                 cfg.gae_lambda) + ro["value"]
            obs_all = (torch.cat(ro["obs"]) if torch.is_tensor(ro["obs"][0])
                       else {kk: torch.cat([o[kk] for o in ro["obs"]]) for kk in ro["obs"][0]})
            for _ in range(cfg.critic_epochs):
                loss_c = ((critic(obs_all) - returns.flatten()) ** 2).mean()
                parts["critic_opt"].zero_grad()
                loss_c.backward()
                g_critic = grad_norm(list(critic.parameters()))
                parts["critic_opt"].step()
            critic_loss = loss_c.item()
        if counts["n_updates"] % cfg.run.log_every == 0:
            run.logger.log("train", run.step, {
                "objective": ro["J"].mean().item(), "actor_loss": path_loss.item(), "node_loss": node_loss.item(),
                "entropy": ro["entropy"].mean().item(), "grad_norm_path": g_path, "grad_norm_node": g_node,
                "grad_norm": g_total, "clipped": float(clipped), "max_grad_norm": cfg.max_grad_norm,
                "critic_loss": critic_loss, "grad_norm_critic": g_critic, "horizon": h,
                "gain_loss": float("nan") if gain_loss is None else gain_loss.item(),
                "lr": actor_opt.param_groups[0]["lr"], **counts})
            run.log_rollout()
        run.evaluate_if_due(lambda: run.evaluate(policy))
        run.checkpoint_if_due(lambda: {**parts, "counts": dict(counts)})
    return run.finish(policy, extra=dict(counts, horizon=cfg.horizon, node=cfg.node, critic=cfg.critic))


def main(argv: list[str] | None = None) -> int:
    return run_cli(APGConfig, "apg", __doc__, train, argv)


if __name__ == "__main__":
    sys.exit(main())
