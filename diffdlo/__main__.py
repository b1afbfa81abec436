"""``python -m diffdlo --info``: what this installation runs on, for bug reports and for checking a setup.

Prints the version, the simulator backend in use (the fused C++ kernel, or the eager torch path and why), the one on
CUDA devices (the Triton kernels, or the eager path and why), the torch version, the devices, torch's threads and the
folder the parameter files are read from. A Simulator's own choice is its ``engine`` (and ``why_not``).
"""
from __future__ import annotations

import argparse
import platform
import sys
import warnings

import torch

import diffdlo
from diffdlo.planar.backends import kernel
from diffdlo.planar.params import PARAMS_DIR


def backend_line() -> str:
    """The CPU simulator backend that ``backend="auto"`` picks, with the reason where it is the slow one."""
    with warnings.catch_warnings():         # the line below says the same as the warning
        warnings.simplefilter("ignore", kernel.KernelUnavailableWarning)
        reason = kernel.unavailable_reason()
    if reason is None:
        return (f"fused C++ kernel ({kernel.lanes()} ropes per lane group, pegs and pins included; library "
                f"{kernel.library_path()}); the PID controller uses the eager torch path")
    return (f"eager torch path, about 100-500x slower per move: the fused C++ kernel is unavailable ({reason}); "
            f"install g++ (or clang++) or set $CXX, then rerun")


def gpu_backend_line() -> str:
    """What ``backend="auto"`` runs on CUDA tensors: the Triton kernels (forward and adjoint) where triton imports,
    else the eager torch path and why."""
    from diffdlo.planar.backends import triton_kernel
    reason = triton_kernel.unavailable_reason()
    if reason is not None:
        return f"eager torch path: {reason}"
    import triton
    here = "" if torch.cuda.is_available() else "; no CUDA device here"
    return (f"fused Triton kernels, forward and adjoint (triton {triton.__version__}); moves with pegs or a pin on the "
            f"eager torch path{here}")


def devices_line() -> str:
    """Every device a Simulator can be put on."""
    devices = ["cpu"]
    if torch.cuda.is_available():
        devices += [f"cuda:{i} ({torch.cuda.get_device_name(i)})" for i in range(torch.cuda.device_count())]
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        devices.append("mps")
    return ", ".join(devices)


def info() -> str:
    """The report ``--info`` prints, one ``name: value`` per line."""
    rows = {
        "diffdlo": f"{diffdlo.__version__} ({diffdlo.__file__})",
        "simulator backend": backend_line(),
        "on CUDA devices": gpu_backend_line(),
        "torch": torch.__version__,
        "devices": devices_line(),
        "torch threads": f"{torch.get_num_threads()} intra-op, {torch.get_num_interop_threads()} inter-op",
        "params files": str(PARAMS_DIR),
        "python": f"{platform.python_version()} on {platform.platform()}",
    }
    width = max(map(len, rows))
    return "\n".join(f"{name + ':':<{width + 1}} {value}" for name, value in rows.items())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m diffdlo",
                                     description="Report what this diffdlo installation runs on.")
    parser.add_argument("--info", action="store_true", help="print the version, backend, devices and paths in use")
    args = parser.parse_args(argv)
    if not args.info:
        parser.print_help()
        return 0
    print(info())
    return 0


if __name__ == "__main__":
    sys.exit(main())
