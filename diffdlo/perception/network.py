"""Perception: the rope's node positions, in order, read back from the env's own pictures.

The simulator labels its pictures for free, so the network is trained on rendered shapes (``diffdlo.tasks.image``) drawn
from the env's own distributions: settled random start shapes (thesis sigma), the shapes that moves make of them,
the named straight targets and smooth random curves, each turned and placed anywhere in the view. A picture must
carry the end marker (env option ``mark_end=True``): without it a rope and its reversal draw the same picture.

Two stages (chosen by measurement, docs/PERCEPTION.md):

1. ``PerceptionNet``: a small CNN with coordinate channels regresses the N node positions from the picture's ink;
2. ``refine``: analysis by synthesis. The nodes are moved by Gauss-Newton-like Adam steps so that the env's own
   renderer draws them onto the picture (coverage and end marker), with the links held at their rest length. The
   renderer is differentiable, so this inverts it exactly where the picture is unambiguous.

``Perception`` holds both and maps an image observation {image, target_image} (B, S, S, 3) uint8 to the points
observation {node_poses, target_poses} (B, N, 2) float32, which is what the env's obs_type "perceived" returns and
what planners and learners read. ``python -m diffdlo.perception --out DIR`` trains it and writes ``results.json``
and ``perception.pt`` (loaded by path: ``Perception.load(path)``); ``--init CHECKPOINT`` fine-tunes one, and
``--pegs-share`` trains on ropes among a route's pegs too (diffdlo/perception/boards.py).

Among a route's pegs (known: the board's fixtures), ``read(images, rope, pegs)`` gives the network the pictures with
the pegs taken out (``unpeg``) and the refinement draws them (docs/PERCEPTION.md, "Among pegs").
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ..tasks import image as rimage
from ..planar.params import CableParams, load_params
from ..planar.shapes import random_curve, random_shape

CHECKPOINT = "perception.pt"
FORMAT = "diffdlo-perception-1"
DEFAULT_VIEW_SIZE = 1.0


class PerceptionError(ValueError):
    """A perception checkpoint that is missing, foreign or made for other pictures, or pictures it cannot read."""


# ====================================================================== pictures -> network input
def ink(images: torch.Tensor) -> torch.Tensor:
    """(B, S, S, 3) uint8 pictures -> (B, 3, S, S) float ink in [0, 1] (0: the white table). Colour-blind to which
    of the env's palettes drew it: one network reads rope and target pictures alike."""
    return 1.0 - images.permute(0, 3, 1, 2).float() / 255.0


def draw(points: torch.Tensor, size: int, view_size: float, rope: bool = True,
         board: torch.Tensor | None = None) -> torch.Tensor:
    """(B, N, 2) curves -> (B, S, S, 3) float pictures in [0, 255] as ``diffdlo.tasks.task.observe`` draws them with the
    end marker (before rounding to uint8): differentiable with respect to ``points``. ``board``: (B, S, S) coverage
    of a route's pegs (``board_coverage``), drawn grey under the curve as the env draws it; None: no pegs."""
    line = rimage.ROPE_COLOR if rope else rimage.TARGET_COLOR
    dot = rimage.ROPE_END_COLOR if rope else rimage.TARGET_END_COLOR
    img = torch.tensor(rimage.BACKGROUND, dtype=points.dtype, device=points.device)
    layers = ((rimage.coverage(points, size, view_size), line), (rimage.end_marker(points, size, view_size), dot))
    if board is not None:
        layers = ((board.to(points.dtype), rimage.PEG_COLOR),) + layers
    for cov, color in layers:
        a = cov.unsqueeze(-1)
        img = img * (1 - a) + torch.tensor(color, dtype=points.dtype, device=points.device) * a
    return img


def board_coverage(pegs: torch.Tensor | None, size: int, view_size: float,
                   batch: int | None = None) -> torch.Tensor | None:
    """(B, K, 3) pegs (x, y, radius) [m], rows of radius 0 empty (the env's padded ``pegs``) -> (B, S, S) their
    coverage as the env draws them (``diffdlo.tasks.image.discs``); None stays None. ``batch``: the pictures' count,
    which the pegs must match (a PerceptionError names a mismatch)."""
    if pegs is None:
        return None
    pegs = torch.as_tensor(pegs)
    if pegs.ndim != 3 or pegs.shape[-1] != 3 or (batch is not None and pegs.shape[0] != batch):
        raise PerceptionError(f"pegs must be ({batch if batch is not None else 'B'}, K, 3) of (x, y, radius) [m], one "
                              f"board per picture, got {tuple(pegs.shape)}")
    if not bool(torch.isfinite(pegs).all()) or bool((pegs[..., 2] < 0).any()):
        raise PerceptionError("pegs must be finite with radius >= 0 (0: an empty row), got "
                              f"{pegs.detach().cpu().tolist()}")
    return rimage.discs(pegs.to(torch.float32), size, view_size)


def render_uint8(points: torch.Tensor, size: int, view_size: float, rope: bool = True,
                 pegs: torch.Tensor | None = None) -> torch.Tensor:
    """(B, N, 2) curves -> the env's (B, S, S, 3) uint8 pictures of them with the end marker; ``pegs`` (B, K, 3): a
    route's board drawn under them (None: none)."""
    board = board_coverage(pegs, size, view_size, len(points))
    return draw(points.detach(), size, view_size, rope,
                None if board is None else board.to(points.device)).round().clamp(0, 255).to(torch.uint8)


def unpeg(images: torch.Tensor, pegs: torch.Tensor, view_size: float, rope: bool = True,
          end_ridge: float = 100.0) -> torch.Tensor:
    """The env's pictures of a curve over a route's known pegs (B, S, S, 3) uint8 -> the same pictures with the pegs
    taken out, as if drawn without them (uint8): what a network trained on peg-free pictures reads.

    The env blends its layers over the table: the pegs' coverage a (known from ``pegs`` (B, K, 3)), then the line,
    then the end marker, so a pixel is B' u + L v + E w with B' = table (1 - a) + grey a, u + v + w = 1, and L, E
    the line's and the marker's colours (the rope's or, ``rope`` False, the target's). Where a > 0 the (v, w) that
    best explain the pixel's three channels are solved for (least squares; ``end_ridge`` [(0-255 units)^2] holds w
    at 0 where the pixel does not ask for the marker: the target's blue and amber and the grey are nearly collinear)
    and the pixel is redrawn as table u + L v + E w. Exact but for the pictures' rounding; other pixels unchanged."""
    board = board_coverage(pegs, images.shape[1], view_size, len(images)).to(images.device)        # (B, S, S)
    line = rimage.ROPE_COLOR if rope else rimage.TARGET_COLOR
    dot = rimage.ROPE_END_COLOR if rope else rimage.TARGET_END_COLOR
    kw = dict(dtype=torch.float32, device=images.device)
    table, grey, lc, ec = (torch.tensor(c, **kw) for c in (rimage.BACKGROUND, rimage.PEG_COLOR, line, dot))
    a = board.unsqueeze(-1)
    under = table * (1 - a) + grey * a                                        # (B, S, S, 3) what lies under the line
    img = images.to(torch.float32)
    d_line, d_dot, r = lc - under, ec - under, img - under
    m11, m12 = (d_line * d_line).sum(-1), (d_line * d_dot).sum(-1)
    m22 = (d_dot * d_dot).sum(-1) + end_ridge
    b1, b2 = (d_line * r).sum(-1), (d_dot * r).sum(-1)
    det = (m11 * m22 - m12 * m12).clamp_min(1e-6)
    v = ((m22 * b1 - m12 * b2) / det).clamp(0.0, 1.0)
    w = ((m11 * b2 - m12 * b1) / det).clamp(0.0, 1.0)
    w = torch.minimum(w, 1 - v)
    clean = table * (1 - v - w).unsqueeze(-1) + lc * v.unsqueeze(-1) + ec * w.unsqueeze(-1)
    out = torch.where(board.unsqueeze(-1) > 0, clean, img)
    return out.round().clamp(0, 255).to(torch.uint8)


# ====================================================================== training shapes
def sample_shapes(n: int, p: CableParams, generator: torch.Generator, sim=None, max_moves: int = 8,
                  spread: float = 0.2) -> torch.Tensor:
    """(n, N, 2) shapes from the env's distributions, turned uniformly and centred uniformly in [-spread, spread]^2:
    a quarter settled random starts moved 0..max_moves times (random node, drag in the action box; ``sim`` a
    Simulator, None: unmoved and unsettled), a quarter straight lines, a quarter random curves, a quarter random
    starts as drawn (kinks included)."""
    q = n // 4
    starts = random_shape(q, p, generator, dtype=torch.float64)
    if sim is not None:
        starts = sim.settle(starts.to(sim.dtype)).double()
        moves = torch.randint(0, max_moves + 1, (q,), generator=generator)
        for k in range(max_moves):
            node = torch.randint(0, p.n_nodes, (q,), generator=generator)
            delta = (torch.rand(q, 2, generator=generator, dtype=torch.float64) * 2 - 1) * p.action_scale
            delta = delta * (moves > k).unsqueeze(-1)
            starts = sim.move(starts.to(sim.dtype), node, delta.to(sim.dtype)).double()
            starts = starts - starts.mean(1, keepdim=True)
    s = torch.linspace(-p.length / 2, p.length / 2, p.n_nodes, dtype=torch.float64)
    lines = torch.stack([s, torch.zeros_like(s)], -1).expand(q, -1, -1)
    curves = random_curve(q, p, generator, dtype=torch.float64)
    raw = random_shape(n - 3 * q, p, generator, dtype=torch.float64)
    shapes = torch.cat([starts, lines, curves, raw])
    theta = torch.rand(n, generator=generator, dtype=torch.float64) * 2 * math.pi
    c, si = torch.cos(theta), torch.sin(theta)
    rot = torch.stack([torch.stack([c, -si], -1), torch.stack([si, c], -1)], -2)          # (n, 2, 2)
    shapes = (shapes - shapes.mean(1, keepdim=True)) @ rot.transpose(1, 2)
    shift = (torch.rand(n, 1, 2, generator=generator, dtype=torch.float64) * 2 - 1) * spread
    return shapes + shift


# ====================================================================== the network
class PerceptionNet(nn.Module):
    """Picture (B, S, S, 3) uint8 -> node positions (B, N, 2) [m].

    Ink and two coordinate channels (CoordConv) through stride-2 conv stages down to an 8 x 8 map, then an MLP
    regresses the N positions in view units. ``size`` must be 8 times a power of two (64, 128, 256)."""

    def __init__(self, size: int, n_nodes: int, view_size: float, width: int = 16, hidden: int = 512):
        super().__init__()
        stages = int(round(math.log2(size / 8)))
        if size < 16 or 8 * 2 ** stages != size:
            raise PerceptionError(f"image_size must be 8 times a power of two (16, 32, 64, 128, 256), got {size}")
        self.size, self.n_nodes, self.view_size, self.width, self.hidden = size, n_nodes, view_size, width, hidden
        layers: list[nn.Module] = []
        c = 5
        for i in range(stages):                    # stride 2 per stage, down to 8 x 8
            c_out = min(width * 2 ** max(i - stages + 3, 0), 4 * width)
            layers += [nn.Conv2d(c, c_out, 3, stride=2, padding=1), nn.ReLU()]
            if i >= stages - 2:                    # a second conv at the two coarsest scales
                layers += [nn.Conv2d(c_out, c_out, 3, padding=1), nn.ReLU()]
            c = c_out
        self.conv = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c * 64, hidden), nn.ReLU(), nn.Linear(hidden, 2 * n_nodes))
        lin = torch.linspace(-1, 1, size)
        gy, gx = torch.meshgrid(-lin, lin, indexing="ij")          # row 0 at the top: y = +1
        self.register_buffer("coords", torch.stack([gx, gy]).unsqueeze(0), persistent=False)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = ink(images)
        x = torch.cat([x, self.coords.expand(x.shape[0], -1, -1, -1).to(x.dtype)], 1)
        return self.head(self.conv(x)).view(-1, self.n_nodes, 2) * (self.view_size / 2)


# ====================================================================== analysis by synthesis
def refine(points: torch.Tensor, images: torch.Tensor, rest_length: float, view_size: float, rope: bool = True,
           iters: int = 60, lr_px: float = 0.5, length_weight: float = 0.1,
           pegs: torch.Tensor | None = None) -> torch.Tensor:
    """Move the nodes ``points`` (B, N, 2) so that the env's renderer draws them onto ``images`` (B, S, S, 3) uint8:
    Adam on the mean squared pixel difference plus ``length_weight`` x the links' squared relative stretch (the
    settled rope is at its rest length to a fraction of a millimetre), steps of ``lr_px`` pixels decaying to 0.
    ``pegs`` (B, K, 3): the route's board the pictures show (known fixtures): the synthesized pictures draw it too,
    under the curve, so that like is compared with like. Returns the refined points (no gradient)."""
    if iters <= 0:
        return points.detach()
    size = images.shape[1]
    board = board_coverage(pegs, size, view_size, len(images))
    board = None if board is None else board.to(images.device)
    px = view_size / size
    target = images.to(torch.float32)
    x = points.detach().to(torch.float32).clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=lr_px * px)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 1.0 - i / iters)
    for _ in range(iters):
        with torch.enable_grad():
            img = draw(x, size, view_size, rope, board)
            pix = ((img - target) / 255.0).pow(2).flatten(1).sum(1)
            link = ((x[:, 1:] - x[:, :-1]).pow(2).sum(-1) + 1e-12).sqrt()     # finite gradient at length 0
            stretch = (link / rest_length - 1).pow(2).sum(1)
            loss = (pix + length_weight * 100 * stretch).sum()
        opt.zero_grad()
        loss.backward()
        x.grad = torch.nan_to_num(x.grad, nan=0.0, posinf=0.0, neginf=0.0)   # a pixel exactly on a node: sqrt'(0)
        opt.step()
        sched.step()
    out = x.detach()
    bad = ~torch.isfinite(out).all(-1).all(-1)
    if bool(bad.any()):
        import warnings
        warnings.warn(f"perception: refinement diverged on {int(bad.sum())} of {len(bad)} pictures; their "
                      "network reading is returned", RuntimeWarning, stacklevel=2)
    return torch.where(bad[:, None, None], points.detach().to(out.dtype), out)


# ====================================================================== the perception a run loads
class Perception:
    """A trained ``PerceptionNet`` and the refinement settings: image observations in, points out.

    ``read(images, rope)`` -> (B, N, 2) float32 positions; ``perceive(obs)`` maps the env's obs_type "image"
    observation {image, target_image} to {node_poses, target_poses}. ``refine_iters`` = 0 reads with the net alone.
    """

    def __init__(self, net: PerceptionNet, rest_length: float, refine_iters: int = 60, meta: dict | None = None):
        self.net = net.eval()
        self.rest_length = float(rest_length)
        self.refine_iters = int(refine_iters)
        self.meta = dict(meta or {})

    @property
    def image_size(self) -> int:
        return self.net.size

    @property
    def n_nodes(self) -> int:
        return self.net.n_nodes

    @property
    def view_size(self) -> float:
        return self.net.view_size

    def to(self, device: torch.device | str) -> "Perception":
        self.net.to(device)
        return self

    def check_pictures(self, images: torch.Tensor, what: str = "images") -> None:
        s = self.image_size
        if images.ndim != 4 or tuple(images.shape[1:]) != (s, s, 3) or images.dtype != torch.uint8:
            raise PerceptionError(f"{what}: this perception reads (B, {s}, {s}, 3) uint8 pictures, got "
                                  f"{tuple(images.shape)} {images.dtype}")

    @torch.no_grad()
    def read(self, images: torch.Tensor, rope: bool = True, pegs: torch.Tensor | None = None) -> torch.Tensor:
        """(B, S, S, 3) uint8 pictures -> (B, N, 2) float32 positions. ``pegs`` (B, K, 3) (x, y, radius) [m], rows
        of radius 0 empty: the route's board the pictures show (known fixtures): the network reads the pictures with
        the pegs taken out (``unpeg``) and the refinement draws them (docs/PERCEPTION.md, "Among pegs")."""
        self.check_pictures(images)
        images = images.to(self.net.coords.device)
        if pegs is not None:                 # the network reads the picture with the known pegs taken out
            pegs = torch.as_tensor(pegs).to(images.device)
            points = self.net(unpeg(images, pegs, self.view_size, rope))          # (a bad board is named there)
        else:
            points = self.net(images)
        if self.refine_iters > 0:
            points = refine(points, images, self.rest_length, self.view_size, rope, iters=self.refine_iters,
                            pegs=pegs)
        return points.to(torch.float32)

    def perceive(self, obs: dict[str, torch.Tensor], target: torch.Tensor | None = None,
                 pegs: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """{image, target_image} -> {node_poses, target_poses}; ``target``: the target's positions when already
        perceived (the env reads a target once per episode). ``pegs`` (B, K, 3): a route's board, known, drawn in
        both pictures: the reading takes it into account and the observation carries it as is ("pegs")."""
        nodes = self.read(obs["image"], rope=True, pegs=pegs)
        if target is None:
            target = self.read(obs["target_image"], rope=False, pegs=pegs)
        out = {"node_poses": nodes, "target_poses": target.to(nodes, copy=True)}
        if pegs is not None:
            out["pegs"] = torch.as_tensor(pegs).detach().to(nodes, copy=True)
        return out

    # ----------------------------------------------------------------- checkpoint: tensors and plain values only
    def save(self, path: Path | str) -> None:
        from ..utils.files import replacing
        net = self.net
        meta = {**self.meta, "image_size": net.size, "n_nodes": net.n_nodes, "view_size": net.view_size,
                "width": net.width, "hidden": net.hidden, "rest_length": self.rest_length,
                "refine_iters": self.refine_iters}
        with replacing(path) as tmp:
            torch.save({"format": FORMAT, "meta": meta,
                        "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()}}, tmp)

    @classmethod
    def load(cls, path: Path | str, device: torch.device | str = "cpu", refine_iters: int | None = None,
             image_size: int | None = None, n_nodes: int | None = None,
             view_size: float | None = None) -> "Perception":
        """Load a checkpoint written by ``save`` (``torch.load(weights_only=True)``: no code runs). The optional
        image_size, n_nodes, view_size are what the caller's pictures are: a mismatch is a PerceptionError."""
        path = Path(path)
        if path.is_dir():
            path = path / CHECKPOINT
        if not path.is_file():
            raise PerceptionError(f"perception checkpoint {str(path)!r} not found (train one with "
                                  f"python -m diffdlo.perception --out DIR)")
        try:
            ck = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:            # pickle errors, truncated files: name the file
            raise PerceptionError(f"perception checkpoint {str(path)!r} cannot be read: {exc}") from None
        if not isinstance(ck, dict) or ck.get("format") != FORMAT:
            raise PerceptionError(f"{str(path)!r} is not a perception checkpoint (format {FORMAT!r})")
        m = ck["meta"]
        for name, want in (("image_size", image_size), ("n_nodes", n_nodes), ("view_size", view_size)):
            if want is not None and m[name] != want:
                raise PerceptionError(f"perception checkpoint {str(path)!r} reads {name}={m[name]}, the pictures "
                                      f"have {name}={want}")
        net = PerceptionNet(m["image_size"], m["n_nodes"], m["view_size"], m["width"], m["hidden"])
        net.load_state_dict(ck["state_dict"])
        return cls(net.to(device), m["rest_length"], m["refine_iters"] if refine_iters is None else refine_iters,
                   meta=m)


# ====================================================================== training
@dataclasses.dataclass
class TrainConfig:
    image_size: int = 64
    steps: int = 12000            # Adam steps of `batch` freshly turned, placed and drawn pictures each
    batch: int = 128
    pool: int = 4096              # shapes drawn once (sample_shapes); every picture turns and places one anew
    lr: float = 1e-3              # cosine-decayed to 0 over `steps`
    width: int = 16
    hidden: int = 512
    spread: float = 0.2           # centroid placed uniformly in [-spread, spread]^2 [m]
    refine_iters: int = 60        # analysis-by-synthesis steps the checkpoint applies after the net (docs/PERCEPTION.md)
    eval_pictures: int = 256      # held-out rope and target pictures (seed + 1)
    eval_every: int = 1000
    seed: int = 0
    pegs_share: float = 0.0       # share of each batch drawn from ropes on random boards, their pegs drawn (routes)
    board_pool: int = 2048        # ropes on random boards drawn once when pegs_share > 0 (diffdlo.perception.boards)
    init: str = ""                # fine-tune: start from this checkpoint's weights ("": from scratch)


def augmented_batch(pool: torch.Tensor, cfg: TrainConfig, generator: torch.Generator,
                    view_size: float, boards: tuple[torch.Tensor, torch.Tensor] | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch of pictures (B, S, S, 3) uint8 and their labels (B, N, 2) float32: pool shapes turned uniformly,
    placed uniformly, drawn in the rope's or the target's palette with equal odds. ``boards`` (ropes (M, N, 2), pegs
    (M, K, 3)), with cfg.pegs_share > 0: each picture is, with odds pegs_share, one of those ropes drawn over its
    pegs, turned and placed with them."""
    b = cfg.batch
    x = pool[torch.randint(0, len(pool), (b,), generator=generator)]
    pegs = None
    if boards is not None and cfg.pegs_share > 0:          # no draw otherwise: the peg-free training is unchanged
        on_board = torch.rand(b, generator=generator) < cfg.pegs_share
        pick = torch.randint(0, len(boards[0]), (b,), generator=generator)
        x = torch.where(on_board[:, None, None], boards[0][pick], x)
        pegs = torch.where(on_board[:, None, None], boards[1][pick], torch.zeros_like(boards[1][pick]))
    theta = torch.rand(b, generator=generator, dtype=torch.float64) * 2 * math.pi
    c, s = theta.cos(), theta.sin()
    rot = torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    shift = (torch.rand(b, 1, 2, generator=generator, dtype=torch.float64) * 2 - 1) * cfg.spread
    centre = x.mean(1, keepdim=True)
    x = ((x - centre) @ rot.transpose(1, 2) + shift).float()
    if pegs is not None:                                   # the board turns and moves with its rope
        xy = (pegs[..., :2] - centre) @ rot.transpose(1, 2) + shift
        pegs = torch.cat([xy, pegs[..., 2:]], -1).float()
    rope = torch.rand(b, generator=generator) < 0.5
    images = torch.where(rope[:, None, None, None], render_uint8(x, cfg.image_size, view_size, True, pegs),
                         render_uint8(x, cfg.image_size, view_size, False, pegs))
    return images, x


def board_pool(n: int, p: CableParams, generator: torch.Generator, sim) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` ropes on random boards, a quarter of each kind of ``boards.BOARD_KINDS`` (the last kind takes the rest),
    and their pegs: (n, N, 2), (n, K, 3) float64."""
    from .boards import BOARD_KINDS, board_shapes
    q = n // len(BOARD_KINDS)
    parts = [board_shapes(q if i < len(BOARD_KINDS) - 1 else n - q * (len(BOARD_KINDS) - 1), p, generator, sim, kind)
             for i, kind in enumerate(BOARD_KINDS)]
    return torch.cat([r for r, _, _ in parts]), torch.cat([pg for _, pg, _ in parts])


def held_out(p: CableParams, cfg: TrainConfig, sim, view_size: float) -> dict[str, torch.Tensor]:
    """Pictures no training step drew (seed + 1): ropes as the env shows them (settled random starts after 0-8
    random moves, placed near the origin) and targets (the named straight lines and random curves at the origin,
    turned)."""
    g = torch.Generator().manual_seed(cfg.seed + 1)
    n = cfg.eval_pictures
    q = n // 4
    ropes = torch.cat([sample_shapes(4 * q, p, g, sim, spread=cfg.spread)[:q] for _ in range(4)]).float()
    targets = sample_shapes(4 * n, p, g, None, spread=0.0)[q:3 * q].float()      # the lines and the curves
    targets = torch.cat([targets, targets.flip(1)])[:n]
    test = {"ropes": ropes, "rope_images": render_uint8(ropes, cfg.image_size, view_size, True),
            "targets": targets, "target_images": render_uint8(targets, cfg.image_size, view_size, False)}
    if cfg.pegs_share > 0:          # and ropes among pegs (drawn after the others: those stay the same)
        board_ropes, pegs = board_pool(n, p, g, sim)
        board_ropes, pegs = board_ropes.float(), pegs.float()
        test.update(peg_ropes=board_ropes, peg_pegs=pegs,
                    peg_rope_images=render_uint8(board_ropes, cfg.image_size, view_size, True, pegs))
    return test


def node_error(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Per picture mean node distance [m]."""
    return (pred - truth).norm(dim=-1).mean(-1)


def evaluate(perception: Perception, test: dict[str, torch.Tensor], chunk: int = 64) -> dict[str, float]:
    out: dict[str, float] = {}
    sets = [("node", test["rope_images"], test["ropes"], True, None),
            ("target", test["target_images"], test["targets"], False, None)]
    if "peg_rope_images" in test:           # ropes among pegs (training with pegs_share > 0)
        sets.append(("peg_node", test["peg_rope_images"], test["peg_ropes"], True, test["peg_pegs"]))
    for key, images, truth, rope, pegs in sets:
        net, fine = [], []
        for i in range(0, len(images), chunk):
            with torch.no_grad():
                guess = perception.net(images[i:i + chunk])
            net.append(node_error(guess, truth[i:i + chunk]))
            if perception.refine_iters > 0:
                done = refine(guess, images[i:i + chunk], perception.rest_length, perception.view_size, rope,
                              iters=perception.refine_iters, pegs=None if pegs is None else pegs[i:i + chunk])
                fine.append(node_error(done, truth[i:i + chunk]))
        e_net = torch.cat(net)
        e = torch.cat(fine) if fine else e_net
        out[f"{key}_error_mm"] = 1000 * float(e.mean())
        out[f"{key}_error_p95_mm"] = 1000 * float(e.quantile(0.95))
        out[f"net_{key}_error_mm"] = 1000 * float(e_net.mean())
    return out


def train(out: Path, cfg: TrainConfig, p: CableParams, view_size: float = DEFAULT_VIEW_SIZE,
          progress: bool = True, resume: bool = False) -> dict[str, Any]:
    """Train a perception into ``out`` (perception.pt, results.json, log.csv, perception.png); a training state
    (train_state.pt) is saved every eval_every steps, and ``resume`` continues from it exactly."""
    from tqdm import tqdm

    from ..utils.files import write_json_atomic, write_text_atomic
    from ..planar.simulator import Simulator

    t0 = time.perf_counter()
    torch.manual_seed(cfg.seed)
    sim = Simulator(p)
    g = torch.Generator().manual_seed(cfg.seed)
    pool = sample_shapes(cfg.pool, p, g, sim, spread=0.0)
    boards = board_pool(cfg.board_pool, p, g, sim) if cfg.pegs_share > 0 else None
    test = held_out(p, cfg, sim, view_size)
    net = PerceptionNet(cfg.image_size, p.n_nodes, view_size, cfg.width, cfg.hidden)
    if cfg.init:                                           # fine-tune: the weights of an earlier checkpoint
        start = Perception.load(cfg.init, image_size=cfg.image_size, n_nodes=p.n_nodes, view_size=view_size)
        if (start.net.width, start.net.hidden) != (cfg.width, cfg.hidden):
            raise PerceptionError(f"--init {cfg.init!r} has width={start.net.width}, hidden={start.net.hidden}; "
                                  f"training asks for width={cfg.width}, hidden={cfg.hidden}")
        net.load_state_dict(start.net.state_dict())
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 0.5 * (1 + math.cos(math.pi * min(i / cfg.steps, 1))))
    state_path, log_path = out / "train_state.pt", out / "log.csv"
    step, wall_before, log = 0, 0.0, ["step,wall_s,train_error_mm,net_node_error_mm,net_target_error_mm"
                                       + (",net_peg_node_error_mm" if boards is not None else "")]
    if resume and state_path.is_file():
        st = torch.load(state_path, map_location="cpu", weights_only=True)
        st["config"] = {**dataclasses.asdict(TrainConfig()), **st["config"]}   # a state saved before a field existed
        same = ("refine_iters",)          # read after training only: a finished run can be re-read with other steps
        if {k: v for k, v in st["config"].items() if k not in same} != \
                {k: v for k, v in dataclasses.asdict(cfg).items() if k not in same}:
            raise PerceptionError(f"--resume: {state_path} was trained with {st['config']}, not {dataclasses.asdict(cfg)}")
        net.load_state_dict(st["net"]), opt.load_state_dict(st["opt"]), sched.load_state_dict(st["sched"])
        g.set_state(st["generator"]), torch.set_rng_state(st["torch_rng"])
        step, wall_before, log = st["step"], st["wall_s"], log_path.read_text().splitlines()[:1 + st["logged"]]
    perception = Perception(net, p.rest_length, 0, meta={"params": p.name if hasattr(p, "name") else None})
    bar = tqdm(total=cfg.steps, initial=step, desc="perception", disable=not progress)
    running = None
    while step < cfg.steps:
        net.train()
        images, labels = augmented_batch(pool, cfg, g, view_size, boards)
        loss = node_error(net(images), labels).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        step += 1
        running = loss.item() if running is None else 0.98 * running + 0.02 * loss.item()
        bar.update(1)
        if step % cfg.eval_every == 0 or step == cfg.steps:
            net.eval()
            e = evaluate(perception, test)
            wall = wall_before + time.perf_counter() - t0
            log.append(f"{step},{wall:.1f},{1000 * running:.3f},{e['net_node_error_mm']:.3f},"
                       f"{e['net_target_error_mm']:.3f}" + (f",{e['net_peg_node_error_mm']:.3f}" if boards is not None
                                                             else ""))
            bar.set_postfix(node_mm=f"{e['net_node_error_mm']:.1f}")
            write_text_atomic(log_path, "\n".join(log) + "\n")
            from ..utils.files import replacing
            with replacing(state_path) as tmp:
                torch.save({"config": dataclasses.asdict(cfg), "net": net.state_dict(), "opt": opt.state_dict(),
                            "sched": sched.state_dict(), "generator": g.get_state(),
                            "torch_rng": torch.get_rng_state(), "step": step, "wall_s": wall,
                            "logged": len(log) - 1}, tmp)
    bar.close()
    net.eval()
    train_wall = wall_before + time.perf_counter() - t0
    meta = {"train_images": cfg.steps * cfg.batch}
    if cfg.pegs_share > 0 or cfg.init:
        meta.update(pegs_share=cfg.pegs_share, init=cfg.init)
    perception = Perception(net, p.rest_length, cfg.refine_iters, meta=meta)
    t1 = time.perf_counter()
    e = evaluate(perception, test)
    read_s = (time.perf_counter() - t1) / (2 * len(test["ropes"]))
    perception.save(out / CHECKPOINT)
    results = {**e, "image_size": cfg.image_size, "view_size": view_size, "mm_per_pixel": 1000 * view_size / cfg.image_size,
               "train_images": cfg.steps * cfg.batch, "pool_shapes": cfg.pool, "eval_pictures": len(test["ropes"]),
               "refine_iters": cfg.refine_iters, "read_s_per_picture": read_s, "wall_s": train_wall,
               "threads": torch.get_num_threads(), "config": dataclasses.asdict(cfg), "checkpoint": CHECKPOINT}
    write_json_atomic(out / "results.json", results)
    plot(perception, test, out / "perception.png")
    return results


def plot(perception: Perception, test: dict[str, torch.Tensor], path: Path, count: int = 6) -> None:
    """Held-out pictures with the true nodes (black) and the perceived ones (white crosses, node 0 circled)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    images, truth = test["rope_images"][:count], test["ropes"][:count]
    pred = perception.read(images)
    half = perception.view_size / 2
    fig, axes = plt.subplots(1, count, figsize=(2.6 * count, 2.8))
    for i, ax in enumerate(axes):
        ax.imshow(images[i].numpy(), extent=(-half, half, -half, half))
        ax.plot(truth[i, :, 0], truth[i, :, 1], "k.", ms=3)
        ax.plot(pred[i, :, 0], pred[i, :, 1], "wx", ms=3)
        ax.plot(pred[i, :1, 0], pred[i, :1, 1], "wo", ms=6, mfc="none")
        ax.set_title(f"{1000 * float(node_error(pred[i:i + 1], truth[i:i + 1])):.1f} mm", fontsize=9)
        ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# ====================================================================== command line
def main(argv: list[str] | None = None) -> int:
    from ..utils.files import check_fresh_out, out_lock
    from ..planar.params import ParamsError

    d = TrainConfig()
    ap = argparse.ArgumentParser(prog="python -m diffdlo.perception", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="output folder: perception.pt, results.json, log.csv, perception.png")
    ap.add_argument("--params", default="cable", help="cable params name or YAML path (default cable)")
    ap.add_argument("--view-size", type=float, default=DEFAULT_VIEW_SIZE, help="the env's view_size [m] (default 1)")
    for f in dataclasses.fields(TrainConfig):
        ap.add_argument("--" + f.name.replace("_", "-"), type=type(getattr(d, f.name)), default=getattr(d, f.name),
                        help=f"(default {getattr(d, f.name)})")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    ap.add_argument("--resume", action="store_true", help="continue the training state in --out")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier perception in --out")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    args = ap.parse_args(argv)
    cfg = TrainConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)})
    for name in ("steps", "batch", "pool", "width", "hidden", "eval_pictures", "eval_every", "board_pool"):
        if getattr(cfg, name) < (4 if name in ("pool", "eval_pictures") else 1):
            ap.error(f"--{name.replace('_', '-')} must be positive (pool, eval-pictures >= 4), got {getattr(cfg, name)}")
    if cfg.refine_iters < 0 or args.threads is not None and args.threads < 1:
        ap.error(f"--refine-iters must be >= 0 and --threads >= 1, got {cfg.refine_iters}, {args.threads}")
    if not (cfg.lr > 0 and math.isfinite(cfg.lr)) or not (0 <= cfg.spread < args.view_size / 2):
        ap.error(f"--lr must be > 0 and --spread in [0, view_size/2), got {cfg.lr}, {cfg.spread}")
    if not 0 <= cfg.pegs_share <= 1:
        ap.error(f"--pegs-share must be in [0, 1] (the share of pictures drawn among pegs), got {cfg.pegs_share}")
    try:
        PerceptionNet(cfg.image_size, 2, args.view_size)
    except PerceptionError as exc:
        ap.error(f"--image-size: {exc}")
    try:
        p = load_params(args.params)
        out = Path(args.out)
        if not args.resume:
            check_fresh_out(out, args.overwrite, "an earlier perception")
        elif not (out / "train_state.pt").is_file():
            raise ValueError(f"--resume: {out / 'train_state.pt'} not found (nothing to continue in {str(out)!r})")
        if cfg.init:                 # a fine-tune's start, checked before any work: named if missing or foreign
            try:
                Perception.load(cfg.init, image_size=cfg.image_size, n_nodes=p.n_nodes, view_size=args.view_size)
            except PerceptionError as exc:
                raise ValueError(f"--init: {exc}") from None
    except (ParamsError, FileExistsError, ValueError) as exc:
        ap.error(str(exc))
    if args.threads:
        torch.set_num_threads(args.threads)
    out.mkdir(parents=True, exist_ok=True)
    from ..utils.signals import exit_code, stop_on_signals
    try:
        with out_lock(out), stop_on_signals():       # SIGINT/SIGTERM stop it however it was started
            r = train(out, cfg, p, args.view_size, progress=not args.no_progress, resume=args.resume)
    except KeyboardInterrupt as exc:
        print(f"perception: stopped by {exc or 'SIGINT'}: --resume continues from the last saved state "
              f"({out / 'train_state.pt'}, written every --eval-every steps)", file=sys.stderr)
        return exit_code(exc)
    print(f"node error {r['node_error_mm']:.2f} mm (net alone {r['net_node_error_mm']:.2f}), target error "
          f"{r['target_error_mm']:.2f} mm at {cfg.image_size} px, {r['train_images']} training pictures, "
          f"{r['wall_s']:.0f} s -> {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
