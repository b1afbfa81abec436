"""Stable-Baselines3 PPO against our PPO with the same settings where SB3 allows them, evaluated like agents.ppo.

    python benchmarks/studies/sb3_ppo.py --total-steps 1000000 --seed 0 --out runs/sb3-ppo-s0
    python -m agents.ppo --set policy=gaussian --total-steps 1000000 --seed 0 --eval-episodes 100 --out runs/ppo-gauss-s0

The check that our learner is not weaker than a well-kept library. SB3 has no hybrid (categorical + Gaussian)
action, so both sides use a Gaussian over the env's Box action (our ``--set policy=gaussian``, the "head" row of the
ablation). Everything else is our tuned preset (params/ppo.yaml): the same task rules (shape_gain reward, success
bonus 5, leaving the workspace a terminal failure with -5), 512 ropes x 16-step rollouts, 4 epochs of 4 minibatches,
Adam 3e-4 annealed linearly, gamma 0.97, lambda 0.95, clip 0.2, [256, 256] tanh networks, orthogonal init, log-std
log 0.5, and the same observation: our target-relative features (agents.models.hybrid.relative_features) running-
normalized by SB3's VecNormalize (norm_obs, no reward normalization). The env is one BatchedShapeControl of 512
ropes behind a small SB3 VecEnv adapter (BatchedVecEnv below), so SB3 steps all ropes in one simulator call as ours
does. Writes results.json (method "sb3_ppo", the fields every method writes) after evaluating on --eval-episodes episodes from
seeds 10000 + i with the deterministic policy. Needs the [dev] extra (SB3).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch
from gymnasium import spaces

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))   # run as a script: the repository root

import diffdlo
from agents.common.config import load_config, preset_path
from agents.common.envs import make_env
from agents.common.evaluation import evaluate
from agents.models.hybrid import relative_features
from agents.ppo import PPOConfig
from benchmarks.studies import sb3_common
from diffdlo.envs import BatchedShapeControl

try:
    from stable_baselines3.common.vec_env import VecEnv
except ImportError as exc:            # the [dev] extra
    raise SystemExit(f"stable-baselines3 is missing ({exc}): pip install -c constraints.txt -e '.[dev]'")


def make_core(cfg: PPOConfig, num_envs: int) -> BatchedShapeControl:
    return make_env(cfg.task, cfg.run, cfg.task.cable_params(), num_envs).core     # the tuned task: points, node


class BatchedVecEnv(VecEnv):
    """SB3's VecEnv over one BatchedShapeControl: observations are our relative features (float32 Box), the
    ended ropes are reset in one masked call, with SB3's terminal_observation and TimeLimit.truncated infos.
    Actions live in [-1, 1] (SB3's usual box, where its Gaussian's mean starts at the centre) and reach the env as
    (a + 1) / 2, so SB3's log-std log 1.0 is our log 0.5 on [0, 1]."""

    def __init__(self, core: BatchedShapeControl, seed: int):
        self.core, self.length, self.seed_value = core, core.params.length, seed
        n = core.params.n_nodes
        obs_space = spaces.Box(-np.inf, np.inf, (4 * n + 2,), np.float32)
        super().__init__(core.num_envs, obs_space, spaces.Box(-1.0, 1.0, (core.action_dim,), np.float32))
        self.actions = None

    def _features(self, obs) -> np.ndarray:
        return relative_features(obs, self.length).numpy().astype(np.float32)

    def reset(self):
        obs, _ = self.core.reset(seed=self.seed_value)
        self.seed_value = None                       # later resets continue each rope's generator
        return self._features(obs)

    def step_async(self, actions) -> None:
        self.actions = (torch.as_tensor(np.asarray(actions), dtype=torch.float64).clamp(-1, 1) + 1) / 2

    def step_wait(self):
        obs, reward, term, trunc, info = self.core.step(self.actions)
        final = self._features(obs)
        done = (term | trunc).numpy()
        infos = [{"is_success": bool(info["is_success"][i])} for i in range(self.num_envs)]
        if done.any():
            for i in np.flatnonzero(done):
                infos[i]["terminal_observation"] = final[i]
                infos[i]["TimeLimit.truncated"] = bool(trunc[i])
            obs, _ = self.core.reset(mask=torch.as_tensor(done))
            final = self._features(obs)
        return final, reward.numpy().astype(np.float32), done, infos

    def close(self) -> None:
        pass

    def get_attr(self, attr_name, indices=None):
        return [getattr(self.core, attr_name)] * self.num_envs

    def set_attr(self, attr_name, value, indices=None) -> None:
        setattr(self.core, attr_name, value)

    def env_method(self, method_name, *args, indices=None, **kwargs):
        return [getattr(self.core, method_name)(*args, **kwargs)]

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * self.num_envs


def main() -> None:
    args = sb3_common.parser(__doc__, total_steps=1_000_000, eval_episodes=100, out="runs/sb3-ppo").parse_args()
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    torch.set_num_threads(args.threads)
    out = Path(args.out)
    if (out / "results.json").exists():
        raise SystemExit(f"{out / 'results.json'} exists: choose another --out (nothing is overwritten)")
    out.mkdir(parents=True, exist_ok=True)
    cfg = load_config(PPOConfig, preset_path("ppo", None), {"target": args.target, "seed": args.seed})
    venv = VecNormalize(BatchedVecEnv(make_core(cfg, cfg.run.num_envs), args.seed), norm_obs=True, norm_reward=False,
                        clip_obs=10.0, gamma=cfg.gamma)
    model = PPO("MlpPolicy", venv, learning_rate=lambda frac: cfg.lr * frac, n_steps=cfg.n_steps,
                batch_size=cfg.batch_size, n_epochs=cfg.n_epochs, gamma=cfg.gamma, gae_lambda=cfg.gae_lambda,
                clip_range=cfg.clip_range, ent_coef=cfg.ent_coef, vf_coef=cfg.vf_coef,
                max_grad_norm=cfg.max_grad_norm,
                policy_kwargs=dict(net_arch=dict(pi=cfg.hidden, vf=cfg.hidden), activation_fn=torch.nn.Tanh,
                                   log_std_init=cfg.log_std_init + float(np.log(2.0))),   # std 0.5 on [0, 1]
                seed=args.seed, verbose=0, device="cpu")
    t0 = time.perf_counter()
    model.learn(total_timesteps=args.total_steps, progress_bar=False)
    train_s = time.perf_counter() - t0
    venv.training = False

    length = diffdlo.load_params(cfg.task.params).length

    def policy(obs, deterministic: bool) -> torch.Tensor:
        x = venv.normalize_obs(relative_features(obs, length).numpy().astype(np.float32))
        action, _ = model.predict(x, deterministic=deterministic)
        return (torch.as_tensor(np.asarray(action), dtype=torch.float64).clamp(-1, 1) + 1) / 2

    result = evaluate(policy, make_core(cfg, min(args.eval_episodes, 32)), args.eval_episodes, seed=args.eval_seed)
    path = sb3_common.write_record(out, "sb3_ppo", args, result, env_steps=int(model.num_timesteps),
                                   wall_s=time.perf_counter() - t0, train_s=train_s)
    moves = [e["steps"] for e in result["episodes"] if e["success"]]
    print(f"sb3 PPO: {model.num_timesteps} steps in {train_s:.0f} s; eval success {result['success_rate']:.2f}, "
          f"moves to success {np.mean(moves) if moves else float('nan'):.1f}, mean final error "
          f"{result['mean_final_error'] * 100:.2f} cm -> {path}")


if __name__ == "__main__":
    main()
