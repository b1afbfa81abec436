"""Compile the Triton kernels for a CUDA architecture without a GPU, and print what ptxas reports for each.

    python -m benchmarks.speed.triton_compile [--arch 90] [--nodes 20]

Triton's wheel carries its own ptxas, so the compiled path (not the interpreter the tests run on the CPU) is checked
on any machine: that every variant of the move kernel (drag or free evolution, with or without checkpoints, with
frames) and of the adjoint (with or without the physics gradients, with frames) compiles, in float32 and float64, and
how many registers and spilled bytes each takes at the warps per program of
``diffdlo.planar.backends.triton_kernel.WARPS`` (the table is chosen so that none spills on sm_90 with 20 nodes).
``--warps`` overrides them, to compare.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import re

import torch

from diffdlo.planar.backends import triton_kernel

POINTERS_INT64 = {"node_ptr", "ngrasp_ptr", "steps_ptr"}
POINTERS_INT8 = {"settled_ptr", "diverged_ptr", "stopped_ptr"}


def signature(kernel, dtype: torch.dtype) -> dict[str, str]:
    """Triton's signature of ``kernel``: pointers by name (float ones in ``dtype``), int32 scalars, constexprs."""
    fp = {torch.float32: "fp32", torch.float64: "fp64"}[dtype]
    out = {}
    for i, name in enumerate(kernel.arg_names):
        if kernel.params[i].is_constexpr:
            out[name] = "constexpr"
        elif name in POINTERS_INT64:
            out[name] = "*i64"
        elif name in POINTERS_INT8:
            out[name] = "*i8"
        elif name.endswith("_ptr"):
            out[name] = f"*{fp}"
        else:
            out[name] = "i32"
    return out


def variants(n_nodes: int, chunk: int):
    """(name, kernel, constexprs) of every variant the simulator launches."""
    shape = {"N": n_nodes, "N_PAD": 1 << (n_nodes - 1).bit_length(), "BLOCK": triton_kernel.BLOCK_ROPES}
    for fixed in (False, True):
        for save in (False, True):
            name = f"move {'free' if fixed else 'drag'}{' +checkpoints' if save else ''}"
            yield name, "move", triton_kernel._move_kernel, {**shape, "FIXED": fixed, "SAVE": save, "CHUNK": chunk,
                                                             "RECORD": False}
    yield ("move drag +checkpoints +frames", "move", triton_kernel._move_kernel,
           {**shape, "FIXED": False, "SAVE": True, "CHUNK": chunk, "RECORD": True})
    for phys, frames in ((False, False), (True, False), (True, True)):
        name = f"adjoint{' +physics' if phys else ''}{' +frames' if frames else ''}"
        yield name, "adjoint", triton_kernel._adjoint_kernel, {**shape, "CHUNK": chunk, "PHYS": phys,
                                                               "NC": 4 if phys else 2, "FRAMES": frames}


def compile_kernel(kernel, dtype: torch.dtype, constexprs: dict, arch: int, warps: int) -> dict:
    """Compile for sm_<arch>; returns registers, spill stores and loads [bytes] from ptxas's log."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    source = ASTSource(kernel, signature(kernel, dtype), constexprs=constexprs)
    log = io.StringIO()
    old = triton.knobs.nvidia.dump_ptxas_log, triton.knobs.compilation.always_compile
    triton.knobs.nvidia.dump_ptxas_log = True           # ptxas's report, printed by Triton to stdout
    triton.knobs.compilation.always_compile = True      # a cached kernel would skip ptxas and its report
    try:
        with contextlib.redirect_stdout(log):
            triton.compile(source, target=GPUTarget("cuda", arch, 32), options={"num_warps": warps})
    finally:
        triton.knobs.nvidia.dump_ptxas_log, triton.knobs.compilation.always_compile = old
    text = log.getvalue()
    registers = re.findall(r"Used (\d+) registers", text)
    spills = re.findall(r"(\d+) bytes spill stores, (\d+) bytes spill loads", text)
    return {"registers": int(registers[-1]) if registers else None,
            "spill_stores": int(spills[-1][0]) if spills else None,
            "spill_loads": int(spills[-1][1]) if spills else None}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arch", type=int, default=90, help="CUDA compute capability x10 (90: H100/H200)")
    parser.add_argument("--nodes", type=int, default=20, help="nodes per rope (default: the thesis's 20)")
    parser.add_argument("--warps", type=int, default=None, help="warps per program for every kernel (default: WARPS)")
    args = parser.parse_args(argv)
    if args.nodes < 3:
        parser.error(f"--nodes must be >= 3, got {args.nodes}")
    if args.warps is not None and (args.warps < 1 or args.warps & (args.warps - 1)):
        parser.error(f"--warps must be a power of two, got {args.warps}")
    if not triton_kernel.available():
        parser.error(triton_kernel.unavailable_reason())
    chunk = triton_kernel.chunk_substeps(2001)
    print(f"sm_{args.arch}, {args.nodes} nodes, {triton_kernel.BLOCK_ROPES} ropes per program, chunk {chunk}")
    print(f"{'kernel':<32} {'dtype':<8} {'warps':>5} {'registers':>9} {'spill st/ld [B]':>16}")
    for dtype in (torch.float32, torch.float64):
        for name, kind, kernel, constexprs in variants(args.nodes, chunk):
            warps = args.warps or triton_kernel.WARPS[kind, dtype]
            r = compile_kernel(kernel, dtype, constexprs, args.arch, warps)
            print(f"{name:<32} {str(dtype).removeprefix('torch.'):<8} {warps:>5} {r['registers']!s:>9} "
                  f"{r['spill_stores']!s:>8}/{r['spill_loads']!s:<7}", flush=True)


if __name__ == "__main__":
    main()
