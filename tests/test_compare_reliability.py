"""The comparison harness as a tool that must not lose or misreport work: the report goes only where it is told,
stopping compare stops its cells, one compare per --out, atomic rewrites, cells whose grid settings changed are not
reported as finished, bad options are named, and the Ray path runs two cells."""
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from benchmarks import compare

COMMITTED_REPORT = compare.ROOT / "docs" / "RESULTS.md"

# a two-cell grid of seconds: greedy, one move, one episode, on diagonal and on random (the per-episode merge)
TINY = {"full": {"seeds": [0], "targets": ["diagonal", "random"], "episodes": 1, "eval_seed_base": 10000,
                 "budgets": "tiny", "methods": {"greedy": {"kind": "planner",
                                                           "variants": {"default": {"args": {"max-steps": 1}}}}}}}


def write_grid(path: Path, max_steps: int = 1, **cem) -> Path:
    grid = json.loads(json.dumps(TINY))
    grid["full"]["methods"]["greedy"]["variants"]["default"]["args"]["max-steps"] = max_steps
    if cem:
        grid["full"]["methods"] = {"cem": {"kind": "planner", "variants": {"default": {"args": cem}}}}
        grid["full"]["targets"] = ["diagonal"]
    path.write_text(yaml.safe_dump(grid))
    return path


def stat_or_none(p: Path):
    return p.stat().st_mtime_ns if p.exists() else None


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The tiny grid run once from a scratch working directory without --report, recording every os.replace."""
    root = tmp_path_factory.mktemp("reliable")
    grid = write_grid(root / "grid.yaml")
    committed = stat_or_none(COMMITTED_REPORT)
    replaced, real_replace = [], os.replace

    def recording_replace(src, dst, *a, **kw):
        replaced.append(Path(dst))
        return real_replace(src, dst, *a, **kw)

    argv = ["--grid", str(grid), "--out", str(root / "cells"), "--jobs", "1", "--no-progress"]
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(root)
        mp.setattr(os, "replace", recording_replace)
        assert compare.main(argv) == 0
    assert stat_or_none(COMMITTED_REPORT) == committed           # docs/RESULTS.md of the repository untouched
    return root, grid, argv, replaced


def copy_cells(root: Path, dest: Path) -> Path:
    shutil.copytree(root / "cells", dest, ignore=shutil.ignore_patterns("RESULTS.md", "figures"))
    return dest


# 1. the report goes where --report names, never into docs/ unless named


def test_a_run_without_report_path_writes_under_its_out_not_docs(tiny):
    root, *_ = tiny
    assert not (root / "docs").exists()
    assert (root / "cells" / "RESULTS.md").exists()
    assert {p.name for p in (root / "cells" / "figures").glob("*.png")} >= {"gallery_diagonal.png"}


def test_report_goes_to_the_named_path_with_figures_beside_it(tiny, tmp_path, monkeypatch):
    root, grid, _, _ = tiny
    monkeypatch.chdir(tmp_path)
    doc = tmp_path / "elsewhere" / "R.md"
    assert compare.main(["--grid", str(grid), "--out", str(root / "cells"), "--report-only", "--report", str(doc)]) == 0
    assert "## Task: diagonal" in doc.read_text() and (doc.parent / "figures" / "gallery_diagonal.png").exists()
    assert not (tmp_path / "docs").exists()


def test_quick_report_only_and_no_report_stay_out_of_docs(tiny, tmp_path, monkeypatch):
    root, grid, argv, _ = tiny
    monkeypatch.chdir(tmp_path)
    committed = stat_or_none(COMMITTED_REPORT)
    assert compare.main(["--quick", "--report-only", "--no-figures"]) == 0          # nothing run: an empty report
    assert (tmp_path / "runs" / "compare-quick" / "RESULTS.md").exists()
    cells = copy_cells(root, tmp_path / "cells")
    assert compare.main(["--grid", str(grid), "--out", str(cells), "--no-progress", "--no-report"]) == 0
    assert not (cells / "RESULTS.md").exists() and not (tmp_path / "docs").exists()
    assert stat_or_none(COMMITTED_REPORT) == committed


# 2. stopping compare stops its cells' processes


def _cell_processes(marker: str) -> list[int]:
    """The pids of the planner processes whose command line holds ``marker`` (their --out)."""
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                cmd = (proc / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            text = [c.decode(errors="replace") for c in cmd]
            if "planners.cem" in text and any(marker in c for c in text):
                pids.append(int(proc.name))
    return pids


def _gone(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return True
    return state in ("Z", "X")


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds the cell's process through /proc")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_stopping_compare_stops_its_running_cells(tmp_path, sig):
    # a CEM cell that would run for many minutes
    grid = write_grid(tmp_path / "grid.yaml", **{"max-steps": 1000, "horizon": 3, "candidates": 2000,
                                                  "elites": 20, "iterations": 20})
    out = tmp_path / "cells"
    env = dict(os.environ, PYTHONPATH=str(compare.ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "benchmarks.compare", "--grid", str(grid), "--out", str(out), "--jobs", "1",
           "--no-progress", "--no-report"]
    harness = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True)
    children: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while not children and time.monotonic() < deadline and harness.poll() is None:
            time.sleep(0.2)
            children = _cell_processes(str(out))
        assert children, f"the cell never started: {harness.poll()=}"
        time.sleep(1.0)                                          # the harness is waiting on it
        os.kill(harness.pid, sig)
        stdout, stderr = harness.communicate(timeout=180)       # generous: CI machines are shared
        assert harness.returncode == (130 if sig == signal.SIGINT else 143), stderr
        assert "stopping 1 running cell process" in stderr and "stopped 1 cell process" in stderr
        deadline = time.monotonic() + 15
        while not all(map(_gone, children)) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert all(map(_gone, children)), f"cell processes {children} still run after compare stopped"
        assert not (out / ".compare.lock").exists()
    finally:
        for pid in [*children, harness.pid]:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        harness.wait(timeout=10)


# 3. one compare per --out


def _write_lock(out: Path, pid: int) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    lock = out / ".compare.lock"
    lock.write_text(json.dumps({"pid": pid, "host": socket.gethostname()}))
    return lock


def test_a_live_lock_stops_a_second_compare_naming_pid_and_path(tmp_path, capsys):
    grid = write_grid(tmp_path / "grid.yaml")
    out = tmp_path / "cells"
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        lock = _write_lock(out, other.pid)
        rc = compare.main(["--grid", str(grid), "--out", str(out), "--jobs", "1", "--no-progress", "--no-report"])
        err = capsys.readouterr().err
        assert rc == 3
        assert f"pid {other.pid}" in err and str(lock) in err
        assert not list(out.rglob("results.json")) and lock.exists()       # nothing ran; its lock kept
    finally:
        other.kill()
        other.wait()


def test_a_stale_lock_is_taken_over_and_the_lock_released_at_the_end(tiny, tmp_path, capsys):
    root, grid, _, _ = tiny
    out = copy_cells(root, tmp_path / "cells")
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    lock = _write_lock(out, dead.pid)
    assert compare.main(["--grid", str(grid), "--out", str(out), "--no-progress", "--no-report"]) == 0
    err = capsys.readouterr().err
    assert "stale lock" in err and str(lock) in err and str(dead.pid) in err
    assert not lock.exists()


def test_the_lock_is_held_while_cells_run_and_released_when_interrupted(tmp_path, monkeypatch, capsys):
    grid = write_grid(tmp_path / "grid.yaml")
    out = tmp_path / "cells"
    seen = []

    def interrupted_run(cells, **kw):
        seen.append(json.loads((out / ".compare.lock").read_text()))
        raise KeyboardInterrupt

    monkeypatch.setattr(compare.cli, "run_cells", interrupted_run)
    assert compare.main(["--grid", str(grid), "--out", str(out), "--no-report"]) == 130
    assert seen == [{"pid": os.getpid(), "host": socket.gethostname()}]
    assert not (out / ".compare.lock").exists()
    assert "stopped" in capsys.readouterr().err


# 4. atomic rewrites


def test_every_file_the_harness_writes_goes_through_a_rename(tiny):
    root, _, _, replaced = tiny
    cells = root / "cells"
    for d in (cells / "greedy/default/diagonal/seed0", cells / "greedy/default/random/seed0"):
        assert d / "cell.json" in replaced
    assert cells / "RESULTS.md" in replaced and cells / "figures" / "gallery_diagonal.png" in replaced
    assert not [p for p in root.rglob("*.tmp*")]                                    # no temporary left


def test_a_failed_rewrite_leaves_the_old_file_and_no_temporary(tmp_path):
    from diffdlo.utils.files import replacing, write_text_atomic

    target = tmp_path / "cell.json"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with replacing(target) as tmp:
            tmp.write_text("half of the new")
            raise RuntimeError("killed while writing")
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["cell.json"]
    write_text_atomic(target, "new")
    assert target.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["cell.json"]


# 5. a finished cell whose grid settings changed is not reported as finished


def test_cell_json_stores_the_settings_the_cell_ran_with(tiny):
    root, *_ = tiny
    meta = json.loads((root / "cells/greedy/default/diagonal/seed0/cell.json").read_text())
    assert meta["argv"][meta["argv"].index("--max-steps") + 1] == "1"
    assert meta["grid_entry"] == {"kind": "planner", "args": {"max-steps": 1}, "set": {}, "episodes": 1,
                                  "eval_seed_base": 10000}


def test_changed_settings_refuse_the_run_and_name_the_setting(tiny, tmp_path, capsys):
    root, *_ = tiny
    out = copy_cells(root, tmp_path / "cells")
    changed = write_grid(tmp_path / "changed.yaml", max_steps=2)
    results = sorted(out.rglob("seed0/results.json"))
    before = {p: p.stat().st_mtime_ns for p in results}
    assert compare.main(["--grid", str(changed), "--out", str(out), "--no-progress", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "--max-steps '1' -> '2'" in err and "greedy/default/diagonal seed 0" in err and "--rerun-changed" in err
    assert {p: p.stat().st_mtime_ns for p in results} == before                   # nothing rerun, nothing moved


def test_the_report_leaves_out_cells_whose_settings_changed(tiny, tmp_path):
    root, *_ = tiny
    out = copy_cells(root, tmp_path / "cells")
    grid = compare.load_grid(path=write_grid(tmp_path / "changed.yaml", max_steps=2))
    compare.write_report(grid, out, tmp_path / "R.md", None)
    md = (tmp_path / "R.md").read_text()
    assert "2 finished cell(s) ran with other settings than the grid's now" in md
    assert "--max-steps '1' -> '2'" in md and "## Task: diagonal" not in md


def test_rerun_changed_moves_the_old_cell_aside_and_runs_it_fresh(tiny, tmp_path, capsys):
    root, *_ = tiny
    out = copy_cells(root, tmp_path / "cells")
    changed = write_grid(tmp_path / "changed.yaml", max_steps=2)
    argv = ["--grid", str(changed), "--out", str(out), "--targets", "diagonal", "--no-progress", "--no-report"]
    assert compare.main([*argv, "--rerun-changed"]) == 0
    assert "the old folder is now" in capsys.readouterr().err
    old, = out.glob("superseded/*/greedy/default/diagonal/seed0")
    assert json.loads((old / "cell.json").read_text())["grid_entry"]["args"] == {"max-steps": 1}
    fresh = json.loads((out / "greedy/default/diagonal/seed0/cell.json").read_text())
    assert fresh["grid_entry"]["args"] == {"max-steps": 2} and "2" in fresh["argv"]
    assert compare.main(argv) == 0                                               # now it matches: skipped


def test_kept_partial_work_with_other_settings_counts_as_changed(tmp_path):
    grid = compare.load_grid(quick=True)
    sac, = compare.build_cells(grid, tmp_path, methods=["sac"], seeds=[0])
    for cell, kept in ((sac, "checkpoint.pt"),):
        d = Path(cell["dir"])
        (d / kept).parent.mkdir(parents=True)
        stored = list(cell["argv"])
        stored[stored.index("--max-steps") + 1] = "99"
        (d / "cell.json").write_text(json.dumps(dict(cell, argv=stored)))
        assert compare.settings_changes(cell) == []                 # nothing kept yet: it reruns from the start
        (d / kept).write_text("{}")                                  # a learner resumes it
        now = cell["argv"][stored.index("--max-steps") + 1]
        assert compare.settings_changes(cell) == [f"--max-steps '99' -> '{now}'"]


def test_out_path_and_learner_device_are_not_settings():
    argv = ["-m", "agents.sac", "--seed", "0", "--set", "lr=0.1", "--threads", "1", "--set", "device=cuda",
            "--set", "env_device=cpu", "--out", "/a/b"]
    assert compare.comparable_argv(argv, "cuda") == ["-m", "agents.sac", "--seed", "0", "--set", "lr=0.1",
                                                     "--threads", "1"]
    now = ["-m", "agents.sac", "--seed", "0", "--set", "lr=0.2", "--quiet", "--out", "elsewhere"]
    assert compare.argv_changes(compare.comparable_argv(argv, "cuda"), compare.comparable_argv(now)) == [
        "--set lr '0.1' -> '0.2'", "--threads removed (was '1')", "--quiet added"]


# 6. bad options are named on one line, exit code 2


@pytest.mark.parametrize("extra, named", [
    (["--variants", "points", "pointz"], ["'pointz'", "default", "points"]),
    (["--methods", "greedy", "cme"], ["'cme'", "greedy", "cem", "planet"]),
    (["--targets", "diagonal", "diagonl"], ["'diagonl'", "diagonal", "random"]),
    (["--seeds", "0", "7"], ["unknown 7;", "0, 1"]),
    (["--methods", "cem", "--variants", "points"], ["'points'", "the methods cem have", "default"]),
    (["--rows", "greedy/default", "ppo/pointz"], ["--rows", "'ppo/pointz'", "ppo/points", "greedy/default"]),
    (["--jobs", "0"], ["--jobs", "0"]),
    (["--jobs", "-3"], ["--jobs", "-3"]),
    (["--ray", "local", "--ray-cpus", "0"], ["--ray-cpus", "0"]),
])
def test_bad_filters_and_counts_exit_2_on_one_line(extra, named, capsys):
    with pytest.raises(SystemExit) as stop:
        compare.main(["--quick", *extra, "--list"])
    err = capsys.readouterr().err
    assert stop.value.code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for word in named:
        assert word in lines[0], (word, lines[0])


def test_rows_select_cells_in_their_order(capsys):
    """--rows runs exactly the named rows, the later-named row's cells after the earlier one's."""
    assert compare.main(["--quick", "--rows", "ppo/points", "greedy/default", "--seeds", "0", "--list"]) == 0
    modules = [line.split()[3] for line in capsys.readouterr().out.splitlines() if line.startswith(("todo", "done"))]
    assert modules and set(modules) == {"agents.ppo", "planners.greedy"}, modules
    assert modules == sorted(modules, key=lambda m: m != "agents.ppo"), modules


# 7. the Ray path


@pytest.mark.ecosystem    # run by .ci/run after installing the optional extras
def test_ray_runs_a_two_cell_grid_on_a_local_ray(tmp_path):
    ray = pytest.importorskip("ray")
    grid = compare.load_grid(quick=True)
    cells = compare.build_cells(grid, tmp_path, methods=["greedy"], targets=["diagonal"], seeds=[0, 1])
    assert len(cells) == 2
    try:
        results = compare.run_cells(cells, ray_address="local", ray_num_cpus=2, progress=False)
        assert not ray.is_initialized()                          # the Ray it started is shut down
    finally:
        ray.shutdown()
    assert sorted(r["status"] for r in results) == ["done", "done"]
    for c in cells:
        assert (Path(c["dir"]) / "results.json").exists()
        assert json.loads((Path(c["dir"]) / "cell.json").read_text())["argv"] == c["argv"]
