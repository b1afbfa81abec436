"""Comparison harness: greedy, CEM, gradient planner, SAC, PPO and PlaNet on the same tasks, several seeds each.

    python -m benchmarks.compare --quick                       # tiny grid, minutes: format example, not results
    python -m benchmarks.compare --methods cem sac --targets diagonal --seeds 0 1 --jobs 2
    python -m benchmarks.compare --report                      # only (re)write docs/RESULTS.md from finished cells

The grid (methods x variants x targets x seeds, with budgets) is data: benchmarks/compare.yaml (``full`` and
``quick``). Each cell runs the project's own entry point (``python -m planners.X`` / ``python -m agents.X``) as a
subprocess into ``<out>/<method>/<variant>/<target>/seed<s>/`` and is finished when its ``results.json`` exists:
finished cells are skipped, a learner cell with a ``checkpoint.pt`` but no ``results.json`` continues with
``--resume``, so a long comparison can be split over sessions. ``--jobs N`` runs N cells at once (subprocesses);
``--ray ADDRESS`` (``local`` for ``ray.init()``) runs them as Ray tasks instead (optional dependency).

The report (docs/RESULTS.md, docs/figures/) only reads finished cells. Confidence intervals (no scipy):
  * t-interval over seeds: mean of the per-seed values +- t_{0.975, n-1} * sd / sqrt(n) (sample sd, ddof 1), the
    Student t quantile computed here from the regularized incomplete beta function; success rates clipped to [0, 1];
    undefined for one seed;
  * Wilson score interval (z = 1.959964) over all episodes of all seeds pooled (ignores between-seed variance).
Success at 1 cm: the episode terminated with shape_error < 0.01 m (the env's success). Success at 2 cm: the
episode's last shape_error < 0.02 m; an episode ends at its first move under 1 cm or after max-steps moves, for
planners and learners alike, so this is "ended within 2 cm". Planners also get "moves to 2 cm" from their per-move
``errors`` (first move under 2 cm).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
GRID_FILE = Path(__file__).resolve().with_name("compare.yaml")
NAMED = ("horizontal", "vertical", "diagonal", "antidiagonal")
Z95 = 1.959963984540054


# ====================================================================== statistics (no scipy)
def _betacf(a: float, b: float, x: float) -> float:
    """Continued fraction of the incomplete beta function (modified Lentz)."""
    tiny, qab, qap, qam = 1e-300, a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 300):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-15:
            break
    return h


def betainc(a: float, b: float, x: float) -> float:
    """Regularized incomplete beta I_x(a, b)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    lbt = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log(1.0 - x)
    if x < (a + 1.0) / (a + b + 2.0):
        return math.exp(lbt) * _betacf(a, b, x) / a
    return 1.0 - math.exp(lbt) * _betacf(b, a, 1.0 - x) / b


def t_cdf(t: float, df: float) -> float:
    tail = 0.5 * betainc(df / 2.0, 0.5, df / (df + t * t))
    return 1.0 - tail if t >= 0 else tail


def t_quantile(p: float, df: float) -> float:
    """Student t quantile by bisection on t_cdf (p in (0.5, 1))."""
    lo, hi = 0.0, 1.0
    while t_cdf(hi, df) < p:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if t_cdf(mid, df) < p else (lo, mid)
    return 0.5 * (lo + hi)


def t_interval(values, clip: tuple[float, float] | None = None) -> tuple[float, float, float]:
    """(mean, low, high): 95 % t-interval of the mean of per-seed values; low = high = nan for fewer than 2 values."""
    x = np.asarray(values, dtype=float)
    m = float(x.mean()) if len(x) else float("nan")
    if len(x) < 2:
        return m, float("nan"), float("nan")
    half = t_quantile(0.975, len(x) - 1) * float(x.std(ddof=1)) / math.sqrt(len(x))
    lo, hi = m - half, m + half
    if clip is not None:
        lo, hi = max(lo, clip[0]), min(hi, clip[1])
    return m, lo, hi


def wilson(successes: int, n: int, z: float = Z95) -> tuple[float, float, float]:
    """(p, low, high): Wilson score interval of a binomial proportion."""
    if n == 0:
        return float("nan"), float("nan"), float("nan")
    p = successes / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z / den * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return p, max(0.0, centre - half), min(1.0, centre + half)


# ====================================================================== the grid
def load_grid(quick: bool = False, path: Path | str = GRID_FILE) -> dict[str, Any]:
    grids = yaml.safe_load(Path(path).read_text())
    name = "quick" if quick else "full"
    grid = dict(grids[name], name=name)
    if not isinstance(grid.get("budgets", ""), str):
        raise ValueError(f"{path}: grid {name!r}: 'budgets' must be text (the report prints it), "
                         f"got {grid['budgets']!r}")
    return grid


def _flags(args: dict[str, Any]) -> list[str]:
    out: list[str] = []
    for k, v in (args or {}).items():
        out += [f"--{k}", str(v)]
    return out


def random_targets(seed0: int, n: int) -> list[str]:
    """The named target the env (target="random") draws at reset(seed=seed0 + i), i < n."""
    import torch
    from diffdlo.envs.shape_control import BatchedShapeControl

    env = BatchedShapeControl(1, target="random")
    shapes = {t: env.sim.target_shape(t).to(env.target.dtype) for t in NAMED}
    names = []
    for i in range(n):
        env.reset(seed=seed0 + i)
        names.append(next(t for t, s in shapes.items() if torch.allclose(env.target[0].cpu(), s.cpu())))
    return names


def build_cells(grid: dict[str, Any], out: Path | str, methods=None, variants=None, targets=None,
                seeds=None, learner_device: str | None = None) -> list[dict[str, Any]]:
    """Every (method, variant, target, seed) cell of the grid after the filters, with its commands.

    ``learner_device`` (e.g. "cuda"): learners put their networks and buffers there and simulate on the CPU
    (``--set device=... --set env_device=cpu``); planners are unchanged."""
    out = Path(out)
    cells = []
    for method, spec in grid["methods"].items():
        if methods and method not in methods:
            continue
        for variant, v in spec["variants"].items():
            if variants and variant not in variants:
                continue
            for target in v.get("targets", grid["targets"]):
                if target not in grid["targets"] or (targets and target not in targets):
                    continue
                for seed in grid["seeds"]:
                    if seeds is not None and seed not in seeds:
                        continue
                    d = out / method / variant / target / f"seed{seed}"
                    eval_seed = int(grid["eval_seed_base"]) + 1000 * int(seed)
                    cell = {"method": method, "variant": variant, "target": target, "seed": seed,
                            "kind": spec["kind"], "dir": str(d), "grid": grid["name"], "eval_seed": eval_seed,
                            "cwd": str(Path.cwd())}   # relative paths are relative to it (also on Ray workers)
                    if spec["kind"] == "agent" and target in grid.get("heldout", {}):
                        continue          # learners never train on a held-out shape (their rows: results "heldout")
                    if spec["kind"] == "planner":
                        base = ["-m", f"planners.{method}", *_flags(v.get("args")), "--quiet", "--no-gif"]
                        if target == "random":   # one run per episode, target drawn as the env would, then merged
                            cell["subruns"] = [["--target", "@random", "--seed", str(eval_seed + i), "--episodes", "1",
                                                "--out", str(d / f"ep{i}")] for i in range(int(grid["episodes"]))]
                        spec_target = grid.get("heldout", {}).get(target, target)       # a held-out name -> its file
                        cell["argv"] = base + ["--target", spec_target, "--seed", str(eval_seed), "--episodes",
                                               str(grid["episodes"]), "--out", str(d)]
                    else:
                        sets = [x for k, val in (v.get("set") or {}).items() for x in ("--set", f"{k}={val}")]
                        cell["argv"] = ["-m", f"agents.{method}", "--target", target, "--seed", str(seed),
                                        *_flags(v.get("args")), "--eval-episodes", str(grid["episodes"]),
                                        "--set", f"eval_seed={eval_seed}", *sets, "--threads", "1", "--no-progress",
                                        "--out", str(d)]
                        if learner_device:
                            cell["argv"][-2:-2] = ["--set", f"device={learner_device}", "--set", "env_device=cpu"]
                            cell["learner_device"] = learner_device
                        cell["total_steps"] = (v.get("args") or {}).get("total-steps")
                    cells.append(cell)
    return cells


def command_line(cell: dict[str, Any]) -> str:
    """The exact command(s) that reproduce a cell, as text."""
    if "subruns" in cell:
        base = [a for a in cell["argv"]]
        i = base.index("--target")
        head = base[:i]
        return " && ".join(shlex.join(["python", *head, *s[:1], t, *s[2:]])
                           for s, t in zip(cell["subruns"], cell.get("subrun_targets", ["?"] * len(cell["subruns"]))))
    return shlex.join(["python", *cell["argv"]])


def cell_dir(cell: dict[str, Any], sub: str | Path | None = None) -> Path:
    d = Path(cell.get("cwd", ".")) / (cell["dir"] if sub is None else sub)
    return d


def machine_info(cell: dict[str, Any]) -> dict[str, Any]:
    """Where a cell runs (its wall time depends on it): host, CPU count, and the GPU a learner uses."""
    info: dict[str, Any] = {"host": platform.node(), "cpus": os.cpu_count()}
    dev = cell.get("learner_device")
    if dev and dev.startswith("cuda"):
        import torch
        info["gpu"] = torch.cuda.get_device_name(torch.device(dev)) if torch.cuda.is_available() else "unavailable"
    return info


def _write_cell_json(d: Path, cell: dict[str, Any]) -> None:
    (d / "cell.json").write_text(json.dumps(dict(cell, command=command_line(cell), machine=machine_info(cell)),
                                            indent=2))


def is_done(cell: dict[str, Any]) -> bool:
    return (cell_dir(cell) / "results.json").exists()


# ====================================================================== running
def _env() -> dict[str, str]:
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _call(argv: list[str], log: Path, cwd: str) -> None:
    with open(log, "a") as f:
        f.write(f"$ {shlex.join(['python', *argv])}\n")
        f.flush()
        rc = subprocess.run([sys.executable, *argv], cwd=cwd, stdout=f, stderr=subprocess.STDOUT, env=_env()).returncode
    if rc != 0:
        raise RuntimeError(f"exit code {rc}: python {shlex.join(argv)} (log: {log})")


def _merge(parts: list[dict[str, Any]], cell: dict[str, Any]) -> dict[str, Any]:
    eps = [e for p in parts for e in p["episodes"]]
    steps = sum(p["env_steps"] for p in parts)
    plan_s = sum(e.get("plan_s", 0.0) for e in eps)
    res = dict(parts[0], target="random", seed=cell["eval_seed"], episodes=eps,
               success_rate=sum(e["success"] for e in eps) / len(eps), env_steps=steps,
               wall_s=sum(p["wall_s"] for p in parts), sim_evals=sum(p.get("sim_evals", 0) for p in parts),
               plan_s_per_step=plan_s / max(steps, 1), episode_targets=cell["subrun_targets"])
    res.pop("config", None)
    return res


def run_cell(cell: dict[str, Any]) -> dict[str, Any]:
    """Run one cell (skipped if finished). Returns {"cell", "status": done|skipped|failed, "wall_s", "error"}."""
    d = cell_dir(cell)
    if is_done(cell):
        return {"cell": cell, "status": "skipped", "wall_s": 0.0}
    d.mkdir(parents=True, exist_ok=True)
    log = d / "log.txt"
    t0 = time.perf_counter()
    try:
        if "subruns" in cell:
            cell = dict(cell, subrun_targets=random_targets(cell["eval_seed"], len(cell["subruns"])))
            i = cell["argv"].index("--target")
            head = cell["argv"][:i]
            parts = []
            for sub, t in zip(cell["subruns"], cell["subrun_targets"]):
                sub_out = cell_dir(cell, sub[-1])
                if not (sub_out / "results.json").exists():
                    _call([*head, "--target", t, *sub[2:]], log, cell["cwd"])
                parts.append(json.loads((sub_out / "results.json").read_text()))
            _write_cell_json(d, cell)
            (d / "results.json").write_text(json.dumps(_merge(parts, cell), indent=2))
        else:
            argv = cell["argv"]
            if cell["kind"] == "agent" and (d / "checkpoint.pt").exists():   # continue an interrupted learner
                argv = ["-m", argv[1], "--out", str(d), "--resume", "--no-progress"]
                if cell.get("total_steps"):
                    argv += ["--total-steps", str(cell["total_steps"])]
                if cell.get("learner_device"):                            # the device asked for now, not the saved one
                    argv += ["--device", cell["learner_device"]]
            _write_cell_json(d, cell)
            _call(argv, log, cell["cwd"])
        return {"cell": cell, "status": "done", "wall_s": time.perf_counter() - t0}
    except Exception as exc:  # noqa: BLE001 - a failed cell must not stop the others; it reruns next time
        return {"cell": cell, "status": "failed", "wall_s": time.perf_counter() - t0, "error": str(exc)}


def run_cells(cells: list[dict[str, Any]], jobs: int = 1, ray_address: str | None = None,
              progress: bool = True) -> list[dict[str, Any]]:
    from tqdm import tqdm

    todo = [c for c in cells if not is_done(c)]
    results = [{"cell": c, "status": "skipped", "wall_s": 0.0} for c in cells if is_done(c)]
    bar = tqdm(total=len(cells), initial=len(results), desc="cells", unit="cell", disable=not progress,
               dynamic_ncols=True)
    if ray_address is not None:
        import ray

        # workers import this module through PYTHONPATH; cells hold absolute working directories, so every node must
        # see the repository and --out at the same paths (a shared filesystem)
        ray.init(address=None if ray_address == "local" else ray_address, ignore_reinit_error=True,
                 runtime_env={"env_vars": {"PYTHONPATH": str(ROOT)}})
        task = ray.remote(num_cpus=1)(run_cell)
        pending = [task.remote(c) for c in todo]
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            r = ray.get(ready[0])
            results.append(r)
            bar.set_postfix_str(f"{r['status']}: {r['cell']['method']}/{r['cell']['variant']}/{r['cell']['target']}")
            bar.update(1)
    else:
        with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:   # each worker drives one subprocess at a time
            futures = [pool.submit(run_cell, c) for c in todo]
            for fut in as_completed(futures):
                r = fut.result()
                results.append(r)
                bar.set_postfix_str(f"{r['status']}: {r['cell']['method']}/{r['cell']['variant']}/"
                                    f"{r['cell']['target']}")
                bar.update(1)
    bar.close()
    for r in results:
        if r["status"] == "failed":
            print(f"FAILED {r['cell']['dir']}: {r.get('error')}", file=sys.stderr)
    return results


# ====================================================================== report
def _load(cell: dict[str, Any]) -> dict[str, Any] | None:
    p = cell_dir(cell) / "results.json"
    if not p.exists():
        return None
    res = json.loads(p.read_text())
    cj = cell_dir(cell) / "cell.json"
    meta = json.loads(cj.read_text()) if cj.exists() else {}
    res["_command"] = meta.get("command") or command_line(cell)
    if meta.get("resume_command"):              # a cell continued elsewhere from its checkpoint (see its machine)
        res["_command"] += "` then `" + meta["resume_command"]
    res["_machine"] = meta.get("machine")
    res["_learner_device"] = meta.get("learner_device")
    return res


def _fmt_ci(m: float, lo: float, hi: float, scale: float = 1.0, nd: int = 2) -> str:
    if math.isnan(m):
        return "—"
    if math.isnan(lo):
        return f"{m * scale:.{nd}f} (n=1)"
    return f"{m * scale:.{nd}f} [{lo * scale:.{nd}f}, {hi * scale:.{nd}f}]"


def row_stats(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate the finished seeds of one (method, variant, target)."""
    s1 = [np.mean([e["success"] for e in r["episodes"]]) for r in runs]
    s2 = [np.mean([e["final_error"] < 0.02 for e in r["episodes"]]) for r in runs]
    err = [np.mean([e["final_error"] for e in r["episodes"]]) for r in runs]
    eps = [e for r in runs for e in r["episodes"]]
    succ = [e["steps"] for e in eps if e["success"]]
    to2 = [next((k for k, x in enumerate(e["errors"]) if x < 0.02), None) for e in eps if "errors" in e]
    to2 = [k for k in to2 if k is not None]
    planner = "sim_evals" in runs[0]
    return {
        "seeds": len(runs), "episodes": len(eps),
        "s1": t_interval(s1, (0.0, 1.0)), "s1_w": wilson(sum(e["success"] for e in eps), len(eps)),
        "s2": t_interval(s2, (0.0, 1.0)), "s2_w": wilson(sum(e["final_error"] < 0.02 for e in eps), len(eps)),
        "err": t_interval(err, (0.0, float("inf"))),
        "moves": (float(np.mean(succ)), len(succ)) if succ else (float("nan"), 0),
        "moves2": float(np.mean(to2)) if to2 else float("nan"),
        "env_steps": float(np.mean([r["env_steps"] for r in runs])),
        "sim_evals": float(np.mean([r["sim_evals"] / len(r["episodes"]) for r in runs])) if planner else None,
        "wall": float(np.mean([r["wall_s"] for r in runs])),
        "s_per_move": float(np.mean([r["plan_s_per_step"] for r in runs])) if planner else None,
    }


def task_groups(done: list, target: str) -> dict[tuple[str, str, str], list]:
    """The rows of one task: (method, variant, trained_on) -> [(cell, results)]. On a held-out shape a learner's row
    is its trained policy evaluated there (results "heldout"), one row per task it was trained on."""
    groups: dict[tuple[str, str, str], list] = {}
    for c, r in done:
        if c["target"] == target:
            groups.setdefault((c["method"], c["variant"], target), []).append((c, r))
    for c, r in done:
        held = (r.get("heldout") or {}).get(target)
        if held and c["target"] != target:
            sub = dict(r, episodes=held["episodes"], success_rate=held["success_rate"])
            groups.setdefault((c["method"], c["variant"], c["target"]), []).append((c, sub))
    return groups


def row_cost(method: str, runs: list[dict[str, Any]], st: dict[str, Any]) -> dict[str, Any]:
    """Simulator moves and wall time of one row: to train (learners: training transitions, each one simulated
    move; planners: none) and per episode (learners: the moves they execute; planners: their simulated
    candidate moves plus the moves executed)."""
    moves = float(np.mean([e["steps"] for r in runs for e in r["episodes"]]))
    if st["sim_evals"] is not None:                                         # a planner
        per_s = float(np.mean([r["wall_s"] / len(r["episodes"]) for r in runs]))
        return {"train_moves": 0.0, "train_s": 0.0, "episode_moves": st["sim_evals"] + moves, "episode_s": per_s,
                "moves": moves, "success": st["s1"][0]}
    per = [r.get("eval_s_per_episode") for r in runs]
    per_s = float(np.mean(per)) if all(x is not None for x in per) else float("nan")
    return {"train_moves": st["env_steps"], "train_s": st["wall"], "episode_moves": moves, "episode_s": per_s,
            "moves": moves, "success": st["s1"][0]}


PAYBACK_SLACK = 0.05   # a learner's payback is reported only if its success is at most this far below CEM's


def payback(learner: dict[str, Any], planner: dict[str, Any], key: str) -> float:
    """Episodes after which a learner (training + its episodes) has cost less than the planner (its episodes), in
    simulator moves (key "moves") or wall seconds ("s"); inf if never, nan if unknown."""
    train, per, per_p = learner[f"train_{key}"], learner[f"episode_{key}"], planner[f"episode_{key}"]
    if any(math.isnan(x) for x in (train, per, per_p)):
        return float("nan")
    return train / (per_p - per) if per_p > per else float("inf")


def cost_section(costs: dict[str, list[dict[str, Any]]], grid: dict[str, Any]) -> list[str]:
    lines = ["## Planning against learning: what each costs", "",
             "Simulator moves are one currency for both: a learner's training transitions and the moves of its "
             "episodes, a planner's simulated candidate moves (sim evals) plus the moves it executes. **Pays back "
             "after**: the number of episodes after which the learner, training included, has cost fewer simulator "
             "moves (or seconds) than CEM on the same task (∞: never, its episodes cost more than CEM's); only "
             f"for a learner whose success is within {PAYBACK_SLACK:.0%} of CEM's. A "
             "learner's seconds per episode are measured with its evaluation episodes run 20 at once (batched); a "
             "planner's one episode at a time. Success counts at 1 cm; moves are over all episodes.", ""]
    head = ["task", "method", "variant", "success @1 cm", "moves / episode", "sim moves to train",
            "sim moves / episode", "wall s to train", "wall s / episode", "pays back after (sim moves; wall s)"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for target, rows in costs.items():
        cem = next((r for r in rows if r["method"] == "cem"), None)
        for r in rows:
            variant = r["variant"] + ("" if r["trained_on"] == target else f", trained on {r['trained_on']}")
            pb = "—"
            if cem is not None and r["train_moves"] > 0 and r["success"] < cem["success"] - PAYBACK_SLACK:
                pb = "— (less success than CEM)"
            elif cem is not None and r["train_moves"] > 0:
                pb = "; ".join("∞" if math.isinf(x) else ("—" if math.isnan(x) else f"{x:.0f}")
                               for x in (payback(r, cem, "moves"), payback(r, cem, "s")))
            es = "—" if math.isnan(r["episode_s"]) else f"{r['episode_s']:.3g}"
            lines.append("| " + " | ".join([target, r["method"], variant, f"{r['success']:.2f}", f"{r['moves']:.1f}",
                                             f"{r['train_moves']:.0f}", f"{r['episode_moves']:.0f}",
                                             f"{r['train_s']:.0f}", es, pb]) + " |")
    return lines + [""]


COLUMNS = ["method", "variant", "seeds × episodes", "success @1 cm: t-CI over seeds; Wilson pooled",
           "success @2 cm (final error < 2 cm): t-CI; Wilson", "final error [cm], t-CI",
           "moves to success (mean; n) (planners: to 2 cm)", "env steps / cell", "sim evals / episode", "wall s / cell (s / move)",
           "command"]


def harness_command(grid: str, out: str, method: str, variant: str, target: str, seeds: list[int],
                    learner_device: str | None = None) -> str:
    q = ["--quick"] if grid == "quick" else []
    dev = ["--learner-device", learner_device] if learner_device else []
    return shlex.join(["python", "-m", "benchmarks.compare", *q, "--methods", method, "--variants", variant,
                       "--targets", target, "--seeds", *map(str, seeds), "--out", out, *dev])


def machine_label(res: dict[str, Any]) -> str:
    m = res.get("_machine")
    if not m:
        return "machine not recorded"
    label = f"{m.get('cpus')}-core CPU" + (f" + {m['gpu']}" if m.get("gpu") else "")
    return label + (f"; {m['note']}" if m.get("note") else "")


def write_report(grid: dict[str, Any], out: Path | str, doc: Path | str, figures: Path | str | None,
                 cells: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """docs/RESULTS.md (and figures) from the finished cells only. Returns {target: [row dicts]}."""
    out, doc = Path(out), Path(doc)
    cells = build_cells(grid, out) if cells is None else cells
    loaded = [(c, _load(c)) for c in cells]
    done = [(c, r) for c, r in loaded if r is not None]
    quick = grid["name"] == "quick"
    lines = ["# Results", ""]
    if quick:
        lines += ["> **QUICK RUN — a format example, NOT results.** Generated by `python -m benchmarks.compare --quick`",
                  "> (budgets: below). Nothing below measures the methods; the full comparison is "
                  "`python -m benchmarks.compare`.", ""]
    lines += [f"Grid `{grid['name']}` of `benchmarks/compare.yaml`: {len(done)} of {len(cells)} cells finished "
              f"(cell directories under `{out}`). Written by `python -m benchmarks.compare"
              f"{' --quick' if quick else ''} --report`.", "",
              "Definitions. A row aggregates the finished seeds of one method/variant on one task; every seed's "
              f"{grid['episodes']} evaluation episodes start from `env.reset(seed={grid['eval_seed_base']} + 1000·seed + i)`. "
              "**Success @1 cm**: the episode terminated with shape error < 1 cm (the env's success). "
              "**Success @2 cm**: the episode's last shape error < 2 cm (an episode ends at its first move under 1 cm "
              "or after max-steps moves, for planners and learners alike). "
              "**CIs (95 %)**: first a t-interval over seeds (mean of per-seed rates ± t₀.₉₇₅,ₙ₋₁·sd/√n, clipped "
              "to [0, 1]; `n=1` when only one seed), then a Wilson score interval over the pooled episodes. "
              "**Final error**: per-seed mean of the episodes' last shape error, t-interval over seeds. "
              "**Moves to success**: mean moves of the successful episodes (n = their number); planners "
              "also: mean first move under 2 cm over the episodes that got there (from their per-move errors). "
              "**Env steps**: learners: training env transitions actually run (the budget, or more: PPO collects "
              "whole rollouts of n_steps × num_envs transitions, as SB3 does, so it stops at the first rollout "
              "boundary at or past the budget); planners: moves executed over the "
              "cell's episodes. **Sim evals**: rope-moves simulated by a planner per episode (learners: none). "
              "**Wall**: seconds per cell (planners: and planning seconds per move).", ""]
    if grid.get("budgets"):
        lines += [f"**Budgets.** {' '.join(grid['budgets'].split())}", ""]
    missing: dict[str, list[str]] = {}
    for c, r in loaded:
        if r is None:
            missing.setdefault(f"{c['method']}/{c['variant']}/{c['target']}", []).append(str(c["seed"]))
    if missing and not quick:
        lines += [f"> **Partial comparison: {len(cells) - len(done)} of {len(cells)} cells not run yet** "
                  "(method/variant/target: seeds missing): "
                  + "; ".join(f"{k}: {' '.join(v)}" for k, v in missing.items())
                  + ". Rows below aggregate the finished seeds only; absent rows were not run.", ""]
    targets = [t for t in grid["targets"]]
    table: dict[str, list[dict[str, Any]]] = {}
    costs: dict[str, list[dict[str, Any]]] = {}
    for target in targets:
        groups = task_groups(done, target)
        if not groups:
            continue
        lines += [f"## Task: {target}", "", "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
        details = []
        for (method, variant, trained_on), items in groups.items():
            st = row_stats([r for _, r in items])
            costs.setdefault(target, []).append(dict(row_cost(method, [r for _, r in items], st),
                                                     method=method, variant=variant, trained_on=trained_on))
            seeds = [c["seed"] for c, _ in items]
            devices = sorted({r.get("_learner_device") or "" for _, r in items})
            row_groups = [(d, [c["seed"] for c, r in items if (r.get("_learner_device") or "") == d]) for d in devices]
            cmd = " ; ".join(harness_command(grid["name"], str(out), method, variant, trained_on, sd, d or None)
                             for d, sd in row_groups)
            if trained_on != target:
                variant = f"{variant}, trained on {trained_on}"
            w = f"{st['wall']:.1f}" + (f" ({st['s_per_move']:.2f})" if st["s_per_move"] is not None else "")
            n_dev = sum(bool(r.get("_learner_device")) for _, r in items)
            if n_dev:
                w += f" ({n_dev} of {len(items)} seeds with --learner-device: machines in the per-seed list)"
            moves = "—" if not st["moves"][1] else f"{st['moves'][0]:.1f}; {st['moves'][1]}"
            if not math.isnan(st["moves2"]):
                moves += f" (to 2 cm: {st['moves2']:.1f})"
            cells_txt = [method, variant, f"{st['seeds']} × {st['episodes'] // max(st['seeds'], 1)}",
                         f"{_fmt_ci(*st['s1'])}; {_fmt_ci(*st['s1_w'])}", f"{_fmt_ci(*st['s2'])}; {_fmt_ci(*st['s2_w'])}",
                         _fmt_ci(*st["err"], scale=100.0), moves, f"{st['env_steps']:.0f}",
                         "—" if st["sim_evals"] is None else f"{st['sim_evals']:.0f}", w, f"`{cmd}`"]
            lines.append("| " + " | ".join(cells_txt) + " |")
            table.setdefault(target, []).append(dict(zip(COLUMNS, cells_txt), stats=st))
            details += [f"- {method}/{variant} seed {c['seed']}: `{r['_command']}` ({machine_label(r)})"
                        for c, r in items]
        lines += ["", "<details><summary>Exact per-seed commands (what the harness ran)</summary>", "", *details, "",
                  "</details>", ""]
    if costs:
        lines += cost_section(costs, grid)
    if figures is not None:
        try:
            figs = make_figures(grid, done, Path(figures)) + make_cost_figures(grid, costs, Path(figures))
        except ImportError:
            figs = []
        if figs:
            rel = os.path.relpath(Path(figures), doc.parent)
            lines += ["## Figures" + (" (quick run: format only, not results)" if quick else ""), ""]
            lines += [f"![{f.stem}]({rel}/{f.name})" for f in figs] + [""]
    doc.parent.mkdir(parents=True, exist_ok=True)
    doc.write_text("\n".join(lines) + "\n")
    return table


# ====================================================================== figures
CURVES = [("eval", "mean_reward", "eval mean reward"), ("eval", "mean_length", "eval episode length"),
          ("rollout", "ep_reward", "rollout mean reward"), ("rollout", "ep_length", "rollout episode length"),
          ("train", "actor_loss", "actor loss"), ("train", "critic_loss", "critic loss"),
          ("train", "loss", "world-model loss (PlaNet)")]


def _series(dirs: list[Path], group: str, key: str):
    """Per-seed (step, value) series of one CSV column, interpolated onto the first seed's steps."""
    from agents.common import read_csv

    runs = []
    for d in dirs:
        p = d / f"{group}.csv"
        if not p.exists():
            continue
        rows = [r for r in read_csv(p) if r.get(key) not in (None, "")]
        if rows:
            runs.append((np.array([float(r["step"]) for r in rows]), np.array([float(r[key]) for r in rows])))
    if not runs:
        return None
    x = runs[0][0]
    ys = np.stack([np.interp(x, sx, sy) for sx, sy in runs])
    return x, ys


def _band(ax, x, ys, label, clip: tuple[float, float] | None = None):
    m = ys.mean(0)
    line, = ax.plot(x, m, marker=".", ms=3, label=f"{label} (n={len(ys)})")
    if len(ys) > 1:
        half = t_quantile(0.975, len(ys) - 1) * ys.std(0, ddof=1) / math.sqrt(len(ys))
        lo, hi = m - half, m + half
        if clip is not None:                       # as the table's intervals: a rate's band stays in [0, 1]
            lo, hi = np.clip(lo, *clip), np.clip(hi, *clip)
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2)


def make_figures(grid: dict[str, Any], done: list, figdir: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figdir.mkdir(parents=True, exist_ok=True)
    tag = "quick_" if grid["name"] == "quick" else ""
    note = " [QUICK RUN: format only]" if tag else ""
    written: list[Path] = []

    def save(fig, name: str, dpi: int = 60) -> None:
        fig.tight_layout()
        path = figdir / f"{tag}{name}.png"
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
        written.append(path)

    by: dict[tuple, list[Path]] = {}
    for c, r in done:
        by.setdefault((c["kind"], c["method"], c["variant"], c["target"]), []).append(cell_dir(c))
    targets = sorted({k[3] for k in by}, key=lambda t: grid["targets"].index(t))
    for target in targets:
        # learning curves per learner (variants as lines: points vs images, rewards), mean +- t-CI over seeds
        for method in [m for m, s in grid["methods"].items() if s["kind"] == "agent"]:
            keys = [k for k in by if k[0] == "agent" and k[1] == method and k[3] == target]
            panels = [(g, key, title) for g, key, title in CURVES
                      if any(_series(by[k], g, key) is not None for k in keys)]
            if not panels:
                continue
            fig, axes = plt.subplots(2, 3, figsize=(11, 5.5), squeeze=False)
            for ax, (g, key, title) in zip(axes.flat, panels[:6]):
                for k in keys:
                    s = _series(by[k], g, key)
                    if s is not None:
                        _band(ax, *s, label=k[2])
                ax.set_title(title, fontsize=9)
                ax.set_xlabel("env steps", fontsize=8)
                ax.legend(fontsize=7)
            for ax in list(axes.flat)[len(panels[:6]):]:
                ax.axis("off")
            fig.suptitle(f"{method} on {target}: mean ± 95% t-CI over seeds{note}", fontsize=10)
            save(fig, f"curves_{method}_{target}")
        # success vs env steps, all learners
        keys = [k for k in by if k[0] == "agent" and k[3] == target]
        if keys:
            fig, ax = plt.subplots(figsize=(5.5, 3.5))
            for k in keys:
                s = _series(by[k], "eval", "success_rate")
                if s is not None:
                    _band(ax, *s, label=f"{k[1]}/{k[2]}", clip=(0.0, 1.0))
            ax.set_xlabel("env steps")
            ax.set_ylabel("eval success @1 cm")
            ax.set_title(f"{target}: success vs env steps{note}", fontsize=9)
            ax.legend(fontsize=7)
            save(fig, f"success_vs_steps_{target}")
        # planners: error vs simulator evaluations (per-move errors; x = move k x sim evals per move)
        keys = [k for k in by if k[0] == "planner" and k[3] == target]
        if any(k[1] != "greedy" for k in keys):
            fig, ax = plt.subplots(figsize=(5.5, 3.5))
            for k in keys:
                curves, per_move = [], []
                for d in by[k]:
                    res = json.loads((d / "results.json").read_text())
                    eps = res["episodes"]
                    n = max(len(e["errors"]) for e in eps)
                    errs = np.array([e["errors"] + [e["errors"][-1]] * (n - len(e["errors"])) for e in eps])
                    curves.append(errs.mean(0))
                    per_move.append(res["sim_evals"] / max(res["env_steps"], 1))
                n = min(len(c) for c in curves)
                ys = np.stack([c[:n] for c in curves]) * 100
                epm = float(np.mean(per_move))
                if epm == 0:   # greedy simulates nothing
                    continue
                _band(ax, np.arange(n) * epm, ys, label=f"{k[1]} ({epm:.0f} evals/move)")
            ax.axhline(1.0, color="k", lw=0.6, ls="--")
            ax.axhline(2.0, color="k", lw=0.6, ls=":")
            ax.set_xlabel("simulator evaluations (rope-moves)")
            ax.set_ylabel("mean shape error [cm]")
            ax.set_title(f"{target}: planners' error vs sim evals{note}", fontsize=9)
            ax.legend(fontsize=7)
            save(fig, f"planner_error_vs_evals_{target}")
        # gallery: the final-shape pictures each entry point drew with diffdlo.render.plot_ropes (first seed)
        pics = []
        for k in sorted((k for k in by if k[3] == target), key=lambda k: list(grid["methods"]).index(k[1])):
            d = sorted(by[k])[0]
            for name in ("shapes.png", "eval_episodes.png", "ep0/shapes.png"):
                if (d / name).exists():
                    pics.append((f"{k[1]}/{k[2]} ({d.name})", d / name))
                    break
        if pics:
            cols = min(3, len(pics))
            rows = (len(pics) + cols - 1) // cols
            fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.2 * rows), squeeze=False)
            for ax in axes.flat:
                ax.axis("off")
            for ax, (title, path) in zip(axes.flat, pics):
                ax.imshow(plt.imread(path))
                ax.set_title(title, fontsize=8)
            fig.suptitle(f"{target}: start and final shapes against the target (dashed), first seed{note}", fontsize=10)
            save(fig, f"gallery_{target}", dpi=70)
    return written


def make_cost_figures(grid: dict[str, Any], costs: dict[str, list[dict[str, Any]]], figdir: Path) -> list[Path]:
    """Per task: cumulative simulator moves and wall seconds against episodes solved, planners and learners on the
    same axes (a learner starts at its training cost; where its line crosses CEM's it has paid back)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figdir.mkdir(parents=True, exist_ok=True)
    tag = "quick_" if grid["name"] == "quick" else ""
    written = []
    episodes = np.logspace(0, 4, 60)
    for target, rows in costs.items():
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
        for ax, key, unit in ((axes[0], "moves", "simulator moves"), (axes[1], "s", "wall seconds")):
            for r in rows:
                if math.isnan(r[f"episode_{key}"]):
                    continue
                label = f"{r['method']}/{r['variant']}" + ("" if r["trained_on"] == target else f" ({r['trained_on']})")
                ax.plot(episodes, r[f"train_{key}"] + episodes * r[f"episode_{key}"], label=f"{label}: {r['success']:.0%}")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("episodes run")
            ax.set_ylabel(f"cumulative {unit}")
            ax.legend(fontsize=6)
        fig.suptitle(f"{target}: cost of planning vs learning (legend: success @1 cm)"
                     + (" [QUICK RUN: format only]" if tag else ""), fontsize=9)
        fig.tight_layout()
        path = figdir / f"{tag}cost_{target}.png"
        fig.savefig(path, dpi=60)
        plt.close(fig)
        written.append(path)
    return written


# ====================================================================== command line
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.compare", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the tiny grid (minutes): a format example, not results")
    ap.add_argument("--grid", default=str(GRID_FILE), help="grid YAML (default benchmarks/compare.yaml)")
    ap.add_argument("--methods", nargs="+", default=None)
    ap.add_argument("--variants", nargs="+", default=None)
    ap.add_argument("--targets", nargs="+", default=None)
    ap.add_argument("--seeds", nargs="+", type=int, default=None)
    ap.add_argument("--out", default=None, help="cell root (default runs/compare; --quick: runs/compare-quick)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="cells at once (default: cores)")
    ap.add_argument("--ray", default=None, metavar="ADDRESS", help="run cells as Ray tasks ('local': ray.init())")
    ap.add_argument("--report", action="store_true", help="only write the report from finished cells")
    ap.add_argument("--no-report", action="store_true", help="run cells, write no report")
    ap.add_argument("--doc", default="docs/RESULTS.md", help="report path (default docs/RESULTS.md)")
    ap.add_argument("--figures", default="docs/figures", help="figure folder ('' for none)")
    ap.add_argument("--list", action="store_true", help="print the selected cells and their commands, run nothing")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--learner-device", default=None, metavar="DEVICE",
                    help="learners' networks on DEVICE (e.g. cuda), simulation on the CPU; planners unchanged")
    args = ap.parse_args(argv)
    grid = load_grid(args.quick, args.grid)
    out = Path(args.out or ("runs/compare-quick" if args.quick else "runs/compare"))
    for name, vals, allowed in (("--methods", args.methods, list(grid["methods"])),
                                ("--targets", args.targets, grid["targets"])):
        bad = sorted(set(vals or []) - set(allowed))
        if bad:
            ap.error(f"{name}: unknown {bad}; this grid has {allowed}")
    cells = build_cells(grid, out, args.methods, args.variants, args.targets, args.seeds, args.learner_device)
    if not cells:
        ap.error("no cell matches the filters")
    if args.list:
        for c in cells:
            print(("done    " if is_done(c) else "todo    ") + command_line(c))
        return 0
    status = 0
    if not args.report:
        results = run_cells(cells, jobs=args.jobs, ray_address=args.ray, progress=not args.no_progress)
        counts = {s: sum(r["status"] == s for r in results) for s in ("done", "skipped", "failed")}
        print(f"cells: {counts['done']} run, {counts['skipped']} already finished (skipped), {counts['failed']} failed")
        status = 1 if counts["failed"] else 0
    if not args.no_report:
        write_report(grid, out, args.doc, args.figures or None, build_cells(grid, out))
        print(f"report: {args.doc}")
    return status


if __name__ == "__main__":
    sys.exit(main())
