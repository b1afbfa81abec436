"""Helpers shared by the learners (agents/sac.py, agents/ppo.py, agents/planet.py): configuration, the training env
with autoreset, network builders and image encoders, the logger, checkpoints, evaluation (also on held-out target
shapes), results and the command line.

Only what the learners share lives here; each algorithm (config -> networks -> loop) reads top to bottom in its own
file.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import json
import math
import os
import random
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import yaml
from gymnasium.utils import seeding

from agents.hybrid import FEATURE_OBS, RunningNorm, relative_features
from diffdlo.envs.shape_control import ACTION_TYPES, EXIT_RULES, OBS_TYPES, BatchedShapeControl
from diffdlo.params import CableParams, ParamsError, load_params
from diffdlo.rewards import REWARDS
from diffdlo.shapes import TARGET_NAMES, TargetError

PARAMS_DIR = Path(__file__).resolve().parent.parent / "params"
CHECKPOINT = "checkpoint.pt"


# ====================================================================== configuration
def preset_path(algo: str, preset: str | None) -> Path:
    """``params/<algo>.yaml`` for the preset "tuned" (the default), ``params/<algo>-<preset>.yaml`` otherwise."""
    if preset in (None, "tuned"):
        return PARAMS_DIR / f"{algo}.yaml"
    path = PARAMS_DIR / f"{algo}-{preset}.yaml"
    if not path.exists():
        known = ["tuned"] + sorted(p.stem[len(algo) + 1:] for p in PARAMS_DIR.glob(f"{algo}-*.yaml"))
        raise ValueError(f"unknown preset {preset!r} for {algo}: use one of {known}")
    return path


def load_config(cls, name: str | Path, overrides: dict[str, Any] | None = None):
    """Dataclass ``cls`` from ``params/<name>.yaml`` (or a YAML path) then ``overrides``; unknown keys raise."""
    path = Path(name) if str(name).endswith((".yaml", ".yml")) else PARAMS_DIR / f"{name}.yaml"
    if not path.exists():
        raise ValueError(f"config file {str(path)!r} does not exist")
    values = yaml.safe_load(path.read_text()) or {}
    values.update(overrides or {})
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - fields)
    if unknown:
        raise ValueError(f"unknown config keys {unknown} for {cls.__name__}: allowed {sorted(fields)}")
    cfg = cls(**values)
    check_config(cfg)
    return cfg


def check_config(cfg) -> None:
    """The checks every learner shares (clear ValueErrors for bad values)."""
    if cfg.obs not in OBS_TYPES:
        raise ValueError(f"unknown obs type {cfg.obs!r}: use one of {list(OBS_TYPES)}")
    if cfg.action not in ACTION_TYPES:
        raise ValueError(f"unknown action type {cfg.action!r}: use one of {list(ACTION_TYPES)}")
    if cfg.reward not in REWARDS:
        raise ValueError(f"unknown reward {cfg.reward!r}: use one of {list(REWARDS)}")
    for key in ("total_steps", "num_envs", "threads", "eval_every", "eval_episodes", "checkpoint_every", "log_every"):
        v = getattr(cfg, key)
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ValueError(f"{key} must be a positive integer, got {v!r}")
    for key in ("device", "env_device"):
        v = getattr(cfg, key, None)
        if key == "env_device" and not v:
            continue                      # "": the learner's device
        try:
            dev = torch.device(v)
        except (RuntimeError, TypeError) as exc:
            raise ValueError(f"{key} must be a torch device such as 'cpu' or 'cuda', got {v!r}") from exc
        if dev.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"{key}={v!r}: CUDA is not available on this machine")
    choices = {"policy": ("hybrid", "gaussian"), "features": ("relative", "raw"), "on_exit": EXIT_RULES,
               "encoder": ENCODERS}
    for key, allowed in choices.items():
        if hasattr(cfg, key) and getattr(cfg, key) not in allowed:
            raise ValueError(f"unknown {key} {getattr(cfg, key)!r}: use one of {list(allowed)}")
    if getattr(cfg, "policy", None) == "hybrid" and cfg.action != "node":
        raise ValueError(f"policy 'hybrid' chooses a node: it needs action 'node', got {cfg.action!r} "
                         "(use --set policy=gaussian for pixel actions)")
    if getattr(cfg, "features", None) == "relative" and cfg.obs not in FEATURE_OBS:
        raise ValueError(f"features 'relative' need obs {list(FEATURE_OBS)}, got {cfg.obs!r} "
                         "(use --set features=raw for images)")
    if getattr(cfg, "normalize_obs", False) and getattr(cfg, "features", None) != "relative":
        raise ValueError("normalize_obs needs features 'relative' (images and raw observations are not normalized)")
    for key, least, what in (("keypoints", 1, "positive"), ("augment_shift", 0, "non-negative")):
        v = getattr(cfg, key, least)
        if not isinstance(v, int) or isinstance(v, bool) or v < least:
            raise ValueError(f"{key} must be a {what} integer, got {v!r}")
    if not isinstance(getattr(cfg, "mark_end", False), bool):
        raise ValueError(f"mark_end must be true or false, got {cfg.mark_end!r}")
    po = cfg.param_overrides
    if po is not None:
        fields = {f.name for f in dataclasses.fields(CableParams)}
        if not isinstance(po, dict) or set(po) - fields:
            raise ValueError(f"param_overrides must map CableParams fields ({sorted(fields)}) to values, got {po!r}"
                             " (YAML flow maps need a space after each colon: {n_nodes: 6})")


def make_params(cfg) -> CableParams:
    p = load_params(cfg.params)
    return dataclasses.replace(p, **(cfg.param_overrides or {})) if cfg.param_overrides else p


# ====================================================================== env with our own autoreset
class TrainEnv:
    """``BatchedShapeControl`` (tensors end to end) with same-step autoreset and episode bookkeeping.

    ``step(actions)`` steps every rope with ONE batched call, then resets the ropes whose episode ended with ONE
    masked ``reset`` and returns (obs, reward, terminated, truncated, info, final_obs): ``obs`` is what the policy
    acts on next (the first observation of a new episode where one ended) and ``final_obs`` the observation the
    step produced (the true last observation of an ended episode, used by bootstraps). No step is wasted, unlike
    gymnasium's NEXT_STEP autoreset. ``start``: an optional fixed (N, 2) start shape placed after every reset
    (custom easy tasks); otherwise the env's random start. ``device``: where the learner wants observations,
    rewards and flags (default: the simulator's device); actions are moved to the simulator's device, so the rope
    can be simulated on the CPU (fused kernel) while the networks learn on a GPU, as SB3 does.
    """

    def __init__(self, core: BatchedShapeControl, start: torch.Tensor | None = None,
                 device: str | torch.device | None = None):
        self.core, self.num_envs = core, core.num_envs
        self.device = core.device if device is None else torch.device(device)
        self.start = None if start is None else torch.as_tensor(start, device=core.device, dtype=core.dtype)
        self.ep_return = torch.zeros(self.num_envs, dtype=torch.float64)
        self.ep_length = torch.zeros(self.num_envs, dtype=torch.int64)

    def _place_start(self, mask: torch.Tensor) -> None:
        if self.start is not None and bool(mask.any()):
            pos = self.core.pos.clone()
            pos[mask.to(pos.device)] = self.start
            self.core.set_state(pos=pos)

    def reset(self, seed: int | None = None, mask: torch.Tensor | None = None) -> Any:
        m = torch.ones(self.num_envs, dtype=torch.bool) if mask is None else mask.cpu()
        self.core.reset(seed=seed, mask=m)
        self._place_start(m)
        self.ep_return[m], self.ep_length[m] = 0.0, 0
        return self.observe()

    def to_learner(self, x: Any) -> Any:
        """A tensor or a dict of tensors on the learner's device."""
        if isinstance(x, dict):
            return {k: v.to(self.device) for k, v in x.items()}
        return x.to(self.device)

    def observe(self) -> Any:
        return self.to_learner(self.core.observe())

    def step(self, actions: torch.Tensor, mask: torch.Tensor | None = None):
        final_obs, reward, term, trunc, info = self.core.step(actions.to(self.core.device), mask=mask)
        active = torch.ones(self.num_envs, dtype=torch.bool) if mask is None else mask.cpu()
        self.ep_return += reward.double().cpu() * active      # bookkeeping from the simulator's tensors
        self.ep_length += active.long()
        done = (term | trunc).cpu()
        info = dict(info, ep_return=self.ep_return.clone(), ep_length=self.ep_length.clone())
        final_obs, reward, term, trunc = (self.to_learner(x) for x in (final_obs, reward, term, trunc))
        obs = self.reset(mask=done) if bool(done.any()) else final_obs
        return obs, reward, term, trunc, info, final_obs

    def state_dict(self) -> dict[str, Any]:
        c = self.core
        return {"pos": c.pos.cpu().clone(), "target": c.target.cpu().clone(), "steps": c.steps.cpu().clone(),
                "info": {k: v.cpu().clone() for k, v in c._info.items()}, "target_spec": c.target_spec,
                "rngs": [None if r is None else r.bit_generator.state for r in c.rngs],
                "ep_return": self.ep_return.clone(), "ep_length": self.ep_length.clone()}

    def load_state_dict(self, s: dict[str, Any]) -> None:
        c = self.core
        c.target_spec = s["target_spec"]
        c.set_state(pos=s["pos"], target=s["target"], steps=s["steps"])
        for k, v in s["info"].items():
            c._info[k] = v.to(c.device)
        for i, st in enumerate(s["rngs"]):
            if st is None:
                c.rngs[i] = None
            else:
                c.rngs[i] = seeding.np_random(0)[0]
                c.rngs[i].bit_generator.state = st
        self.ep_return, self.ep_length = s["ep_return"].clone(), s["ep_length"].clone()


def make_env(cfg, num_envs: int) -> TrainEnv:
    """The training/evaluation env of a config (targets, obs, actions, reward, params, optional fixed start)."""
    params = make_params(cfg)
    shaping = {k: getattr(cfg, k) for k in ("success_bonus", "step_penalty", "on_exit", "exit_penalty",
                                            "curve_max_turn_deg", "mark_end") if hasattr(cfg, k)}
    # ^ the task's episode-end rules and target family (PlaNet keeps the env's defaults)
    core = BatchedShapeControl(num_envs=num_envs, target=cfg.target, obs_type=cfg.obs, action_type=cfg.action,
                               reward=cfg.reward, max_steps=cfg.max_steps, success_tol=cfg.success_tol, params=params,
                               image_size=cfg.image_size, device=cfg.env_device or cfg.device, **shaping)
    start = None
    if cfg.start:
        start = torch.as_tensor(np.load(cfg.start) if isinstance(cfg.start, str) else np.asarray(cfg.start))
        if tuple(start.shape) != (params.n_nodes, 2):
            raise ValueError(f"start shape must be ({params.n_nodes}, 2), got {tuple(start.shape)}")
    return TrainEnv(core, start, device=cfg.device)


# ====================================================================== networks
def mlp(in_dim: int, hidden: Sequence[int], out_dim: int | None, act: type[nn.Module] = nn.ReLU) -> nn.Sequential:
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(in_dim, h), act()]
        in_dim = h
    if out_dim is not None:
        layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


class CNN(nn.Module):
    """Nature-DQN style encoder (SB3's NatureCNN) for (B, H, W, C) uint8 images: /255, channels first."""

    def __init__(self, in_channels: int, size: int, channels: Sequence[int] = (32, 64, 64), features_dim: int = 256):
        super().__init__()
        kernels, strides = (8, 4, 3), (4, 2, 1)
        layers: list[nn.Module] = []
        c = in_channels
        for out, k, s in zip(channels, kernels, strides):
            layers += [nn.Conv2d(c, out, k, s), nn.ReLU()]
            c = out
        self.conv = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():
            n = self.conv(torch.zeros(1, in_channels, size, size)).shape[1]
        self.head = nn.Sequential(nn.Linear(n, features_dim), nn.ReLU())
        self.out_dim = features_dim

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        return self.head(self.conv(img.permute(0, 3, 1, 2).float() / 255.0))


class KeypointCNN(nn.Module):
    """Spatial-softmax encoder (Levine et al. 2016, "End-to-end training of deep visuomotor policies") for (B, H, W, C)
    uint8 images: a stride-4 8x8 conv (SB3 NatureCNN's first layer, the cheap one on a CPU), a 3x3 conv to
    ``keypoints`` feature maps, and per map the softmax-weighted mean pixel position in [-1, 1]^2 (temperature
    learned). Out: 2 * keypoints coordinates. Positions, not a flattened map, are what this task needs (a move must
    remove ~1 cm of error with 15.6 mm pixels): the expectation over a soft map resolves a fraction of a pixel."""

    def __init__(self, in_channels: int, size: int, channels: Sequence[int] = (32,), keypoints: int = 32):
        super().__init__()
        layers: list[nn.Module] = []
        c = in_channels
        for i, out in enumerate(channels):
            layers += [nn.Conv2d(c, out, 8, 4, 2) if i == 0 else nn.Conv2d(c, out, 3, 1, 1), nn.ReLU()]
            c = out
        self.conv = nn.Sequential(*layers, nn.Conv2d(c, keypoints, 3, 1, 1))
        with torch.no_grad():
            h, w = self.conv(torch.zeros(1, in_channels, size, size)).shape[-2:]
        self.register_buffer("xs", torch.linspace(-1.0, 1.0, w), persistent=False)
        self.register_buffer("ys", torch.linspace(1.0, -1.0, h), persistent=False)   # row 0 is the top
        # a low starting temperature: with default conv init the maps differ by ~1e-2 across the picture, and at
        # temperature 1 every keypoint starts at the centre; at 0.01 they start spread (std ~0.1 over a batch)
        self.log_temperature = nn.Parameter(torch.tensor(math.log(0.01)))
        self.out_dim = 2 * keypoints

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        # ink, not light: 1 - x/255 makes the white table 0 and the thin rope the signal. On raw x/255 the maps are
        # near-uniform over the background, every keypoint sits at the centre (std over a batch ~2e-4 at init) and
        # a regression from them collapses to predicting the mean.
        maps = self.conv(1.0 - img.permute(0, 3, 1, 2).float() / 255.0)
        b, k, h, w = maps.shape
        p = torch.softmax(maps.flatten(2) / self.log_temperature.exp(), dim=-1).view(b, k, h, w)
        return torch.cat([(p.sum(2) * self.xs).sum(-1), (p.sum(3) * self.ys).sum(-1)], dim=1)


def random_shift(images: torch.Tensor, pad: int) -> torch.Tensor:
    """DrQ's augmentation (Kostrikov et al. 2021): (B, H, W, C) images padded by ``pad`` pixels (edge replicated)
    and cropped back at a random integer offset in [0, 2 pad]^2 per image: a random shift of up to ``pad`` pixels.
    Draws from torch's global generator (seeded, saved in checkpoints)."""
    if pad <= 0:
        return images
    b, h, w, _ = images.shape
    padded = F.pad(images.permute(0, 3, 1, 2).float(), (pad, pad, pad, pad), mode="replicate")
    dy, dx = torch.randint(0, 2 * pad + 1, (2, b, 1), device=images.device)
    rows = (dy + torch.arange(h, device=images.device))[:, :, None]            # (B, H, 1)
    cols = (dx + torch.arange(w, device=images.device))[:, None, :]            # (B, 1, W)
    out = padded.permute(0, 2, 3, 1)[torch.arange(b, device=images.device)[:, None, None], rows, cols]
    return out.to(images.dtype)


def shift_images(obs: Any, pad: int) -> Any:
    """An observation with its uint8 pictures shifted by ``random_shift``: rope and target pictures by the SAME
    offset (stacked along channels first), so they stay one scene; float parts and non-image observations as
    they are. A shift keeps every node-action label right: the node and the drag vector do not move with the
    camera (a pixel action, eq 2.5, would)."""
    if pad <= 0 or not isinstance(obs, dict):
        return obs
    keys = sorted(k for k, v in obs.items() if not v.is_floating_point())
    if not keys:
        return obs
    shifted = random_shift(torch.cat([obs[k] for k in keys], dim=-1), pad)
    return {**obs, **dict(zip(keys, shifted.split([obs[k].shape[-1] for k in keys], dim=-1)))}


ENCODERS = ("nature", "keypoints")


class ObsEncoder(nn.Module):
    """Any env observation -> a flat feature vector.

    Float parts (points, distance) are flattened, scaled by ``scale`` (1 / rope length: coordinates become O(1))
    and concatenated. uint8 image parts (image, target_image) are stacked along channels into ONE small CNN:
    ``encoder`` "nature" (SB3's NatureCNN) or "keypoints" (KeypointCNN).
    """

    def __init__(self, obs_example: Any, scale: float = 1.0, cnn_channels: Sequence[int] = (32, 64, 64),
                 features_dim: int = 256, encoder: str = "nature", keypoints: int = 32):
        super().__init__()
        ex = obs_example if isinstance(obs_example, dict) else {"obs": obs_example}
        self.is_dict = isinstance(obs_example, dict)
        self.float_keys = sorted(k for k, v in ex.items() if v.is_floating_point())
        self.image_keys = sorted(k for k, v in ex.items() if not v.is_floating_point())
        self.scale = scale
        self.out_dim = sum(int(np.prod(ex[k].shape[1:])) for k in self.float_keys)
        self.cnn = None
        if self.image_keys:
            img = ex[self.image_keys[0]]
            c = 3 * len(self.image_keys)
            self.cnn = (KeypointCNN(c, img.shape[1], cnn_channels, keypoints) if encoder == "keypoints"
                        else CNN(c, img.shape[1], cnn_channels, features_dim))
            self.out_dim += self.cnn.out_dim

    def forward(self, obs: Any) -> torch.Tensor:
        ex = obs if self.is_dict else {"obs": obs}
        parts = [ex[k].flatten(1).float() * self.scale for k in self.float_keys]
        if self.cnn is not None:
            parts.append(self.cnn(torch.cat([ex[k] for k in self.image_keys], dim=-1)))
        return torch.cat(parts, dim=1)


class Features(nn.Module):
    """A learner's network input: target-relative features (agents/hybrid.py), running-normalized when
    ``cfg.normalize_obs``, or SB3's encoder (``ObsEncoder``: flattened floats in rope lengths, NatureCNN on images).
    ``update_norm``: fold this batch into the normalizer's statistics first (only while collecting data)."""

    def __init__(self, obs_example: Any, cfg, length: float):
        super().__init__()
        self.relative, self.length = cfg.features == "relative", length
        if self.relative:
            self.enc = None
            self.out_dim = relative_features(obs_example, length).shape[1]
        else:
            self.enc = ObsEncoder(obs_example, 1.0 / length, cfg.cnn_channels, cfg.features_dim,
                                  getattr(cfg, "encoder", "nature"), getattr(cfg, "keypoints", 32))
            self.out_dim = self.enc.out_dim
        self.norm = RunningNorm(self.out_dim) if cfg.normalize_obs else None

    def forward(self, obs: Any, update_norm: bool = False) -> torch.Tensor:
        x = relative_features(obs, self.length) if self.relative else self.enc(obs)
        if self.norm is None:
            return x
        if update_norm:
            self.norm.update(x)
        return self.norm(x)


# ====================================================================== logging
class Logger:
    """CSV files ``<out>/<group>.csv`` (always) and TensorBoard scalars ``<group>/<key>`` when it is installed.

    ``resume_step``: rows logged after that step (by a run killed after its last checkpoint) are dropped, so the
    resumed run rewrites them and the CSVs read as one uninterrupted run.
    """

    def __init__(self, out: Path, resume_step: int | None = None, tensorboard: bool = True):
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.fields: dict[str, list[str]] = {}
        for path in self.out.glob("*.csv"):
            rows = read_csv(path)
            if resume_step is None:
                path.unlink()
                continue
            keep = [r for r in rows if float(r["step"]) <= resume_step]
            with open(path, "w", newline="") as f:
                if rows:
                    w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
                    w.writeheader()
                    w.writerows(keep)
                    self.fields[path.stem] = list(rows[0].keys())
        self.tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
                self.tb = SummaryWriter(str(self.out / "tb"), purge_step=resume_step)
            except ImportError:
                self.tb = None

    def log(self, group: str, step: int, values: dict[str, float]) -> None:
        row = {"step": step, **{k: float(v) for k, v in values.items()}}
        path = self.out / f"{group}.csv"
        new = group not in self.fields
        if new:
            self.fields[group] = list(row.keys())
        with open(path, "a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=self.fields[group], extrasaction="ignore")
            if new:
                w.writeheader()
            w.writerow(row)
        if self.tb is not None:
            for k, v in values.items():
                self.tb.add_scalar(f"{group}/{k}", float(v), step)

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()


def read_csv(path: Path | str) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


class EpisodeStats:
    """The last ``window`` finished training episodes (SB3's ep_info_buffer): return, length, success."""

    def __init__(self, window: int = 100):
        self.buf: deque = deque(maxlen=window)

    def add(self, info: dict[str, torch.Tensor], done: torch.Tensor) -> None:
        """Record the episodes that ended (``done``); success is ``info["is_success"]`` (a terminated episode may
        also be a failure: the env's on_exit="fail")."""
        success = info["is_success"].cpu()
        for i in done.cpu().nonzero().flatten().tolist():
            self.buf.append((float(info["ep_return"][i]), int(info["ep_length"][i]), bool(success[i])))

    def means(self) -> dict[str, float]:
        if not self.buf:
            return {}
        r, n, s = zip(*self.buf)
        return {"ep_reward": float(np.mean(r)), "ep_length": float(np.mean(n)), "success_rate": float(np.mean(s))}


# ====================================================================== checkpoints and RNG
def warn_if_large_buffer(rows: int, num_envs: int, obs: Any, limit: float = 4e9) -> None:
    """Warn (stderr) when a replay buffer of rows x num_envs observations like ``obs`` would exceed ``limit`` bytes."""
    obs_bytes = sum(v[0].numel() * v.element_size() for v in (obs.values() if isinstance(obs, dict) else [obs]))
    if rows * num_envs * obs_bytes > limit:
        print(f"warning: the replay buffer will hold {rows * num_envs * obs_bytes / 1e9:.1f} GB of observations; "
              f"lower it with --set buffer_size=N (images: 64x64 pairs are 24.6 kB each)", file=sys.stderr)


def rng_state() -> dict[str, Any]:
    s = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        s["cuda"] = torch.cuda.get_rng_state_all()
    return s


def set_rng_state(s: dict[str, Any]) -> None:
    torch.set_rng_state(s["torch"].cpu())      # a checkpoint loaded onto a GPU has its RNG states there too
    np.random.set_state(s["numpy"])
    random.setstate(s["python"])
    if "cuda" in s and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([t.cpu() for t in s["cuda"]])


@contextlib.contextmanager
def torch_threads(n: int):
    """Run with ``n`` torch intra-op CPU threads, then restore. On a small shared CPU, 1 thread is much faster for
    these small networks (measured on this project's 2-core machine under load: 0.3 s vs 15 s for the same run)."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def save_checkpoint(path: Path | str, state: dict[str, Any]) -> None:
    """Everything in one file, written atomically (temp file + rename: a kill never leaves half a checkpoint)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path | str) -> dict[str, Any]:
    """A checkpoint, loaded onto the CPU: every part (networks, optimizers, buffer, env, planners) moves its own
    tensors to its device when loaded, and RNG states must stay CPU tensors."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"--resume: no checkpoint at {path}")
    return torch.load(path, map_location="cpu", weights_only=False)


# ====================================================================== evaluation
@torch.no_grad()
def evaluate(policy: Callable[[Any, bool], torch.Tensor], env: TrainEnv | BatchedShapeControl, n_episodes: int,
             deterministic: bool = True, seed: int = 10_000) -> dict[str, Any]:
    """Run ``n_episodes`` full episodes (in waves of env.num_envs, wave w reset with seed + w * num_envs).

    ``policy(obs, deterministic) -> (B, A) actions``. Returns success_rate, mean_reward, mean_length,
    mean_final_error, episodes [{success, steps, final_error, return}], final ropes and targets.
    """
    env = env if isinstance(env, TrainEnv) else TrainEnv(env)
    b = env.num_envs
    t0 = time.perf_counter()
    episodes, ropes, targets = [], [], []
    wave = 0
    while len(episodes) < n_episodes:
        obs = env.reset(seed=seed + wave * b)
        wave += 1
        active = torch.ones(b, dtype=torch.bool)
        ret = torch.zeros(b, dtype=torch.float64)
        final_err = torch.zeros(b)
        success = torch.zeros(b, dtype=torch.bool)
        steps = torch.zeros(b, dtype=torch.int64)
        final_pos = env.core.pos.clone()
        while bool(active.any()):
            actions = policy(obs, deterministic)
            obs, reward, term, trunc, info = env.core.step(actions.to(env.core.device), mask=active)
            obs = env.to_learner(obs)
            ret += reward.double().cpu() * active
            steps += active.long()
            done = (term | trunc).cpu() & active
            final_err[done] = info["shape_error"].cpu().float()[done]
            success[done] = info["is_success"].cpu()[done]
            final_pos[done.to(final_pos.device)] = env.core.pos[done.to(final_pos.device)]
            active &= ~done
        for i in range(min(b, n_episodes - len(episodes))):
            episodes.append({"success": bool(success[i]), "steps": int(steps[i]),
                             "final_error": float(final_err[i]), "return": float(ret[i])})
            ropes.append(final_pos[i].detach().cpu().clone())
            targets.append(env.core.target[i].detach().cpu().clone())   # a copy: the next wave resets in place
    return {"success_rate": float(np.mean([e["success"] for e in episodes])),
            "mean_reward": float(np.mean([e["return"] for e in episodes])),
            "mean_length": float(np.mean([e["steps"] for e in episodes])),
            "mean_final_error": float(np.mean([e["final_error"] for e in episodes])),
            "episodes": episodes, "ropes": torch.stack(ropes), "targets": torch.stack(targets),
            "s_per_episode": (time.perf_counter() - t0) / len(episodes)}


def heldout_envs(cfg) -> dict[str, tuple[Any, TrainEnv]]:
    """One evaluation env per entry of ``cfg.eval_targets`` (target shapes the learner does not train on, e.g.
    planners/targets/arc.npy), keyed by a label (the file's stem, or the name): label -> (spec, env). Built before
    training, so a bad target is an error at once, not after the run."""
    envs: dict[str, tuple[Any, TrainEnv]] = {}
    for spec in getattr(cfg, "eval_targets", None) or []:
        label = Path(spec).stem if str(spec).endswith((".npy", ".yaml", ".yml")) else str(spec)
        if label in envs:
            raise ValueError(f"eval_targets: {spec!r} repeats the label {label!r}")
        envs[label] = (spec, make_env(dataclasses.replace(cfg, target=spec), min(cfg.eval_episodes, 32)))
    return envs


def evaluate_heldout(policy: Callable[[Any, bool], torch.Tensor], envs: dict[str, tuple[Any, TrainEnv]],
                     cfg, policy_for: Callable[[TrainEnv], Callable] | None = None) -> dict[str, Any]:
    """``evaluate`` on every held-out target (as many episodes, from the same start seeds, as the main evaluation):
    label -> {target, success_rate, mean_final_error, episodes}. ``policy_for(env)``: a policy bound to that env
    (PlaNet's planners keep per-rope state), instead of ``policy``."""
    out = {}
    for label, (spec, env) in envs.items():
        r = evaluate(policy if policy_for is None else policy_for(env), env, cfg.eval_episodes, seed=cfg.eval_seed)
        out[label] = {"target": str(spec), "success_rate": r["success_rate"],
                      "mean_final_error": r["mean_final_error"],
                      "episodes": [{k: e[k] for k in ("success", "steps", "final_error")} for e in r["episodes"]]}
    return out


def eval_row(result: dict[str, Any]) -> dict[str, float]:
    return {k: result[k] for k in ("success_rate", "mean_reward", "mean_length", "mean_final_error")}


def write_results(out: Path, method: str, cfg, result: dict[str, Any], env_steps: int, wall_s: float,
                  max_pictures: int = 8, heldout: dict[str, Any] | None = None,
                  extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """``results.json`` (the fields every method writes: method, target, seed, success_rate, episodes, env_steps,
    wall_s; ``heldout``: per held-out target, its success rate and episodes;
    ``extra``: a learner's own figures, e.g. SAC's ms per update) and ``eval_episodes.png`` (final shapes against
    targets)."""
    out = Path(out)
    eps = result["episodes"]
    results = {"method": method, "target": cfg.target if isinstance(cfg.target, str) else "custom",
               "seed": cfg.seed, "success_rate": result["success_rate"],
               "episodes": [{"success": e["success"], "steps": e["steps"], "final_error": e["final_error"]}
                            for e in eps],
               "env_steps": int(env_steps), "wall_s": float(wall_s),
               "mean_reward": result["mean_reward"], "mean_length": result["mean_length"],
               "eval_s_per_episode": result.get("s_per_episode"),
               "obs": cfg.obs, "action": cfg.action, "reward": cfg.reward}
    results.update(extra or {})
    if heldout:
        results["heldout"] = heldout
    (out / "results.json").write_text(json.dumps(results, indent=2))
    try:
        import matplotlib
        matplotlib.use("Agg")
        from diffdlo.render import plot_ropes
        import matplotlib.pyplot as plt
        k = min(max_pictures, len(eps))
        titles = [f"{'success' if e['success'] else 'fail'}: {e['final_error'] * 100:.2f} cm, {e['steps']} steps"
                  for e in eps[:k]]
        fig = plot_ropes(result["ropes"][:k], result["targets"][:k], path=out / "eval_episodes.png", titles=titles)
        plt.close(fig)
    except ImportError:   # matplotlib is the optional [plot] extra
        print("matplotlib not installed: no eval_episodes.png", file=sys.stderr)
    return results


# ====================================================================== command line
def positive_int(text: str) -> int:
    try:
        v = int(float(text)) if "e" in text.lower() else int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def make_parser(prog: str, doc: str | None) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=prog, description=(doc or "").split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--preset", default=None,
                    help="named defaults: 'tuned' (params/<algo>.yaml, the default) or e.g. 'sb3-default' "
                         "(params/<algo>-sb3-default.yaml)")
    ap.add_argument("--config", default=None, help="YAML of defaults (instead of a preset)")
    ap.add_argument("--target", default=None, help=f"'random' or one of {list(TARGET_NAMES)} or a .npy/.yaml path")
    ap.add_argument("--obs", choices=OBS_TYPES, default=None, help="observation type")
    ap.add_argument("--action", choices=ACTION_TYPES, default=None, help="action type")
    ap.add_argument("--reward", choices=REWARDS, default=None, help="reward function")
    ap.add_argument("--total-steps", type=positive_int, default=None, help="env transitions (all envs together)")
    ap.add_argument("--num-envs", type=positive_int, default=None, help="ropes stepped together")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--out", required=True, help="output directory (logs, checkpoint, results.json, pictures)")
    ap.add_argument("--device", default=None, help="torch device, e.g. cpu or cuda")
    ap.add_argument("--resume", action="store_true",
                    help="continue from <out>/checkpoint.pt up to --total-steps (config from the checkpoint)")
    ap.add_argument("--eval-every", type=positive_int, default=None, help="env steps between evaluations")
    ap.add_argument("--eval-episodes", type=positive_int, default=None)
    ap.add_argument("--checkpoint-every", type=positive_int, default=None, help="env steps between checkpoints")
    ap.add_argument("--max-steps", type=positive_int, default=None, help="actions per episode")
    ap.add_argument("--params", default=None, help="cable params name or YAML path")
    ap.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default 1)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override any config key (YAML value), e.g. --set batch_size=128 --set hidden=[64,64]")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


CLI_KEYS = ("threads", "target", "obs", "action", "reward", "total_steps", "num_envs", "seed", "device", "eval_every",
            "eval_episodes", "checkpoint_every", "max_steps", "params")


def config_from_args(cls, algo: str, args: argparse.Namespace, ap: argparse.ArgumentParser):
    overrides: dict[str, Any] = {}
    for item in args.set:
        if "=" not in item:
            ap.error(f"--set expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        overrides[key.strip()] = yaml.safe_load(value)
    for key in CLI_KEYS:
        v = getattr(args, key)
        if v is not None:
            overrides[key] = v
    if args.config and args.preset:
        ap.error("give --config or --preset, not both")
    try:
        return load_config(cls, args.config or preset_path(algo, args.preset), overrides)
    except (ValueError, TypeError) as exc:
        ap.error(str(exc))


def run_cli(cls, algo: str, doc: str | None, train: Callable, argv: list[str] | None = None) -> int:
    """Parse, build the config (or take it from the checkpoint with --resume), train, report."""
    ap = make_parser(f"python -m agents.{algo}", doc)
    args = ap.parse_args(argv)
    out = Path(args.out)
    if args.resume:
        ckpt = out / CHECKPOINT
        if not ckpt.exists():
            ap.error(f"--resume: no checkpoint at {ckpt}")
        saved = torch.load(ckpt, map_location="cpu", weights_only=False)["config"]
        changes = {k: getattr(args, k) for k in ("total_steps", "eval_every", "eval_episodes", "checkpoint_every",
                                                  "device") if getattr(args, k) is not None}
        cfg = dataclasses.replace(cls(**saved), **changes)
        check_config(cfg)
    else:
        cfg = config_from_args(cls, algo, args, ap)
    try:
        res = train(cfg, out, resume=args.resume, progress=not args.no_progress)
    except (ValueError, TargetError, ParamsError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{algo}: success rate {res['success_rate']:.2f} over {len(res['episodes'])} eval episodes, "
          f"{res['env_steps']} env steps, {res['wall_s']:.1f} s -> {out}/results.json")
    return 0


def fmt_postfix(success: float | None, **extra: float) -> dict[str, str]:
    d = {"success": "n/a" if success is None or math.isnan(success) else f"{success:.2f}"}
    d.update({k: f"{v:.3g}" for k, v in extra.items()})
    return d


