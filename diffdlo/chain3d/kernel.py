"""The fused C++ CPU kernel of the grippers' move on the 3-D chain (diffdlo/chain3d/csrc/chain3d.cpp), forward only:
built on first use (diffdlo/utils/native.py), called through ctypes.

``grippers.move`` and ``grippers.settle`` run it where nothing needs a gradient (``usable``): on the CPU, float32 or
float64, no tensor of the state, the goal or the cable's parameters requiring grad, no extra acceleration (the
learned residual is a torch network). Everything else (the gradient planner, the stand-in's residual, CUDA) runs
the eager path of diffdlo/chain3d/chain.py, which is the reference: the kernel mirrors it step by step and the tests
hold the two together. If no compiler is found or the build fails, one ``KernelUnavailableWarning`` says so and the
eager path runs.
"""
from __future__ import annotations

import ctypes
import threading
import warnings
from importlib import resources
from typing import Any, Callable

import torch

from ..planar.backends.kernel import KernelUnavailableWarning
from ..utils import native
from .chain import DIVERGENCE_RADIUS, ChainDivergedError, ChainParams, _resolve

SOURCE = resources.files(__package__) / "csrc" / "chain3d.cpp"
_SCALARS = ("EI", "EA", "axial_damping", "bending_damping", "gravity", "floor_height", "floor_stiffness",
            "floor_damping", "floor_width")           # chain3d.cpp's enum Scalar, in its order

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_error: str | None = None
_compiler = native.find_compiler


def _build() -> ctypes.CDLL:
    lib = native.build(SOURCE, "diffdlo/chain3d/csrc/chain3d.cpp", "C++ kernel of the 3-D chain", _compiler())
    lib.chain3d_lanes.restype = ctypes.c_int64
    for suffix in ("f32", "f64"):
        fn = getattr(lib, f"chain3d_move_{suffix}")
        fn.argtypes = [ctypes.c_void_p] * 13
        fn.restype = None
    return lib


def _load() -> ctypes.CDLL | None:
    global _lib, _error
    if _lib is None and _error is None:
        with _lock:
            if _lib is None and _error is None:
                try:
                    _lib = _build()
                except (RuntimeError, OSError) as exc:
                    _error = str(exc)
                    warnings.warn(
                        f"diffdlo: the fused C++ kernel of the 3-D chain is unavailable ({_error}), so the "
                        f"two-gripper task's moves run on the eager PyTorch path, about 30-100x slower. Install a C++ "
                        f"compiler (g++, e.g. `apt install g++`, or clang++) or point $CXX at a working one, then "
                        f"restart Python.", KernelUnavailableWarning)
    return _lib


def available() -> bool:
    """True if the kernel is built (building it now if needed)."""
    return _load() is not None


def unavailable_reason() -> str | None:
    _load()
    return _error


def _needs_grad(params: ChainParams, tensors: list[Any]) -> bool:
    fields = [getattr(params, f.name) for f in params.__dataclass_fields__.values()]
    return any(torch.is_tensor(t) and t.requires_grad for t in tensors + fields)


def usable(x: torch.Tensor, tensors: list[Any], params: ChainParams, accel: Callable | None) -> bool:
    """Whether a move of state ``x`` can run on the kernel: CPU, float32/64, no gradient wanted through ``tensors``
    (the state, the goal) or ``params``, no ``accel``, and the kernel built."""
    if accel is not None or x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64):
        return False
    if torch.is_grad_enabled() and _needs_grad(params, [x, *tensors]):
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


def move(x: torch.Tensor, v: torch.Tensor | None, held: tuple[int, ...], path: torch.Tensor, hold: torch.Tensor,
         params: ChainParams, substeps: int, *, frame_dt: float, rest_speed: float, check_frames: int,
         settle_frames: int, threads: int | None = None
         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The held nodes along ``path`` (P, B, H, 3) (frame 0 the start, P - 1 move frames; P = 1: none), then at
    ``hold`` (B, H, 3) until the free nodes are slower than ``rest_speed`` (checked every ``check_frames`` frames,
    at most ``settle_frames``). Returns (x, v, settled, frames) as grippers.MoveResult's fields. ChainDivergedError
    for a chain that runs away, naming it and the frame."""
    lib = _load()
    batch, n = x.shape[:2]
    dtype = x.dtype
    x0 = x.detach().contiguous()
    v0 = None if v is None else v.detach().to(dtype).contiguous()
    path = path.detach().to(dtype).contiguous()
    hold = hold.detach().to(dtype).contiguous()
    held_ids = torch.tensor(held, dtype=torch.int64)
    phys = _physics(params, x0)
    fp = torch.tensor([frame_dt, rest_speed, DIVERGENCE_RADIUS], dtype=torch.float64)
    ip = torch.tensor([batch, n, len(held), substeps, path.shape[0], check_frames, settle_frames,
                       threads or torch.get_num_threads()], dtype=torch.int64)
    x_out, v_out = torch.empty_like(x0), torch.empty_like(x0)
    settled = torch.zeros(batch, dtype=torch.uint8)
    frames = torch.zeros(batch, dtype=torch.int64)
    diverged = torch.full((batch,), -1, dtype=torch.int64)
    ptr = [ctypes.c_void_p(t.data_ptr()) if t is not None else None
           for t in (fp, ip, held_ids, x0, v0, path, hold, phys, x_out, v_out, settled, frames, diverged)]
    getattr(lib, "chain3d_move_f32" if dtype == torch.float32 else "chain3d_move_f64")(*ptr)
    if bool((diverged >= 0).any()):
        ids = (diverged >= 0).nonzero().flatten().tolist()
        frame = int(diverged[ids[0]])
        raise ChainDivergedError(
            f"the chain diverged (NaN/inf or farther than {DIVERGENCE_RADIUS} m) for batch members {ids} at frame "
            f"{frame} of the move (t = {frame * frame_dt:.4g} s, {path.shape[0] - 1} frames of gripper motion) with "
            f"substeps of {frame_dt / substeps:.3g} s: use more substeps")
    return x_out, v_out, settled.bool(), frames
