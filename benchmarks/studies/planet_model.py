"""How well can PlaNet's world models (agents/models/: ensemble, latent, rssm) predict the rope, apart from the
planning loop?

Collect random-move episodes (uniform actions, the same distribution as ``openloop.open_loop_eval``'s
held-out ropes) into the shared replay buffer, train the model on chunks exactly as ``agents/planet.py`` does, and
print the open-loop node error after 1, 2, 5 and 10 moves next to the "nothing moves" baseline at a few update counts.

    python benchmarks/studies/planet_model.py --updates 2000            # ~5 min on one CPU core
    python benchmarks/studies/planet_model.py --updates 4000 --set obs_std=0.01
    python benchmarks/studies/planet_model.py --plan-time --envs 16     # seconds per planned move of 16 ropes
    python benchmarks/studies/planet_model.py --preset rssm --set obs=image --update-time --envs 16 --moves 40
                                                                # seconds per model update (one core)
    python benchmarks/studies/planet_model.py --envs 64 --moves 160 --preset rssm --updates 4000 \
        --set rssm_frame=centroid        # or rssm_residual=true, kl_balance=dreamerv3 (+ free_nats=1): the RSSM's
                                         # diagnosis options (issue 47, docs/WORLD_MODELS.md), one at a time
    python benchmarks/studies/planet_model.py --envs 64 --moves 160 --preset latent --updates 3000 \
        --set latent_kind=vector         # the latent world model (agents/models/latent.py) and its options

Used to size ``seed_episodes`` in params/planet.yaml: trained on random moves only, the model beats the baseline
after ~1000 updates; trained in the loop on 500 random and 9500 planner-chosen moves (the old default), it did not.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from agents.models import openloop                          # noqa: E402
from agents import planet
from agents.common.buffer import ReplayBuffer                       # noqa: E402
from agents.common.config import load_config, preset_path  # noqa: E402
from agents.common.envs import make_env  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--updates", type=int, default=2000)
    ap.add_argument("--envs", type=int, default=64, help="ropes collected in parallel")
    ap.add_argument("--moves", type=int, default=300, help="random moves per rope (episodes end after max_steps)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--preset", default=None, help="PlaNet preset: tuned (the ensemble, default) or rssm")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="PlaNet config key")
    ap.add_argument("--plan-time", action="store_true",
                    help="only time the latent planner: one planned move of --envs ropes (untrained model)")
    ap.add_argument("--update-time", action="store_true",
                    help="only time model updates (the config's batch of chunks) on --moves random moves of "
                         "--envs ropes")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    bad = [item for item in args.set if "=" not in item]
    if bad:
        ap.error(f"--set expects KEY=VALUE, got {bad[0]!r}")
    overrides = {k.strip(): yaml.safe_load(v) for k, v in (item.split("=", 1) for item in args.set)}
    cfg = load_config(planet.PlaNetConfig, preset_path("planet", args.preset), overrides)
    torch.manual_seed(args.seed)
    params = cfg.task.cable_params()
    env = make_env(cfg.task, cfg.run, params, args.envs)
    obs = env.reset(seed=args.seed)
    model = planet.build_model(cfg, obs, env.core.action_dim, params)
    if args.plan_time:
        planner = planet.make_planner(model, cfg, env.core, args.seed)
        for i in range(3):
            t0 = time.perf_counter()
            action = planner(obs, deterministic=False)
            print(f"planned move {i} of {args.envs} ropes: {time.perf_counter() - t0:.2f} s")
            obs, *_ = env.step(action)
        return 0
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, eps=cfg.adam_eps)
    rb = ReplayBuffer(args.moves + 2, args.envs, obs, env.core.action_dim, "cpu")
    g = torch.Generator().manual_seed(args.seed)
    t0 = time.perf_counter()
    for _ in range(args.moves):
        a = torch.rand(args.envs, env.core.action_dim, generator=g)
        nxt, r, term, trunc, _, final = env.step(a)
        rb.add(obs, a, r, term, trunc, final_obs=final)
        obs = nxt
    print(f"data: {args.moves * args.envs} random transitions in {time.perf_counter() - t0:.1f} s")
    chunks = cfg.batch_size * (cfg.members if cfg.model == "ensemble" else 1)

    def update() -> dict[str, torch.Tensor]:
        seq = rb.sample_sequences(chunks, cfg.chunk_length)
        loss = model.loss(seq["obs"], seq["action"], seq["reward"], seq["mask"])
        opt.zero_grad()
        loss["loss"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        opt.step()
        return loss

    if args.update_time:
        update()                                   # the first one allocates
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            update()
            times.append(time.perf_counter() - t0)
        phases = max(0, cfg.run.total_steps - cfg.seed_episodes * env.core.max_steps) // cfg.train_every
        print(f"model update ({chunks} chunks of {cfg.chunk_length}, obs {cfg.task.obs}): median "
              f"{sorted(times)[2]:.2f} s, min {min(times):.2f} s over 5; a run of total_steps {cfg.run.total_steps} "
              f"makes {phases * cfg.updates_per_train} updates")
        return 0
    print("open-loop node error [cm] on held-out ropes (model / nothing moves), after k moves:")
    marks = {u for u in (250, 500, 1000, 2000, 4000, 8000, 16000) if u < args.updates} | {args.updates}
    t0 = time.perf_counter()
    for u in range(1, args.updates + 1):
        loss = update()
        if u in marks:
            model.eval()
            ol = openloop.open_loop_eval(model, cfg, horizons=(1, 2, 5, 10))
            model.train()
            errs = "  ".join(f"k={k}: {100 * ol[f'pred_err_{k}']:.2f} / {100 * ol[f'base_err_{k}']:.2f}"
                             for k in (1, 2, 5, 10))
            shown = "  ".join(f"{k} {v.item():.3g}" for k, v in loss.items() if torch.is_tensor(v) and v.numel() == 1)
            print(f"{u:6d} updates ({time.perf_counter() - t0:5.0f} s)  {shown}  {errs}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
