"""Can an image encoder see what the policy needs? A supervised probe of the learners' picture encoders.

    python -m benchmarks.studies.image_probe --encoders keypoints nature --samples 16384 --epochs 10 --out runs/image_probe

The points learners act on the per-node error (centred rope - centred target, agents/models/hybrid.py). This trains each
encoder (the one in front of the image learners, agents.models.networks.ObsEncoder, plus the learners' MLP) to REGRESS that
error from the env's image observation (rope picture + target picture, params/ppo-image.yaml's settings: 64 px,
end markers), on rope states visited by random moves from random starts, and reports the error of the regression
on held-out states in centimetres per node coordinate. If an encoder cannot read the per-node error to well under
the 1 cm success tolerance, no policy on top of it can finish the task; if it can, what is missing is learning.
Prints a table and writes ``<out>/results.json`` (an existing one only with ``--overwrite``).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
import torch.nn as nn
from tqdm import tqdm

from agents.common.checkpoints import seed_everything
from agents.models.networks import ObsEncoder, mlp, shift_images
from agents.models.hybrid import relative_features
from diffdlo.envs import BatchedShapeControl


def collect(samples: int, seed: int, image_size: int, mark_end: bool, target: str, envs: int = 512):
    """(images dict of uint8 (S, H, W, 3), per-node error (S, N, 2) [m]) over states visited by random moves."""
    env = BatchedShapeControl(envs, target=target, obs_type="image", image_size=image_size, mark_end=mark_end)
    obs, _ = env.reset(seed=seed)
    g = torch.Generator().manual_seed(seed)
    images, errors = {k: [] for k in obs}, []
    n = env.params.n_nodes
    while sum(len(e) for e in errors) < samples:
        for k in obs:
            images[k].append(obs[k])
        state = env.get_state(generators=False)
        pos, tgt = state.pos.detach(), state.target.detach()
        errors.append(relative_features(pos - tgt, 1.0).view(envs, n, 2))   # the points learners' diff, in m
        obs, _, term, trunc, _ = env.step(torch.rand(envs, 3, generator=g))
        ended = term | trunc
        if bool(ended.any()):
            obs, _ = env.reset(mask=ended)
    return {k: torch.cat(v)[:samples] for k, v in images.items()}, torch.cat(errors)[:samples].to(torch.float32), n


def probe(encoder: str, train, test, n_nodes: int, epochs: int, batch: int, shift: int, seed: int,
          progress: bool) -> dict:
    seed_everything(seed)
    (x_tr, y_tr), (x_te, y_te) = train, test
    example = {k: v[:2] for k, v in x_tr.items()}
    channels = [16] if encoder == "keypoints" else [32, 64, 64]     # params/ppo-image.yaml; SB3 NatureCNN
    enc = ObsEncoder(example, 1.0, channels, 256, encoder, 32)
    head = mlp(enc.out_dim, [256, 256], n_nodes * 2, nn.Tanh)
    params = list(enc.parameters()) + list(head.parameters())
    opt = torch.optim.Adam(params, lr=1e-3)
    scale = 100.0                                                  # regress centimetres
    t0 = time.perf_counter()
    steps = epochs * (len(y_tr) // batch)
    bar = tqdm(total=steps, desc=encoder, disable=not progress, file=sys.stderr)
    for _ in range(epochs):
        perm = torch.randperm(len(y_tr))
        for i in range(0, len(perm) - batch + 1, batch):
            idx = perm[i:i + batch]
            xb = shift_images({k: v[idx] for k, v in x_tr.items()}, shift)
            loss = ((head(enc(xb)) - scale * y_tr[idx].flatten(1)) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            bar.update()
    bar.close()
    with torch.no_grad():
        pred = torch.cat([head(enc({k: v[i:i + 1024] for k, v in x_te.items()})) for i in range(0, len(y_te), 1024)])
    err = pred / scale - y_te.flatten(1)                           # [m]
    baseline = y_te.flatten(1) - y_tr.flatten(1).mean(0)
    return {"encoder": encoder, "rmse_cm": 100 * float(err.pow(2).mean().sqrt()),
            "mean_abs_cm": 100 * float(err.abs().mean()),
            "baseline_rmse_cm": 100 * float(baseline.pow(2).mean().sqrt()),
            "node_error_rmse_cm": 100 * float(err.view(-1, n_nodes, 2).norm(dim=-1).pow(2).mean().sqrt()),
            "train_s": time.perf_counter() - t0, "epochs": epochs, "train_samples": len(y_tr)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--encoders", nargs="+", default=["keypoints", "nature"], choices=["keypoints", "nature"])
    ap.add_argument("--samples", type=int, default=16384, help="training states (test: a quarter as many)")
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--shift", type=int, default=4, help="DrQ random shift during training [pixels]")
    ap.add_argument("--image-size", type=int, default=64)
    ap.add_argument("--no-mark-end", action="store_true", help="the thesis's pictures (no dot on node 0)")
    ap.add_argument("--target", default="random")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("runs/image_probe"))
    ap.add_argument("--overwrite", action="store_true", help="replace an existing <out>/results.json")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    if (a.out / "results.json").exists() and not a.overwrite:
        ap.error(f"{a.out / 'results.json'} exists: pass --overwrite to replace it, or another --out")
    for name in ("samples", "epochs", "batch", "threads"):
        if getattr(a, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    if a.shift < 0:
        ap.error(f"--shift must be >= 0, got {a.shift}")
    torch.set_num_threads(a.threads)
    mark = not a.no_mark_end
    x_tr, y_tr, n = collect(a.samples, a.seed, a.image_size, mark, a.target)
    x_te, y_te, _ = collect(max(a.samples // 4, 1), a.seed + 1, a.image_size, mark, a.target)
    rows = [probe(e, (x_tr, y_tr), (x_te, y_te), n, a.epochs, a.batch, a.shift, a.seed, not a.no_progress)
            for e in a.encoders]
    a.out.mkdir(parents=True, exist_ok=True)
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
    (a.out / "results.json").write_text(json.dumps({"settings": settings, "rows": rows}, indent=2))
    print("| encoder | per-coordinate RMSE [cm] | per-node error RMSE [cm] | predict-the-mean RMSE [cm] | train s |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['encoder']} | {r['rmse_cm']:.2f} | {r['node_error_rmse_cm']:.2f} | {r['baseline_rmse_cm']:.2f} "
              f"| {r['train_s']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
