"""PlaNet's open-loop prediction check: how far a world model's predicted ropes drift from the true ones over k
moves it has not seen (fresh ropes, uniform random moves), against the "nothing moves" baseline; and its picture."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.common.buffer import as_dict
from agents.models.ensemble import EnsembleDynamics, k_step_errors
from agents.models.latent import LatentWorldModel
from agents.common.envs import make_env
from agents.models.rssm import RSSM, decoded_positions
from diffdlo.planar.params import CableParams
from diffdlo.tasks.task import COORDINATE_OBS


@torch.no_grad()
def open_loop_eval(model: RSSM | EnsembleDynamics | LatentWorldModel, cfg, n_episodes: int | None = None,
                   context: int | None = None, horizons: tuple[int, ...] = (1, 2, 5, 10),
                   seed: int | None = None, params: CableParams | None = None) -> dict[str, Any]:
    """Open-loop prediction error on held-out episodes (fresh ropes, uniform random moves, never in the buffer).

    Filter the posterior over ``context`` moves (context + 1 observations), then roll the prior mean forward under
    the next K = max(horizons) executed moves and decode. Returns, for each k in horizons, ``pred_err_k`` (mean node
    distance [m] between the decoded and the true rope after k open-loop moves) and ``base_err_k`` (the "nothing
    moves" baseline: the last observed rope), for points and distance observations; for images the same keys hold
    the mean squared pixel error (model units, [-0.5, 0.5]) of the decoded image vs the last observed image.
    Ropes whose episode ends before the last move are left out. Also returns the trajectories for pictures.
    The ensemble and the latent model need no filter: they predict from the rope observed after ``context`` moves. ``params``: the run's
    cable params (default: resolved from cfg.task).
    """
    n = n_episodes or cfg.openloop_episodes
    context = cfg.openloop_context if context is None else context
    k_max = max(horizons)
    max_steps = max(context + k_max + 1, cfg.task.max_steps or 0)
    env = make_env(dataclasses.replace(cfg.task, max_steps=max_steps),
                   dataclasses.replace(cfg.run, env_device=cfg.run.device), params or cfg.task.cable_params(), n)
    obs = env.reset(seed=cfg.openloop_seed if seed is None else seed)
    g = torch.Generator().manual_seed(cfg.openloop_seed if seed is None else seed)
    dev = cfg.run.device
    obs_seq, pos_seq, acts = [obs], [env.core.get_state(generators=False).pos], []
    alive = torch.ones(n, dtype=torch.bool)
    for _ in range(context + k_max):
        a = torch.rand(n, env.core.action_dim, generator=g).to(dev)
        obs, _, term, trunc, _ = env.core.step(a, mask=alive)
        alive &= ~(term | trunc).cpu()
        obs_seq.append(obs)
        pos_seq.append(env.core.get_state(generators=False).pos)
        acts.append(a)
    true = torch.stack(pos_seq[context + 1:], 1).float()                              # (n, K, N, 2)
    if not isinstance(model, RSSM):            # a model of node positions that predicts from the observed rope
        pegs = env.core.get_state(generators=False).pegs if getattr(model, "max_pegs", 0) else None
        out = k_step_errors(model, pos_seq[context].float(), torch.stack(acts[context:], 1), true, horizons,
                            alive.to(true.device), pegs)
        out.update({"n": int(alive.sum()), "context": context, "true": true.cpu(), "alive": alive,
                    "target": env.core.get_state(generators=False).target.float().cpu()})
        out["pred"] = out["pred"].cpu()
        return out
    state = None
    for t in range(context + 1):
        state, _ = model.obs_step(state, None if t == 0 else acts[t - 1], model.embed(obs_seq[t]), sample=False,
                                  obs=obs_seq[t])
    traj = model.imagine(state, torch.stack(acts[context:], 1), sample=False)
    feat = torch.stack([RSSM.feature(s) for s in traj], 1)                            # (n, K, F)
    target = env.core.get_state(generators=False).target.float()
    out: dict[str, Any] = {"n": int(alive.sum()), "context": context}
    a_ = alive.to(true.device)
    if cfg.task.obs in COORDINATE_OBS:
        pred = decoded_positions(model, feat, cfg.task.obs, target[:, None], model.decode_traj(traj))
        last = pos_seq[context].float()[:, None].expand_as(true)
        for k in horizons:
            out[f"pred_err_{k}"] = float((pred[:, k - 1] - true[:, k - 1]).norm(dim=-1).mean(-1)[a_].mean())
            out[f"base_err_{k}"] = float((last[:, k - 1] - true[:, k - 1]).norm(dim=-1).mean(-1)[a_].mean())
        out["pred"], out["true"] = pred.cpu(), true.cpu()
    else:
        dec = model.decode_traj(traj)
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
    images = obs_type not in COORDINATE_OBS
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
