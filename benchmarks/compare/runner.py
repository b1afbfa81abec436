"""Running cells: each one a subprocess of the project's own entry point, N at once or as Ray tasks, finished cells
skipped, interrupted learners resumed from their checkpoint."""
from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from diffdlo.utils.files import write_json_atomic
from .grid import ROOT, cell_dir, command_line, is_done
from .processes import allow_children, run_in_own_group, stop_children


def machine_info(cell: dict[str, Any]) -> dict[str, Any]:
    """Where a cell runs (its wall time depends on it): host, CPU count, and the GPU a learner uses."""
    info: dict[str, Any] = {"host": platform.node(), "cpus": os.cpu_count()}
    dev = cell.get("learner_device")
    if dev and dev.startswith("cuda"):
        import torch
        info["gpu"] = torch.cuda.get_device_name(torch.device(dev)) if torch.cuda.is_available() else "unavailable"
    return info


def _write_cell_json(d: Path, cell: dict[str, Any]) -> None:
    """cell.json: the cell (its argv and grid entry: the settings it runs with), the command that reproduces it and
    the machine it ran on (read by the report and by the check of changed settings)."""
    write_json_atomic(d / "cell.json", dict(cell, command=command_line(cell), machine=machine_info(cell)))


def _env() -> dict[str, str]:
    """The entry points' environment: one thread each (cells run side by side), this repository importable."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _call(argv: list[str], log: Path, cwd: str) -> None:
    with open(log, "a") as f:
        f.write(f"$ {shlex.join(['python', *argv])}\n")
        f.flush()
        rc = run_in_own_group([sys.executable, *argv], cwd=cwd, stdout=f, stderr=subprocess.STDOUT, env=_env())
    if rc != 0:
        raise RuntimeError(f"exit code {rc}: python {shlex.join(argv)} (log: {log})")


def fresh_argv(argv: list[str]) -> list[str]:
    """A cell's run from the start: its folder already holds the harness's cell.json and log.txt (and maybe an
    interrupted attempt's files, which the harness always restarts), so the entry point may replace them."""
    return [*argv, "--overwrite"]


def _resume_argv(cell: dict[str, Any]) -> list[str]:
    """Continue an interrupted learner from its checkpoint.pt, on the device asked for now, not the saved one."""
    argv = ["-m", cell["argv"][1], "--out", str(cell_dir(cell)), "--resume", "--no-progress"]
    if cell.get("total_steps"):
        argv += ["--total-steps", str(cell["total_steps"])]
    if cell.get("learner_device"):
        argv += ["--device", cell["learner_device"]]
    return argv


def run_cell(cell: dict[str, Any]) -> dict[str, Any]:
    """Run one cell (skipped if finished). Returns {"cell", "status": done|skipped|failed, "wall_s", "error"}."""
    d = cell_dir(cell)
    if is_done(cell):
        return {"cell": cell, "status": "skipped", "wall_s": 0.0}
    d.mkdir(parents=True, exist_ok=True)
    log = d / "log.txt"
    t0 = time.perf_counter()
    try:
        resume = cell["kind"] == "agent" and (d / "checkpoint.pt").exists()
        _write_cell_json(d, cell)
        _call(_resume_argv(cell) if resume else fresh_argv(cell["argv"]), log, cell["cwd"])
        return {"cell": cell, "status": "done", "wall_s": time.perf_counter() - t0}
    except Exception as exc:  # noqa: BLE001 - a failed cell must not stop the others; it reruns next time
        return {"cell": cell, "status": "failed", "wall_s": time.perf_counter() - t0, "error": str(exc)}


def _run_on_ray(todo: list[dict[str, Any]], ray_address: str, num_cpus: int | None, finished) -> None:
    """The cells as Ray tasks on ``ray_address`` ("local": a Ray started here, with ``num_cpus`` CPUs), one CPU each.
    A Ray that is already running in this process is used as it is; one started here is shut down at the end. A task
    that dies (its worker lost) is a failed cell, not the end of the run."""
    import ray

    started = not ray.is_initialized()
    if started:
        # workers import this module through PYTHONPATH; cells hold absolute working directories, so every node must
        # see the repository and --out at the same paths (a shared filesystem)
        local = ray_address == "local"
        ray.init(address=None if local else ray_address, num_cpus=num_cpus if local else None,
                 runtime_env={"env_vars": {"PYTHONPATH": str(ROOT)}})
    task = ray.remote(num_cpus=1)(run_cell)
    pending = {task.remote(c): c for c in todo}
    try:
        while pending:
            (ready,), _ = ray.wait(list(pending), num_returns=1)
            cell = pending.pop(ready)
            try:
                finished(ray.get(ready))
            except Exception as exc:  # noqa: BLE001 - a lost worker fails its cell only
                finished({"cell": cell, "status": "failed", "wall_s": 0.0, "error": f"Ray task: {exc}"})
    except KeyboardInterrupt:
        print(f"compare: interrupted: cancelling {len(pending)} Ray task(s) (each ends its cell's process group)",
              file=sys.stderr, flush=True)
        for ref in pending:
            ray.cancel(ref)              # KeyboardInterrupt inside the task: run_in_own_group ends its subprocess
        raise
    finally:
        if started:
            ray.shutdown()


def _run_in_threads(todo: list[dict[str, Any]], jobs: int, finished) -> None:
    """The cells ``jobs`` at once, each thread driving one subprocess; on an interrupt no new cell starts and the
    running ones' process groups are ended before the interrupt goes on."""
    pool = ThreadPoolExecutor(max_workers=jobs)
    try:
        for fut in as_completed([pool.submit(run_cell, c) for c in todo]):
            finished(fut.result())
    except KeyboardInterrupt as exc:
        stop_children(f"interrupted ({type(exc).__name__}{': ' + str(exc) if str(exc) else ''})")
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def run_cells(cells: list[dict[str, Any]], jobs: int = 1, ray_address: str | None = None,
              progress: bool = True, ray_num_cpus: int | None = None) -> list[dict[str, Any]]:
    """Run the unfinished cells, ``jobs`` at once (threads, each driving one subprocess) or as Ray tasks on
    ``ray_address`` ("local": ray.init(num_cpus=ray_num_cpus)). Returns run_cell's answer for every cell, finished
    ones "skipped". Interrupted (Ctrl-C, or SIGTERM under cli.main), it stops the cells' processes and re-raises."""
    from tqdm import tqdm

    if jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    allow_children()                      # a new run (an earlier one in this process may have been stopped)
    todo = [c for c in cells if not is_done(c)]
    results = [{"cell": c, "status": "skipped", "wall_s": 0.0} for c in cells if is_done(c)]
    bar = tqdm(total=len(cells), initial=len(results), desc="cells", unit="cell", disable=not progress,
               dynamic_ncols=True)

    def finished(r: dict[str, Any]) -> None:
        results.append(r)
        bar.set_postfix_str(f"{r['status']}: {r['cell']['method']}/{r['cell']['variant']}/{r['cell']['target']}")
        bar.update(1)

    try:
        if todo and ray_address is not None:
            _run_on_ray(todo, ray_address, ray_num_cpus, finished)
        elif todo:
            _run_in_threads(todo, jobs, finished)
    finally:
        bar.close()
    for r in results:
        if r["status"] == "failed":
            print(f"FAILED {r['cell']['dir']}: {r.get('error')}", file=sys.stderr)
    return results
