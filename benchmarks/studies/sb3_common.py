"""What the Stable-Baselines3 checks (benchmarks/studies/sb3_sac.py, sb3_ppo.py) share: their command line and their
results.json (the fields every method writes, evaluated with ``agents.common.evaluation.evaluate``)."""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import diffdlo


def parser(doc: str | None, total_steps: int, eval_episodes: int, out: str) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--total-steps", type=int, default=total_steps)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--target", default="random")
    ap.add_argument("--eval-episodes", type=int, default=eval_episodes)
    ap.add_argument("--eval-seed", type=int, default=10_000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=out)
    return ap


def write_record(out: Path, method: str, args: argparse.Namespace, result: dict[str, Any],
                 **extra: Any) -> Path:
    """``out/results.json`` with the method's evaluation and the SB3 and diffdlo versions; returns its path."""
    record = {"method": method, "target": args.target, "seed": args.seed, "success_rate": result["success_rate"],
              "episodes": [{k: e[k] for k in ("success", "steps", "final_error")} for e in result["episodes"]],
              "mean_final_error": result["mean_final_error"], **extra,
              "sb3_version": __import__("stable_baselines3").__version__, "diffdlo_version": diffdlo.__version__}
    path = Path(out) / "results.json"
    path.write_text(json.dumps(record, indent=2))
    return path
