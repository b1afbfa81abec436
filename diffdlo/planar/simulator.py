"""The batched, differentiable cable simulator: grasp -> drag -> release -> settle (Algorithm 2, model.move_idx).

State is plain tensors with a leading batch dimension: positions and velocities (B, N, 2). The Simulator only
holds the (immutable) parameters, device and dtype; every method is a function of its inputs.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import torch

from . import contact, control, shapes
from .backends import kernel, triton_kernel
from .forces import energy, internal_forces
from .integrate import max_speed, semi_implicit_step
from .params import CableParams, check_contact_stability, load_params
from .physics import Physics

# A rope farther than this from the origin [m] has diverged (50x the thesis's 2 m workspace).
DIVERGENCE_RADIUS = 100.0
# Consecutive nodes of an input state closer than this fraction of the rest length are (nearly) coincident: their
# link has no direction, so the spring and bending forces are garbage or NaN. No rope state a move produces comes
# near it: after random 0.1 m moves the shortest link is ~90% of the rest length (default params, both controllers)
# and ~10% with 1 m/s drags and no settling on a 6-node rope.
MIN_STATE_LINK_FRACTION = 0.01
# A start state may overlap a peg by at most the rope's radius (its axis outside the peg). No move ends deeper: a
# rope the settle leaves with its axis inside a peg (pressed in by the rope's own tension, wedged between pegs, or a
# lifted link released across one, where the penalty's compliance is the model's, not the post's) is pushed out at
# the end of the move to PUSH_OUT_CLEARANCE_RADII of the rope's radius clear of the axis (contact.push_out), so a
# move's result is always a valid start (tests/test_contact.py, benchmarks/physics_checks.py).
MAX_START_DEPTH_RADII = 1.0
PUSH_OUT_CLEARANCE_RADII = 0.02
PUSH_OUT_ITERATIONS = 1000
# A rope that no push-out gets out is moved again with the gripper letting go at these shares of its drag, in turn.
LET_GO_EARLIER = (0.5, 0.25, 0.0)


class SimulationError(RuntimeError):
    """The simulation produced NaN/inf or diverged; the message names the batch members and the action."""


@dataclasses.dataclass
class MoveInfo:
    """What one ``move`` did, per rope (CPU tensors of shape (B,))."""

    drag_substeps: torch.Tensor      # substeps with the node grasped
    settle_substeps: torch.Tensor    # substeps of free evolution after release
    settled: torch.Tensor            # bool: reached the speed threshold (False: stopped by the cap)
    frames: torch.Tensor | None = None   # (T, B, N, 2) positions every ``record_every`` substeps, if asked
    pushed_out: torch.Tensor | None = None   # bool: the settle left the rope's axis inside a peg, pushed out after
    drag_share: torch.Tensor | None = None   # float64: the share of the drag done before the release (1 unless the
                                             # gripper let go earlier so as not to put the rope down inside a peg)

    @property
    def substeps(self) -> torch.Tensor:
        return self.drag_substeps + self.settle_substeps


BACKENDS = ("auto", "kernel", "torch", "triton")
ENGINES = ("kernel", "triton", "torch")          # what runs the moves, in the order "auto" prefers them
CONTACT_ENGINES = ("kernel", "torch")            # the engines that run moves with pegs and the pin


def _resolve_engine(params: CableParams, device: torch.device, backend: str) -> tuple[str, dict[str, str]]:
    """The engine that runs every move and free evolution of a Simulator (one of ENGINES), and for each fused kernel
    ("kernel", "triton") not in use, why not. An explicit "kernel" or "triton" backend must already have passed the
    Simulator's checks. The C++ kernel is asked whether it is available (built or loaded on first use, then cached
    for the process) only where "auto" would run it: CPU tensors and the kinematic controller."""
    why_not = {}
    if backend in ("torch", "triton"):
        why_not["kernel"] = f"backend is {backend!r}"
    elif device.type != "cpu":
        why_not["kernel"] = f"the fused C++ kernel runs on the CPU only, not on {device}"
    elif params.controller != "kinematic":
        why_not["kernel"] = f"the fused C++ kernel supports the kinematic controller only, not {params.controller!r}"
    elif backend == "auto" and not kernel.available():
        why_not["kernel"] = f"the fused C++ kernel is unavailable: {kernel.unavailable_reason()}"
    if backend not in ("triton", "auto"):
        why_not["triton"] = f"backend is {backend!r}"
    elif backend == "auto" and device.type != "cuda":
        why_not["triton"] = "backend 'auto' uses the Triton kernel on CUDA devices only"
    elif params.controller != "kinematic":
        why_not["triton"] = f"the Triton kernel supports the kinematic controller only, not {params.controller!r}"
    elif (reason := triton_kernel.device_reason(device)) is not None:
        why_not["triton"] = reason
    engine = next(name for name in ENGINES if name == "torch" or name not in why_not)
    return engine, why_not


def _merge_frames(frames: torch.Tensor, sub: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
    """(T, B, N, 2) frames with the ropes ``where`` (b,) replaced by ``sub`` (T', b, N, 2), the shorter of the two
    runs padded with its last frame."""
    length = max(frames.shape[0], sub.shape[0])

    def pad(f: torch.Tensor) -> torch.Tensor:
        return torch.cat([f, f[-1:].expand(length - f.shape[0], *f.shape[1:])]) if f.shape[0] < length else f

    frames, sub = pad(frames), pad(sub.to(frames))
    index = where.view(1, -1, 1, 1).expand(length, -1, *frames.shape[2:])
    return frames.scatter(1, index, sub)


class Simulator:
    """Batched planar mass-spring cable on ``device`` in ``dtype``. docs/SIMULATOR.md "Use the simulator" shows the API.

    ``backend``: "torch" is the eager reference path (every controller, any device); "kernel" is the fused C++
    CPU kernel (kinematic controller; diffdlo/planar/backends/csrc/cable.cpp) with a hand-written adjoint, per-rope
    physics and frame recording included; "auto" (default) uses the kernel where it applies (CPU tensors, kinematic
    drag) and the torch path elsewhere. "triton" is the fused Triton kernel (diffdlo/planar/backends/triton_kernel.py:
    one launch per move and one for its adjoint, kinematic controller, per-rope physics and frame recording included) on
    CUDA tensors, or on CPU tensors in Triton's interpreter (TRITON_INTERPRET=1); "auto" picks it on CUDA where triton
    imports and the controller is kinematic.
    All run the same scheme and agree to rounding.

    The engine is chosen once, here: ``engine`` is "kernel", "triton" or "torch", what every ``move``, ``settle``
    and ``integrate`` runs, and ``why_not`` says for each fused kernel not in use why not (where "auto" fell back
    to "torch", the reason).
    """

    def __init__(self, params: CableParams | str | None = None, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32, backend: str = "auto"):
        if params is None or isinstance(params, str):
            params = load_params(params or "cable")
        if not isinstance(params, CableParams):
            raise TypeError(f"params must be a CableParams, a params name or None, got {type(params).__name__}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        try:
            self.device = torch.device(device)
            torch.empty(0, device=self.device)
        except (RuntimeError, AssertionError) as exc:
            raise ValueError(f"device {str(device)!r} is not available: {exc}") from exc
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if backend == "kernel":
            if self.device.type != "cpu":
                raise ValueError(f"backend 'kernel' runs on the CPU only, not on {self.device}; use 'auto' or 'torch'")
            if params.controller != "kinematic":
                raise ValueError(f"backend 'kernel' supports the kinematic controller only, not "
                                 f"{params.controller!r}; use 'auto' or 'torch'")
            if not kernel.available():
                raise RuntimeError(f"backend 'kernel' is unavailable: {kernel.unavailable_reason()}")
        if backend == "triton":
            if params.controller != "kinematic":
                raise ValueError(f"backend 'triton' supports the kinematic controller only, not "
                                 f"{params.controller!r}; use 'auto' or 'torch'")
            reason = triton_kernel.device_reason(self.device)
            if reason is not None:
                raise RuntimeError(f"backend 'triton' is unavailable on {self.device}: {reason}")
        self.params = params
        self.dtype = dtype
        self.backend = backend
        self.engine, self.why_not = _resolve_engine(params, self.device, backend)
        # moves with pegs or a pin: the C++ kernel has contact and the pin; the Triton kernel not yet (eager path)
        self.contact_engine = self.engine if self.engine in CONTACT_ENGINES else "torch"
        if self.contact_engine != self.engine:
            self.why_not["contact"] = (f"the {self.engine} engine has no pegs nor pin yet: moves and free evolution "
                                       f"with pegs or a pin run the eager torch path")

    def __repr__(self) -> str:
        return (f"Simulator(n_nodes={self.params.n_nodes}, controller={self.params.controller!r}, "
                f"device={str(self.device)!r}, dtype={self.dtype}, backend={self.backend!r})")

    # ----------------------------------------------------------------- input checks
    def _check_state(self, name: str, x: torch.Tensor) -> None:
        n = self.params.n_nodes
        if not torch.is_tensor(x):
            raise TypeError(f"{name} must be a torch.Tensor of shape (B, {n}, 2), got {type(x).__name__}")
        if x.ndim != 3 or x.shape[1:] != (n, 2):
            raise ValueError(f"{name} must have shape (B, {n}, 2), got {tuple(x.shape)}")
        self._check_placement(name, x)
        if not torch.isfinite(x).all():
            bad = (~torch.isfinite(x)).flatten(1).any(1).nonzero().flatten().tolist()
            raise ValueError(f"{name} contains NaN or inf (batch members {bad})")
        if name != "vel":                                 # positions: no coincident consecutive nodes
            shapes.check_link_lengths(x, self.params.rest_length, name, MIN_STATE_LINK_FRACTION)

    def _check_placement(self, name: str, x: torch.Tensor) -> None:
        if x.device != self.device and not (x.device.type == self.device.type and self.device.index is None):
            raise ValueError(f"{name} is on {x.device} but the simulator is on {self.device}")
        if x.dtype != self.dtype:
            raise ValueError(f"{name} has dtype {x.dtype} but the simulator uses {self.dtype}")

    def _check_action(self, pos: torch.Tensor, node: Any, delta: torch.Tensor) -> torch.Tensor:
        batch, n = pos.shape[0], self.params.n_nodes
        if not torch.is_tensor(node) or node.dtype not in (torch.int64, torch.int32):
            raise TypeError(f"node must be an integer tensor of shape ({batch},), got {node!r}")
        if node.shape != (batch,):
            raise ValueError(f"node must have shape ({batch},), got {tuple(node.shape)}")
        if ((node < 0) | (node >= n)).any():
            bad = node[(node < 0) | (node >= n)].tolist()
            raise ValueError(f"node ids must be in [0, {n - 1}], got {bad}")
        if not torch.is_tensor(delta) or delta.shape != (batch, 2):
            shape = tuple(delta.shape) if torch.is_tensor(delta) else type(delta).__name__
            raise ValueError(f"delta must be a tensor of shape ({batch}, 2) in metres, got {shape}")
        self._check_placement("delta", delta)
        if not torch.isfinite(delta).all():
            raise ValueError(f"delta contains NaN or inf: {delta[~torch.isfinite(delta).all(-1)].tolist()}")
        return node.to(device=pos.device, dtype=torch.int64)

    def _check_pegs(self, pos: torch.Tensor, pegs: Any) -> torch.Tensor | None:
        """(B, K, 3) pegs, or None; a PegError names bad pegs, a ValueError a start state inside one."""
        if pegs is None:
            return None
        check_contact_stability(self.params)
        pegs = contact.check_pegs(pegs, pos.shape[0], self.dtype, self.device, self.params.rope_radius)
        limit = MAX_START_DEPTH_RADII * self.params.rope_radius
        with torch.no_grad():
            if self.contact_engine == "kernel":       # the same test in C++, torch only to name a failure
                if not bool((kernel.deepest_overlap(pos.detach(), pegs, self.params.rope_radius) > limit).any()):
                    return pegs
            overlap = contact.overlap(pos.detach(), pegs, self.params.rope_radius)   # (B, L, K)
            if bool((overlap > limit).any()):
                b, link, k = (int(i) for i in (overlap > limit).nonzero()[0])
                raise ValueError(f"pos: rope {b}'s link {link}-{link + 1} lies {float(overlap[b, link, k]) * 1e3:.3g} "
                                 f"mm deep in peg {k} {[round(v, 4) for v in pegs[b, k].tolist()]} (at most "
                                 f"{limit * 1e3:.3g} mm, the rope's radius: its axis must be outside every peg)")
        return pegs

    def _check_pin(self, pin: Any, node: torch.Tensor) -> torch.Tensor | None:
        """(B,) int64 pin (-1: none), or None; ValueError naming a pin out of range or on the grasped node."""
        if pin is None:
            return None
        batch, n = node.shape[0], self.params.n_nodes
        if not torch.is_tensor(pin) or pin.dtype not in (torch.int64, torch.int32):
            raise TypeError(f"pin must be an integer tensor of shape ({batch},) (-1: no pin), got {pin!r}")
        if pin.shape != (batch,):
            raise ValueError(f"pin must have shape ({batch},) (-1: no pin), got {tuple(pin.shape)}")
        pin = pin.to(device=node.device, dtype=torch.int64)
        if ((pin < -1) | (pin >= n)).any():
            bad = pin[(pin < -1) | (pin >= n)].tolist()
            raise ValueError(f"pin node ids must be in [0, {n - 1}] or -1 for no pin, got {bad}")
        if (pin == node).any():
            bad = (pin == node).nonzero().flatten().tolist()
            raise ValueError(f"pin must differ from the grasped node: ropes {bad} pin node "
                             f"{pin[bad].tolist()} which they also grasp")
        return pin

    def _check_finite(self, pos: torch.Tensor, where: str) -> None:
        with torch.no_grad():
            bad = ~torch.isfinite(pos).flatten(1).all(1) | (pos.abs().flatten(1).amax(1) > DIVERGENCE_RADIUS)
            if bad.any():
                ids = bad.nonzero().flatten().tolist()
                raise SimulationError(f"simulation diverged (NaN/inf or farther than {DIVERGENCE_RADIUS} m) for "
                                      f"batch members {ids} {where}")

    # ----------------------------------------------------------------- physics
    def energy(self, pos: torch.Tensor) -> torch.Tensor:
        """(B, N, 2) -> (B,) potential energy [J]."""
        p = self.params
        return energy(pos, p.rest_length, p.k_s, p.k_b)

    def internal_forces(self, pos: torch.Tensor) -> torch.Tensor:
        """(B, N, 2) -> (B, N, 2) axial + bending forces [N] (no damping, no grasp)."""
        p = self.params
        return internal_forces(pos, p.rest_length, p.k_s, p.k_b)

    def contact_energy(self, pos: torch.Tensor, pegs: torch.Tensor) -> torch.Tensor:
        """(B, N, 2), pegs (K, 3) or (B, K, 3) -> (B,) contact energy with the pegs [J] (diffdlo/planar/contact.py)."""
        p = self.params
        pegs = contact.check_pegs(pegs, pos.shape[0], pos.dtype, pos.device)
        return contact.energy(pos, pegs, p.rope_radius, p.contact_stiffness, p.contact_width)

    def contact_forces(self, pos: torch.Tensor, pegs: torch.Tensor) -> torch.Tensor:
        """(B, N, 2), pegs (K, 3) or (B, K, 3) -> (B, N, 2) the pegs' forces on the nodes [N]."""
        p = self.params
        pegs = contact.check_pegs(pegs, pos.shape[0], pos.dtype, pos.device)
        return contact.forces(pos, pegs, p.rope_radius, p.contact_stiffness, p.contact_width)

    def substep(self, pos: torch.Tensor, vel: torch.Tensor, external: torch.Tensor | None = None,
                physics: Physics | None = None, pegs: torch.Tensor | None = None,
                link_weight: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """One integrator substep of dt (semi-implicit Euler, implicit damping); ``physics``: per-rope parameters
        in place of the params' numbers; ``pegs`` (B, K, 3) push the links on the table (``link_weight`` (B, N-1)
        1, 0 where lifted)."""
        p = self.params
        if physics is None:
            force = internal_forces(pos, p.rest_length, p.k_s, p.k_b)
            node_mass, k_d = p.node_mass, p.k_d
        else:
            force = internal_forces(pos, p.rest_length, physics.k_s, physics.k_b)
            node_mass, k_d = physics.node_mass(p.n_nodes), physics.k_d
        if pegs is not None:
            force = force + contact.forces(pos, pegs, p.rope_radius, p.contact_stiffness, p.contact_width,
                                           link_weight)
        if external is not None:
            force = force + external
        return semi_implicit_step(pos, vel, force, p.dt, node_mass, k_d)

    def integrate(self, pos: torch.Tensor, vel: torch.Tensor | None, n_substeps: int,
                  physics: Physics | None = None, pegs: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Free evolution (no grasp) for n_substeps substeps of dt. Returns (pos, vel). ``physics``: per-rope
        parameters (diffdlo.planar.physics), differentiable (in the kernel too, where it applies); ``pegs``: (K, 3) or
        (B, K, 3) of (x, y, radius) [m] on the table."""
        self._check_state("pos", pos)
        if physics is not None:
            physics.check(pos.shape[0], self.params.n_nodes)
        vel = torch.zeros_like(pos) if vel is None else vel
        self._check_state("vel", vel)
        if not isinstance(n_substeps, int) or n_substeps < 0:
            raise ValueError(f"n_substeps must be a non-negative integer, got {n_substeps!r}")
        pegs = self._check_pegs(pos, pegs)
        engine = self.engine if pegs is None else self.contact_engine
        if n_substeps > 0 and engine != "torch":
            if self.engine == "kernel":
                out = self._kernel_apply(pos, vel, None, None, None, None, physics, fixed_steps=n_substeps,
                                         pegs=pegs)
            else:
                out = self._triton_apply(pos, vel, None, None, None, n_substeps, physics)
            if bool(out.diverged.any()):
                self._check_finite(out.pos, f"after {n_substeps} free substeps")
            return out.pos, out.vel
        for _ in range(n_substeps):
            pos, vel = self.substep(pos, vel, physics=physics, pegs=pegs)
        self._check_finite(pos, f"after {n_substeps} free substeps")
        return pos, vel

    def settle(self, pos: torch.Tensor, vel: torch.Tensor | None = None, return_info: bool = False,
               pegs: torch.Tensor | None = None) -> torch.Tensor | tuple[torch.Tensor, MoveInfo]:
        """Free evolution until each rope is at rest (the thesis's model.free); settled ropes stop changing."""
        batch = pos.shape[0] if torch.is_tensor(pos) and pos.ndim == 3 else 1
        node = torch.zeros(batch, dtype=torch.int64, device=self.device)
        delta = torch.zeros(batch, 2, dtype=self.dtype, device=self.device)
        return self.move(pos, node, delta, vel=vel, return_info=return_info, pegs=pegs)

    def move(self, pos: torch.Tensor, node: torch.Tensor, delta: torch.Tensor, pegs: torch.Tensor | None = None,
             pin: torch.Tensor | None = None, *, vel: torch.Tensor | None = None, return_info: bool = False,
             record_every: int = 0, physics: Physics | None = None,
             differentiable_frames: bool = False) -> torch.Tensor | tuple[torch.Tensor, MoveInfo]:
        """Grasp ``node`` (B,), drag it by ``delta`` (B, 2) [m], release, and settle. Returns the new positions.

        The rope starts at rest unless ``vel`` is given. Drags longer than ``max_disp`` are shortened along their
        direction. Each rope runs its own drag and its own settle (speed checked every ``settle_check_every``
        substeps after its release, capped at ``settle_max_substeps``) and is frozen once settled, so batch
        members never influence each other. Differentiable w.r.t. ``pos``, ``delta`` (and ``vel``).
        With ``return_info`` returns ``(pos, MoveInfo)``; ``record_every > 0`` also records frames. ``physics``:
        per-rope k_s, k_b, k_d and mass (diffdlo.planar.physics) in place of the params' numbers, differentiable (in the
        kernel too, where it applies). ``differentiable_frames``: the recorded frames keep their graph (a loss over
        a trajectory, as the calibration fits), instead of detached copies for pictures.

        ``pegs``: (K, 3) or (B, K, 3) fixed posts (x, y, radius) [m] that push the rope (diffdlo/planar/contact.py); the
        grasped node and its two links are lifted over them during the drag, the rest of the rope stays on the
        table. ``pin``: (B,) a second node per rope held where it lies during the drag and released with the grasp
        (-1: no pin). Without pegs and pins a move is what it always was, bit for bit.
        """
        p = self.params
        self._check_state("pos", pos)
        node = self._check_action(pos, node, delta)
        vel = torch.zeros_like(pos) if vel is None else vel
        self._check_state("vel", vel)
        batch = pos.shape[0]
        if physics is not None:
            physics.check(batch, p.n_nodes)
        pegs = self._check_pegs(pos, pegs)
        pin = self._check_pin(pin, node)
        if pin is not None and not bool((pin >= 0).any()):
            pin = None
        delta = control.clip_drag(delta, p.max_disp)
        result = self._run_move(pos, vel, node, delta, pegs, pin, physics, record_every, return_info,
                                differentiable_frames)
        if pegs is None:
            if return_info:
                result[1].pushed_out = torch.zeros(batch, dtype=torch.bool)
                result[1].drag_share = torch.ones(batch, dtype=torch.float64)
            return result if return_info else result[0]
        return self._put_down(result, pos, vel, node, delta, pegs, pin, physics, record_every, return_info,
                              differentiable_frames)

    def _run_move(self, pos, vel, node, delta, pegs, pin, physics, record_every, return_info, differentiable_frames):
        """One move of checked inputs (``delta`` clipped) on the engine that runs it: (pos, MoveInfo or None)."""
        p = self.params
        engine = self.engine if pegs is None and pin is None else self.contact_engine
        distance = delta.norm(dim=-1)
        speed = control.drag_speed(distance, p)
        path_steps = control.path_substeps(distance, p)                       # (B,) on device
        if engine != "torch":
            every = record_every if return_info else 0
            if engine == "kernel":
                # speed's dependence on delta is inside the kernel's adjoint, so it goes in detached
                out = self._kernel_apply(pos, vel, node, delta, speed.detach(), path_steps, physics,
                                         record_every=every, pegs=pegs, pin=pin)
            else:
                out = self._triton_apply(pos, vel, node, delta, path_steps, -1, physics, every)
            result = self._fused_result(out, node, delta, path_steps, return_info, every, differentiable_frames)
            return result if return_info else (result, None)
        new_pos, _, grasp_steps_cpu, finished_at, settled, frames = self._move_eager(
            pos, vel, node, delta, speed, path_steps, physics, record_every, differentiable_frames, pegs, pin)
        if not return_info:
            return new_pos, None
        if frames is not None and frames[-1] is not new_pos:
            frames.append(new_pos if differentiable_frames else new_pos.detach().clone())
        return new_pos, MoveInfo(drag_substeps=grasp_steps_cpu, settle_substeps=finished_at - grasp_steps_cpu,
                                 settled=settled, frames=torch.stack(frames) if frames is not None else None)

    def _put_down(self, result, pos, vel, node, delta, pegs, pin, physics, record_every, return_info,
                  differentiable_frames):
        """A move's result with every rope's axis out of every peg, so a valid start for the next move; the ropes
        already out bit for bit as they were. A rope the settle left with its axis inside a peg is pushed out
        (``contact.push_out``, keeping its links' lengths); one that cannot be (a lifted link put down across a
        small peg and held there by the rope's tension) is moved again with the gripper letting go earlier on its
        path, at each share of LET_GO_EARLIER in turn (0: no drag, a settle from the valid start), pushed out if
        need be, the first that gets out kept. MoveInfo flags ``pushed_out`` and gives ``drag_share``; its frames
        end on the returned state. SimulationError naming the rope if none gets it out."""
        r = self.params.rope_radius
        clearance = PUSH_OUT_CLEARANCE_RADII * r
        new_pos, info = result
        batch, device = new_pos.shape[0], new_pos.device
        pushed = torch.zeros(batch, dtype=torch.bool)
        share = torch.ones(batch, dtype=torch.float64)
        reruns = []                                    # (ropes, their MoveInfo rows) of the moves made again
        todo = self._inside(new_pos, pegs, clearance)
        for drag_share in (1.0, *LET_GO_EARLIER):
            if not bool(todo.any()):
                break
            ids = todo.nonzero().flatten()
            at = ids.to(device)
            if drag_share == 1.0:
                candidate = new_pos[at]
            else:                                      # the same move, the gripper letting go earlier
                candidate, sub_info = self._run_move(
                    pos[at], vel[at], node[at], delta[at] * drag_share, pegs[at], None if pin is None else pin[at],
                    None if physics is None else physics.take(at), record_every, return_info, differentiable_frames)
            still = self._inside(candidate, pegs[at], clearance)
            got_out = ~still
            if bool(still.any()):
                rows = still.nonzero().flatten()
                moved, lack = contact.push_out(candidate[rows.to(device)], pegs[at[rows.to(device)]],
                                               2.0 * clearance, clearance, PUSH_OUT_ITERATIONS, keep_lengths=True)
                candidate = candidate.index_put((rows.to(device),), moved)
                cleared = (lack <= clearance).cpu()
                got_out[rows[cleared]] = True
                pushed[ids[rows[cleared]]] = True
            kept = got_out.nonzero().flatten()
            new_pos = new_pos.index_put((at[kept.to(device)],), candidate[kept.to(device)])
            share[ids[kept]] = drag_share
            if drag_share < 1.0 and info is not None:
                reruns.append((ids[kept], sub_info, kept))
            todo[ids[kept]] = False
        if bool(todo.any()):
            b = int(todo.nonzero()[0])
            raise SimulationError(f"rope {b}'s move ends with its axis inside a peg of "
                                  f"{[[round(v, 4) for v in row] for row in pegs[b].tolist()]} and neither a push-out "
                                  f"nor an earlier release gets it out (node={int(node[b])}, "
                                  f"delta={delta[b].tolist()})")
        if info is None:
            return new_pos
        for ids, sub, kept in reruns:
            info.drag_substeps[ids] = sub.drag_substeps[kept]
            info.settle_substeps[ids] = sub.settle_substeps[kept]
            info.settled[ids] = sub.settled[kept]
            if info.frames is not None:
                info.frames = _merge_frames(info.frames, sub.frames[:, kept.to(sub.frames.device)],
                                            ids.to(info.frames.device))
        if info.frames is not None and bool((share < 1).any() or pushed.any()):
            last = new_pos if differentiable_frames else new_pos.detach().clone()
            info.frames = torch.cat([info.frames, last.to(info.frames.device)[None]])
        info.pushed_out, info.drag_share = pushed, share
        return new_pos, info

    def _inside(self, pos: torch.Tensor, pegs: torch.Tensor, clearance: float) -> torch.Tensor:
        """(B,) bool on the CPU: a rope's axis within ``clearance`` of being inside a peg (the push-out's trigger)."""
        r = self.params.rope_radius
        with torch.no_grad():
            return (contact.overlap(pos.detach(), pegs, r) > r - clearance).flatten(1).any(1).cpu()

    def _move_eager(self, pos, vel, node, delta, speed, path_steps, physics=None, record_every=0,
                    differentiable_frames=False, pegs=None, pin=None):
        """The eager reference loop of ``move`` (``delta`` already clipped; ``pegs`` (B, K, 3) and ``pin`` checked):
        returns (pos, vel, grasp_steps on the CPU, finished_at, settled, frames list or None). Raises
        SimulationError on divergence."""
        p = self.params
        batch = pos.shape[0]
        grasp_steps = torch.where(path_steps > 0, path_steps + control.hold_substeps(p), path_steps)
        grasp_steps_cpu = grasp_steps.cpu()
        grasped = torch.nn.functional.one_hot(node, p.n_nodes).to(torch.bool).unsqueeze(-1)   # (B, N, 1)
        start = pos.gather(1, node.view(batch, 1, 1).expand(batch, 1, 2)).squeeze(1)           # (B, 2)
        integral = torch.zeros_like(start)
        if pin is not None:           # the second gripper holds its node where it lies until the release
            pinned = (torch.nn.functional.one_hot(pin.clamp_min(0), p.n_nodes).to(torch.bool)
                      & (pin >= 0).view(batch, 1)).unsqueeze(-1)
            pin_start = pos.gather(1, pin.clamp_min(0).view(batch, 1, 1).expand(batch, 1, 2))      # (B, 1, 2)
        # links at the grasped node are lifted with it during the drag (no contact), all on the table after
        on_table = contact.lifted_links(node, p.n_nodes, pos.dtype) if pegs is not None else None

        done = torch.zeros(batch, dtype=torch.bool)                      # CPU copy drives the loop
        done_dev = done.to(pos.device, copy=True)
        settled = torch.zeros(batch, dtype=torch.bool)
        finished_at = torch.zeros(batch, dtype=torch.int64)
        keep = (lambda x: x) if differentiable_frames else (lambda x: x.detach().clone())
        frames = [keep(pos)] if record_every > 0 else None
        phi = control.last_substep_fraction(delta.norm(dim=-1), speed, path_steps, p)
        last_share = phi.view(batch, 1, 1)
        k = 0
        while not bool(done.all()):
            k += 1
            prev_pos, prev_vel = pos, vel
            dragging = (k <= grasp_steps).view(batch, 1, 1)
            ref_pos, ref_vel = control.reference(start, delta, speed, k, p.dt)
            external = None
            if p.controller == "pid":
                node_pos = (pos * grasped).sum(1)
                error = ref_pos - node_pos
                integral = integral + p.dt * error
                force = control.pid_force(error, integral, ref_vel, k * p.dt, p,
                                          None if physics is None else physics.k_d)
                external = (grasped & dragging) * force.unsqueeze(1)
            link_weight = None
            if pegs is not None:
                link_weight = torch.where(dragging.view(batch, 1), on_table, torch.ones_like(on_table))
            new_pos, new_vel = self.substep(pos, vel, external, physics, pegs, link_weight)
            if pin is not None:
                held = pinned & dragging
                release = held & ((k == path_steps) & (phi < 1)).view(batch, 1, 1)
                new_pos = torch.where(release, new_pos + last_share * (pin_start - new_pos),
                                      torch.where(held, pin_start, new_pos))
                new_vel = torch.where(release, new_vel - last_share * new_vel,
                                      torch.where(held, torch.zeros_like(new_vel), new_vel))
            if p.controller == "kinematic":
                on_path = grasped & dragging
                ref_pos, ref_vel = ref_pos.unsqueeze(1), ref_vel.unsqueeze(1)
                blend = on_path & ((k == path_steps) & (phi < 1)).view(batch, 1, 1)
                new_pos = torch.where(blend, new_pos + last_share * (ref_pos - new_pos),
                                      torch.where(on_path, ref_pos, new_pos))
                new_vel = torch.where(blend, new_vel + last_share * (ref_vel - new_vel),
                                      torch.where(on_path, ref_vel, new_vel))
            frozen = done_dev.view(batch, 1, 1)
            pos = torch.where(frozen, pos, new_pos)
            vel = torch.where(frozen, vel, new_vel)
            since_release = k - grasp_steps_cpu
            check = ~done & (since_release > 0) & (since_release % p.settle_check_every == 0)
            capped = ~done & (since_release >= p.settle_max_substeps)
            if bool(check.any()) or bool(capped.any()):
                self._check_finite(pos, f"during a move (node={node.tolist()}, delta={delta.tolist()})")
                at_rest = max_speed(vel.detach()).cpu() < p.settle_threshold
                now_settled = check & at_rest
                settled |= now_settled
                stopped_by_cap = (capped & ~now_settled).to(pos.device).view(batch, 1, 1) & (last_share < 1)
                if bool(stopped_by_cap.any()):
                    pos = torch.where(stopped_by_cap, prev_pos + last_share * (pos - prev_pos), pos)
                    vel = torch.where(stopped_by_cap, prev_vel + last_share * (vel - prev_vel), vel)
                newly_done = now_settled | capped
                finished_at[newly_done] = k
                done = done | newly_done                         # out of place: `where` saved the old mask
                done_dev = done.to(pos.device, copy=True)
            if frames is not None and k % record_every == 0:    # after the settle cap's release share
                frames.append(keep(pos))

        self._check_finite(pos, f"after a move (node={node.tolist()}, delta={delta.tolist()})")
        return pos, vel, grasp_steps_cpu, finished_at, settled, frames

    def _kernel_apply(self, pos, vel, node, delta, speed, path_steps, physics, fixed_steps=-1,
                      record_every=0, pegs=None, pin=None) -> kernel.MoveOutputs:
        """The C++ kernel's move (``delta`` already clipped), or with ``fixed_steps`` >= 0 free evolution for that
        many substeps (node, delta, speed and path_steps then unused: pass None). ``pegs`` (B, K, 3) and ``pin``
        (B,) as checked by ``move``, or None."""
        batch = pos.shape[0]
        setup = kernel.Setup(self.params, batch, fixed_steps=fixed_steps, divergence_radius=DIVERGENCE_RADIUS,
                             record_every=record_every)
        if fixed_steps >= 0:
            node = path_steps = torch.zeros(batch, dtype=torch.int64)
            delta = torch.zeros(batch, 2, dtype=self.dtype)
            speed = torch.full((batch,), self.params.max_speed, dtype=self.dtype)
        phys = None if physics is None else kernel.physics_columns(self.params, physics, batch)
        return kernel.MoveOutputs._make(kernel.KernelRun.apply(setup, pos, vel, node, delta, speed, path_steps, phys,
                                                               pegs, pin))

    def _triton_apply(self, pos, vel, node, delta, path_steps, fixed_steps, physics,
                      record_every=0) -> kernel.MoveOutputs:
        """The Triton kernel's move or free evolution (``triton_kernel.TritonMove``)."""
        phys = triton_kernel.columns(self.params, physics, pos.shape[0], pos.device, pos.dtype)
        return kernel.MoveOutputs._make(triton_kernel.TritonMove.apply(self, pos, vel, node, delta, path_steps,
                                                                       fixed_steps, phys, record_every))

    @staticmethod
    def _fused_result(out: kernel.MoveOutputs, node, delta, path_steps, return_info, record_every,
                      differentiable_frames):
        """What the fused kernels (C++ or Triton) return to ``move``: a diverged rope raised, else pos, and with
        ``return_info`` its MoveInfo (on the CPU, whatever the device)."""
        if bool(out.diverged.any()):
            ids = out.diverged.nonzero().flatten().tolist()
            raise SimulationError(f"simulation diverged (NaN/inf or farther than {DIVERGENCE_RADIUS} m) for batch "
                                  f"members {ids} during a move (node={node.tolist()}, delta={delta.tolist()})")
        if not return_info:
            return out.pos
        frames = (kernel.assemble_frames(record_every, out.frames, out.pos, out.steps, differentiable_frames)
                  if record_every > 0 else None)
        path_steps, steps = path_steps.cpu(), out.steps.cpu()
        return out.pos, MoveInfo(drag_substeps=path_steps, settle_substeps=steps - path_steps,
                                 settled=out.settled.cpu(), frames=frames)

    # ----------------------------------------------------------------- shapes
    def random_shape(self, batch: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """(B, N, 2) random initial shapes (thesis sigma), centred at the origin, on this device and dtype."""
        return shapes.random_shape(batch, self.params, generator, self.device, self.dtype)

    def target_shape(self, spec: Any) -> torch.Tensor:
        """(N, 2) target shape on this device and dtype (see diffdlo.target_shape)."""
        return shapes.target_shape(spec, self.params, self.device, self.dtype)
