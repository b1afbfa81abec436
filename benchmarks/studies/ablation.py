"""Ablation of the tuned learners: each tuned choice reverted alone to its sb3-default value, same budget and seeds.

    python -m benchmarks.studies.ablation --algo ppo --total-steps 1000000 --seeds 0 --out runs/ablation-ppo
    python -m benchmarks.studies.ablation --algo sac --total-steps 50000 --seeds 0 --variants tuned head --out runs/ablation-sac

Every variant is one run of ``python -m agents.<algo>`` (its tuned preset plus the variant's ``--set`` keys) into
``<out>/<variant>/seed<s>/``; a finished run (its results.json exists) is skipped, so the script resumes where it
stopped. Prints a markdown table (success at 1 cm, mean moves of the successful episodes, mean final error, env
steps, wall time; mean over seeds) and writes it to ``<out>/ablation.md``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

# variant -> the config keys it changes (each one choice of the tuned preset set back to sb3-default's)
VARIANTS = {
    "tuned": {},
    "head": {"policy": "gaussian"},                                        # eq 2.6's continuous node scalar
    "features": {"features": "raw", "normalize_obs": "false"},             # observation as it is
    "reward": {"reward": "position_orientation", "success_bonus": "null"},  # the thesis's eq 2.9 and +20
    "termination": {"on_exit": "truncate", "exit_penalty": "0.0"},         # leaving the workspace truncates
    "gamma": {"gamma": "0.99"},
}
SCALE = {"ppo": {"num_envs": "16", "n_steps": "2048", "batch_size": "64", "n_epochs": "10", "anneal_lr": "false"},
         "sac": {"num_envs": "16", "gradient_steps": "1", "learning_starts": "100", "ent_coef_init": "1.0"}}


def run(algo: str, variant: str, seed: int, args, out: Path) -> dict:
    d = out / variant / f"seed{seed}"
    if not (d / "results.json").exists():
        keys = SCALE[algo] if variant == "scale" else VARIANTS[variant]
        sets = [x for k, v in keys.items() for x in ("--set", f"{k}={v}")]
        cmd = [sys.executable, "-m", f"agents.{algo}", "--seed", str(seed), "--total-steps", str(args.total_steps),
               "--eval-episodes", str(args.eval_episodes), "--eval-every", str(args.total_steps), "--threads", "1",
               "--no-progress", *sets, "--out", str(d)]
        if (d / "checkpoint.pt").exists():
            cmd = [sys.executable, "-m", f"agents.{algo}", "--out", str(d), "--resume", "--no-progress"]
        print("$", " ".join(cmd[1:]), flush=True)
        d.mkdir(parents=True, exist_ok=True)
        with open(d / "log.txt", "a") as log:
            rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode
        if rc != 0:
            raise SystemExit(f"{variant} seed {seed} failed (exit {rc}): see {d / 'log.txt'}")
    return json.loads((d / "results.json").read_text())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.ablation", description=__doc__.split("\n\n")[0])
    ap.add_argument("--algo", choices=("ppo", "sac"), required=True)
    ap.add_argument("--variants", nargs="+", default=[*VARIANTS, "scale"],
                    help=f"of {[*VARIANTS, 'scale']} (scale: SB3's rollout/update scale)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--total-steps", type=int, required=True)
    ap.add_argument("--eval-episodes", type=int, default=100)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    bad = sorted(set(args.variants) - {*VARIANTS, "scale"})
    if bad:
        ap.error(f"--variants: unknown {bad}; use some of {[*VARIANTS, 'scale']}")
    out = Path(args.out)
    lines = [f"| {args.algo} variant | changed keys | success @1 cm | moves to success | final error [cm] | "
             "env steps | wall s |", "|---|---|---|---|---|---|---|"]
    for variant in args.variants:
        res = [run(args.algo, variant, s, args, out) for s in args.seeds]
        eps = [e for r in res for e in r["episodes"]]
        moves = [e["steps"] for e in eps if e["success"]]
        keys = SCALE[args.algo] if variant == "scale" else VARIANTS[variant]
        lines.append(f"| {variant} | {', '.join(f'{k}={v}' for k, v in keys.items()) or '(preset)'} | "
                     f"{np.mean([e['success'] for e in eps]):.2f} | "
                     f"{np.mean(moves) if moves else float('nan'):.1f} | "
                     f"{100 * np.mean([e['final_error'] for e in eps]):.2f} | "
                     f"{np.mean([r['env_steps'] for r in res]):.0f} | {np.mean([r['wall_s'] for r in res]):.0f} |")
    text = "\n".join(lines)
    (out / "ablation.md").write_text(text + "\n")
    print(f"{args.algo}, seeds {args.seeds}, {args.eval_episodes} eval episodes per seed:\n{text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
