"""The fused C++ CPU kernel of the grippers' move on the 3-D chain (diffdlo/chain3d/csrc/chain3d.cpp) and its
adjoint: built on first use (diffdlo/utils/native.py), called through ctypes, wrapped as an autograd Function whose
gradient flows to the start state (x, v) and the grippers' path and hold (so on to their goal poses).

``grippers.move`` and ``grippers.settle`` run it where it applies (``usable``): on the CPU, float32 or float64, no
parameter of the cable requiring grad (the kernel has no gradient for them) and no extra acceleration (the learned
residual is a torch network). Everything else (a fit of the parameters, the stand-in's residual, CUDA) runs the eager
path of diffdlo/chain3d/chain.py, which is the reference: the kernel mirrors it step by step and the tests hold the
two together, values and gradients. If no compiler is found or the build fails, one ``KernelUnavailableWarning``
says so and the eager path runs.
"""
from __future__ import annotations

import ctypes
import warnings
from importlib import resources
from typing import Any, Callable

import torch

from ..planar.backends.kernel import KernelUnavailableWarning
from ..utils import native
from .chain import (DIVERGENCE_RADIUS, ChainDivergedError, ChainError, ChainParams, _check_rollout_inputs,
                    _resolve)

SOURCE = resources.files(__package__) / "csrc" / "chain3d.cpp"
_SCALARS = ("EI", "EA", "axial_damping", "bending_damping", "gravity", "floor_height", "floor_stiffness",
            "floor_damping", "floor_width")           # chain3d.cpp's enum Scalar, in its order

_compiler = native.find_compiler


def _build() -> ctypes.CDLL:
    lib = native.build(SOURCE, "diffdlo/chain3d/csrc/chain3d.cpp", "C++ kernel of the 3-D chain", _compiler())
    lib.chain3d_lanes.restype = ctypes.c_int64
    for suffix in ("f32", "f64"):
        for name, count in (("move", 13), ("backward", 15)):
            fn = getattr(lib, f"chain3d_{name}_{suffix}")
            fn.argtypes = [ctypes.c_void_p] * count
            fn.restype = None
    return lib


def _warn_unavailable(reason: str) -> None:
    warnings.warn(f"diffdlo: the fused C++ kernel of the 3-D chain is unavailable ({reason}), so the two-gripper "
                  f"task's moves run on the eager PyTorch path, about 40-200x slower. Install a C++ compiler (g++, "
                  f"e.g. `apt install g++`, or clang++) or point $CXX at a working one, then restart Python.",
                  KernelUnavailableWarning)


_library = native.Library(lambda: _build(), _warn_unavailable)


def _load() -> ctypes.CDLL | None:
    return _library.load()


def available() -> bool:
    """True if the kernel is built (building it now if needed)."""
    return _load() is not None


def unavailable_reason() -> str | None:
    _load()
    return _library.error


def params_need_grad(params: ChainParams) -> bool:
    return any(torch.is_tensor(getattr(params, f)) and getattr(params, f).requires_grad
               for f in params.__dataclass_fields__)


def usable(x: torch.Tensor, params: ChainParams, accel: Callable | None) -> bool:
    """Whether a move of state ``x`` can run on the kernel: CPU, float32/64, no gradient wanted w.r.t. ``params``,
    no ``accel``, and the kernel built."""
    if accel is not None or x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64):
        return False
    if torch.is_grad_enabled() and params_need_grad(params):
        return False
    return available()


def _physics(params: ChainParams, x: torch.Tensor) -> torch.Tensor:
    """(B, (N-1) + N + N + 9) each chain's rest lengths, node masses, drags c_d lambda_j and the 9 scalars, in x's
    dtype (chain.py's resolved parameters, so both paths start from the same numbers)."""
    batch, n = x.shape[:2]
    p = _resolve(params, x)

    def rows(t: torch.Tensor | None, width: int) -> torch.Tensor:    # (), (B|1, 1) or (B|1, width) -> (B, width)
        if t is None:
            return x.new_zeros(batch, width)
        t = t.detach()
        return (t.view(1, 1) if t.ndim == 0 else t).expand(batch, width)

    columns = [rows(p.rest, n - 1), rows(p.mass, n), rows(p.drag, n)]
    columns += [rows(getattr(p, name), 1) for name in _SCALARS]
    return torch.cat(columns, 1).contiguous()


class _Call:
    """One move's constants as the kernel takes them."""

    def __init__(self, x: torch.Tensor, held: tuple[int, ...], path: torch.Tensor, params: ChainParams,
                 substeps: int, frame_dt: float, rest_speed: float, check_frames: int, settle_frames: int,
                 threads: int | None):
        batch, n = x.shape[:2]
        self.held = torch.tensor(held, dtype=torch.int64)
        self.phys = _physics(params, x.detach())
        self.fp = torch.tensor([frame_dt, rest_speed, DIVERGENCE_RADIUS], dtype=torch.float64)
        self.ip = torch.tensor([batch, n, len(held), substeps, path.shape[0], check_frames, settle_frames,
                                threads or torch.get_num_threads()], dtype=torch.int64)
        self.frame_dt, self.substeps, self.suffix = frame_dt, substeps, "f32" if x.dtype == torch.float32 else "f64"


def _ptrs(*tensors: torch.Tensor | None) -> list[ctypes.c_void_p | None]:
    return [None if t is None else ctypes.c_void_p(t.data_ptr()) for t in tensors]


class _Move(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x0, v0, path, hold, call: _Call):
        batch = x0.shape[0]
        x_out, v_out = torch.empty_like(x0), torch.empty_like(x0)
        settled = torch.zeros(batch, dtype=torch.uint8)
        frames = torch.zeros(batch, dtype=torch.int64)
        diverged = torch.full((batch,), -1, dtype=torch.int64)
        getattr(_load(), f"chain3d_move_{call.suffix}")(*_ptrs(call.fp, call.ip, call.held, x0, v0, path, hold,
                                                               call.phys, x_out, v_out, settled, frames, diverged))
        if bool((diverged >= 0).any()):
            ids = (diverged >= 0).nonzero().flatten().tolist()
            frame = int(diverged[ids[0]])
            raise ChainDivergedError(
                f"the chain diverged (NaN/inf or farther than {DIVERGENCE_RADIUS} m) for batch members {ids} at "
                f"frame {frame} of the move (t = {frame * call.frame_dt:.4g} s, {path.shape[0] - 1} frames of "
                f"gripper motion) with substeps of {call.frame_dt / call.substeps:.3g} s: use more substeps")
        ctx.save_for_backward(x0, v0 if v0 is not None else x0.new_zeros(0), path, hold, frames)
        ctx.call, ctx.has_v0 = call, v0 is not None
        ctx.mark_non_differentiable(settled, frames)
        return x_out, v_out, settled.bool(), frames

    @staticmethod
    def backward(ctx, gx, gv, _settled, _frames):
        x0, v0, path, hold, frames = ctx.saved_tensors
        call = ctx.call
        gx = torch.zeros_like(x0) if gx is None else gx.contiguous()
        gv = torch.zeros_like(x0) if gv is None else gv.contiguous()
        gx0, gv0 = torch.empty_like(x0), torch.empty_like(x0)
        gpath, ghold = torch.empty_like(path), torch.empty_like(hold)
        getattr(_load(), f"chain3d_backward_{call.suffix}")(*_ptrs(
            call.fp, call.ip, call.held, x0, v0 if ctx.has_v0 else None, path, hold, call.phys, frames, gx, gv,
            gx0, gv0, gpath, ghold))
        return gx0, gv0 if ctx.has_v0 else None, gpath, ghold, None


def move(x: torch.Tensor, v: torch.Tensor | None, held: tuple[int, ...], path: torch.Tensor, hold: torch.Tensor,
         params: ChainParams, substeps: int, *, frame_dt: float, rest_speed: float, check_frames: int,
         settle_frames: int, threads: int | None = None
         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The held nodes along ``path`` (P, B, H, 3) (frame 0 the start, P - 1 move frames; P = 1: none), then at
    ``hold`` (B, H, 3) until the free nodes are slower than ``rest_speed`` (checked every ``check_frames`` frames,
    at most ``settle_frames``). Returns (x, v, settled, frames) as grippers.MoveResult's fields, differentiable
    w.r.t. x, v, path and hold. ChainDivergedError for a chain that runs away, naming it and the frame."""
    dtype = x.dtype
    held_mask = torch.zeros(x.shape[1], dtype=torch.bool)
    held_mask[list(held)] = True
    _check_rollout_inputs(x, v, held_mask, path.to(dtype), substeps, frame_dt, None)    # the eager chain's checks
    params.check(x.shape[0], x.shape[1])
    if not torch.is_tensor(hold) or tuple(hold.shape) != (x.shape[0], len(held), 3):
        raise ChainError(f"hold must have shape ({x.shape[0]}, {len(held)}, 3), got "
                         f"{tuple(hold.shape) if torch.is_tensor(hold) else type(hold).__name__}")
    call = _Call(x, held, path, params, substeps, frame_dt, rest_speed, check_frames, settle_frames, threads)
    return _Move.apply(x.contiguous(), None if v is None else v.to(dtype).contiguous(),
                       path.to(dtype).contiguous(), hold.to(dtype).contiguous(), call)
