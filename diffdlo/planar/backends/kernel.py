"""The fused C++ CPU kernel (diffdlo/planar/backends/csrc/cable.cpp): build on first use, call through ctypes, autograd
wrapper.

The kernel is plain C++ with a C ABI, built on first use by diffdlo/utils/native.py (a C++ compiler is all it needs;
cached in ``$DIFFDLO_CACHE``). If no compiler is found or the build fails, ``available()`` is False, the reason is in
``unavailable_reason()``, one ``KernelUnavailableWarning`` says so, and the simulator uses its pure-torch path.

Per-rope physics (diffdlo.planar.physics.Physics) goes in as a (B, 4) float64 tensor of k_s, k_b, 1 / node_mass and the
implicit damping factor 1 / (1 + dt k_d / node_mass) (``physics_columns``); the adjoint returns the gradient w.r.t.
those four numbers and autograd carries it on to k_d and mass. Frames (positions every ``record_every`` substeps)
come back per rope up to its own stop (``assemble_frames`` makes the eager path's (F, B, N, 2) of them), and their
gradients are injected at their substeps in the backward sweep.

Pegs (diffdlo/planar/contact.py) go in as a contiguous (B, K, 3) tensor in the state's dtype (None: no contact, the
kernel then runs exactly its code without them) and the pin as a (B,) int64 tensor (-1: none; None: no pins); the
contact parameters rope_radius, contact_stiffness and contact_width are always in ``Setup.fp``. The pegs get no
gradient.
"""
from __future__ import annotations

import ctypes
import warnings
from importlib import resources
from typing import NamedTuple

import torch

from ...utils import native

SOURCE = resources.files(__package__) / "csrc" / "cable.cpp"
FLAGS = native.FLAGS



class KernelUnavailableWarning(RuntimeWarning):
    """The fused kernel could not be built, so every move runs on the much slower eager torch path."""


def _warn_unavailable(reason: str) -> None:
    """Say once, loudly, that the simulator is on its slow path, why, and how to get the fast one."""
    warnings.warn(
        f"diffdlo: the fused C++ simulator kernel is unavailable ({reason}), so the simulator falls back to its "
        f"eager PyTorch path, about 100-500x slower per move on the CPU. Install a C++ compiler (g++, e.g. "
        f"`apt install g++`, or clang++) or point $CXX at a working one, then restart Python. "
        f"`python -m diffdlo --info` shows the backend in use.", KernelUnavailableWarning)


_compiler = native.find_compiler


def _build() -> ctypes.CDLL:
    lib = native.build(SOURCE, "diffdlo/planar/backends/csrc/cable.cpp", "C++ simulator kernel", _compiler(), FLAGS)
    lib.diffdlo_lanes.restype = ctypes.c_int64
    ptr, i64 = ctypes.c_void_p, ctypes.c_int64
    for suffix in ("f32", "f64"):     # ..., phys, pegs, n_pegs, pin, ...
        getattr(lib, f"diffdlo_forward_{suffix}").argtypes = [ptr] * 10 + [i64] + [ptr] * 7
        getattr(lib, f"diffdlo_backward_{suffix}").argtypes = [ptr] * 10 + [i64] + [ptr] * 8
        getattr(lib, f"diffdlo_hvp_{suffix}").argtypes = [ptr, i64, ptr, ptr, ptr, ptr, i64, i64]
        getattr(lib, f"diffdlo_overlap_{suffix}").argtypes = [i64, i64, ptr, ptr, i64, ctypes.c_double, ptr]
        getattr(lib, f"diffdlo_overlap_{suffix}").restype = None
        for name in ("forward", "backward", "hvp"):
            getattr(lib, f"diffdlo_{name}_{suffix}").restype = None
    return lib


_library = native.Library(lambda: _build(), _warn_unavailable)


def _load() -> ctypes.CDLL | None:
    return _library.load()


def available() -> bool:
    """True if the kernel is built (building it now if needed)."""
    return _load() is not None


def unavailable_reason() -> str | None:
    _load()
    return _library.error


def library_path() -> str | None:
    """The built shared library in use, or None where the kernel is unavailable."""
    lib = _load()
    return None if lib is None else lib._name


def lanes() -> int:
    """Ropes per vectorized lane group (full groups take the vectorized path, the rest the per-rope path)."""
    return int(_load().diffdlo_lanes())


def _ptr(t: torch.Tensor | None) -> ctypes.c_void_p | None:
    return None if t is None else ctypes.c_void_p(t.data_ptr())


def _suffix(dtype: torch.dtype) -> str:
    return {torch.float32: "f32", torch.float64: "f64"}[dtype]


class Setup:
    """Scalars and integers passed to the kernel for one call (fp and ip arrays, see cable.cpp). ``record_every``
    > 0: the forward also returns frames every that many substeps (``frame_cap`` slots per rope, enough for the
    longest possible move)."""

    def __init__(self, p, batch: int, fixed_steps: int = -1, threads: int | None = None,
                 divergence_radius: float = 100.0, lane_groups: bool = True, record_every: int = 0):
        self.fp = torch.tensor([p.rest_length, p.k_s, p.k_b, p.dt, 1.0 / p.node_mass,
                                1.0 / (1.0 + p.dt * p.k_d / p.node_mass), p.max_speed, p.settle_threshold,
                                divergence_radius, p.rope_radius, p.contact_stiffness, p.contact_width],
                               dtype=torch.float64)
        longest = fixed_steps if fixed_steps >= 0 else p.max_drag_steps + p.settle_max_substeps + 1
        self.record_every = int(record_every)
        self.frame_cap = longest // record_every + 1 if record_every > 0 else 0
        self.ip = torch.tensor([batch, p.n_nodes, p.max_drag_steps, p.settle_check_every, p.settle_max_substeps,
                                fixed_steps, threads or torch.get_num_threads(), int(lane_groups),
                                self.record_every, self.frame_cap], dtype=torch.int64)


def physics_columns(p, physics, batch: int, device="cpu", dtype=torch.float64) -> torch.Tensor:
    """(B, 4) k_s, k_b, 1 / node_mass, 1 / (1 + dt k_d / node_mass) of a Physics (floats or (B,)/() tensors),
    differentiable where its tensors are; float64 on the CPU (this kernel's) unless told."""
    def column(v):
        if torch.is_tensor(v):
            return torch.broadcast_to(v.to(device=device, dtype=dtype), (batch,))
        return torch.full((batch,), float(v), dtype=dtype, device=device)

    k_s, k_b, k_d, mass = (column(getattr(physics, key)) for key in ("k_s", "k_b", "k_d", "mass"))
    node_mass = mass / p.n_nodes
    return torch.stack([k_s, k_b, 1.0 / node_mass, 1.0 / (1.0 + p.dt * k_d / node_mass)], dim=-1)


def _contig(*tensors):
    return [None if t is None else t.detach().contiguous() for t in tensors]


def _pegs_and_pin(pos, pegs, pin):
    """(pegs, K, pin) as the kernel takes them: pegs (B, K, 3) contiguous in pos's dtype or None (K = 0: None),
    pin (B,) contiguous int64 or None."""
    batch = pos.shape[0]
    if pegs is not None:
        if pegs.ndim != 3 or pegs.shape[0] != batch or pegs.shape[2] != 3:
            raise ValueError(f"pegs must have shape ({batch}, K, 3), got {tuple(pegs.shape)}")
        pegs = pegs.detach().to(device="cpu", dtype=pos.dtype).contiguous() if pegs.shape[1] > 0 else None
    if pin is not None:
        if pin.shape != (batch,):
            raise ValueError(f"pin must have shape ({batch},), got {tuple(pin.shape)}")
        pin = pin.detach().to(device="cpu", dtype=torch.int64).contiguous()
        if batch and (int(pin.min()) < -1 or int(pin.max()) >= pos.shape[1]):     # the kernel indexes with it
            raise ValueError(f"pin node ids must be in [-1, {pos.shape[1] - 1}], got {pin.tolist()}")
    return pegs, 0 if pegs is None else pegs.shape[1], pin


def forward(setup: Setup, pos, vel, node, delta, speed, n_grasp, phys=None, pegs=None, pin=None):
    """Run the kernel; returns (pos, vel, steps, settled, diverged, frames): frames (B, frame_cap, N, 2) where
    ``setup.record_every`` > 0 (rope b's frame j valid for j <= steps[b] // record_every), else None. ``pegs``
    (B, K, 3) and ``pin`` (B,) int64 (-1: none), or None."""
    lib = _load()
    pos, vel, node, delta, speed, n_grasp = _contig(pos, vel, node, delta, speed, n_grasp)
    phys = None if phys is None else phys.detach().to(torch.float64).contiguous()
    pegs, n_pegs, pin = _pegs_and_pin(pos, pegs, pin)
    out_pos, out_vel = torch.empty_like(pos), torch.empty_like(pos)
    batch = pos.shape[0]
    steps, settled, diverged = (torch.empty(batch, dtype=torch.int64) for _ in range(3))
    frames = (pos.new_empty(batch, setup.frame_cap, *pos.shape[1:]) if setup.record_every > 0 else None)
    getattr(lib, f"diffdlo_forward_{_suffix(pos.dtype)}")(
        _ptr(setup.fp), _ptr(setup.ip), _ptr(pos), _ptr(vel), _ptr(node), _ptr(delta), _ptr(speed),
        _ptr(n_grasp), _ptr(phys), _ptr(pegs), n_pegs, _ptr(pin), _ptr(out_pos), _ptr(out_vel), _ptr(steps),
        _ptr(settled), _ptr(diverged), _ptr(frames))
    return out_pos, out_vel, steps, settled.bool(), diverged.bool(), frames


def backward(setup: Setup, pos, vel, node, delta, speed, n_grasp, grad_pos_out, grad_vel_out, phys=None,
             grad_frames=None, want_phys: bool = False, pegs=None, pin=None):
    """Adjoint of ``forward``: returns (grad_pos, grad_vel, grad_delta, grad_phys); grad_frames (B, frame_cap, N, 2)
    the incoming gradients of the frames (or None); grad_phys (B, 4) float64 if ``want_phys``, else None."""
    lib = _load()
    pos, vel, node, delta, speed, n_grasp, grad_pos_out, grad_vel_out, grad_frames = _contig(
        pos, vel, node, delta, speed, n_grasp, grad_pos_out, grad_vel_out, grad_frames)
    phys = None if phys is None else phys.detach().to(torch.float64).contiguous()
    pegs, n_pegs, pin = _pegs_and_pin(pos, pegs, pin)
    if grad_frames is not None and setup.record_every <= 0:
        raise ValueError("frame gradients need a Setup with record_every > 0")
    grad_pos, grad_vel, grad_delta = torch.empty_like(pos), torch.empty_like(pos), torch.empty_like(delta)
    grad_phys = pos.new_empty(pos.shape[0], 4) if want_phys else None
    getattr(lib, f"diffdlo_backward_{_suffix(pos.dtype)}")(
        _ptr(setup.fp), _ptr(setup.ip), _ptr(pos), _ptr(vel), _ptr(node), _ptr(delta), _ptr(speed),
        _ptr(n_grasp), _ptr(phys), _ptr(pegs), n_pegs, _ptr(pin), _ptr(grad_pos_out), _ptr(grad_vel_out),
        _ptr(grad_frames), _ptr(grad_pos), _ptr(grad_vel), _ptr(grad_delta), _ptr(grad_phys))
    return grad_pos, grad_vel, grad_delta, None if grad_phys is None else grad_phys.to(torch.float64)


def deepest_overlap(pos: torch.Tensor, pegs: torch.Tensor, rope_radius: float) -> torch.Tensor:
    """(B,) the deepest overlap [m] of each rope's (B, N, 2) links with its pegs (B, K, 3), as
    diffdlo.planar.contact.depth computes it (CPU tensors of one dtype)."""
    lib = _load()
    pos, pegs = _contig(pos, pegs.to(pos.dtype))
    out = pos.new_empty(pos.shape[0])
    getattr(lib, f"diffdlo_overlap_{_suffix(pos.dtype)}")(pos.shape[0], pos.shape[1], _ptr(pos), _ptr(pegs),
                                                           pegs.shape[1], float(rope_radius), _ptr(out))
    return out


def hvp(p, pos: torch.Tensor, u: torch.Tensor, pegs: torch.Tensor | None = None, lift: int = -1) -> torch.Tensor:
    """Hessian-vector product of the energy for one rope (N, 2), with the contact energy of ``pegs`` (K, 3) where
    given (the links at node ``lift`` off the table, -1: none); exposed for tests."""
    lib = _load()
    setup = Setup(p, 1)
    pos, u = _contig(pos, u)
    pegs = None if pegs is None else pegs.detach().to(pos.dtype).contiguous()
    out = torch.empty_like(pos)
    getattr(lib, f"diffdlo_hvp_{_suffix(pos.dtype)}")(_ptr(setup.fp), pos.shape[0], _ptr(pos), _ptr(u), _ptr(out),
                                                       _ptr(pegs), 0 if pegs is None else pegs.shape[0], int(lift))
    return out


class MoveOutputs(NamedTuple):
    """What the fused moves' autograd functions (``KernelRun`` here, ``triton_kernel.TritonMove``) return, in this
    order: the final positions and velocities (differentiable), then per rope the substeps run, the settled and
    diverged flags (not differentiable), and the frames, (B, frame slots, N, 2) differentiable where recorded, else
    an empty tensor. ``Simulator`` makes its MoveInfo of them."""

    pos: torch.Tensor
    vel: torch.Tensor
    steps: torch.Tensor
    settled: torch.Tensor
    diverged: torch.Tensor
    frames: torch.Tensor


def move_outputs(ctx, pos, vel, steps, settled, diverged, frames=None) -> MoveOutputs:
    """The end of both fused moves' forward: marks on ``ctx`` the outputs that are not differentiable, and makes
    ``frames`` None (no recording) the empty tensor."""
    ctx.set_materialize_grads(False)        # unused outputs (vel, frames) send None, not buffers of zeros
    ctx.mark_non_differentiable(steps, settled, diverged)
    if frames is None:
        frames = pos.new_empty(0)
        ctx.mark_non_differentiable(frames)
    return MoveOutputs(pos, vel, steps, settled, diverged, frames)


def frames_gradient(grad_frames: torch.Tensor | None) -> torch.Tensor | None:
    """The incoming gradient of a fused move's frames output, None where there is none (or no frames)."""
    return None if grad_frames is None or grad_frames.numel() == 0 else grad_frames


class KernelRun(torch.autograd.Function):
    """Differentiable kernel call: (pos, vel, delta, phys) -> ``MoveOutputs``. ``phys``: None or the (B, 4) of
    ``physics_columns``; ``pegs`` (B, K, 3) and ``pin`` (B,) int64, or None (no gradient w.r.t. the pegs)."""

    @staticmethod
    def forward(ctx, setup, pos, vel, node, delta, speed, n_grasp, phys=None, pegs=None, pin=None):
        out_pos, out_vel, steps, settled, diverged, frames = forward(setup, pos, vel, node, delta, speed, n_grasp,
                                                                     phys, pegs, pin)
        ctx.setup = setup
        ctx.save_for_backward(pos, vel, node, delta, speed, n_grasp, phys, pegs, pin)
        return move_outputs(ctx, out_pos, out_vel, steps, settled, diverged, frames)

    @staticmethod
    def backward(ctx, grad_pos, grad_vel, _steps, _settled, _diverged, grad_frames):
        pos, vel, node, delta, speed, n_grasp, phys, pegs, pin = ctx.saved_tensors
        if grad_pos is None:
            grad_pos = torch.zeros_like(pos)
        want_phys = phys is not None and ctx.needs_input_grad[7]
        g_pos, g_vel, g_delta, g_phys = backward(ctx.setup, pos, vel, node, delta, speed, n_grasp, grad_pos, grad_vel,
                                                 phys, frames_gradient(grad_frames), want_phys, pegs, pin)
        return None, g_pos, g_vel, None, g_delta, None, None, g_phys, None, None


def assemble_frames(every: int, buffer: torch.Tensor, pos: torch.Tensor, steps: torch.Tensor,
                    differentiable: bool) -> torch.Tensor:
    """(F, B, N, 2) frames as ``Simulator.move``'s eager loop records them, from the kernel's per-rope ``buffer``
    (B, frame_cap, N, 2) and final ``pos``: a frame at every k = 0, E, 2E, ... up to the longest rope's last
    substep (a rope that stopped earlier stays frozen at its final pos), then the final pos appended unless the
    last frame already is it (with detached frames the eager loop always appends it)."""
    if not differentiable:
        buffer, pos = buffer.detach(), pos.detach()
    last = int(steps.max())
    count = last // every + 1
    grid = buffer[:, :count]
    frozen = torch.arange(count, device=steps.device)[None, :] > (steps // every)[:, None]   # (B, F): past its stop
    frames = torch.where(frozen[..., None, None], pos[:, None], grid).transpose(0, 1)
    if not differentiable or last % every != 0:
        frames = torch.cat([frames, pos[None]])
    return frames
