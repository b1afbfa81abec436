"""The learners' command line: one parser for the options every run shares, presets, ``--set``, ``--resume``."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Callable

import torch
import yaml

from agents import config as config_lib
from agents.checkpoints import CHECKPOINT
from diffdlo.params import ParamsError
from diffdlo.rewards import REWARDS
from diffdlo.shapes import TARGET_NAMES, TargetError
from diffdlo.task import ACTION_TYPES, OBS_TYPES


def positive_int(text: str) -> int:
    try:
        v = int(float(text)) if "e" in text.lower() else int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def make_parser(prog: str, doc: str | None) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=prog, description=(doc or "").split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--preset", default=None,
                    help="named defaults: 'tuned' (params/<algo>.yaml, the default) or e.g. 'sb3-default' "
                         "(params/<algo>-sb3-default.yaml)")
    ap.add_argument("--config", default=None, help="YAML of defaults (instead of a preset)")
    ap.add_argument("--target", default=None, help=f"'random' or one of {list(TARGET_NAMES)} or a .npy/.yaml path")
    ap.add_argument("--obs", choices=OBS_TYPES, default=None, help="observation type")
    ap.add_argument("--action", choices=ACTION_TYPES, default=None, help="action type")
    ap.add_argument("--reward", choices=REWARDS, default=None, help="reward function")
    ap.add_argument("--total-steps", type=positive_int, default=None, help="env transitions (all envs together)")
    ap.add_argument("--num-envs", type=positive_int, default=None, help="ropes stepped together")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--out", required=True, help="output directory (logs, checkpoint, results.json, pictures)")
    ap.add_argument("--device", default=None, help="torch device, e.g. cpu or cuda")
    ap.add_argument("--resume", action="store_true",
                    help="continue from <out>/checkpoint.pt up to --total-steps (config from the checkpoint)")
    ap.add_argument("--eval-every", type=positive_int, default=None, help="env steps between evaluations")
    ap.add_argument("--eval-episodes", type=positive_int, default=None)
    ap.add_argument("--checkpoint-every", type=positive_int, default=None, help="env steps between checkpoints")
    ap.add_argument("--max-steps", type=positive_int, default=None, help="actions per episode")
    ap.add_argument("--params", default=None, help="cable params name or YAML path")
    ap.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default 1)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override any config key (YAML value), e.g. --set batch_size=128 --set hidden=[64,64]")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


RESUME_KEYS = ("total_steps", "eval_every", "eval_episodes", "checkpoint_every", "device")   # may change at --resume
CLI_KEYS = ("threads", "target", "obs", "action", "reward", "total_steps", "num_envs", "seed", "device", "eval_every",
            "eval_episodes", "checkpoint_every", "max_steps", "params")


def config_from_args(cls, algo: str, args: argparse.Namespace, ap: argparse.ArgumentParser):
    overrides: dict[str, Any] = {}
    for item in args.set:
        if "=" not in item:
            ap.error(f"--set expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        overrides[key.strip()] = yaml.safe_load(value)
    for key in CLI_KEYS:
        v = getattr(args, key)
        if v is not None:
            overrides[key] = v
    if args.config and args.preset:
        ap.error("give --config or --preset, not both")
    try:
        return config_lib.load_config(cls, args.config or config_lib.preset_path(algo, args.preset), overrides)
    except (ValueError, TypeError) as exc:
        ap.error(str(exc))


def run_cli(cls, algo: str, doc: str | None, train: Callable, argv: list[str] | None = None) -> int:
    """Parse, build the config (or take it from the checkpoint with --resume), train, report."""
    ap = make_parser(f"python -m agents.{algo}", doc)
    args = ap.parse_args(argv)
    out = Path(args.out)
    if args.resume:
        ckpt = out / CHECKPOINT
        if not ckpt.exists():
            ap.error(f"--resume: no checkpoint at {ckpt}")
        saved = torch.load(ckpt, map_location="cpu", weights_only=False)["config"]
        changes = {k: getattr(args, k) for k in RESUME_KEYS if getattr(args, k) is not None}
        try:
            cfg = config_lib.replace(config_lib.from_flat(cls, saved), **changes)
            cfg.check()
        except (ValueError, TypeError) as exc:
            ap.error(f"--resume: the checkpoint's config: {exc}")
    else:
        cfg = config_from_args(cls, algo, args, ap)
    try:
        res = train(cfg, out, resume=args.resume, progress=not args.no_progress)
    except (ValueError, TargetError, ParamsError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{algo}: success rate {res['success_rate']:.2f} over {len(res['episodes'])} eval episodes, "
          f"{res['env_steps']} env steps, {res['wall_s']:.1f} s -> {out}/results.json")
    return 0
