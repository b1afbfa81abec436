"""Network builders and observation encoders shared by the learners: MLPs, SB3's NatureCNN, a spatial-softmax
keypoint CNN, DrQ's random image shift, ``ObsEncoder`` (any observation -> a flat vector) and ``Features`` (the
learners' network input, from ``agents.common.config.InputOptions``)."""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from agents.models.hybrid import RunningNorm, relative_features


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
    """A learner's network input: target-relative features (agents/models/hybrid.py), running-normalized when
    ``cfg.normalize_obs``, or SB3's encoder (``ObsEncoder``: flattened floats in rope lengths, NatureCNN on images).
    ``update_norm``: fold this batch into the normalizer's statistics first (only while collecting data)."""

    def __init__(self, obs_example: Any, cfg, length: float):
        """``cfg``: the learner's InputOptions."""
        super().__init__()
        self.relative, self.length = cfg.features == "relative", length
        if self.relative:
            self.enc = None
            self.out_dim = relative_features(obs_example, length).shape[1]
        else:
            self.enc = ObsEncoder(obs_example, 1.0 / length, cfg.cnn_channels, cfg.features_dim, cfg.encoder,
                                  cfg.keypoints)
            self.out_dim = self.enc.out_dim
        self.norm = RunningNorm(self.out_dim) if cfg.normalize_obs else None

    def forward(self, obs: Any, update_norm: bool = False) -> torch.Tensor:
        x = relative_features(obs, self.length) if self.relative else self.enc(obs)
        if self.norm is None:
            return x
        if update_norm:
            self.norm.update(x)
        return self.norm(x)
