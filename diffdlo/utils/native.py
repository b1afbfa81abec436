"""Building the project's C++ kernels (diffdlo/planar/backends/csrc/cable.cpp, diffdlo/chain3d/csrc/chain3d.cpp) on
first use, for ctypes.

A kernel is plain C++ with a C ABI, so building it needs only a C++ compiler (g++ or c++ on PATH, or $CXX) and
takes a few seconds; nothing from PyTorch's headers is compiled. The source is package data (read through
``importlib.resources``, so an installed wheel builds it too). The shared library is cached in ``$DIFFDLO_CACHE``
(default ``~/.cache/diffdlo``) under a hash of the source, the compiler, the flags and the CPU.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable

# -march=native: the lane-group loops vectorize across chains with the widest vectors this CPU has (the cache key
# includes the CPU, so a cached build never runs on another model); -fno-math-errno lets sqrt vectorize.
FLAGS = ["-O3", "-march=native", "-fno-math-errno", "-std=c++17", "-fPIC", "-shared", "-pthread"]


def cache_dir() -> Path:
    return Path(os.environ.get("DIFFDLO_CACHE", Path.home() / ".cache" / "diffdlo"))


def find_compiler() -> str | None:
    for name in (os.environ.get("CXX"), "g++", "c++", "clang++"):
        if name and shutil.which(name):
            return name
    return None


def cpu_id() -> str:
    """The CPU model and feature flags (for -march=native builds), or the platform where /proc is absent."""
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        import platform
        return platform.processor() or platform.machine()
    fields = [line for line in info.splitlines() if line.startswith(("model name", "flags"))][:2]
    return "\n".join(fields)


def build(source: Any, shown_as: str, what: str, compiler: str | None, flags: list[str] = FLAGS) -> ctypes.CDLL:
    """The shared library of C++ ``source`` (a path or an importlib.resources file), built with ``compiler`` unless
    a build of the same source, compiler, flags and CPU is cached. RuntimeError (naming ``shown_as``, the source's
    path in the repository) when there is no compiler or the build fails."""
    if compiler is None:
        raise RuntimeError("no C++ compiler found (set $CXX or install g++)")
    code = source.read_bytes()
    key = hashlib.sha256(code + " ".join([compiler, *flags, sys.platform, cpu_id()]).encode()).hexdigest()[:16]
    target = cache_dir() / f"{Path(shown_as).stem}-{key}.so"
    if not target.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
        print(f"diffdlo: compiling the {what} with {compiler} (first use only, a few seconds)...",
              file=sys.stderr, flush=True)
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
            src, out = Path(tmp) / Path(shown_as).name, Path(tmp) / target.name
            src.write_bytes(code)       # a copy on disk for the compiler, wherever the package data lives
            result = subprocess.run([compiler, *flags, str(src), "-o", str(out)], capture_output=True, text=True)
            if result.returncode != 0:
                raise RuntimeError(f"{compiler} failed to build {shown_as}:\n{result.stderr[-2000:]}")
            os.replace(out, target)     # atomic: concurrent processes never load a half-written file
    return ctypes.CDLL(str(target))


class Library:
    """A kernel's shared library, built once per process on first use: ``load()`` returns it, or None where the
    build failed (``error`` then says why, and ``on_error`` was called with it once)."""

    def __init__(self, build: Callable[[], ctypes.CDLL], on_error: Callable[[str], None]):
        self._build, self._on_error, self._lock = build, on_error, threading.Lock()
        self.lib: ctypes.CDLL | None = None
        self.error: str | None = None

    def load(self) -> ctypes.CDLL | None:
        if self.lib is None and self.error is None:
            with self._lock:
                if self.lib is None and self.error is None:
                    try:
                        self.lib = self._build()
                    except (RuntimeError, OSError) as exc:
                        self.error = str(exc)
                        self._on_error(self.error)
        return self.lib
