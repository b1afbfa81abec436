"""A learned residual correction to the 3-D chain (chain3d.py), trained through the differentiable rollout.

The physics-only chain (fit.py) leaves what five scalar parameters cannot say: the cable's twist, mass and stiffness
varying along it, a quadratic air drag, the markers' own inertia, the grippers' moments. This module adds a small
learned **acceleration** to every free node, on top of the chain's forces, and trains it by backpropagation through
time through whole multi-step rollouts of the chain (the project's world-model skill: the network is judged by the
trajectories it produces, not by one-step targets). The physical parameters stay at the physics-only fit's values
(they are reported apart): only the network learns.

The correction (``ResidualNet``)
--------------------------------
- **Per node, shared along the chain**: a 1-D convolution over the nodes (the first layer sees each node and its
  ``kernel // 2`` neighbours on each side, the next layers are per node), so the same small network serves every node
  and a cable with any number of nodes; a node's place on the chain enters as a feature (its normalised index s_i and,
  with ``onehot``, a one-hot of its index: a per-node bias, as DEFORM learns per-node masses).
- **Frame-invariant as far as the physics allows**: translation invariant (only differences of positions, and
  positions relative to the held nodes' centroid) and equivariant to rotations about the vertical: every vector is
  expressed in the chain's own frame (x' the horizontal direction from node 0 to node n-1, z' = z up, y' = z' x x')
  and the output is rotated back. Gravity fixes z, so z stays meaningful (sag, height above the held ends).
- **Features** per node i, in that frame: its velocity v_i; the links to its neighbours x_i - x_{i-1} and
  x_{i+1} - x_i and their rates (zero past the ends); its position relative to the held nodes' centroid; the chain's
  span (horizontal distance and height difference between node 0 and node n-1); s_i; the one-hot. Standardised by a
  mean and standard deviation measured on the training recordings (``feature_stats``; stored in the checkpoint).
  The held nodes are nodes like the others (their features carry the grippers' motion, prescribed and so known
  in advance, as in DEFORM's protocol), but their correction is zeroed (they follow the recording).
- **Bounded, and zero at the start**: the output is ``max_accel * tanh(raw)`` [m/s^2], the last layer initialised to
  zero, so an untrained network is *exactly* the physics-only model (bit for bit: the correction adds exact zeros)
  and training starts from the physics-only fit. The bound keeps a learned term from ever feeding the explicit
  integrator an unbounded force; the chain's own stability estimate is unchanged (see below).
- **When it acts**: evaluated once per recorded frame (10 ms) from the state at the frame's start, the held nodes'
  velocity being that of their path over the frame, and held constant over the frame's substeps (a zero-order hold,
  as a controller at the recording's rate). So it costs one small network call per frame, not per substep, and the
  substeps (chosen for the physics' stiffness) need not change. A correction that acts like a velocity feedback of
  rate k is stable under this hold while k * dt < 2 (k < 200/s); ``max_accel`` bounds it anyway.

The rollout (``rollout``) is chain3d.rollout's semi-implicit Euler, step for step, with the correction a added in the
velocity update: v+ = (v + h F / m + h a) / (1 + h c_d lambda / m). It reuses chain3d's checks, forces and
divergence test (ChainDivergedError naming the frame). With a = 0 it reproduces chain3d.rollout exactly (tested).

Training (``fit_residual``): Adam on the network's weights (cosine-decayed learning rate, gradient norm clipped) over
``iterations`` steps, each on ``batch`` windows of ``window`` frames drawn at random from the training recordings
(fit._windows: a recorded start frame s and the velocity (x_s - x_{s-1}) / dt, the held markers on the recording,
the loss the free markers' mean absolute coordinate error, exactly fit.window_loss with the correction added). A step
whose rollout diverges is skipped and counted. Optionally, ``validation`` recordings (held out of the training ones:
never the eval split) are predicted open loop by DEFORM's protocol every ``eval_every`` steps, from step 0 (the
physics-only model) on, and the best state is kept: the open-loop horizon (498 frames) is far longer than the
training windows, and a correction that helps over 0.2-0.4 s may drift over 5 s; with validation, the result is never
worse on it than physics only. Deterministic for a seed (the initial weights and the windows come from seeded
generators) and a number of torch threads.

Prediction (``predict``, ``evaluate``): fit.predict's and fit.evaluate's protocol with the correction.

Checkpoints (``save``, ``load``): a dict of plain values and tensors (the configuration, the state dict, the
feature statistics, caller's metadata such as the physics values it was trained with), read back with
``torch.load(weights_only=True)``: loading runs no code.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import nn
from tqdm import tqdm

from . import chain as chain3d, fit
from .chain import ChainDivergedError, ChainParams
from .fit import FIT_NAMES, CableModel

FORMAT = "diffdlo.chain3d.residual/1"
N_VECTOR_FEATURES = 6          # v, link back, link forward, their rates, position from the held centroid
N_SPAN_FEATURES = 2            # the chain's span: horizontal distance and height difference of its end nodes
_EPS_FRAME = 1e-3              # [m] horizontal span under which the chain's frame fades (no NaN when ends align)


class ResidualError(ValueError):
    """Bad input to the residual correction; the message names the value."""


@dataclasses.dataclass(frozen=True)
class ResidualConfig:
    """The network's shape. ``n``: nodes; ``held``: held node indices (non-negative, sorted); ``hidden``: channels;
    ``layers``: hidden layers (the first a convolution over ``kernel`` nodes, odd); ``max_accel`` [m/s^2]: the
    correction's bound; ``onehot``: a one-hot of the node index among the features."""
    n: int
    held: tuple[int, ...]
    hidden: int = 64
    layers: int = 2
    kernel: int = 3
    max_accel: float = 2.0
    onehot: bool = True

    def check(self) -> None:
        for name, least in (("n", 3), ("hidden", 1), ("layers", 1), ("kernel", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ResidualError(f"{name} must be an integer >= {least}, got {value!r}")
        if self.kernel % 2 != 1:
            raise ResidualError(f"kernel must be odd (a node and as many neighbours on each side), got {self.kernel}")
        if isinstance(self.max_accel, bool) or not isinstance(self.max_accel, (int, float)) \
                or not 0 < self.max_accel < math.inf:
            raise ResidualError(f"max_accel must be a number > 0 [m/s^2], got {self.max_accel!r}")
        if not isinstance(self.onehot, bool):
            raise ResidualError(f"onehot must be True or False, got {self.onehot!r}")
        held = tuple(self.held)
        if any(isinstance(h, bool) or not isinstance(h, int) or not 0 <= h < self.n for h in held) \
                or len(set(held)) != len(held):
            raise ResidualError(f"held must be distinct node indices in [0, {self.n}), got {self.held!r}")

    @property
    def n_features(self) -> int:
        return 3 * N_VECTOR_FEATURES + N_SPAN_FEATURES + 1 + (self.n if self.onehot else 0)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["held"] = list(self.held)
        return d


def _chain_frame(x: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) rows x', y', z' of each chain's frame: x' the horizontal direction from node 0 to node n-1 (fading
    to 0 as that span falls below _EPS_FRAME), z' up, y' = z' x x'."""
    d = x[:, -1, :2] - x[:, 0, :2]
    u = d / (d.square().sum(-1, keepdim=True) + _EPS_FRAME ** 2).sqrt()
    zero, one = torch.zeros_like(u[:, 0]), torch.ones_like(u[:, 0])
    return torch.stack([torch.stack([u[:, 0], u[:, 1], zero], -1),
                        torch.stack([-u[:, 1], u[:, 0], zero], -1),
                        torch.stack([zero, zero, one], -1)], 1)


def raw_features(x: torch.Tensor, v: torch.Tensor, held: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """The unstandardised features (B, n, 3 * N_VECTOR_FEATURES + N_SPAN_FEATURES) in each chain's frame, and the
    frames (B, 3, 3). See the module's docstring."""
    R = _chain_frame(x)
    pad = x.new_zeros(x.shape[0], 1, 3)
    e, de = x[:, 1:] - x[:, :-1], v[:, 1:] - v[:, :-1]
    centre = (x[:, list(held)] if held else x).mean(1, keepdim=True)
    vectors = torch.cat([v, torch.cat([pad, e], 1), torch.cat([e, pad], 1), torch.cat([pad, de], 1),
                         torch.cat([de, pad], 1), x - centre], -1)                        # (B, n, 18), world frame
    local = torch.einsum("bnkj,bij->bnki", vectors.unflatten(-1, (N_VECTOR_FEATURES, 3)), R).flatten(-2)
    span = x[:, -1] - x[:, 0]
    span = torch.stack([span[:, :2].norm(dim=-1), span[:, 2]], -1)
    return torch.cat([local, span.unsqueeze(1).expand(-1, x.shape[1], -1)], -1), R


class ResidualNet(nn.Module):
    """The learned correction: (x, v) of B chains (B, n, 3) -> an acceleration (B, n, 3) [m/s^2], world frame, zero
    on the held nodes. Its parameters may be float32 or float64; the states are cast to them and the output back to
    the states' dtype. ``meta``: a dict of plain values carried by the checkpoint (e.g. the physics values)."""

    def __init__(self, config: ResidualConfig, seed: int = 0):
        super().__init__()
        config = dataclasses.replace(config, held=tuple(sorted(config.held)))
        config.check()
        self.config = config
        self.meta: dict = {}
        n_raw = 3 * N_VECTOR_FEATURES + N_SPAN_FEATURES
        self.register_buffer("feature_mean", torch.zeros(n_raw))
        self.register_buffer("feature_std", torch.ones(n_raw))
        index = torch.arange(config.n, dtype=torch.float32)
        place = [(index / (config.n - 1)).view(-1, 1)]
        if config.onehot:
            place.append(torch.eye(config.n))
        self.register_buffer("place", torch.cat(place, 1))                               # (n, 1 [+ n])
        free = torch.ones(config.n, 1)
        free[list(config.held)] = 0.0
        self.register_buffer("free", free)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            layers: list[nn.Module] = [nn.Conv1d(config.n_features, config.hidden, config.kernel,
                                                 padding=config.kernel // 2), nn.SiLU()]
            for _ in range(config.layers - 1):
                layers += [nn.Conv1d(config.hidden, config.hidden, 1), nn.SiLU()]
            last = nn.Conv1d(config.hidden, 3, 1)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.net = nn.Sequential(*layers, last)

    @property
    def dtype(self) -> torch.dtype:
        return self.feature_mean.dtype

    def forward(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        if x.ndim != 3 or x.shape[1] != self.config.n or x.shape[2] != 3 or v.shape != x.shape:
            raise ResidualError(f"the residual network expects x and v of shape (B, {self.config.n}, 3), got "
                                f"{tuple(x.shape)} and {tuple(v.shape)}")
        raw, R = raw_features(x, v, self.config.held)
        feat = (raw.to(self.dtype) - self.feature_mean) / self.feature_std
        feat = torch.cat([feat, self.place.unsqueeze(0).expand(x.shape[0], -1, -1)], -1)
        out = self.net(feat.transpose(1, 2)).transpose(1, 2)                            # (B, n, 3), chain frame
        accel = self.config.max_accel * torch.tanh(out) * self.free
        return torch.einsum("bni,bij->bnj", accel.to(x.dtype), R)                       # back to the world frame


def feature_stats(recordings: Any, held: tuple[int, ...], dt: float, every: int = 5) -> tuple[torch.Tensor,
                                                                                                torch.Tensor]:
    """Mean and standard deviation (floored at 1e-6) of the unstandardised features over every ``every``-th frame
    of the recordings, with finite-difference velocities."""
    _, X = fit.as_recordings(recordings)
    x = X[:, 1::every].flatten(0, 1)
    v = ((X[:, 1:] - X[:, :-1])[:, ::every] / dt).flatten(0, 1)
    raw, _ = raw_features(x, v, tuple(held))
    flat = raw.flatten(0, 1)
    return flat.mean(0), flat.std(0).clamp_min(1e-6)


# ====================================================================== the rollout
def rollout(net: ResidualNet | None, x0: torch.Tensor, v0: torch.Tensor | None, held_mask: torch.Tensor | None,
            held_path: torch.Tensor | None, params: ChainParams, substeps: int, *, frame_dt: float = chain3d.FRAME_DT,
            frames: int | None = None, return_velocities: bool = False
            ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """chain3d.rollout with ``net``'s acceleration (its ``accel`` hook: once per frame, from the state at the frame's
    start, held over its substeps). ``net`` None: chain3d.rollout as it is. Same arguments, return values and errors
    as chain3d.rollout; differentiable with respect to the network's parameters too."""
    n = x0.shape[-2] if torch.is_tensor(x0) and x0.dim() == 3 else None
    if net is not None and (not isinstance(net, ResidualNet) or net.config.n != n):
        raise ResidualError(f"net must be a ResidualNet for {n} nodes, got "
                            f"{net.config.n if isinstance(net, ResidualNet) else type(net).__name__}")
    return chain3d.rollout(x0, v0, held_mask, held_path, params, substeps, frame_dt=frame_dt, frames=frames,
                           return_velocities=return_velocities, accel=net)


def _check_net(net: Any, model: CableModel) -> ResidualNet:
    if not isinstance(net, ResidualNet):
        raise ResidualError(f"net must be a ResidualNet (from fit_residual, ResidualNet or load), got "
                            f"{type(net).__name__}")
    if net.config.n != model.n or tuple(net.config.held) != tuple(model.held):
        raise ResidualError(f"the residual network is for {net.config.n} nodes held at {list(net.config.held)}, the "
                            f"cable model has {model.n} nodes held at {list(model.held)}")
    return net


def _check_values(values: Any) -> None:
    if not isinstance(values, Mapping) or any(k not in values for k in FIT_NAMES):
        got = sorted(values) if isinstance(values, Mapping) else type(values).__name__
        raise ResidualError(f"values must map each of {FIT_NAMES} to its physics-only fitted value, got {got}")


def simulate(model: CableModel, values: Mapping[str, Any], net: ResidualNet | None, x0: torch.Tensor,
             v0: torch.Tensor, held_path: torch.Tensor, substeps: int | None = None) -> torch.Tensor:
    """fit.simulate with the correction: (T, B, n, 3) from (x0, v0), the held markers on held_path (T, B, H, 3)."""
    return fit.simulate(model, values, x0, v0, held_path, substeps, accel=None if net is None else _check_net(net, model))


def window_loss(model: CableModel, values: Mapping[str, Any], net: ResidualNet | None, X: torch.Tensor,
                files: torch.Tensor, starts: torch.Tensor, window: int) -> torch.Tensor:
    """fit.window_loss with the correction: the free markers' mean absolute error [m] over ``window`` frames after
    each (file, start), started from the recorded frame and its finite-difference velocity, the held markers on the
    recording."""
    return fit.window_loss(model, values, X, files, starts, window, accel=None if net is None else _check_net(net, model))


# ====================================================================== DEFORM's protocol
def predict(model: CableModel, values: Mapping[str, Any], net: ResidualNet | None, recordings: Any, start: int = 1,
            dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """fit.predict with the correction: (B, T-start-1, n, 3) open-loop predictions of frames start+1 .. T-1 from
    frame ``start`` and the velocity (x_start - x_{start-1}) / dt, the held markers on the recording at every frame,
    in ``dtype`` (float64 or float32). A batch that diverges is rerun one recording at a time with 2x, then 4x, the
    substeps (ChainDivergedError if it still diverges). ``net`` None: physics only (fit.predict)."""
    _check_values(values)
    if net is not None:
        _check_net(net, model)
    _, X = fit.as_recordings(recordings)
    if X.shape[2] != model.n:
        raise ResidualError(f"recordings have {X.shape[2]} markers, the cable model {model.n}")
    try:
        return fit.predict(model, values, X, start, accel=net, dtype=dtype)
    except fit.FitError as exc:
        raise ResidualError(str(exc)) from None


def evaluate(model: CableModel, values: Mapping[str, Any], net: ResidualNet | None, recordings: Any,
             repeats: int = 1) -> tuple[dict, torch.Tensor]:
    """fit.evaluate with the correction: ``fit.score`` of ``predict`` with the best of ``repeats`` wall times per
    trajectory-frame (``time_per_frame_s``)."""
    return fit.evaluate(model, values, recordings, repeats,
                        predictor=lambda m, v, r: predict(m, v, net, r))


# ====================================================================== training
@dataclasses.dataclass
class ResidualResult:
    """A trained correction: the network (its best state loaded) and the training's record."""
    net: ResidualNet
    state_dict: dict[str, torch.Tensor]      # the kept state (the best on validation, else the last)
    config: ResidualConfig
    history: list[float]                     # training loss [m] per step taken (free markers' mean L1, windows)
    validation: list[tuple[int, float]]      # (step, open-loop L1 [m] over all markers) on the validation recordings
    best_step: int                           # the step whose state is kept (``iterations`` without validation)
    settings: dict[str, Any]
    seconds: float
    skipped: int = 0                         # steps skipped because a window diverged

    def to_dict(self) -> dict:
        return {"config": self.config.to_dict(), "history_m": self.history,
                "final_train_loss_m": self.history[-1] if self.history else None,
                "validation_m": [list(v) for v in self.validation], "best_step": self.best_step,
                "settings": self.settings, "seconds": self.seconds, "skipped_steps": self.skipped}


def _int(name: str, value: Any, least: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ResidualError(f"{name} must be an integer >= {least}, got {value!r}")


def _positive(name: str, value: Any, zero_ok: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not (value >= 0 if zero_ok else value > 0):
        raise ResidualError(f"{name} must be a finite number {'>=' if zero_ok else '>'} 0, got {value!r}")


def fit_residual(model: CableModel, values: Mapping[str, float], train_recordings: Any, *, iterations: int = 300,
                 window: int = 20, batch: int = 8, lr: float = 2e-3, seed: int = 0, hidden: int = 64,
                 layers: int = 2, kernel: int = 3, max_accel: float = 2.0, onehot: bool = True,
                 weight_decay: float = 0.0, clip: float = 1.0, validation: Any = None, eval_every: int = 50,
                 dtype: torch.dtype = torch.float64, progress: bool = True, desc: str = "residual"
                 ) -> ResidualResult:
    """Train a ResidualNet on a cable's training recordings through the chain's rollout, its physics at ``values``
    (the physics-only fit, FIT_NAMES [SI], kept fixed): Adam (``lr``, cosine decay to 0.1x, ``weight_decay``,
    gradient norm clipped at ``clip``) for ``iterations`` steps of ``batch`` random ``window``-frame windows.
    ``validation``: recordings (not the eval split) predicted open loop every ``eval_every`` steps from step 0 (the
    physics-only model); the state with the lowest error is kept. Deterministic for a seed and a number of threads."""
    if not isinstance(model, CableModel):
        raise ResidualError(f"model must be a fit.CableModel (fit.cable_model or fit_cable's result.model), got "
                            f"{type(model).__name__}")
    _check_values(values)
    try:
        _, X = fit.as_recordings(train_recordings, "train_recordings")
    except fit.FitError as exc:
        raise ResidualError(str(exc)) from None
    for name, value, least in (("iterations", iterations, 0), ("window", window, 1), ("batch", batch, 1),
                               ("eval_every", eval_every, 1), ("seed", seed, 0)):
        _int(name, value, least)
    _positive("lr", lr)
    _positive("weight_decay", weight_decay, zero_ok=True)
    _positive("clip", clip)
    if dtype not in (torch.float32, torch.float64):
        raise ResidualError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    if X.shape[2] != model.n:
        raise ResidualError(f"train_recordings have {X.shape[2]} markers, the cable model {model.n}")
    if window > X.shape[1] - 2:
        raise ResidualError(f"window {window} needs recordings of more than {window + 1} frames, got {X.shape[1]}")
    V = None
    if validation is not None:
        try:
            _, V = fit.as_recordings(validation, "validation")
        except fit.FitError as exc:
            raise ResidualError(str(exc)) from None
        if V.shape[2] != model.n:
            raise ResidualError(f"validation recordings have {V.shape[2]} markers, the cable model {model.n}")
    config = ResidualConfig(n=model.n, held=tuple(model.held), hidden=hidden, layers=layers, kernel=kernel,
                            max_accel=max_accel, onehot=onehot)
    config.check()
    t0 = time.perf_counter()
    net = ResidualNet(config, seed=seed)
    mean, std = feature_stats(X, config.held, model.dt)
    net.feature_mean.copy_(mean)
    net.feature_std.copy_(std)
    net = net.to(dtype)
    X = X.to(dtype)
    values = {k: float(values[k]) for k in FIT_NAMES}
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(net.parameters(), lr=lr, weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * i / max(1, iterations))))

    def state() -> dict[str, torch.Tensor]:
        return {k: t.detach().clone() for k, t in net.state_dict().items()}

    validated: list[tuple[int, float]] = []
    best = (math.inf, iterations, None)

    def check(step: int) -> None:
        nonlocal best
        if V is None:
            return
        try:
            err = fit.score(predict(model, values, net, V, dtype=dtype), V)["l1_m"]
        except ChainDivergedError:
            err = math.inf
        validated.append((step, err))
        if err < best[0]:
            best = (err, step, state())

    history, skipped = [], 0
    check(0)
    bar = tqdm(range(iterations), desc=desc, disable=not progress, dynamic_ncols=True, leave=False)
    for i in bar:
        f, s = fit._windows(X, batch, window, gen)
        opt.zero_grad()
        try:
            loss = window_loss(model, values, net, X, f, s, window)
        except ChainDivergedError:
            skipped += 1
            sched.step()
            continue
        loss.backward()
        nn.utils.clip_grad_norm_(net.parameters(), clip)
        opt.step()
        sched.step()
        history.append(float(loss.detach()))
        bar.set_postfix(loss_cm=f"{100 * history[-1]:.3f}")
        if (i + 1) % eval_every == 0 or i + 1 == iterations:
            check(i + 1)
    if best[2] is not None:
        net.load_state_dict(best[2])
    best_step = best[1]
    settings = {"iterations": iterations, "window": window, "batch": batch, "lr": lr, "seed": seed,
                "weight_decay": weight_decay, "clip": clip, "eval_every": eval_every, "dtype": str(dtype),
                "train_recordings": int(X.shape[0]), "validation_recordings": 0 if V is None else int(V.shape[0]),
                "values": values, "threads": torch.get_num_threads()}
    net.meta = {"values": values, "substeps": model.substeps, "dt_s": model.dt}
    return ResidualResult(net=net, state_dict=state(), config=config, history=history, validation=validated,
                          best_step=best_step, settings=settings, seconds=time.perf_counter() - t0, skipped=skipped)


# ====================================================================== checkpoints: data only
def save(net: ResidualNet | ResidualResult, path: Path | str, meta: Mapping[str, Any] | None = None) -> Path:
    """Write ``net`` (or a result's net) to ``path``: its configuration, state dict and ``meta`` (merged over
    net.meta; plain numbers, strings, lists and dicts only), loadable with torch.load(weights_only=True)."""
    from ..utils.files import replacing
    if isinstance(net, ResidualResult):
        net = net.net
    if not isinstance(net, ResidualNet):
        raise ResidualError(f"save needs a ResidualNet or ResidualResult, got {type(net).__name__}")
    merged = {**net.meta, **(meta or {})}
    path = Path(path)
    with replacing(path) as tmp:
        torch.save({"format": FORMAT, "config": net.config.to_dict(), "dtype": str(net.dtype).removeprefix("torch."),
                    "meta": merged, "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()}}, tmp)
    return path


def load(path: Path | str) -> ResidualNet:
    """A ResidualNet from a checkpoint written by ``save`` (torch.load(weights_only=True): no code runs), in the
    dtype it was saved in, with its ``meta``. ResidualError names a missing or unreadable file."""
    path = Path(path)
    if not path.is_file():
        raise ResidualError(f"residual checkpoint {str(path)!r} not found")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:            # pickle errors, truncated files, refused globals: name the file
        raise ResidualError(f"residual checkpoint {str(path)!r} cannot be read: {exc}") from None
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise ResidualError(f"{str(path)!r} is not a residual checkpoint (format {FORMAT!r})")
    try:
        c = dict(ck["config"])
        config = ResidualConfig(**dict(c, held=tuple(c["held"])))
        net = ResidualNet(config)
        dtype = {"float32": torch.float32, "float64": torch.float64}[ck["dtype"]]
        net = net.to(dtype)
        net.load_state_dict(ck["state_dict"])
    except (KeyError, TypeError, RuntimeError, ValueError) as exc:
        raise ResidualError(f"residual checkpoint {str(path)!r} is malformed: {exc}") from None
    net.meta = dict(ck.get("meta") or {})
    return net
