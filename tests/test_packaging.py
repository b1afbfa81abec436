"""Packaging and setup: a built wheel works outside the repository, a missing compiler is said once and loudly,
and ``python -m diffdlo --info`` reports what the installation runs on."""
import os
import re
import shutil
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import pytest
import torch

import diffdlo
from diffdlo.planar.backends import kernel
from diffdlo.__main__ import main as diffdlo_main
from diffdlo.planar.params import PARAMS_DIR

ROOT = Path(__file__).resolve().parents[1]
SHIPPED_PACKAGES = ("diffdlo", "agents", "planners")     # what a wheel must hold, every module of them
NOT_SOURCES = shutil.ignore_patterns(".git", ".venv", "runs", "build", "dist", "*.egg-info", "__pycache__",
                                     ".pytest_cache")

# Run in a fresh interpreter with only the installed wheel (and the environment's dependencies) importable.
WHEEL_SMOKE = """
import gymnasium as gym, diffdlo
from agents import sac
from agents.common.config import PARAMS_DIR, load_config, preset_path
from diffdlo.planar.params import PARAMS_DIR as CABLE_PARAMS_DIR
env = gym.make("DiffDLO/ShapeControl-v0")
env.reset(seed=0)
env.step(env.action_space.sample())
load_config(sac.SACConfig, preset_path("sac", None))
load_config(sac.SACConfig, preset_path("sac", "sb3-default"))
assert PARAMS_DIR == CABLE_PARAMS_DIR
print("diffdlo", diffdlo.__file__)
print("params", PARAMS_DIR)
"""


@pytest.fixture(scope="module")
def installed_wheel(tmp_path_factory):
    """Build a wheel from a copy of the sources (so the repository gets no build/ folder) and install it into a
    folder of its own: (wheel file, install folder). Offline: no build isolation, no index."""
    tmp = tmp_path_factory.mktemp("packaging")
    source, wheels, target = tmp / "source", tmp / "wheels", tmp / "installed"
    shutil.copytree(ROOT, source, ignore=NOT_SOURCES)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    build = subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", str(wheels),
                            str(source)], capture_output=True, text=True, timeout=120)
    if build.returncode != 0 and "No module named" in build.stderr:
        pytest.skip(f"cannot build a wheel offline here: {build.stderr.strip().splitlines()[-1]}")
    assert build.returncode == 0, build.stderr
    (wheel,) = wheels.glob("diffdlo-*.whl")
    install = subprocess.run([*pip, "install", "--no-deps", "--no-index", "--target", str(target), str(wheel)],
                             capture_output=True, text=True, timeout=120)
    assert install.returncode == 0, install.stderr
    return wheel, target


def run_outside_repo(args, target: Path, cwd: Path) -> str:
    env = {**os.environ, "PYTHONPATH": str(target), "OMP_NUM_THREADS": "1"}
    result = subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_wheel_holds_every_module_the_params_and_the_kernel_source(installed_wheel):
    wheel, _ = installed_wheel
    names = set(zipfile.ZipFile(wheel).namelist())
    modules = {str(p.relative_to(ROOT)) for pkg in SHIPPED_PACKAGES for p in (ROOT / pkg).rglob("*.py")
               if (p.parent / "__init__.py").is_file() and "__pycache__" not in p.parts}
    assert modules and modules <= names, f"missing from the wheel (list the package in setup.cfg): " \
                                         f"{sorted(modules - names)}"
    params = {f"diffdlo/_params/{p.name}" for p in (ROOT / "params").glob("*.yaml")}
    assert "diffdlo/_params/cable.yaml" in params and "diffdlo/_params/sac.yaml" in params
    assert params <= names, sorted(params - names)
    kernels = {str(p.relative_to(ROOT)) for p in (ROOT / "diffdlo").rglob("csrc/*.cpp")}
    assert {"diffdlo/planar/backends/csrc/cable.cpp", "diffdlo/chain3d/csrc/chain3d.cpp"} <= kernels
    assert kernels <= names, sorted(kernels - names)
    layouts = {f"diffdlo/tasks/layouts/{p.name}" for p in (ROOT / "diffdlo" / "tasks" / "layouts").glob("*.yaml")}
    assert "diffdlo/tasks/layouts/u_two_pegs.yaml" in layouts and layouts <= names, sorted(layouts - names)


def test_installed_wheel_runs_the_env_and_loads_presets_outside_the_repository(installed_wheel, tmp_path):
    _, target = installed_wheel
    out = run_outside_repo(["-c", WHEEL_SMOKE], target, tmp_path)
    assert f"diffdlo {target / 'diffdlo' / '__init__.py'}" in out          # the wheel's copy, not the checkout's
    assert f"params {target / 'diffdlo' / '_params'}" in out
    info = run_outside_repo(["-m", "diffdlo", "--info"], target, tmp_path)
    assert str(target / "diffdlo" / "_params") in info


def test_a_source_checkout_reads_the_repository_params():
    """In the repository (editable install) the files are the ones the README names: params/ at the root."""
    from agents.common import config
    assert PARAMS_DIR == ROOT / "params" and config.PARAMS_DIR == PARAMS_DIR
    assert config.preset_path("sac", None) == ROOT / "params" / "sac.yaml"


@pytest.fixture
def fresh_kernel(monkeypatch, tmp_path):
    """The kernel as in a new process: not built yet, cache in tmp_path. Restored after the test."""
    monkeypatch.setattr(kernel._library, "lib", None)
    monkeypatch.setattr(kernel._library, "error", None)
    monkeypatch.setenv("DIFFDLO_CACHE", str(tmp_path))


@pytest.mark.parametrize("compiler,reason", [(None, r"no C\+\+ compiler found"), ("false", "false failed to build")])
def test_kernel_unavailable_warns_once_with_the_slowdown_and_the_fix(fresh_kernel, monkeypatch, params, compiler,
                                                                    reason):
    """No compiler, or one that fails: one KernelUnavailableWarning per process, then the eager path, quietly."""
    monkeypatch.setattr(kernel, "_compiler", lambda: compiler)
    with pytest.warns(diffdlo.KernelUnavailableWarning, match=rf"(?s)unavailable \({reason}.*slower.*g\+\+.*\$CXX"):
        assert not kernel.available()
    with warnings.catch_warnings():
        warnings.simplefilter("error", diffdlo.KernelUnavailableWarning)          # a second warning would raise
        assert not kernel.available()
        sim = diffdlo.Simulator(params)
        assert sim.engine != "kernel"
        pos = sim.random_shape(1, torch.Generator().manual_seed(0))
        assert sim.move(pos, torch.tensor([0]), torch.tensor([[0.01, 0.0]])).shape == pos.shape


def test_info_reports_version_backend_torch_devices_threads_and_params(capsys):
    assert diffdlo_main(["--info"]) == 0
    out = capsys.readouterr().out
    assert diffdlo.__version__ in out and "torch:" in out and torch.__version__ in out
    backend = "fused C++ kernel" if kernel.available() else "eager torch path"
    assert f"simulator backend: {backend}" in out
    from diffdlo.planar.backends import triton_kernel
    gpu = "fused Triton kernels, forward and adjoint" if triton_kernel.available() else "eager torch path: triton"
    assert re.search(rf"on CUDA devices: +{gpu}", out), out
    assert "devices:" in out and "cpu" in out
    assert f"{torch.get_num_threads()} intra-op" in out
    assert re.search(rf"params files: +{re.escape(str(PARAMS_DIR))}\n", out)


def test_info_says_why_the_backend_is_eager(fresh_kernel, monkeypatch, capsys):
    monkeypatch.setattr(kernel, "_compiler", lambda: None)
    with warnings.catch_warnings():
        warnings.simplefilter("error", diffdlo.KernelUnavailableWarning)          # --info says it itself
        assert diffdlo_main(["--info"]) == 0
    out = capsys.readouterr().out
    assert "simulator backend: eager torch path, about 100-500x slower" in out
    assert "no C++ compiler found" in out and "install g++" in out
