"""Pegs and the second gripper, checked (docs/SIMULATOR.md "Pegs and the second gripper"; rows of
``python -m benchmarks.physics_checks``, which calls ``run_all`` and ``rows`` here; tests/test_contact.py asserts the
same properties on fewer cases).

- the contact forces against autograd of the contact energy, and gradcheck through a move in contact with a pin;
- the deepest overlap of any link with any peg, in every recorded substep and at the end of every move, over random
  ropes, pegs (1-4, 2-30 mm), drags (up to the largest) and pins;
- a rope dragged around a peg: its winding round the peg, its overlap, and after 2 s released;
- momentum with contact off and on, energy without damping and with it;
- the gradient's quality at the onset of contact: d(result)/d(drag) as the drag carries the rope into a peg,
  analytic (autograd through the move) against central finite differences, and the first-order (the analytic
  gradient averaged over Gaussian perturbations of the drag) against the zero-order (randomly smoothed, antithetic)
  estimate of the smoothed result's gradient, for several contact widths and perturbation scales: bias and spread.

    python -m benchmarks.contact_checks                 # prints the rows (a few minutes on 2 cores)
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import torch

from diffdlo.planar import contact
from diffdlo.tasks import routing
from diffdlo.planar.params import CableParams, load_params
from diffdlo.planar.shapes import target_shape
from diffdlo.planar.simulator import Simulator
from diffdlo.utils.files import check_fresh_file

F64 = torch.float64


def line(p: CableParams, batch: int = 1) -> torch.Tensor:
    return target_shape("horizontal", p, dtype=F64)[None].repeat(batch, 1, 1)


def winding(pos: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """(B,) the angle [rad] each rope (B, N, 2) turns around one ``centre`` (2,) (routing.winding)."""
    return routing.winding(pos, centre.expand(pos.shape[0], 1, 2))[:, 0]


def frames_depth(frames: torch.Tensor, pegs: torch.Tensor, radius: float) -> torch.Tensor:
    """(B,) the deepest overlap over recorded frames (T, B, N, 2) with pegs (B, K, 3)."""
    t, b = frames.shape[:2]
    flat = frames.reshape(t * b, *frames.shape[2:])
    return contact.depth(flat, pegs.repeat(t, 1, 1), radius).view(t, b).amax(0)


# ====================================================================== the model
def forces_vs_autograd(p: CableParams, batch: int = 64, seed: int = 0) -> dict:
    """Random ropes among random pegs, some links lifted: max |F + dE/dx| relative to max |F|."""
    g = torch.Generator().manual_seed(seed)
    sim = Simulator(p, dtype=F64)
    pos = sim.random_shape(batch, g).double()
    nodes = pos[torch.arange(batch), torch.randint(0, p.n_nodes, (batch,), generator=g)]       # (B, 2)
    offset = 0.03 * torch.randn(batch, 4, 2, generator=g, dtype=F64)
    pegs = torch.cat([nodes[:, None] + offset, 0.005 + 0.02 * torch.rand(batch, 4, 1, generator=g, dtype=F64)], -1)
    weight = contact.lifted_links(torch.randint(0, p.n_nodes, (batch,), generator=g), p.n_nodes, F64)
    args = (p.rope_radius, p.contact_stiffness, p.contact_width)
    x = pos.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(contact.energy(x, pegs, *args, weight).sum(), x)
    f = contact.forces(pos, pegs, *args, weight)
    z = contact.overlap(pos, pegs, p.rope_radius)
    return {"ropes": batch, "pairs_in_contact": int((z > 0).sum()), "pairs_past_width": int((z > p.contact_width).sum()),
            "max_rel_error": float((f + grad).abs().max() / f.abs().max())}


def gradcheck_move(p: CableParams) -> dict:
    """torch.autograd.gradcheck (float64) of a 6-node move pulled into a peg with a pin, w.r.t. start and drag."""
    small = dataclasses.replace(p, n_nodes=6, length=0.15, max_speed=1.0, settle_max_substeps=30, settle_check_every=10)
    sim = Simulator(small, dtype=F64)
    pos = line(small)
    pegs = torch.tensor([[float(pos[0, 4, 0]), 0.006 + small.rope_radius + 0.0005, 0.006]], dtype=F64)
    node, delta, pin = torch.tensor([5]), torch.tensor([[0.0, 0.0305]], dtype=F64), torch.tensor([0])
    _, info = sim.move(pos, node, delta, pegs, pin, return_info=True, record_every=1)
    deepest = float(frames_depth(info.frames, pegs[None], small.rope_radius)[0])
    f = lambda x, d: sim.move(x, node, d, pegs, pin)
    ok = torch.autograd.gradcheck(f, (pos.clone().requires_grad_(True), delta.clone().requires_grad_(True)),
                                  eps=1e-7, atol=1e-5, rtol=1e-4, raise_exception=False)
    return {"passed": bool(ok), "deepest_overlap": deepest, "engine": sim.contact_engine}


# ====================================================================== no rope ends inside a peg
def random_scenes(p: CableParams, batch: int, seed: int) -> tuple[torch.Tensor, ...]:
    """Random ropes (the env's sigma) with boards of 4 slots (pegs of 2-30 mm, 1-4 in play, the others empty:
    radius 0) scattered around the rope, none touching the start (so every overlap measured comes from the moves)
    and each two the rope's diameter apart (the simulator's board rule); drags of 2 cm to the largest, pins on half
    of the ropes."""
    g = torch.Generator().manual_seed(seed)
    sim = Simulator(p, dtype=F64)
    pos = sim.random_shape(batch, g).double()
    radius = 0.002 + 0.028 * torch.rand(batch, 4, 1, generator=g, dtype=F64)
    anchor = pos[torch.arange(batch)[:, None], torch.randint(0, p.n_nodes, (batch, 4), generator=g)]
    centre = anchor + (radius + p.rope_radius) * 1.5 * torch.randn(batch, 4, 2, generator=g, dtype=F64)
    in_play = torch.arange(4)[None] < torch.randint(1, 5, (batch, 1), generator=g)
    pegs = torch.cat([centre, radius], -1)
    touching = (contact.overlap(pos, pegs, p.rope_radius) > 0).any(1)               # (B, K): drop those pegs
    gap = (centre[:, :, None] - centre[:, None]).norm(dim=-1) - radius - radius.transpose(1, 2)     # (B, K, K)
    crowded = ((gap < 2 * p.rope_radius) & torch.ones(4, 4, dtype=torch.bool).tril(-1)).any(2)   # and the later
    pegs[..., 2] *= (in_play & ~touching & ~crowded).to(F64)        # of two pegs closer than the rope's diameter
    node = torch.randint(0, p.n_nodes, (batch,), generator=g)
    angle = 2 * math.pi * torch.rand(batch, generator=g, dtype=F64)
    length = torch.where(torch.rand(batch, generator=g) < 0.5, torch.full((batch,), p.max_disp, dtype=F64),
                         0.02 + (p.max_disp - 0.02) * torch.rand(batch, generator=g, dtype=F64))
    delta = length[:, None] * torch.stack([angle.cos(), angle.sin()], -1)
    pin = torch.randint(0, p.n_nodes, (batch,), generator=g)
    pin = torch.where((pin == node) | (torch.rand(batch, generator=g) < 0.5), -1, pin)
    return pos, pegs, node, delta, pin


def path_scenes(p: CableParams, batch: int, seed: int, slots: int = 4, small: tuple[float, float] = (0.002, 0.008),
                pins: bool = True) -> tuple[torch.Tensor, ...]:
    """The hard case for putting the rope down: random ropes and drags (4-10 cm) with 1-``slots`` pegs, the first a
    small one (radius in ``small``) on the grasped node's path past half of it, so that the lifted links are carried
    over it and put down across it; the others beside the path; none touching the start rope nor the drag's end,
    each two the rope's diameter apart; pins on half of the ropes with ``pins``. Returns (pos, pegs (B, slots, 3)
    with empty rows of radius 0, node, delta, pin)."""
    g = torch.Generator().manual_seed(seed)
    sim = Simulator(p, dtype=F64)
    pos = sim.random_shape(batch, g).double()
    node = torch.randint(0, p.n_nodes, (batch,), generator=g)
    angle = 2 * math.pi * torch.rand(batch, generator=g, dtype=F64)
    along = torch.stack([angle.cos(), angle.sin()], -1)
    delta = (0.04 + 0.06 * torch.rand(batch, generator=g, dtype=F64))[:, None] * along
    start = pos[torch.arange(batch), node]
    across = torch.stack([-along[:, 1], along[:, 0]], -1)
    pegs = torch.zeros(batch, slots, 3, dtype=F64)
    unit = lambda: float(torch.rand(1, generator=g, dtype=F64))
    for b in range(batch):
        want, k = int(torch.randint(1, slots + 1, (1,), generator=g)), 0
        for attempt in range(100):
            if k == want:
                break
            if attempt == 0:                   # small, on the path near its end: carried over, put down across it
                radius = small[0] + (small[1] - small[0]) * unit()
                centre = start[b] + (0.55 + 0.4 * unit()) * delta[b] + 0.004 * (2 * unit() - 1) * across[b]
            else:                              # beside the path
                radius = 0.004 + 0.012 * unit()
                side = 1.0 if unit() < 0.5 else -1.0
                centre = start[b] + unit() * delta[b] + side * (radius + 0.02 * unit()) * across[b]
            peg = torch.cat([centre, torch.tensor([radius], dtype=F64)])
            if float(contact.overlap(pos[b:b + 1], peg[None, None], p.rope_radius).max()) > 0:
                continue
            if float((start[b] + delta[b] - centre).norm()) < radius + 0.002:
                continue
            gaps = (pegs[b, :k, :2] - centre).norm(dim=-1) - pegs[b, :k, 2] - radius
            if bool((gaps < 2 * p.rope_radius).any()):
                continue
            pegs[b, k] = peg
            k += 1
    pin = torch.randint(0, p.n_nodes, (batch,), generator=g)
    pin = torch.where((pin == node) | (torch.rand(batch, generator=g) < 0.5) | (not pins), -1, pin)
    return pos, pegs, node, delta, pin


def put_down(p: CableParams, batch: int = 512, batches: int = 8, seed: int = 0) -> dict:
    """``path_scenes``' moves (``batches`` x ``batch``), each followed by a second move from its result: how many
    ended with the rope's axis inside a peg before it was put down (pushed out; let go earlier), the deepest overlap
    after, and whether every next move accepted its start."""
    sim = Simulator(p, dtype=F64)
    pushed = early = 0
    deepest = -1.0
    t0 = time.perf_counter()
    for i in range(batches):
        pos, pegs, node, delta, pin = path_scenes(p, batch, seed + i)
        out, info = sim.move(pos, node, delta, pegs, pin, return_info=True)
        sim.move(out, node, -0.5 * delta, pegs)                  # raises if a result is no valid start
        pushed += int(info.pushed_out.sum())
        early += int((info.drag_share < 1).sum())
        deepest = max(deepest, float(contact.depth(out, pegs, p.rope_radius).max()))
    return {"moves": batch * batches, "pushed_out": pushed, "let_go_earlier": early, "deepest_after": deepest,
            "engine": sim.contact_engine, "seconds": time.perf_counter() - t0}


def max_depth(p: CableParams, batch: int = 256, moves: int = 3, seed: int = 0, every: int = 10) -> dict:
    """``moves`` random moves in a row of ``batch`` random scenes, recorded every ``every`` substeps: the deepest
    overlap of the links on the table during the drags (the grasped node's two links lifted), the deepest at the
    end of the moves, and the moves that released their node above a peg (its axis inside one)."""
    sim = Simulator(p, dtype=F64)
    pos, pegs, _, _, _ = random_scenes(p, batch, seed)
    drag, after, released_inside, touched = [], [], 0, 0
    t0 = time.perf_counter()
    for m in range(moves):
        _, _, node, delta, pin = random_scenes(p, batch, seed + 1000 * (m + 1))
        pos, info = sim.move(pos, node, delta, pegs, pin, return_info=True, record_every=every)
        frames = info.frames                                                         # (T, B, N, 2)
        t, b = frames.shape[:2]
        z = contact.overlap(frames.reshape(t * b, *frames.shape[2:]), pegs.repeat(t, 1, 1), p.rope_radius)
        z = z.view(t, b, p.n_nodes - 1, -1).amax(-1)                                  # (T, B, L)
        dragging = (torch.arange(t)[:, None] * every <= info.drag_substeps[None]).unsqueeze(-1)   # (T, B, 1)
        on_table = contact.lifted_links(node, p.n_nodes, F64).bool()[None]             # (1, B, L)
        drag.append(torch.where(dragging & on_table, z, torch.full_like(z, -1.0)).amax((0, 2)))
        at_release = frames[(info.drag_substeps // every).clamp(max=t - 1), torch.arange(b)]       # (B, N, 2)
        node_xy = at_release[torch.arange(b), node][:, None]                                       # (B, 1, 2)
        inside = ((node_xy - pegs[..., :2]).norm(dim=-1) < pegs[..., 2]).any(-1) & (info.drag_substeps > 0)
        released_inside += int(inside.sum())
        touched += int((z.amax((0, 2)) > 0).sum())
        after.append(contact.depth(pos, pegs, p.rope_radius))
    drag, after = torch.stack(drag), torch.stack(after)
    return {"moves": batch * moves, "touched": touched, "deepest_drag_on_table": float(drag.max()),
            "deepest_after": float(after.max()), "median_after_touching": float(after[after > 0].median()),
            "released_above_a_peg": released_inside, "engine": sim.contact_engine,
            "seconds": time.perf_counter() - t0}


def largest_pull(p: CableParams) -> dict:
    """The rope wrapped round a peg (``wrap``), pinned at node 0 and its end dragged 0.1 m away, three times: the
    overlap and the rope's stretch (the tension the peg holds)."""
    sim = Simulator(p, dtype=F64)
    pos, pegs, _ = wrapped(p, sim)
    deepest, stretch = -1.0, 0.0
    for _ in range(3):
        pos, info = sim.move(pos, torch.tensor([19]), torch.tensor([[-0.1, 0.0]], dtype=F64), pegs, torch.tensor([0]),
                             return_info=True, record_every=1)
        deepest = max(deepest, float(frames_depth(info.frames, pegs[None], p.rope_radius)[0]))
        length = (info.frames[:, 0, 1:] - info.frames[:, 0, :-1]).norm(dim=-1).sum(-1).max()
        stretch = max(stretch, float(length) / p.length - 1.0)
    return {"deepest": deepest, "stretch": stretch, "winding": float(winding(pos, pegs[0, :2])[0])}


# ====================================================================== wrap
WRAP_MOVES = [(19, (0.0, 0.1))] + [(19, (-0.1, 0.0))] * 3 + [(19, (-0.1, -0.03)), (19, (-0.1, 0.0)), (19, (-0.1, 0.0)),
                                                             (0, (-0.1, 0.0))]


def wrapped(p: CableParams, sim: Simulator, record_every: int = 0) -> tuple[torch.Tensor, torch.Tensor, list]:
    """A straight rope with a peg 2 cm above its middle, its end dragged up, over and past the peg, then the loop
    tightened (WRAP_MOVES). Returns (pos, pegs, the recorded frames of every move)."""
    pos = line(p)
    pegs = torch.tensor([[0.0, 0.02, 0.01]], dtype=F64)
    frames = []
    for node, d in WRAP_MOVES:
        out = sim.move(pos, torch.tensor([node]), torch.tensor([d], dtype=F64), pegs, return_info=record_every > 0,
                       record_every=record_every)
        pos = out[0] if record_every > 0 else out
        if record_every > 0:
            frames.append(out[1].frames[:, 0])
    return pos, pegs, frames


def wrap(p: CableParams) -> dict:
    sim = Simulator(p, dtype=F64)
    pos, pegs, _ = wrapped(p, sim)
    rest, _ = sim.integrate(pos, None, 2000, pegs=pegs)
    return {"moves": len(WRAP_MOVES), "winding": float(winding(pos, pegs[0, :2])[0]),
            "depth": float(contact.depth(pos, pegs[None], p.rope_radius)[0]),
            "winding_after_2s": float(winding(rest, pegs[0, :2])[0]),
            "depth_after_2s": float(contact.depth(rest, pegs[None], p.rope_radius)[0])}


# ====================================================================== momentum, energy
def conservation(p: CableParams) -> dict:
    """A straight rope thrown at +0.5 m/s (k_d = 0, dt = 0.25 ms, which keeps the contact stable undamped) at a peg:
    momentum with the peg out of reach and in reach; energy (kinetic + elastic + contact) without damping and with
    k_d = 0.05 N s/m."""
    res = {}
    for k_d in (0.0, 0.05):
        q = dataclasses.replace(p, k_d=k_d, dt=2.5e-4)
        sim = Simulator(q, dtype=F64, backend="torch")
        vel = torch.zeros(1, q.n_nodes, 2, dtype=F64)
        vel[0, :, 1] = 0.5
        for name, peg in (("off", [0.02, 0.5, 0.01]), ("on", [0.02, 0.03, 0.01])):
            pegs = torch.tensor([peg], dtype=F64)
            pos, v = line(q), vel
            energy = lambda x, u: float(0.5 * q.node_mass * (u ** 2).sum() + sim.energy(x).sum()
                                        + sim.contact_energy(x, pegs).sum())
            e = [energy(pos, v)]
            for _ in range(40):
                pos, v = sim.integrate(pos, v, 10, pegs=pegs)
                e.append(energy(pos, v))
            momentum = float(v[0].sum(0).norm() / vel[0].sum(0).norm()) - 1.0
            res[f"k_d={k_d:g}, contact {name}"] = {
                "momentum_rel_change": momentum, "energy_rel_spread": (max(e) - min(e)) / e[0],
                "energy_max_rise": max(b - a for a, b in zip(e, e[1:])) / e[0], "energy_left": e[-1] / e[0]}
    return res


# ====================================================================== the gradient at the onset of contact
ONSET_PEG = (0.19, -0.03, 0.01)       # the rope's end node (19) dragged straight down by s carries node 17 into it


def onset_result(sim: Simulator, s: torch.Tensor, pegs: torch.Tensor) -> torch.Tensor:
    """(S,) the final y of node 17 after dragging node 19 of the straight rope down by s (S,) with the peg."""
    pos = line(sim.params, len(s))
    delta = torch.stack([torch.zeros_like(s), -s], -1)
    return sim.move(pos, torch.full((len(s),), 19), delta, pegs)[:, 17, 1]


def onset_gradients(p: CableParams, width: float, sigmas=(0.001, 0.005), grid: int = 13, samples: int = 32,
                    fd_step: float = 1e-6, seed: int = 0) -> dict:
    """At ``grid`` drags s across the onset of contact (first touch near s = 0.075 m, 1 mm apart): the
    analytic df/ds, central differences, and for each perturbation scale sigma the first-order estimate mean(f'(s +
    sigma u)) and the zero-order one mean((f(s + sigma u) - f(s - sigma u)) u / (2 sigma)) over ``samples``
    antithetic draws u ~ N(0, 1) (the same draws for both), their means and standard errors."""
    q = dataclasses.replace(p, contact_width=width)
    sim = Simulator(q, dtype=F64)
    pegs = torch.tensor([ONSET_PEG], dtype=F64)
    # half a substep's path (0.05 mm) off the whole numbers of substeps, where the drag's length enters the move only
    # through the release share's clamp (docs/SIMULATOR.md "Pegs and the second gripper" on that boundary)
    s = torch.linspace(0.070, 0.082, grid, dtype=F64) + 0.5 * p.max_speed * p.dt
    x = s.clone().requires_grad_(True)
    f = onset_result(sim, x, pegs)
    (analytic,) = torch.autograd.grad(f.sum(), x)
    with torch.no_grad():
        fd = (onset_result(sim, s + fd_step, pegs) - onset_result(sim, s - fd_step, pegs)) / (2 * fd_step)
    # a planner's step: how well f(s) + f'(s) (s' - s) predicts the next grid point's f(s')
    change = f.detach().diff()
    linear = (analytic[:-1] * s.diff() - change).abs() / change.abs()
    out = {"width": width, "s": s.tolist(), "f": f.detach().tolist(), "analytic": analytic.tolist(), "fd": fd.tolist(),
           "fd_rel_error": float((analytic - fd).abs().max() / analytic.abs().max()),
           "linear_step": float(s[1] - s[0]), "linear_rel_error": linear.tolist(), "smoothed": {}}
    g = torch.Generator().manual_seed(seed)
    for sigma in sigmas:
        u = torch.randn(grid, samples, generator=g, dtype=F64)
        xs = (s[:, None] + sigma * u).flatten().requires_grad_(True)
        fp = onset_result(sim, xs, pegs)
        (first,) = torch.autograd.grad(fp.sum(), xs)
        with torch.no_grad():
            fm = onset_result(sim, (s[:, None] - sigma * u).flatten(), pegs)
        zero = ((fp.detach() - fm) * u.flatten() / (2 * sigma)).view(grid, samples)
        first = first.view(grid, samples)
        se = lambda v: (v.std(1) / math.sqrt(samples)).tolist()
        out["smoothed"][str(sigma)] = {"first_order": first.mean(1).tolist(), "first_order_se": se(first),
                                       "zero_order": zero.mean(1).tolist(), "zero_order_se": se(zero)}
    return out


def sawtooth(p: CableParams, drags=(0.070, 0.080), shares=(0.01, 0.25, 0.5, 0.75, 0.99)) -> dict:
    """df/ds (onset_result) at s = drag + share x max_speed dt: the move's derivative along the drag within one
    substep of the path (the release blended within the last substep makes it a sawtooth)."""
    sim = Simulator(p, dtype=F64)
    pegs = torch.tensor([ONSET_PEG], dtype=F64)
    out = {}
    for drag in drags:
        s = (drag + torch.tensor(shares, dtype=F64) * p.max_speed * p.dt).requires_grad_(True)
        (g,) = torch.autograd.grad(onset_result(sim, s, pegs).sum(), s)
        out[str(drag)] = dict(zip(map(str, shares), g.tolist()))
    return out


def gradient_quality(p: CableParams, widths=(0.0005, 0.0025, 0.005), **kw) -> list[dict]:
    return [onset_gradients(p, w, **kw) for w in widths]


def wrap_figure(path: Path, p: CableParams | None = None) -> Path:
    """The wrap, drawn: the rope (its capsules to scale) after selected moves of WRAP_MOVES, pinned and pulled, and
    2 s after its release; the peg grey, node 0 a red square, the grasped node an orange star."""
    from diffdlo.utils.render import _pyplot
    plt = _pyplot()
    p = p or load_params("cable")
    sim = Simulator(p, dtype=F64)
    pos, pegs = line(p), torch.tensor([[0.0, 0.02, 0.01]], dtype=F64)
    panels = [("start", pos, None)]
    for i, (node, d) in enumerate(WRAP_MOVES, 1):
        pos = sim.move(pos, torch.tensor([node]), torch.tensor([d], dtype=F64), pegs)
        if i in (1, 4, 5, len(WRAP_MOVES)):
            panels.append((f"move {i}: node {node} by ({d[0]:+.2f}, {d[1]:+.2f}) m", pos, node))
    pos = sim.move(pos, torch.tensor([19]), torch.tensor([[-0.1, 0.0]], dtype=F64), pegs, torch.tensor([0]))
    panels.append(("node 0 pinned, node 19 by (-0.10, +0.00) m", pos, 19))
    rest, _ = sim.integrate(pos, None, 2000, pegs=pegs)
    panels.append(("released, 2 s later", rest, None))
    panels.append(("the same, near the peg", rest, None))
    fig, axes = plt.subplots(2, 4, figsize=(16, 4.6))
    for ax, (title, rope, grasped) in zip(axes.flat, panels):
        xy = rope[0].numpy()
        ax.add_patch(plt.Circle(tuple(pegs[0, :2].tolist()), float(pegs[0, 2]), color="0.6", zorder=1))
        ax.plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=4.0, alpha=0.6, zorder=2,   # ~ the 1 cm cable
                solid_capstyle="round")
        ax.plot(xy[:, 0], xy[:, 1], "o", color="tab:blue", ms=3, zorder=3)
        ax.plot(xy[0, 0], xy[0, 1], "s", color="tab:red", ms=6, zorder=4)
        if grasped is not None:
            ax.plot(xy[grasped, 0], xy[grasped, 1], "*", color="tab:orange", ms=12, zorder=5)
        turn = float(winding(rope, pegs[0, :2])[0]) / math.pi
        ax.set_title(f"{title}\nwinding {turn:.2f} pi", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlim(-0.3, 0.3)
        ax.set_ylim(-0.06, 0.1)
        ax.tick_params(labelsize=8)
    zoom = axes.flat[-1]
    zoom.set_xlim(-0.05, 0.05)
    zoom.set_ylim(-0.03, 0.07)
    fig.suptitle("A rope dragged round a peg (grey, 1 cm) wraps and stays wrapped: "
                 "python -m benchmarks.contact_checks --figure docs/figures/wrap.png", fontsize=10)
    fig.tight_layout()
    fig.canvas.draw()                                                          # sets the equal-aspect box
    points_per_m = zoom.get_window_extent().width / fig.dpi * 72 / 0.1        # the zoom's x span is 0.1 m
    for a, b in zip(rest[0, :-1].numpy(), rest[0, 1:].numpy()):               # the rope's capsules, to scale
        zoom.plot([a[0], b[0]], [a[1], b[1]], "-", color="tab:blue", alpha=0.3, zorder=2, solid_capstyle="round",
                  lw=2 * p.rope_radius * points_per_m)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# ====================================================================== all, and the rows
def run_all(p: CableParams | None = None, scenes: int = 256) -> dict:
    p = p or load_params("cable")
    t0 = time.perf_counter()
    res = {"forces": forces_vs_autograd(p), "gradcheck": gradcheck_move(p), "depth": max_depth(p, scenes),
           "put_down": put_down(p),
           "largest_pull": largest_pull(p), "wrap": wrap(p), "conservation": conservation(p),
           "gradient_quality": gradient_quality(p), "sawtooth": sawtooth(p)}
    res["seconds"] = time.perf_counter() - t0
    return res


def rows(res: dict, cmd: str = "`python -m benchmarks.contact_checks`") -> list[str]:
    """Markdown rows: the checks (the physics table's columns), then the gradient-quality table."""
    fo, gc, de, lp, wr = res["forces"], res["gradcheck"], res["depth"], res["largest_pull"], res["wrap"]
    pd = res["put_down"]
    out = [
        f"| contact forces vs -grad of the contact energy, {fo['ropes']} random ropes among 4 pegs, links lifted | "
        f"equal | max rel. error {fo['max_rel_error']:.1e} ({fo['pairs_in_contact']} link-peg pairs touching, "
        f"{fo['pairs_past_width']} past the width) | {cmd} |",
        f"| gradcheck (float64) through a 6-node move pulled {gc['deepest_overlap'] * 1e3:.1f} mm into a peg, with a "
        f"pin | passes | {'passes' if gc['passed'] else 'FAILS'} ({gc['engine']}) | {cmd} |",
        f"| deepest overlap with a peg, {de['moves']} random moves (1-4 pegs of 2-30 mm, drags to 0.1 m, pins on "
        f"half), {de['touched']} touching, {de['released_above_a_peg']} releasing their node above a peg | "
        f"< the rope's radius (5 mm: its axis outside) | links on the table during the drag "
        f"{de['deepest_drag_on_table'] * 1e3:.2f} mm; after the move {de['deepest_after'] * 1e3:.2f} mm (median of "
        f"those touching {de['median_after_touching'] * 1e3:.2f} mm) | {cmd} |",
        f"| putting the rope down: {pd['moves']} moves with a small peg (2-8 mm) on the grasped node's path and "
        f"0-3 beside it, pins on half; {pd['pushed_out']} left by the settle with an axis inside a peg and pushed "
        f"out, {pd['let_go_earlier']} let go earlier | every result a valid start (its axis outside every peg) | "
        f"deepest overlap after the move {pd['deepest_after'] * 1e3:.2f} mm; every next move accepted its start "
        f"({pd['engine']}) | {cmd} |",
        f"| a wrapped rope pinned at one end, its other end dragged 0.1 m away 3 times (stretched "
        f"{lp['stretch'] * 100:.0f} %) | not pulled through | deepest {lp['deepest'] * 1e3:.2f} mm, winding "
        f"{lp['winding'] / math.pi:.2f} pi | {cmd} |",
        f"| a rope dragged round a peg ({wr['moves']} moves), then 2 s released | wraps, stays wrapped | winding "
        f"{wr['winding'] / math.pi:.2f} pi, overlap {wr['depth'] * 1e3:.2f} mm; after 2 s "
        f"{wr['winding_after_2s'] / math.pi:.2f} pi, {wr['depth_after_2s'] * 1e3:.2f} mm | {cmd} |",
    ]
    expected = {"k_d=0, contact off": "momentum conserved; energy bounded",
                "k_d=0, contact on": "momentum changed by the peg; energy bounded",
                "k_d=0.05, contact off": "energy non-increasing", "k_d=0.05, contact on": "energy non-increasing"}
    for name, c in res["conservation"].items():
        out.append(f"| {name}: a rope thrown at a peg, 400 substeps of 0.25 ms: momentum; energy | "
                   f"{expected[name]} | momentum "
                   f"{c['momentum_rel_change']:+.1e}; energy spread {c['energy_rel_spread']:.1e}, largest rise "
                   f"{c['energy_max_rise']:+.1e}, {c['energy_left']:.3f} left | {cmd} |")
    out += ["", "| contact width | analytic vs central FD (max rel.) | df/ds across the onset (min / max) | "
            "linear prediction over one grid step (max rel. error) | smoothing sigma | first-order minus zero-order "
            "(max, in standard errors) | spread: zero-order / first-order standard error (median) |",
            "|---|---|---|---|---|---|---|"]
    for gq in res["gradient_quality"]:
        for j, (sigma, sm) in enumerate(gq["smoothed"].items()):
            fo, zo = torch.tensor(sm["first_order"]), torch.tensor(sm["zero_order"])
            fse, zse = torch.tensor(sm["first_order_se"]), torch.tensor(sm["zero_order_se"])
            bias = float(((fo - zo).abs() / (fse ** 2 + zse ** 2).sqrt()).max())
            spread = float((zse / fse).median())
            lead = (f"| {gq['width'] * 1e3:g} mm | {gq['fd_rel_error']:.1e} | {min(gq['analytic']):+.3f} / "
                    f"{max(gq['analytic']):+.3f} | {max(gq['linear_rel_error']):.2f} ({gq['linear_step'] * 1e3:g} mm) "
                    if j == 0 else "| | | | ")
            out.append(f"{lead}| {float(sigma) * 1e3:g} mm | {bias:.1f} | {spread:.1f}x |")
    default = next(gq for gq in res["gradient_quality"] if math.isclose(gq["width"], load_params("cable").contact_width))
    out += ["", f"At the default width ({default['width'] * 1e3:g} mm), per drag s [m]: the result f (node 17's final y "
            f"[m]), df/ds analytic and by central differences, and the smoothed estimates (mean ± standard error):",
            "", "| s | f | analytic | central FD | " + " | ".join(
                f"sigma {float(k) * 1e3:g} mm: first-order | zero-order" for k in default["smoothed"]) + " |",
            "|---|---|---|---|" + "---|---|" * len(default["smoothed"])]
    for i, s in enumerate(default["s"]):
        cells = [f"{s:.5f}", f"{default['f'][i]:+.5f}", f"{default['analytic'][i]:+.4f}", f"{default['fd'][i]:+.4f}"]
        for sm in default["smoothed"].values():
            cells += [f"{sm['first_order'][i]:+.3f} ± {sm['first_order_se'][i]:.3f}",
                      f"{sm['zero_order'][i]:+.3f} ± {sm['zero_order_se'][i]:.3f}"]
        out.append("| " + " | ".join(cells) + " |")
    for drag, by_share in res["sawtooth"].items():
        values = list(by_share.values())
        out.append(f"\nAlong the drag, within one substep of its path at s = {float(drag):.3f} m (s + 0.01 ... 0.99 of "
                   f"max_speed dt): df/ds {', '.join(f'{v:+.3f}' for v in values)}.")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.contact_checks", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="write results.json here (refuses an existing one without --overwrite)")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--scenes", type=int, default=256, help="random scenes of the overlap check (default 256)")
    ap.add_argument("--figure", type=Path, help="only draw the wrap to this PNG (refuses an existing file without "
                                                  "--overwrite)")
    args = ap.parse_args(argv)
    if args.scenes < 1:
        ap.error(f"--scenes must be >= 1, got {args.scenes}")
    written = args.figure if args.figure is not None else None if args.out is None else args.out / "results.json"
    try:
        if written is not None:
            check_fresh_file(written, args.overwrite)
    except FileExistsError as exc:
        print(exc, file=sys.stderr)
        return 2
    if args.figure is not None:
        print(f"wrote {wrap_figure(args.figure)}")
        return 0
    res = run_all(scenes=args.scenes)
    print("\n".join(rows(res)))
    print(f"\n({res['seconds']:.0f} s)")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "results.json").write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
