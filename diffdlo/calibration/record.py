"""Make a recording with the simulator: a known "true" rope for the calibration to find.

python -m diffdlo.calibration.record --out FILE.npz [--moves 20] [--seed S] [--params cable] [--noise 0.001] [--dropout 0.0]
                         [--record-every 50] [--scale k_s=1.3 --scale k_d=0.8 ...] [--overwrite]

A random start rope (the thesis's sigma) is settled, then ``--moves`` random moves are made (a random node, a drag
drawn uniformly from the action box [-action_scale, action_scale]^2 and shortened to max_disp as the controller
would), recording the rope every ``--record-every`` substeps and at the end of each settle. Gaussian noise of std
``--noise`` metres is added to every position, and each (frame, node) is dropped with probability ``--dropout``
(NaN, visible False). ``--scale NAME=FACTOR`` multiplies a physical parameter (k_s, k_b, k_d, mass) of the
parameters for the true rope. The format is described in ``diffdlo/calibration/recording.py``.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import torch

from ..planar import control
from ..planar.physics import PHYSICAL, physical_values as true_params, scaled_params   # the hidden rope
from ..planar.params import CableParams, ParamsError, load_params
from .recording import Recording, save_recording
from ..planar.simulator import Simulator

PROG = "python -m diffdlo.calibration.record"


# ====================================================================== simulating
def frame_substeps(total: int, record_every: int) -> list[int]:
    """Substep of each frame ``Simulator.move(..., record_every=K)`` returns for a move of ``total`` substeps: 0,
    K, 2K, ... and the end, which it appends even when it falls on a multiple of K (that copy is left out here)."""
    steps = list(range(0, total + 1, record_every))
    return steps if steps[-1] == total else steps + [total]


def simulate(params: CableParams, n_moves: int, seed: int = 0, record_every: int = 50,
             meta: dict | None = None) -> Recording:
    """A noiseless recording of ``n_moves`` random moves of a settled random rope (float64). Each move's start
    frame is the previous move's end frame."""
    if not isinstance(n_moves, int) or n_moves < 1:
        raise ValueError(f"n_moves must be an integer >= 1, got {n_moves!r}")
    if not isinstance(record_every, int) or record_every < 1:
        raise ValueError(f"record_every must be an integer >= 1, got {record_every!r}")
    sim = Simulator(params, dtype=torch.float64)
    generator = torch.Generator().manual_seed(seed)
    pos = sim.settle(sim.random_shape(1, generator))
    frames, substeps = [pos[0]], [0]
    nodes, drags, starts, ends = [], [], [], []
    for _ in range(n_moves):
        node = torch.randint(params.n_nodes, (1,), generator=generator)
        box = (torch.rand(1, 2, generator=generator, dtype=torch.float64) * 2 - 1) * params.action_scale
        drag = control.clip_drag(box, params.max_disp)       # the drag performed, so replaying it is exact
        pos, info = sim.move(pos, node, drag, return_info=True, record_every=record_every)
        total = int(info.substeps[0])
        if total < 1:
            raise RuntimeError(f"a move of node {int(node)} by {drag[0].tolist()} took no substeps: nothing to record")
        steps = frame_substeps(total, record_every)
        starts.append(len(frames) - 1)
        frames.extend(info.frames[1:len(steps), 0])          # frame 0 is the start, already recorded
        base = substeps[-1]
        substeps.extend(base + k for k in steps[1:])
        ends.append(len(frames) - 1)
        nodes.append(int(node))
        drags.append(drag[0])
    positions = torch.stack(frames)
    return Recording(
        positions=positions,
        times=torch.tensor(substeps, dtype=torch.float64) * params.dt,
        move_node=torch.tensor(nodes, dtype=torch.int64),
        move_delta=torch.stack(drags),
        move_start=torch.tensor(starts, dtype=torch.int64),
        move_end=torch.tensor(ends, dtype=torch.int64),
        visible=torch.ones(positions.shape[:2], dtype=torch.bool),
        meta=dict(meta or {"source": "simulator"}),
    )


def observe(rec: Recording, noise: float, dropout: float, seed: int) -> Recording:
    """``rec`` as a tracker would see it: Gaussian noise of std ``noise`` [m] on every position, and each (frame,
    node) lost with probability ``dropout`` (NaN, visible False). Its own random stream, so the noise never changes
    the moves."""
    if not (math.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise must be a finite number >= 0, got {noise!r}")
    if not (0 <= dropout < 1):
        raise ValueError(f"dropout must be in [0, 1), got {dropout!r}")
    generator = torch.Generator().manual_seed(seed)
    positions = rec.positions + noise * torch.randn(rec.positions.shape, generator=generator, dtype=torch.float64)
    visible = rec.visible & (torch.rand(rec.visible.shape, generator=generator, dtype=torch.float64) >= dropout)
    positions = torch.where(visible.unsqueeze(-1), positions, torch.full_like(positions, math.nan))
    return dataclasses.replace(rec, positions=positions, visible=visible)


def make_recording(params: CableParams, n_moves: int, seed: int = 0, noise: float = 0.0, dropout: float = 0.0,
                   record_every: int = 50, scale: dict[str, float] | None = None,
                   params_name: str = "cable") -> Recording:
    """The recording ``python -m diffdlo.calibration.record`` writes: ``simulate`` the rope with ``params`` scaled by ``scale``,
    then ``observe`` it; meta records every setting and the true parameters."""
    scale = dict(scale or {})
    true = scaled_params(params, scale)
    moves_seed, noise_seed = (int(s.generate_state(1)[0]) for s in np.random.SeedSequence(seed).spawn(2))
    meta = {"source": "simulator", "params": params_name, "dt": true.dt, "noise": noise, "seed": seed,
            "record_every": record_every, "dropout": dropout, "scale": scale, "true_params": true_params(true)}
    clean = simulate(true, n_moves, moves_seed, record_every, meta)
    return observe(clean, noise, dropout, noise_seed)


# ====================================================================== command line
class UsageError(Exception):
    """A bad flag or value: main prints its one line and returns 2."""


class OneLineParser(argparse.ArgumentParser):
    def error(self, message: str):
        raise UsageError(message)


def _number(text: str, kind: type, least: float, inclusive: bool = True, below: float | None = None):
    try:
        value = kind(text)
    except ValueError:
        value = math.nan
    ok = math.isfinite(value) and (value >= least if inclusive else value > least) and (below is None or
                                                                                       value < below)
    if not ok:
        interval = f"{'[' if inclusive else '('}{least}, {below if below is not None else 'inf'})"
        raise argparse.ArgumentTypeError(f"must be {'an integer' if kind is int else 'a number'} in {interval}, "
                                         f"got {text!r}")
    return value


def _scale(text: str) -> tuple[str, float]:
    name, sep, factor = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"must be NAME=FACTOR with NAME one of {', '.join(PHYSICAL)}, got {text!r}")
    if name not in PHYSICAL:
        raise argparse.ArgumentTypeError(f"can scale only {', '.join(PHYSICAL)}, got {name!r} in {text!r}")
    try:
        value = float(factor)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"the factor must be a positive finite number, got {factor!r} in {text!r}")
    return name, value


def parser() -> OneLineParser:
    ap = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="the recording to write (must end in .npz)")
    ap.add_argument("--moves", type=lambda t: _number(t, int, 1), default=20, help="random moves (default 20)")
    ap.add_argument("--seed", type=lambda t: _number(t, int, 0), default=0, help="random seed (default 0)")
    ap.add_argument("--params", default="cable", help="cable parameters: a name or a YAML path (default cable)")
    ap.add_argument("--noise", type=lambda t: _number(t, float, 0), default=0.001,
                    help="std of the Gaussian position noise [m] (default 0.001)")
    ap.add_argument("--dropout", type=lambda t: _number(t, float, 0, below=1), default=0.0,
                    help="probability that a node is lost in a frame (default 0)")
    ap.add_argument("--record-every", type=lambda t: _number(t, int, 1), default=50,
                    help="substeps between frames during a move (default 50)")
    ap.add_argument("--scale", type=_scale, action="append", default=[], metavar="NAME=FACTOR",
                    help=f"multiply a parameter of the true rope ({', '.join(PHYSICAL)}); repeatable")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    return ap


def _run(argv: list[str] | None) -> str:
    args = parser().parse_args(argv)
    out = Path(args.out)
    if out.suffix != ".npz":
        raise UsageError(f"--out must end in .npz, got {args.out!r}")
    if out.is_dir():
        raise UsageError(f"--out {args.out!r} is a folder, not a file")
    if out.exists() and not args.overwrite:
        raise UsageError(f"--out {args.out!r} already exists: choose another --out or pass --overwrite to replace it")
    scale: dict[str, float] = {}
    for name, factor in args.scale:
        if name in scale:
            raise UsageError(f"--scale {name} given twice ({scale[name]:g} and {factor:g})")
        scale[name] = factor
    try:
        params = load_params(args.params)
        scaled_params(params, scale)
    except ParamsError as exc:
        raise UsageError(f"--params {args.params!r} with --scale {scale}: {exc}") from None
    rec = make_recording(params, args.moves, args.seed, args.noise, args.dropout, args.record_every, scale,
                         args.params)
    save_recording(out, rec)
    true = ", ".join(f"{k}={v:g}" for k, v in rec.meta["true_params"].items())
    scaled = f" (scaled: {', '.join(f'{k} x{v:g}' for k, v in scale.items())})" if scale else ""
    lost = f", {int((~rec.visible).sum())} of {rec.visible.numel()} node positions dropped" if args.dropout else ""
    return (f"wrote {out}: {rec.n_frames} frames of {rec.n_nodes} nodes, {rec.n_moves} moves, {rec.duration:.3f} s "
            f"(a frame every {args.record_every} substeps of {params.dt:g} s), noise {args.noise:g} m{lost}; "
            f"true parameters {true}{scaled}")


def main(argv: list[str] | None = None) -> int:
    try:
        summary = _run(argv)
    except UsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    print(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
