"""Fitting the 3-D chain (chain3d.py) to recordings of a real cable, and DEFORM's evaluation protocol.

The chain: one node per tracked marker (``cable_model``). Each link's rest length is the median, over every frame of
every training recording, of the distance between its two markers (a chord: between markers the cable is curved,
and the marker gaps of DEFORM's recordings vary by 2-10 % around the median). Mass: the cable's own mass per length
(``mass / length``; the paper's table does not say whether the markers are in its weights: by default they are
taken NOT to be, ``markers_in_mass=False``) lumped on the nodes by chain3d, plus each marker's ``marker_mass``
(0.4 g on DEFORM's cables) as a point mass on its node. The held markers follow the recording (chain3d's held path,
linear between frames). No floor: DEFORM's free markers stay above 3 cm in 99.9 % of the training frames.

The evaluation (``predict``, ``evaluate``), as DEFORM scores its models (train_DEFORM.py, roahmlab/DEFORM): start
at recorded frame 1 with the velocity (x_1 - x_0) / dt, roll out open loop to frame T-1 (498 frames for T = 500)
with the held markers set to the recording at every frame, and score the mean absolute coordinate error (L1 over
x, y, z, averaged) over all markers, the held ones included (whose error is zero), and over frames 2..T-1.

The fit (``fit_cable``): the physical parameters ``FIT_NAMES`` (EI [N m^2], EA [N], drag [N s/m^2], axial
damping [N s], bending damping [N m^2 s]) as log-parameters, bounded (``DEFAULT_BOUNDS``, so that the explicit
integrator stays stable at the model's fixed substeps), fitted with Adam to the mean absolute error of the free
markers over multi-step windows (``window`` frames started from a recorded frame and its finite-difference
velocity, the held markers following the recording) drawn at random from the training recordings. A coarse scan of
EI picks the start. Uncertainty: the spread (standard deviation of the log-parameters, reported as a factor) over
``bootstrap`` refits on resamples of the training recordings drawn with replacement, each continued from the fit
for ``bootstrap_iterations`` steps (a warm-started bootstrap: it measures how much the optimum moves with the data,
and underestimates the spread of independent fits).
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Mapping, Sequence

import torch
from tqdm import tqdm

from . import chain as chain3d
from .chain import ChainDivergedError, ChainParams
from .deform import DT, HELD_MARKERS, MARKER_MASS

FIT_NAMES = ("EI", "EA", "drag", "axial_damping", "bending_damping")
UNITS = {"EI": "N m^2", "EA": "N", "drag": "N s/m^2", "axial_damping": "N s", "bending_damping": "N m^2 s"}
DEFAULT_START = {"EI": 1e-3, "EA": 50.0, "drag": 0.02, "axial_damping": 5e-3, "bending_damping": 1e-6}
# Bounds of the fit [SI]. EA is kept "stiff but simulable": 5-100 N stretches a 1 m cable under its own weight and
# the swings' tensions (< 1 N) by under a few %, about the marker gaps' own spread; the upper bounds of EA and the
# dampings set the substeps the explicit integrator needs (``substeps_for``).
DEFAULT_BOUNDS = {"EI": (1e-6, 0.05), "EA": (5.0, 60.0), "drag": (1e-4, 2.0), "axial_damping": (1e-5, 0.02),
                  "bending_damping": (1e-9, 3e-5)}
STABILITY_TARGET = 0.5    # substeps are chosen so that chain3d.stability_margin stays below this at the bounds


class FitError(ValueError):
    """Bad input to the fit or the evaluation; the message names the value."""


# ====================================================================== recordings
def as_recordings(recordings: Mapping[str, torch.Tensor] | Sequence[torch.Tensor] | torch.Tensor,
                  what: str = "recordings") -> tuple[list[str], torch.Tensor]:
    """Ids and a (B, T, n, 3) float64 stack of a dict {id: (T, n, 3)}, a list of (T, n, 3) tensors or a (B, T, n, 3)
    tensor. All must share T (>= 3) and n (>= 4) and be finite; FitError names the first that does not."""
    if torch.is_tensor(recordings):
        if recordings.ndim == 3:
            recordings = [recordings]
        else:
            recordings = list(recordings)
    if isinstance(recordings, Mapping):
        ids, tensors = [str(k) for k in recordings], list(recordings.values())
    elif isinstance(recordings, (list, tuple)):
        ids, tensors = [str(i) for i in range(len(recordings))], list(recordings)
    else:
        raise FitError(f"{what} must be a dict or list of (T, n, 3) tensors, got {type(recordings).__name__}")
    if not tensors:
        raise FitError(f"{what} is empty: need at least one (T, n, 3) recording")
    shape = None
    for key, t in zip(ids, tensors):
        if not torch.is_tensor(t) or not t.is_floating_point() or t.ndim != 3 or t.shape[2] != 3:
            got = tuple(t.shape) if torch.is_tensor(t) else type(t).__name__
            raise FitError(f"{what}[{key!r}] must be a floating-point tensor of shape (T, n, 3), got {got}")
        if t.shape[0] < 3 or t.shape[1] < 4:
            raise FitError(f"{what}[{key!r}] has shape {tuple(t.shape)}: need T >= 3 frames and n >= 4 markers")
        if shape is None:
            shape = tuple(t.shape)
        elif tuple(t.shape) != shape:
            raise FitError(f"{what}[{key!r}] has shape {tuple(t.shape)}, the first has {shape}: all recordings of a "
                           f"cable must share T and n")
        if not bool(torch.isfinite(t).all()):
            raise FitError(f"{what}[{key!r}] holds {int((~torch.isfinite(t)).sum())} non-finite values")
    return ids, torch.stack([t.detach().to(torch.float64) for t in tensors])


def held_indices(held: Sequence[int], n: int) -> tuple[int, ...]:
    """``held`` as sorted non-negative marker indices of n markers; FitError for an index out of range, a
    repeat, or every marker held."""
    out = []
    for h in held:
        if isinstance(h, bool) or not isinstance(h, int) or not -n <= h < n:
            raise FitError(f"held marker index {h!r} is not an integer in [-{n}, {n})")
        out.append(h % n)
    if len(set(out)) != len(out):
        raise FitError(f"held markers {tuple(held)} name a marker twice (of {n} markers)")
    if len(out) >= n - 1:
        raise FitError(f"held markers {tuple(held)} leave {n - len(out)} free marker(s) of {n}: need at least 2")
    return tuple(sorted(out))


# ====================================================================== the model of a cable
@dataclasses.dataclass(frozen=True)
class CableModel:
    """The chain of one cable: everything but the fitted parameters."""
    rest_lengths: torch.Tensor    # (n-1,) [m]
    mass_per_length: float        # [kg/m]
    point_mass: torch.Tensor      # (n,) [kg]
    held: tuple[int, ...]         # held node (marker) indices, non-negative
    substeps: int                 # per recorded frame of dt
    dt: float = DT                # [s] between recorded frames

    @property
    def n(self) -> int:
        return self.rest_lengths.shape[0] + 1

    def held_mask(self) -> torch.Tensor:
        mask = torch.zeros(self.n, dtype=torch.bool)
        mask[list(self.held)] = True
        return mask

    def params(self, values: Mapping[str, Any]) -> ChainParams:
        """ChainParams with the fitted ``values`` (floats or tensors, keys FIT_NAMES)."""
        return ChainParams(rest_lengths=self.rest_lengths, mass_per_length=self.mass_per_length,
                           point_mass=self.point_mass, **{k: values[k] for k in FIT_NAMES})

    def stability(self, values: Mapping[str, Any], substeps: int | None = None) -> float:
        """chain3d.stability_margin at ``values``, with the links between two held nodes (which never move
        under the chain's forces) left out of its shortest rest length."""
        held = self.held_mask()
        between = held[:-1] & held[1:]
        rest = torch.where(between, self.rest_lengths.max(), self.rest_lengths)
        params = dataclasses.replace(self.params(values), rest_lengths=rest)
        return chain3d.stability_margin(params, self.n, self.dt / (substeps or self.substeps), held)

    def to_dict(self) -> dict:
        return {"rest_lengths_m": [round(float(v), 6) for v in self.rest_lengths],
                "chain_length_m": round(float(self.rest_lengths.sum()), 6),
                "mass_per_length_kg_per_m": self.mass_per_length,
                "point_mass_kg": [float(v) for v in self.point_mass], "held": list(self.held),
                "substeps": self.substeps, "dt_s": self.dt}


def substeps_for(model_or_rest: CableModel, values: Mapping[str, Any], target: float = STABILITY_TARGET,
                 most: int = 200) -> int:
    """The fewest substeps per frame with chain3d.stability_margin below ``target`` at ``values``."""
    for s in range(1, most + 1):
        if model_or_rest.stability(values, s) < target:
            return s
    raise FitError(f"no number of substeps up to {most} keeps the chain stable at {dict(values)}")


def cable_model(recordings: Any, held: Sequence[int] = HELD_MARKERS, *, mass: float, length: float,
                marker_mass: float = MARKER_MASS, markers_in_mass: bool = False,
                bounds: Mapping[str, tuple[float, float]] | None = None, dt: float = DT,
                rest_lengths: torch.Tensor | Sequence[float] | None = None) -> CableModel:
    """The chain of a cable from its training recordings: a node per marker, each link's rest length the median
    marker gap, the mass per length ``mass / length`` [kg, m] (less the markers' ``n * marker_mass`` where
    ``markers_in_mass``), a ``marker_mass`` point mass on every node, and the substeps that keep the integrator
    stable at the upper ``bounds`` of the fitted parameters. ``rest_lengths`` (n-1,) [m], where given, replace the
    median marker gaps (a cable whose rest lengths are known)."""
    _, X = as_recordings(recordings)
    n = X.shape[2]
    held = held_indices(held, n)
    for name, value in (("mass", mass), ("length", length), ("dt", dt)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
            raise FitError(f"{name} must be a number > 0, got {value!r}")
    if isinstance(marker_mass, bool) or not isinstance(marker_mass, (int, float)) or not 0 <= marker_mass < math.inf:
        raise FitError(f"marker_mass must be a number >= 0 [kg], got {marker_mass!r}")
    own = mass - (n * marker_mass if markers_in_mass else 0.0)
    if own <= 0:
        raise FitError(f"mass {mass} kg less the {n} markers' {n * marker_mass} kg leaves nothing for the cable")
    if rest_lengths is None:
        rest = (X[:, :, 1:] - X[:, :, :-1]).norm(dim=-1).flatten(0, 1).median(0).values
    else:
        rest = torch.as_tensor(rest_lengths, dtype=torch.float64).flatten()
        if rest.shape != (n - 1,) or not bool(torch.isfinite(rest).all()):
            raise FitError(f"rest_lengths must be {n - 1} finite lengths [m] (one per link of {n} markers), got "
                           f"{rest.tolist()}")
    if bool((rest <= 0).any()):
        raise FitError(f"rest lengths of links {rest.le(0).nonzero().flatten().tolist()} are not > 0 (markers on "
                       f"their neighbours?)")
    model = CableModel(rest_lengths=rest, mass_per_length=own / length,
                       point_mass=torch.full((n,), float(marker_mass), dtype=torch.float64), held=held,
                       substeps=1, dt=dt)
    upper = {k: hi for k, (lo, hi) in _bounds(bounds).items()}
    return dataclasses.replace(model, substeps=substeps_for(model, upper))


def _bounds(bounds: Mapping[str, tuple[float, float]] | None) -> dict[str, tuple[float, float]]:
    out = dict(DEFAULT_BOUNDS)
    for k, v in (bounds or {}).items():
        if k not in FIT_NAMES:
            raise FitError(f"bounds names {k!r}, not one of {FIT_NAMES}")
        lo, hi = v
        if not 0 < lo <= hi < math.inf:
            raise FitError(f"bounds[{k!r}] must be 0 < low <= high, got {v!r}")
        out[k] = (float(lo), float(hi))
    return out


# ====================================================================== rollouts and the protocol
def simulate(model: CableModel, values: Mapping[str, Any], x0: torch.Tensor, v0: torch.Tensor,
             held_path: torch.Tensor, substeps: int | None = None, accel: Any = None) -> torch.Tensor:
    """(T, B, n, 3) chain3d.rollout of B chains from (x0, v0) with the held markers on held_path (T, B, H, 3);
    frame 0 is the start. ``accel``: chain3d.rollout's extra acceleration (a learned correction)."""
    return chain3d.rollout(x0, v0, model.held_mask(), held_path, model.params(values), substeps or model.substeps,
                           frame_dt=model.dt, accel=accel)


def predict(model: CableModel, values: Mapping[str, Any], recordings: Any, start: int = 1, accel: Any = None,
            dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """(B, T-start-1, n, 3): the open-loop prediction of frames start+1 .. T-1 of every recording, from frame
    ``start`` and the velocity (x_start - x_{start-1}) / dt, the held markers set to the recording at every frame,
    in ``dtype`` (``accel``: an extra acceleration, ``simulate``'s). A batch that diverges is rerun one recording at a
    time with 2x, then 4x, the substeps (ChainDivergedError if it still diverges)."""
    _, X = as_recordings(recordings)
    if isinstance(start, bool) or not isinstance(start, int) or not 1 <= start <= X.shape[1] - 2:
        raise FitError(f"start must be an integer in [1, {X.shape[1] - 2}] for {X.shape[1]} frames, got {start!r}")
    if dtype not in (torch.float32, torch.float64):
        raise FitError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    X = X.to(dtype)
    held = list(model.held)

    def run(Y: torch.Tensor, substeps: int) -> torch.Tensor:
        path = Y[:, start:, held].transpose(0, 1).contiguous()
        out = simulate(model, values, Y[:, start], (Y[:, start] - Y[:, start - 1]) / model.dt, path, substeps,
                       accel)
        return out[1:].transpose(0, 1)

    with torch.no_grad():
        try:
            return run(X, model.substeps)
        except ChainDivergedError:
            pass
        out = []
        for b in range(X.shape[0]):
            for factor in (1, 2, 4):
                try:
                    out.append(run(X[b:b + 1], model.substeps * factor))
                    break
                except ChainDivergedError:
                    if factor == 4:
                        raise
        return torch.cat(out)


def frozen_prediction(recordings: Any, held: Sequence[int] = HELD_MARKERS, start: int = 1) -> torch.Tensor:
    """(B, T-start-1, n, 3) the baseline "markers frozen at frame ``start``, held ones driven": every free marker
    stays where it is at frame ``start``, the held ones follow the recording."""
    _, X = as_recordings(recordings)
    held = list(held_indices(held, X.shape[2]))
    pred = X[:, start:start + 1].expand(-1, X.shape[1] - start - 1, -1, -1).clone()
    pred[:, :, held] = X[:, start + 1:, held]
    return pred


def l1_error(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute coordinate error [m] over every axis, marker and frame (the last three dims); (B,) or ()."""
    if pred.shape != target.shape:
        raise FitError(f"prediction shape {tuple(pred.shape)} differs from the target's {tuple(target.shape)}")
    return (pred - target).abs().mean(dim=(-3, -2, -1))


def score(pred: torch.Tensor, recordings: Any, start: int = 1) -> dict:
    """DEFORM's score of predictions (B, T-start-1, n, 3) of recordings (B, T, n, 3): the mean L1 error [m] over
    all markers and frames start+1..T-1 (``l1_m``), per recording, per frame, and DEFORM's own convention
    (``deform_convention_m``: the sum over the F = T-start-1 frames divided by T, i.e. ``l1_m * F / T``)."""
    ids, X = as_recordings(recordings)
    target = X[:, start + 1:]
    per_recording = l1_error(pred, target)
    per_frame = (pred - target).abs().mean(dim=(0, 2, 3))
    mean = float(per_recording.mean())
    return {"l1_m": mean, "deform_convention_m": mean * target.shape[1] / X.shape[1],
            "per_recording_m": {i: float(e) for i, e in zip(ids, per_recording)},
            "per_frame_m": [float(e) for e in per_frame], "frames": int(target.shape[1]),
            "recordings": len(ids)}


def evaluate(model: CableModel, values: Mapping[str, Any], recordings: Any, repeats: int = 1,
             predictor: Any = None) -> tuple[dict, torch.Tensor]:
    """``score`` of ``predict`` (batched over every recording; ``predictor(model, values, recordings)`` in its place
    where given, e.g. the residual's), with the wall time per trajectory-frame (``time_per_frame_s``: the best of
    ``repeats`` runs over (B * frames)) under the current torch threads."""
    best = math.inf
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        pred = (predictor or predict)(model, values, recordings)
        best = min(best, time.perf_counter() - t0)
    result = score(pred, recordings)
    result["time_per_frame_s"] = best / (result["recordings"] * result["frames"])
    result["threads"] = torch.get_num_threads()
    return result, pred


# ====================================================================== the fit
@dataclasses.dataclass
class FitResult:
    """A fitted cable: the model, the parameters [SI] and their uncertainty, and the fit's record."""
    model: CableModel
    values: dict[str, float]              # fitted FIT_NAMES [SI]
    spread: dict[str, float]              # bootstrap std of log(value) (0 without bootstrap): a factor exp(spread)
    bootstrap: list[dict[str, float]]     # each resample's fitted values
    history: list[float]                  # training loss [m] per Adam step (free markers' mean L1 over windows)
    scan: list[tuple[float, float]]       # (EI, loss) of the start's scan
    settings: dict[str, Any]
    seconds: float
    skipped: int = 0                      # steps skipped because a window diverged

    def to_dict(self) -> dict:
        return {"values": self.values, "units": UNITS,
                "spread_log": self.spread,
                "interval_68": {k: [self.values[k] * math.exp(-self.spread[k]),
                                    self.values[k] * math.exp(self.spread[k])] for k in FIT_NAMES},
                "bootstrap": self.bootstrap, "final_train_loss_m": self.history[-1] if self.history else None,
                "history_m": self.history, "scan": [list(s) for s in self.scan], "settings": self.settings,
                "seconds": self.seconds, "skipped_steps": self.skipped, "model": self.model.to_dict()}


def _windows(X: torch.Tensor, count: int, window: int, gen: torch.Generator, files: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """(file, start) of ``count`` windows: start in [1, T-1-window], file from ``files`` (default all)."""
    B, T = X.shape[:2]
    pool = torch.arange(B) if files is None else files
    f = pool[torch.randint(len(pool), (count,), generator=gen)]
    s = torch.randint(1, T - window, (count,), generator=gen)
    return f, s


def window_loss(model: CableModel, values: Mapping[str, Any], X: torch.Tensor, files: torch.Tensor,
                starts: torch.Tensor, window: int, accel: Any = None) -> torch.Tensor:
    """Mean absolute error [m] of the free markers over ``window`` frames after each (file, start), the chain
    started from the recorded frame and its finite-difference velocity, the held markers on the recording
    (``accel``: an extra acceleration, ``simulate``'s)."""
    idx = starts.view(-1, 1) + torch.arange(window + 1).view(1, -1)              # (W, window+1)
    seg = X[files.view(-1, 1), idx]                                                # (W, window+1, n, 3)
    prev = X[files, starts - 1]
    held = list(model.held)
    free = [i for i in range(model.n) if i not in model.held]
    path = seg[:, :, held].transpose(0, 1).contiguous()
    out = simulate(model, values, seg[:, 0], (seg[:, 0] - prev) / model.dt, path, accel=accel)
    return (out[1:, :, free] - seg[:, 1:, free].transpose(0, 1)).abs().mean()


def _adam(model: CableModel, X: torch.Tensor, start: dict[str, float], bounds: dict[str, tuple[float, float]],
          names: Sequence[str], iterations: int, batch: int, window: int, lr: float, gen: torch.Generator,
          files: torch.Tensor | None, desc: str, progress: bool) -> tuple[dict[str, float], list[float], int]:
    """Adam on the log of ``names`` (others held at ``start``), projected on the bounds, cosine-decayed lr."""
    theta = torch.tensor([math.log(start[k]) for k in names], dtype=torch.float64, requires_grad=True)
    lo = torch.tensor([math.log(bounds[k][0]) for k in names], dtype=torch.float64)
    hi = torch.tensor([math.log(bounds[k][1]) for k in names], dtype=torch.float64)
    opt = torch.optim.Adam([theta], lr=lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * i / max(1, iterations))))
    history, skipped = [], 0
    bar = tqdm(range(iterations), desc=desc, disable=not progress, dynamic_ncols=True, leave=False)
    for _ in bar:
        f, s = _windows(X, batch, window, gen, files)
        values = dict(start)
        values.update({k: theta[i].exp() for i, k in enumerate(names)})
        opt.zero_grad()
        try:
            loss = window_loss(model, values, X, f, s, window)
        except ChainDivergedError:
            skipped += 1
            sched.step()
            continue
        loss.backward()
        opt.step()
        sched.step()
        with torch.no_grad():
            theta.copy_(torch.maximum(torch.minimum(theta, hi), lo))
        history.append(float(loss.detach()))
        bar.set_postfix(loss_cm=f"{100 * float(loss.detach()):.3f}", EI=f"{math.exp(float(theta.detach()[0])):.3g}"
                        if names[0] == "EI" else "")
    out = dict(start)
    out.update({k: math.exp(float(theta.detach()[i])) for i, k in enumerate(names)})
    return out, history, skipped


def fit_cable(train_recordings: Any, held: Sequence[int] = HELD_MARKERS, *, mass: float, length: float,
              marker_mass: float = MARKER_MASS, markers_in_mass: bool = False, window: int = 40,
              iterations: int = 200, batch: int = 8, lr: float = 0.08, scan_points: int = 9,
              bootstrap: int = 3, bootstrap_iterations: int = 40, seed: int = 0,
              start: Mapping[str, float] | None = None, bounds: Mapping[str, tuple[float, float]] | None = None,
              names: Sequence[str] = FIT_NAMES, rest_lengths: Any = None, progress: bool = True,
              desc: str = "fit") -> FitResult:
    """Fit the chain's physical parameters to a cable's training recordings (a dict {id: (T, n, 3)} or a list of
    tensors [m], z up, at 1 / DT Hz; ``held`` the marker indices the robots hold), by Adam on the log-parameters
    over ``iterations`` steps of ``batch`` random ``window``-frame windows; the start's EI is the best of a
    ``scan_points`` log-spaced scan of the bounds (one fixed batch of windows). ``names``: the parameters fitted
    (the others stay at ``start``); ``rest_lengths``: see ``cable_model``. Uncertainty: ``bootstrap`` warm-started
    refits on resamples of the recordings (``bootstrap_iterations`` steps each). Deterministic for a seed and a
    number of torch threads."""
    ids, X = as_recordings(train_recordings, "train_recordings")
    for name, value, least in (("window", window, 1), ("iterations", iterations, 0), ("batch", batch, 1),
                               ("scan_points", scan_points, 0), ("bootstrap", bootstrap, 0),
                               ("bootstrap_iterations", bootstrap_iterations, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise FitError(f"{name} must be an integer >= {least}, got {value!r}")
    if window > X.shape[1] - 2:
        raise FitError(f"window {window} needs recordings of more than {window + 1} frames, got {X.shape[1]}")
    names = tuple(names)
    if not names or any(k not in FIT_NAMES for k in names):
        raise FitError(f"names must be a non-empty subset of {FIT_NAMES}, got {names!r}")
    t0 = time.perf_counter()
    bounds_ = _bounds(bounds)
    model = cable_model(X, held, mass=mass, length=length, marker_mass=marker_mass, markers_in_mass=markers_in_mass,
                        bounds=bounds_, rest_lengths=rest_lengths)
    values = dict(DEFAULT_START)
    for k, v in (start or {}).items():
        if k not in FIT_NAMES or not 0 < float(v) < math.inf:
            raise FitError(f"start[{k!r}] = {v!r}: must name one of {FIT_NAMES} with a value > 0")
        values[k] = float(v)
    for k in FIT_NAMES:
        lo, hi = bounds_[k]
        values[k] = min(max(values[k], lo), hi)
    gen = torch.Generator().manual_seed(seed)
    scan = []
    if scan_points and "EI" in names:
        f, s = _windows(X, batch, window, gen)
        lo, hi = bounds_["EI"]
        best = (math.inf, values["EI"])
        for j in range(scan_points):
            ei = math.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * j / max(1, scan_points - 1))
            try:
                with torch.no_grad():
                    loss = float(window_loss(model, dict(values, EI=ei), X, f, s, window))
            except ChainDivergedError:
                loss = math.inf
            scan.append((ei, loss))
            best = min(best, (loss, ei))
        values["EI"] = best[1]
    values, history, skipped = _adam(model, X, values, bounds_, names, iterations, batch, window, lr, gen, None,
                                     desc, progress)
    boots = []
    for b in range(bootstrap):
        files = torch.randint(X.shape[0], (X.shape[0],), generator=gen)
        v, _, sk = _adam(model, X, values, bounds_, names, bootstrap_iterations, batch, window, lr * 0.5, gen, files,
                         f"{desc} bootstrap {b + 1}/{bootstrap}", progress)
        boots.append(v)
        skipped += sk
    spread = {}
    for k in FIT_NAMES:
        logs = torch.tensor([math.log(v[k]) for v in boots], dtype=torch.float64)
        spread[k] = float(logs.std()) if len(boots) > 1 else 0.0
    settings = {"window": window, "iterations": iterations, "batch": batch, "lr": lr, "scan_points": scan_points,
                "bootstrap": bootstrap, "bootstrap_iterations": bootstrap_iterations, "seed": seed,
                "names": list(names), "bounds": bounds_, "mass": mass, "length": length, "marker_mass": marker_mass,
                "markers_in_mass": markers_in_mass, "train_recordings": len(ids), "threads": torch.get_num_threads(),
                "uncertainty": "std of log(value) over warm-started bootstrap refits on train recordings resampled "
                               "with replacement"}
    return FitResult(model=model, values=values, spread=spread, bootstrap=boots, history=history, scan=scan,
                     settings=settings, seconds=time.perf_counter() - t0, skipped=skipped)
